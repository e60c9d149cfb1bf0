"""One validation per simulated lens, as a batch unit (``fieldcal validate --lenses N``).

Lens ``k`` of a run with seed ``s`` is :func:`fieldcal.fit.synthetic.random_lens` drawn from
``numpy.random.default_rng([s, k])`` (random curvature to ρ⁶, colour, tilt, decentre, astigmatism, F/2-F/4,
focus breathing, stage axis tilt; every 4th lens mono), so a lens does not depend on how many are drawn or
on which worker runs it. :func:`validate_unit` runs :func:`fieldcal.validation.run.validate` on it and writes
its report into ``OUT/lens-KKK/`` (the files of ``fieldcal validate``, each written atomically, plus the lens
as ``lens.json`` so ``fieldcal validate OUT/lens-KKK/lens.json`` repeats it).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

REPORT_FILES = ("index.html", "report.md", "summary.json", "lens.json")


@dataclass(frozen=True)
class LensJob:
    """Lens ``index`` of the seed ``seed``, validated with ``config`` into the folder ``out``."""

    index: int
    seed: int
    config: object  # fieldcal.validation.run.ValidateConfig
    out: str
    keep_stacks: bool = False
    plots: bool = True


def unit_name(k: int) -> str:
    return f"lens-{k:03d}"


def random_fleet_lens(k: int, seed: int = 0):
    """Lens ``k`` of seed ``seed`` (module docstring), named after its unit."""
    from fieldcal.fit.synthetic import random_lens

    spec = random_lens(np.random.default_rng([int(seed), int(k)]),
                       channels=("R", "G", "B") if k % 4 else ("Y",), optics=True)
    return replace(spec, name=f"random-{seed}-{unit_name(k)}")


def validate_unit(job: LensJob) -> dict:
    """Validate one random lens and write its report (the task body); returns pass/fail and the failed checks."""
    from fieldcal.validation.report import write_report
    from fieldcal.validation.run import validate

    spec = random_fleet_lens(job.index, job.seed)
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    spec.save(out / "lens.json")
    result = validate(spec, job.config, workdir=out / "stacks" if job.keep_stacks else None, quiet=True)
    write_report(result, out, plots=job.plots)
    return {"lens": spec.name, "passed": bool(result.passed), "failed_checks": [c.name for c in result.failed]}
