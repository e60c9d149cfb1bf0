"""Traced best focus of the paper's triplet vs models/triplet-uncorrected.json (the table in docs/raytrace.md).

    python benchmarks/bench_raytrace.py            # 9 heights x R, G, B + on-axis tolerance (~2-3 min)
    python benchmarks/bench_raytrace.py --quick    # 3 heights, G only (~15 s)

Prints markdown tables: traced best focus (mean of T and S MTF at 80 cy/mm) per channel and height, the model's
value and the difference, T - S, the traced peak MTF, a least-squares refit of the model's polynomial, and the
through-focus tolerance on axis at 587.6 nm.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fieldcal.simulate.lens import LensSpec  # noqa: E402
from fieldcal.raytrace.bestfocus import SearchSettings, trace_focus_table, through_focus_tolerance_um  # noqa: E402
from fieldcal.raytrace.build import compare_with_spec, fit_even_polynomial  # noqa: E402
from fieldcal.raytrace.prescription import load_prescription  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3 heights, G only, no tolerance run")
    ap.add_argument("--fs", type=float, default=80.0)
    args = ap.parse_args(argv)
    rx = load_prescription(REPO / "models" / "triplet-uncorrected.prescription.csv")
    model = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    heights = np.linspace(0, 3.6, 3 if args.quick else 9)
    channels = {"G": 546.1} if args.quick else {"R": 656.3, "G": 546.1, "B": 486.1}
    t0 = time.time()
    table = trace_focus_table(rx, heights, channels, 2.0, SearchSettings(fs_cyc_per_mm=args.fs))
    cmp = {(r["channel"], r["h_mm"]): r for r in compare_with_spec(table, model)}
    print(f"Traced best focus, µm from the stated image plane (peak of the mean T/S MTF at {args.fs:g} cy/mm); "
          "model = models/triplet-uncorrected.json\n")
    print("| h (mm) | " + " | ".join(f"{c} traced | {c} model | {c} diff | {c} T−S | {c} peak MTF" for c in channels) + " |")
    print("| --- " * (1 + 5 * len(channels)) + "|")
    for h in heights:
        cells = []
        for c in channels:
            p = table.get(c, float(h))
            r = cmp[(c, float(h))]
            cells += [f"{p.z_um:.1f}", f"{r['model_um']:.1f}", f"{r['diff_um']:+.1f}",
                      f"{p.z_tangential_um - p.z_sagittal_um:+.1f}", f"{p.peak_mtf:.3f}"]
        print(f"| {h:.2f} | " + " | ".join(cells) + " |")
    z = np.concatenate([table.column(c) for c in channels])
    print(f"\nrange D over the traced heights and channels: {np.ptp(z):.1f} µm")
    print("\nLeast-squares refit z = a0 + a1 rho^2 + a2 rho^4 through the traced heights:\n")
    print("| channel | a0 (µm) | a1 (µm) | a2 (µm) | RMS (µm) | model a0, a1, a2 |")
    print("| --- | --- | --- | --- | --- | --- |")
    for c in channels:
        hs = np.array(sorted(p.h_mm for p in table.points if p.channel == c))
        a0, (a1, a2), rms = fit_even_polynomial(hs, table.column(c), 3.6, 2)
        m = model.channel(c)
        print(f"| {c} | {a0:.3f} | {a1:.3f} | {a2:.3f} | {rms:.2f} | {m.focus_offset_um}, "
              f"{', '.join(str(v) for v in m.curvature_um)} |")
    if not args.quick:
        zb, lo, hi = through_focus_tolerance_um(rx, 587.56, 2.0, args.fs, 0.05)
        print(f"\nOn axis, 587.6 nm: best focus {zb:+.2f} µm; MTF at {args.fs:g} cy/mm within 5% of its peak "
              f"from {lo - zb:+.2f} to {hi - zb:+.2f} µm around it ({lo:+.2f} to {hi:+.2f} µm from the stated plane)")
    print(f"\n({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
