"""Planning benchmark: stack-plan counts (optimal vs the paper's placement) and the focal-sweep α trade.

For each simulated lens in models/: D, δ, N (optimal and paper placement), the ceil(D/2δ) optimum, planning
time; then for the paper triplet the α trade (total time T, IPSF MTF at fs, Wiener noise gain) and a sweep plan's
timing. Writes ``results.md``, ``results.json`` and PNG pictures into --out.

    python benchmarks/bench_sweep.py --quick --out /tmp/bench-plan     # small images, seconds
    python benchmarks/bench_sweep.py --out benchmarks/results/plan      # native sensor sizes (the lead runs it)
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small images (320 px wide) for a fast check")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "plan"))
    ap.add_argument("--fs", type=float, default=80.0)
    ap.add_argument("--q", type=float, default=0.05)
    args = ap.parse_args(argv)

    from fieldcal.simulate.lens import LensSpec
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.plan.plots import plot_alpha_trade, plot_masks, plot_stack_plan, plot_windows
    from fieldcal.plan.stack_plan import optimal_uniform_count
    from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep
    from fieldcal.simulate.truth import TruthProfile

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {"quick": args.quick, "fs_cyc_per_mm": args.fs, "q": args.q, "stack": [], "sweep": {}}
    lines = [f"# Planning benchmark ({'quick, 320 px wide' if args.quick else 'native sensor sizes'})", "",
             f"Stack plans at fs = {args.fs:g} cycles/mm, q = {args.q:g}, all channels, whole field.", "",
             "| lens | size (px) | D (µm) | δ (µm) | ceil(D/2δ) | N optimal | N paper | plan time (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for model in ("triplet-uncorrected", "doublet-mono", "singlet-colour"):
        spec = LensSpec.load(REPO / "models" / f"{model}.json")
        w = 320 if args.quick else spec.sensor.width_px
        h = round(w * spec.sensor.height_px / spec.sensor.width_px)
        prof = TruthProfile(spec, w, h)
        t0 = time.perf_counter()
        opt = plan_stack(prof, StackRequest(fs_cyc_per_mm=args.fs, q=args.q))
        dt = time.perf_counter() - t0
        pap = plan_stack(prof, StackRequest(fs_cyc_per_mm=args.fs, q=args.q, placement="paper"))
        tol = min(v["min_um"] for v in opt.tolerance.values())
        row = {"lens": model, "size": [w, h], "D_um": opt.field.range_um, "tolerance_um": tol,
               "ceil_D_2d": optimal_uniform_count(opt.field.range_um, tol), "n_optimal": opt.n_frames,
               "n_paper": pap.n_frames, "plan_s": dt}
        res["stack"].append(row)
        lines.append(f"| {model} | {w}x{h} | {row['D_um']:.1f} | {tol:.2f} | {row['ceil_D_2d']} | {opt.n_frames} | "
                     f"{pap.n_frames} | {dt:.2f} |")
        plot_stack_plan(prof, opt, out / f"stack-{model}.png")

    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    w = 320 if args.quick else 1280
    prof = TruthProfile(spec, w, round(w * 9 / 16))
    t0 = time.perf_counter()
    sw = plan_sweep(prof, SweepRequest(alpha_um=20.0, pixel_exposure_ms=16.0, device="pixel",
                                       scene=__import__("fieldcal.plan", fromlist=["Scene"]).Scene(channels=("G",)),
                                       fs_cyc_per_mm=args.fs))
    dt = time.perf_counter() - t0
    # the noise gain depends on the pixel pitch (Nyquist): take the trade at the native sensor's pitch
    from fieldcal.plan import ipsf as ip
    native = TruthProfile(spec)
    sw.trade = ip.alpha_trade(native, sw.range_um, 16.0, [5, 10, 15, 20, 30, 40, 60], "G", args.fs, 0.01)
    res["sweep"] = {"lens": "triplet-uncorrected", "channel": "G", "size": list(prof.image_size_px),
                    "D_um": sw.range_um, "alpha_um": 20.0, "t_s_ms": 16.0, "T_ms": sw.total_time_ms,
                    "plan_s": dt, "trade": sw.trade}
    lines += ["", f"Focal sweep, paper triplet (G, {prof.image_size_px[0]}x{prof.image_size_px[1]} px), "
              f"D = {sw.range_um:.1f} µm, t_s = 16 ms, planned in {dt:.2f} s; IPSF trade at the native "
              f"{native.pixel_pitch_um:.3f} µm pitch (Nyquist {500 / native.pixel_pitch_um:.0f} cycles/mm), "
              "Wiener NSR 0.01:", "",
              "| α (µm) | T (ms) | v (µm/ms) | IPSF MTF at fs | Wiener noise gain | restored MTF at fs | "
              "noise gain to in-focus MTF (f ≤ fs) |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in sw.trade:
        lines.append(f"| {r['alpha_um']:g} | {r['total_time_ms']:.1f} | {r['velocity_um_per_ms']:.3f} | "
                     f"{r['mtf_at_fs']:.3f} | {r['noise_gain']:.3f} | {r['restored_mtf_at_fs']:.3f} | "
                     f"{r['noise_gain_to_in_focus']:.3f} |")
    plot_alpha_trade(prof, sw, out / "alpha-trade.png")
    plot_masks(sw, out / "sweep-masks.png")
    plot_windows(sw, out / "sweep-windows.png")
    (out / "results.md").write_text("\n".join(lines) + "\n")
    (out / "results.json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
