"""Are two lens profiles the same calibration? Every value of the two lens.json, and every array of their samples
sidecars, compared exactly; only timings (``timing_s``, ``time_*``), the creation date, the stack's path and the
sidecar's file name may differ. For speed work that must not change a result: the same stack calibrated by the
code before and after.

    python benchmarks/same_profile.py before.json after.json      # exit 0 when identical, 1 with the differences
    python benchmarks/same_profile.py a.json b.json --bands       # and, per channel, how far the surfaces and bands moved

``--bands`` is for a change that may move Monte Carlo samples (a sampler's tuning): per channel, on a 17 x 9 grid
over the image, the largest difference of the MAP surface, of the 90 % band's edges, and the range of the ratio
of the bands' half-widths. Compare them with the same figures between two ``--seed`` values of one code.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

IGNORED = {"timing_s", "created_utc", "stack", "file"}


def differences(a, b, path: str = "") -> list[str]:
    """Paths at which two JSON values differ (NaN equals NaN; ignored keys skipped)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k in IGNORED or k.startswith("time_"):
                continue
            if k not in a or k not in b:
                out.append(f"{path}/{k}: only in {'the second' if k not in a else 'the first'}")
            else:
                out += differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    same = a == b or (isinstance(a, float) and isinstance(b, float) and a != a and b != b)
    return [] if same else [f"{path}: {a!r} vs {b!r}"]


def sidecar_differences(pa: Path, a: dict, pb: Path, b: dict) -> list[str]:
    """Arrays of the two samples sidecars that differ (none when neither profile has one)."""
    fa, fb = (d.get("sidecar", {}).get("file") for d in (a, b))
    if not fa and not fb:
        return []
    if not fa or not fb:
        return ["sidecar: only one profile has one"]
    with np.load(pa.parent / fa) as x, np.load(pb.parent / fb) as y:
        if sorted(x.files) != sorted(y.files):
            return [f"sidecar arrays: {sorted(x.files)} vs {sorted(y.files)}"]
        return [f"sidecar/{k}" for k in x.files
                if not np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind in "fc")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first", type=Path)
    ap.add_argument("second", type=Path)
    ap.add_argument("--bands", action="store_true", help="also print how far the surfaces and their bands moved")
    args = ap.parse_args(argv)
    a, b = (json.loads(p.read_text()) for p in (args.first, args.second))
    out = differences(a, b) + sidecar_differences(args.first, a, args.second, b)
    print(f"{len(out)} differences" + "".join(f"\n  {d}" for d in out[:40]))
    if args.bands:
        print("\n".join(band_differences(args.first, args.second)))
    return 1 if out else 0


def band_differences(pa: Path, pb: Path, level: float = 0.9) -> list[str]:
    """Per channel: max |MAP surface difference|, max |band edge difference| (µm) and the range of the ratio of the
    band half-widths (second / first), on a 17 x 9 grid over the image."""
    from fieldcal.profile.lens_profile import LensProfile

    A, B = LensProfile.load(pa), LensProfile.load(pb)
    w, h = A.image_size_px
    x, y = (g.ravel() for g in np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 9)))
    lines = []
    for ch in A.channels:
        za, zb = A.best_focus_um(x, y, ch), B.best_focus_um(x, y, ch)
        (la, ha), (lb, hb) = A.best_focus_interval_um(x, y, ch, level), B.best_focus_interval_um(x, y, ch, level)
        ratio = (hb - lb) / (ha - la)
        lines.append(f"{ch}: MAP surface max |diff| {np.max(np.abs(za - zb)):.3g} µm; band edges max |diff| "
                     f"{max(np.max(np.abs(la - lb)), np.max(np.abs(ha - hb))):.3g} µm (median half-width "
                     f"{np.median(0.5 * (ha - la)):.3g} µm); half-width ratio {ratio.min():.3f}-{ratio.max():.3f}")
    return lines


if __name__ == "__main__":
    sys.exit(main())
