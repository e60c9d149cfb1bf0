"""Coverage of ``warp_sd_px``: the geometry maps' stated uncertainty against their error on simulated lenses.

For the two lenses of ``bench_geometry.py`` (models/triplet-distortion.json: distortion changing with z and lateral
colour; the same lens without distortion) and several noise seeds, it renders a ChArUco stack (9 frames, -120 …
40 µm, z_ref 0), measures the board's corners (``measure_geometry_map``) and compares ``warp_px`` with the truth's
on a 33 x 25 grid over the frame, every channel, every z but the reference channel's z_ref (where the map is the
identity by definition). Reported per run: the worst RMS error over the field at any z, the mean sd, the RMS of
error / sd per axis (1 for an honest sd) and the fraction of points inside ±1.96 sd (0.95 for an honest sd).

    PYTHONPATH=$PWD python benchmarks/bench_warp_sd.py --seeds 1,2,3 [--size 480x360]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import md_table  # noqa: E402
from bench_geometry import lenses  # noqa: E402


def coverage(gmap, truth, z_um) -> dict:
    w, h = truth.image_size_px
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 25))
    zs, worst, sds = [], 0.0, []
    for c in gmap.channels:
        for z in z_um:
            if c == gmap.reference_channel and abs(z - gmap.z_ref_um) < 1e-9:
                continue
            tx, ty = truth.warp_px(xs, ys, z, c)
            fx, fy = gmap.warp_px(xs, ys, z, c)
            sx, sy = gmap.warp_sd_px(xs, ys, z, c)
            zs += [((fx - tx) / sx).ravel(), ((fy - ty) / sy).ravel()]
            worst = max(worst, float(np.sqrt(np.mean((fx - tx) ** 2 + (fy - ty) ** 2))))
            sds.append(float(np.sqrt(np.mean(sx ** 2 + sy ** 2))))
    zz = np.concatenate(zs)
    return {"worst_rms_px": worst, "mean_sd_px": float(np.mean(sds)), "rms_z": float(np.sqrt(np.mean(zz ** 2))),
            "cover95": float(np.mean(np.abs(zz) < 1.96))}


def main(argv=None) -> int:
    from fieldcal.measure.charuco import measure_geometry_map
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.simulate.truth import TruthProfile

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="480x360", help="render size WxH (default 480x360)")
    ap.add_argument("--seeds", default="1,2,3", help="noise seeds (default 1,2,3)")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    z = np.arange(-120.0, 40.0 + 1e-9, 20.0)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_warp_sd-") as tmp:
        for label, spec in lenses().items():
            spec = spec.with_sensor_size(*size)
            for seed in (int(s) for s in args.seeds.split(",")):
                st = simulate_stack(spec, Path(tmp) / "stack", z, scene="charuco", seed=seed, progress=False,
                                    overwrite=True)
                gmap = measure_geometry_map(st, 0.0, source="charuco")
                rows.append({"lens": label, "seed": seed,
                             **coverage(gmap, TruthProfile(spec, *size, z_ref_um=gmap.z_ref_um), z)})
                print(rows[-1], flush=True)
    print("\n".join(md_table(rows, [("lens", "lens", ""), ("seed", "seed", "d"),
                                    ("worst RMS error (px)", "worst_rms_px", ".4f"),
                                    ("mean warp_sd (px)", "mean_sd_px", ".4f"), ("RMS error/sd", "rms_z", ".2f"),
                                    ("inside ±1.96 sd", "cover95", ".3f")])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
