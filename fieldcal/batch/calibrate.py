"""One calibration per stack, as a batch unit (``fieldcal batch calibrate``).

:func:`calibrate_unit` runs on a worker: it does what ``fieldcal calibrate STACK --out DIR/NAME.json`` does
(the same library calls with the same arguments, so the profile is the same byte for byte apart from the
times it records, see :func:`profile_without_times`), writes the profile atomically (``LensProfile.save``:
the samples sidecar, then the JSON renamed into place) and returns the unit's surfaces, uncertainties and
tolerances sampled on the fleet grid (:mod:`fieldcal.batch.fleet`), so the fleet report needs no second pass.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: ``calibrate()`` keyword -> the CLI option's dest (the options ``batch calibrate`` shares with ``calibrate``)
CALIBRATE_OPTIONS = {"fs_cyc_per_mm": "fs", "q": "q", "effort": "effort", "z_ref_um": "z_ref_um",
                     "tile_px": "tile_px", "measure": "measure", "chart": "chart", "seed": "seed",
                     "stage_repeatability_um": "stage_repeatability_um"}
# Keys of a profile that record when it was made or how long it took: all that differs between two runs.
_TIME_KEY = re.compile(r"^(created_utc|timings?_s|time_s|time_[a-z_]+_s)$")


@dataclass(frozen=True)
class CalibrateJob:
    """One stack to calibrate: where it is, where its profile goes, and ``calibrate()``'s keywords."""

    stack: str
    out: str
    options: dict = field(default_factory=dict)
    verify: bool = True
    grid: tuple[int, int] = (25, 15)


def unit_names(stacks: list[str | Path]) -> list[str]:
    """Output names of the stacks: each folder's name, ``-2``, ``-3`` ... after a name already taken."""
    names: list[str] = []
    taken: set[str] = set()
    for s in stacks:
        p = Path(s)
        base = (p.parent.name if p.name == "stack.json" else p.name) or "stack"
        base = re.sub(r"[^A-Za-z0-9._-]", "_", base).lstrip(".") or "stack"
        name, k = base, 1
        while name.casefold() in taken:  # case-only twins are one file on macOS and Windows
            k += 1
            name = f"{base}-{k}"
        taken.add(name.casefold())
        names.append(name)
    return names


def calibrate_unit(job: CalibrateJob) -> dict:
    """Calibrate one stack and save its profile (the task body); returns its fleet maps and a summary."""
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.formats.atomic import protect
    from fieldcal.formats.stack import Stack

    from .fleet import unit_maps

    stack_dir = Path(job.stack)
    if stack_dir.name == "stack.json":
        stack_dir = stack_dir.parent
    protect(stack_dir)  # as `fieldcal calibrate`: nothing of this unit may be written into its input
    stack = Stack.open(stack_dir, verify=job.verify)
    profile = calibrate(stack, quiet=True, **job.options)
    profile.save(job.out)
    return {"profile": str(job.out), "model": profile.surfaces.model.name,
            "n_tiles_ok": profile.diagnostics.get("n_tiles_ok"),
            "maps": unit_maps(profile, job.grid, job.options.get("fs_cyc_per_mm", 80.0),
                              job.options.get("q", 0.05))}


def without_times(doc):
    """A copy of a JSON document without the keys that record times (``created_utc``, ``timing_s``,
    ``timings_s``, ``time_s``, ``time_*_s``), at any depth."""
    if isinstance(doc, dict):
        return {k: without_times(v) for k, v in doc.items() if not _TIME_KEY.match(k)}
    if isinstance(doc, list):
        return [without_times(v) for v in doc]
    return doc


def profile_without_times(path: str | Path) -> bytes:
    """A profile's JSON re-serialised without its time keys, plus its samples sidecar's bytes: two runs of the
    same calibration give the same bytes, whatever the profiles' file names. The sidecar's name is kept
    without the profile's own stem (``<stem>.<sha256[:16]>.samples.npz``: its content hash is compared)."""
    path = Path(path)
    doc = json.loads(path.read_text(encoding="utf-8"))
    side = dict(doc.get("sidecar") or {})
    data = b""
    if side.get("file"):
        data = (path.parent / side["file"]).read_bytes()
        side["file"] = side["file"].removeprefix(path.stem + ".")
        doc["sidecar"] = side
    return json.dumps(without_times(doc), indent=1, sort_keys=True).encode() + b"\0" + data
