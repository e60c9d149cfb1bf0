"""Size of a sweep plan's device masks at 4K RGB (issue 17: ≤ 10 MB), against the plan's ``.npz`` sidecar.

The colour singlet (models/singlet-colour.json, strong lateral and axial colour) is planned at 3840x2160 for
the pixel-wise sensor (one start/stop map pair per channel R, G, B, and per Bayer site) and for the LCoS on a
Bayer sensor (one 1-bit PNG per slot); each export is written, loaded back, compared with the plan's arrays
(must be equal) and its files' total size measured. Writes the table into docs/benchmarks.md
(``--docs``) and prints it.

    python benchmarks/bench_device_masks.py --docs                 # 3840x2160 (about a minute, ~2 GB RAM)
    python benchmarks/bench_device_masks.py --size 960x540         # a quick check
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import REPO, write_docs_section


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="3840x2160", help="image size WxH (default 3840x2160)")
    ap.add_argument("--docs", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))

    from fieldcal.plan import device_masks as dm
    from fieldcal.plan import masks as mk
    from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile

    prof = TruthProfile(LensSpec.load(REPO / "models" / "singlet-colour.json"), w, h)
    cases = [
        ("pixelwise, R,G,B planes", dict(device="pixel", clock_us=10.0)),
        ("pixelwise, RGGB sites", dict(device="pixel", clock_us=10.0, cfa="RGGB")),
        ("lcos 16 ms slots, RGGB", dict(device="lcos", cfa="RGGB")),
        ("lcos 4 ms slots, RGGB", dict(device="lcos", cfa="RGGB", slot_ms=4.0)),
    ]
    rows = []
    for label, kw in cases:
        plan = plan_sweep(prof, SweepRequest(alpha_um=20.0, pixel_exposure_ms=16.0, trade_alphas_um=(20.0,), **kw))
        arrays = plan.mask_arrays()
        with tempfile.TemporaryDirectory() as tmp:
            sha = mk.write_npz(Path(tmp) / "plan.masks.npz", arrays)
            npz_mb = (Path(tmp) / "plan.masks.npz").stat().st_size / 1e6
            t0 = time.perf_counter()
            man = dm.export_device_masks(plan.to_dict(masks_sha256=sha), arrays, Path(tmp) / "dev")
            t_export = time.perf_counter() - t0
            t0 = time.perf_counter()
            back = dm.load_device_masks(Path(tmp) / "dev")
            t_load = time.perf_counter() - t0
            on_disk = sum(p.stat().st_size for p in (Path(tmp) / "dev").iterdir())
        keys = ("mask_bits", "mask_shape") if plan.device.name == "lcos" else ("start_tick", "stop_tick")
        exact = all(np.array_equal(back.arrays[k], arrays[k]) for k in keys)
        rows.append({"case": label, "files": len(man["files"]), "slots": plan.n_slots, "mb": on_disk / 1e6,
                     "npz_mb": npz_mb, "export_s": t_export, "load_s": t_load, "exact": exact})
        print(rows[-1], flush=True)
        del plan, arrays, back

    lines = [f"Device mask files of a focal-sweep plan (`fieldcal plan export-masks`) for the colour singlet at "
             f"{w}x{h}, α = 20 µm, t_s = 16 ms, against the plan's `.npz` "
             "sidecar. Files and masks.json included; \"exact\": loaded back, equal to the plan's arrays. "
             "Target (issue 17): ≤ 10 MB at 4K RGB.", "",
             "| case | files | slots | device files (MB) | .npz sidecar (MB) | export (s) | load (s) | exact |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['files'] + 1} | {r['slots'] or '-'} | {r['mb']:.3f} | {r['npz_mb']:.1f} | "
                     f"{r['export_s']:.1f} | {r['load_s']:.1f} | {'yes' if r['exact'] else 'NO'} |")
    lines += ["", "`python benchmarks/bench_device_masks.py --docs` (2-core machine)."]
    text = "## Sweep masks in device formats\n\n" + "\n".join(lines) + "\n"
    print(text)
    if args.docs:
        write_docs_section("device_masks", text)
    return 0 if all(r["exact"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
