"""How often the surface fit's model selection adds terms a lens does not have, and finds those it has.

Over seeds, three G-only lenses at the flat-lens test's setting (320x240, quick, chart stack):
``flat`` (no curvature, no tilt), ``tilted`` (tilt 12, -8 µm/mm) and ``curved`` (a modest rho^2 curvature,
``--curv-um`` µm at the corner, rho = 1). Each stack is rendered and measured once; the tiles handed to
:func:`fieldcal.fit.fit_surfaces` are cached (``--cache``), so the selection alone can be re-run on them.

Prints per seed the chosen model and the paired held-out test of the simplest compared candidate (its loss
above the best's and the test's margin, :func:`fieldcal.fit.select.paired_test_choice`), and per lens the rates:
spurious terms (flat), tilt found with the right values (tilted), curvature found (curved).

Example::

    PYTHONPATH=$PWD python benchmarks/bench_select_seeds.py --seeds 20 --cache /tmp/s8sel
"""

from __future__ import annotations

import argparse
import pickle
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

import fieldcal.fit as fit_pkg
from fieldcal.calibration.pipeline import calibrate
from fieldcal.fit.synthetic import base_lens
from fieldcal.simulate.stackgen import simulate_stack
from fieldcal.validation.run import chart_positions_um, default_fs


def lenses(curv_um: float):
    g = base_lens(("G",))
    flat = replace(g, channels=tuple(replace(c, curvature_um=()) for c in g.channels))
    return {"flat": flat, "tilted": replace(flat, tilt_um_per_mm=(12.0, -8.0)),
            "curved": replace(flat, channels=tuple(replace(c, curvature_um=(curv_um,)) for c in flat.channels))}


def fit_inputs(spec, root: Path, seed: int):
    """Render and measure one stack; return the (tiles, geometry, kwargs) the pipeline passes to fit_surfaces."""
    cache = root / "inputs.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    spec = spec.with_sensor_size(320, 240)
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    simulate_stack(spec, root / "stack", z, scene="chart", seed=seed, progress=False)
    got = {}
    real = fit_pkg.fit_surfaces

    def capture(tiles, geometry, **kw):
        got.setdefault("args", (tiles, geometry, kw))
        return real(tiles, geometry, **kw)

    fit_pkg.fit_surfaces = capture
    try:
        calibrate(root / "stack", fs_cyc_per_mm=fs, effort="quick", z_ref_um=0.0, quiet=True)
    finally:
        fit_pkg.fit_surfaces = real
    cache.write_bytes(pickle.dumps(got["args"]))
    return got["args"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--curv-um", type=float, default=2.5, help="rho^2 curvature of the curved lens at rho = 1")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_select_seeds"))
    ap.add_argument("--lens", nargs="*", default=["flat", "tilted", "curved"])
    a = ap.parse_args(argv)
    for name in a.lens:
        spec = lenses(a.curv_um)[name]
        picks, ok, found = Counter(), 0, 0
        for s in range(a.seeds):
            tag = f"{name}_{a.curv_um:g}" if name == "curved" else name
            root = a.cache / f"{tag}_{s}"
            root.mkdir(parents=True, exist_ok=True)
            tiles, geom, kw = fit_inputs(spec, root, s)
            f = fit_pkg.fit_surfaces(tiles, geom, **{**kw, "quiet": True})
            m = f.model
            picks[m.name] += 1
            if name == "flat":
                good = m.order == 0 and not m.tilt and not m.decentre
                hit = not good
            elif name == "tilted":
                c = f.coefficients_um("G")
                hit = (m.tilt and abs(c.get("tilt_x_um_per_mm", 0.0) - 12.0) <= 1.5
                       and abs(c.get("tilt_y_um_per_mm", 0.0) + 8.0) <= 1.5)
                good = hit and m.order == 0 and not m.decentre
            else:
                hit = m.order >= 1
                good = hit and not m.tilt and not m.decentre
            ok += good
            found += hit
            # the simplest compared candidate's held-out loss above the best, and the paired test's margin
            cv = [e for e in f.candidates if e.get("cv_margin") is not None]
            simplest = min(cv, key=lambda e: e["n_params"]) if cv else None
            why = (f" (simplest compared {simplest['name']}: {simplest['cv_delta']:.1f} above the best, "
                   f"margin {simplest['cv_margin']:.1f})") if simplest else ""
            print(f"{name} seed {s}: {m.name} {'ok' if good else 'WRONG'}{why}", flush=True)
        what = {"flat": "spurious terms", "tilted": "tilt found within 1.5 µm/mm",
                "curved": "curvature found"}[name]
        print(f"== {name}: {ok}/{a.seeds} exactly the lens's terms; {what} {found}/{a.seeds}; picks {dict(picks)}",
              flush=True)


if __name__ == "__main__":
    main()
