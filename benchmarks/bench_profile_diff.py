"""`fieldcal profile diff`: false alarms between two calibrations of one lens, and detection of real changes.

Each trial renders the paper's triplet (``models/triplet-uncorrected.json``) as a small chart stack twice, with
different noise seeds and different scans (the second scan's start offset by a fraction of a step and one frame
longer), calibrates both (quick effort) and compares them with :func:`fieldcal.profile.diff.diff_profiles` at
the 95 % level. Two changed lenses are calibrated from the second scan too and compared with the first
calibration:

* **tilt**: the sensor tilted so that best focus moves by 3 µm at the frame's corner (``tilt_um_per_mm``
  changed by ``3 µm / r_corner`` along the corner's direction);
* **breathing**: the exit pupil moved so that the magnification at the ends of the scan changes by 0.1 %
  (``d m / d z`` changed by ``0.001 / (scan length / 2)``).

Done when (issue #16): no significant difference in >= 90 % of 20 null trials; both changes flagged every time.

Writes a table into docs/benchmarks.md between ``<!-- bench_profile_diff:start -->`` and ``end``.

    python benchmarks/bench_profile_diff.py --trials 3      # smoke run
    python benchmarks/bench_profile_diff.py --docs          # 20 trials (the lead)

Split between two processes (each its own trials and rows file, one table at the end):

    python benchmarks/bench_profile_diff.py --trials 10 --size 320x180 --effort standard --keep K --rows r0.json &
    python benchmarks/bench_profile_diff.py --start 10 --trials 20 --size 320x180 --effort standard --keep K --rows r1.json
    python benchmarks/bench_profile_diff.py --trials 20 --size 320x180 --effort standard --merge r0.json r1.json --docs
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, md_table, write_docs_section  # noqa: E402

NAME = "profile_diff"
LENS = REPO / "models" / "triplet-uncorrected.json"
SIZE = (256, 144)
FS = 16.0                    # below this size's Nyquist (20 cycles/mm at 24.5 µm pixels)
Z_START, Z_STOP, Z_STEP = -400.0, 100.0, 20.0   # the field's best focus -320..-8 µm with margin
TILT_CORNER_UM = 3.0
TILT_PER_MM = 3.0            # the lens spec's unit: µm of best focus per mm on the sensor
BREATHING_CHANGE = 0.001     # change of magnification at the scan's ends


def changed_specs(spec) -> dict:
    """The changed lenses: tilted by 3 µm at the frame's corner, tilted by 3 µm/mm, and breathing 0.1 % more."""
    half_w, half_h = (0.5 * v for v in spec.sensor.size_mm)
    r2 = half_w ** 2 + half_h ** 2
    tx, ty = spec.tilt_um_per_mm
    rate = 1.0 / (spec.exit_pupil_mm * 1000.0) + BREATHING_CHANGE / (0.5 * (Z_STOP - Z_START))
    return {
        "tilt": dataclasses.replace(spec, tilt_um_per_mm=(tx + TILT_CORNER_UM * half_w / r2,
                                                          ty + TILT_CORNER_UM * half_h / r2)),
        "tilt_mm": dataclasses.replace(spec, tilt_um_per_mm=(tx + TILT_PER_MM, ty)),
        "breathing": dataclasses.replace(spec, exit_pupil_mm=1.0 / rate / 1000.0),
    }


def calibrate_one(spec, workdir: Path, name: str, seed: int, z_offset_um: float, extra_frames: int,
                  size=SIZE, effort: str = "quick"):
    """Simulate and calibrate one scan; returns the saved profile's path (reused when it exists: ``--keep``)."""
    import shutil

    import fieldcal
    from fieldcal.simulate.stackgen import simulate_stack, z_grid

    out = workdir / f"{name}.json"
    if out.exists():
        return out
    stack = workdir / name
    z = z_grid(Z_START + z_offset_um, Z_STOP + z_offset_um + extra_frames * Z_STEP, Z_STEP)
    simulate_stack(spec, stack, z, scene="chart", seed=seed, size=tuple(size), progress=False, overwrite=True)
    prof = fieldcal.calibrate(stack, fs_cyc_per_mm=FS, effort=effort, quiet=True)
    prof.save(out)
    shutil.rmtree(stack, ignore_errors=True)
    return out


def trial(k: int, workdir: Path, level: float = 0.95, changes=True, n_null: int = 10000, size=SIZE,
          effort: str = "quick") -> dict:
    """One trial: the same lens twice (null), and the changed lenses against the first calibration.

    ``changes``: True for every changed lens of :func:`changed_specs`, or the names of some, or False.
    """
    from fieldcal.profile import LensProfile
    from fieldcal.profile.diff import diff_profiles
    from fieldcal.simulate.lens import LensSpec

    spec = LensSpec.load(LENS)
    t0 = time.perf_counter()
    offset = Z_STEP * ((k % 4) / 4.0 + 0.125)     # the second scan: another start, one frame longer
    a = LensProfile.load(calibrate_one(spec, workdir, f"a{k}", 1000 + 2 * k, 0.0, 0, size, effort))
    b = LensProfile.load(calibrate_one(spec, workdir, f"b{k}", 1001 + 2 * k, offset, 1, size, effort))
    t_cal = time.perf_counter() - t0
    t1 = time.perf_counter()
    null, _ = diff_profiles(a, b, level=level, n_null=n_null)
    t_diff = time.perf_counter() - t1
    fams = [e for c in null["channels"].values() for e in c["orientations"].values()]
    flagged = [f"{ch}/{o}" for ch, c in null["channels"].items() for o, e in c["orientations"].items()
               if e["significant"]]
    flagged += [f"{ch}/tolerance" for ch, c in null["channels"].items() if (c.get("tolerance") or {}).get("significant")]
    flagged += [f"{ch}/geometry" for ch, g in null["geometry"]["channels"].items() if g["significant"]]
    row = {"trial": k, "null_significant": null["significant"], "null_p": null["p_value"],
           "null_flagged": " ".join(flagged) or "-",
           "null_tile_mode_max_z": max((abs(v["z_score"] or 0.0) for e in fams for v in (e["tile_modes"] or {}).values()),
                                       default=float("nan")),
           "null_max_z": max(c["max_z_score"] for c in null["channels"].values()),
           "null_max_diff_um": max(c["max_abs_diff_um"] for c in null["channels"].values()),
           "time_calibrate_s": t_cal / 2, "time_diff_s": t_diff}
    if changes:
        for label, s in changed_specs(spec).items():
            if changes is not True and label not in changes:
                continue
            c = LensProfile.load(calibrate_one(s, workdir, f"{label}{k}", 1001 + 2 * k, offset, 1, size, effort))
            d, _ = diff_profiles(a, c, level=level, n_null=n_null)
            row[f"{label}_significant"] = d["significant"]
            row[f"{label}_p"] = d["p_value"]
            if label.startswith("tilt"):
                comps = [e["components"] for ch in d["channels"].values() for e in ch["orientations"].values()]
                row[f"{label}_z"] = max(math.hypot(cc["tilt_x_um_per_mm"]["z_score"] or 0.0,
                                               cc["tilt_y_um_per_mm"]["z_score"] or 0.0) for cc in comps)
                tms = [e["tile_modes"] for ch in d["channels"].values() for e in ch["orientations"].values()
                       if e["tile_modes"]]
                row[f"{label}_tile_z"] = max((math.hypot(tm["tilt_x_um_per_mm"]["z_score"] or 0.0,
                                                         tm["tilt_y_um_per_mm"]["z_score"] or 0.0) for tm in tms),
                                             default=float("nan"))
                row[f"{label}_surface_flagged"] = any(ch["significant"] for ch in d["channels"].values())
            else:
                row["breathing_z"] = max(abs(g["statistics"]["breathing_per_um"]["z_score"] or 0.0)
                                         for g in d["geometry"]["channels"].values()
                                         if "breathing_per_um" in g["statistics"])
                row["breathing_geometry_flagged"] = bool(d["geometry"]["significant"])
                st = next(g["statistics"]["breathing_per_um"] for g in null["geometry"]["channels"].values()
                          if "breathing_per_um" in g["statistics"])
                row["breathing_sd_rel"] = st["sd"] / abs(st["a"])
    return row


def run(trials: int, level: float = 0.95, changes: bool = True, quiet: bool = False, on_row=None, size=SIZE,
        effort: str = "quick", keep: str | None = None, start: int = 0) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-profile-diff-") as tmp:
        work = Path(keep) if keep else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for k in range(start, trials):
            try:
                rows.append(trial(k, work, level, changes, size=size, effort=effort))
            except Exception as e:   # a calibration that fails is reported, not a reason to lose the others
                print(f"trial {k}: FAILED ({type(e).__name__}: {e})", flush=True)
                continue
            if not quiet:
                r = rows[-1]
                print(f"trial {k}: null significant={r['null_significant']} p={r['null_p']:.3f}"
                      + (f"; tilt flagged={r['tilt_significant']} (z {r['tilt_z']:.1f}); 3 µm/mm tilt flagged="
                         f"{r['tilt_mm_significant']}; breathing flagged="
                         f"{r['breathing_significant']} (z {r['breathing_z']:.1f})" if changes else ""),
                      flush=True)
            if on_row is not None:
                on_row(rows)
    return rows


def summarise(rows: list[dict], level: float) -> dict:
    n = len(rows)
    out = {"trials": n, "level": level,
           "null_no_difference": sum(not r["null_significant"] for r in rows) / n,
           "time_calibrate_s": float(np.median([r["time_calibrate_s"] for r in rows])),
           "time_diff_s": float(np.median([r["time_diff_s"] for r in rows]))}
    if "tilt_significant" in rows[0]:
        out.update(tilt_flagged=sum(r["tilt_significant"] for r in rows) / n,
                   tilt_min_z=min(r["tilt_z"] for r in rows),
                   tilt_tile_min_z=min(r["tilt_tile_z"] for r in rows),
                   tilt_mm_flagged=sum(r["tilt_mm_significant"] for r in rows) / n,
                   tilt_mm_min_z=min(r["tilt_mm_z"] for r in rows),
                   breathing_flagged=sum(r["breathing_significant"] for r in rows) / n,
                   breathing_geometry_flagged=sum(r["breathing_geometry_flagged"] for r in rows) / n,
                   breathing_min_z=min(r["breathing_z"] for r in rows),
                   breathing_sd_rel=float(np.median([r["breathing_sd_rel"] for r in rows])))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=20, help="number of trials (default 20)")
    ap.add_argument("--level", type=float, default=0.95, help="the diff's level (default 0.95)")
    ap.add_argument("--docs", action="store_true", help="write the section of docs/benchmarks.md")
    ap.add_argument("--size", default="x".join(map(str, SIZE)), help="render size WxH (default 256x144)")
    ap.add_argument("--effort", default="quick", help="calibration effort (default quick)")
    ap.add_argument("--keep", metavar="DIR", help="keep the profiles in DIR (and reuse those already there)")
    ap.add_argument("--start", type=int, default=0,
                    help="first trial (to split the trials between processes; each with its own --rows)")
    ap.add_argument("--rows", metavar="JSON", help="also write the rows (and the wall time) to this file")
    ap.add_argument("--merge", metavar="JSON", nargs="+",
                    help="write the table from the --rows files of split runs instead of running trials")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    args.size_px = tuple(int(v) for v in args.size.lower().split("x"))

    def report(rows, wall=None):
        if not rows:
            return ""
        wall = time.perf_counter() - t0 if wall is None else wall
        text = section(rows, args, wall)
        if args.rows:
            Path(args.rows).write_text(json.dumps({"wall_s": wall, "rows": rows}, default=_json_safe))
        if args.docs and rows:   # after every trial: an interrupted run leaves its trials so far
            write_docs_section(section_name(args), text)
        return text

    if args.merge:   # split runs ran side by side: the wall clock is the longest one's
        parts = [json.loads(Path(f).read_text()) for f in args.merge]
        rows = sorted((r for part in parts for r in part["rows"]), key=lambda r: r["trial"])
        print(report(rows, max(part["wall_s"] for part in parts)))
        return 0
    rows = run(args.trials, args.level, on_row=report, size=args.size_px, effort=args.effort, keep=args.keep,
               start=args.start)
    print(report(rows))
    return 0


def _json_safe(v):
    """numpy scalars in the rows (bool_, float64) as plain Python values."""
    return v.item() if hasattr(v, "item") else str(v)


def section_name(args) -> str:
    """The docs section: the default size and effort keep the historical name; others get their own."""
    size = getattr(args, "size_px", SIZE)
    if tuple(size) == SIZE and args.effort == "quick":
        return NAME
    return f"{NAME}_{size[0]}x{size[1]}_{args.effort}"


def section(rows: list[dict], args, wall: float) -> str:
    s = summarise(rows, args.level)
    size = getattr(args, "size_px", SIZE)
    cols = [("trial", "trial", "d"), ("null: significant", "null_significant", ""), ("null p", "null_p", ".3f"),
            ("null: flagged families", "null_flagged", ""), ("null tile-mode max |z|", "null_tile_mode_max_z", ".1f"),
            ("tilt flagged", "tilt_significant", ""), ("tilt |z| (GLS components)", "tilt_z", ".1f"),
            ("tilt |z| (tile modes)", "tilt_tile_z", ".1f"),
            ("3 µm/mm tilt flagged", "tilt_mm_significant", ""), ("its |z| (tile modes)", "tilt_mm_tile_z", ".1f"),
            ("breathing flagged", "breathing_significant", ""), ("breathing |z|", "breathing_z", ".1f")]
    cmd = (f"python benchmarks/bench_profile_diff.py --trials {args.trials} --size {size[0]}x{size[1]} "
           f"--effort {args.effort} --docs")
    text = "\n".join([
        f"## profile diff: false alarms and detection, {size[0]}x{size[1]} px, {args.effort} effort "
        "(`benchmarks/bench_profile_diff.py`)",
        "",
        f"`{cmd}` ({len(rows)} trials done of {args.trials}, {wall / 60:.1f} min wall clock, "
        f"2 cores shared with other jobs). The triplet at {size[0]}x{size[1]} px, {args.effort} effort, calibrated "
        "twice per trial (different noise seed; the second scan starts a fraction of a step later and is one frame "
        "longer); the changed lenses are calibrated from the second scan's seed and positions and compared "
        "with the first calibration. Level 95 % for the whole diff (every channel, surface, tolerance, geometry). "
        "Trials whose calibration failed are left out (printed by the script).",
        "",
        f"* same lens, **no significant difference in {100 * s['null_no_difference']:.0f} % of {s['trials']} "
        "trials** (target ≥ 90 %; the stated level promises ≥ 95 % if the profiles' uncertainties are honest); "
        "the families that flagged are listed per trial",
        f"* tilt of 3 µm at the frame's corner **flagged in {100 * s['tilt_flagged']:.0f} %** (target 100 %; "
        f"smallest tilt |z| of the tile modes {s['tilt_tile_min_z']:.1f}, of the GLS components of the surface "
        f"difference {s['tilt_min_z']:.1f}; each the two tilt components' z in quadrature)",
        f"* tilt of 3 µm/mm (the lens spec's unit) **flagged in {100 * s['tilt_mm_flagged']:.0f} %**",
        f"* breathing changed by 0.1 % of magnification over the scan **flagged in "
        f"{100 * s['breathing_flagged']:.0f} %** (smallest |z| {s['breathing_min_z']:.1f}; target 100 %)",
        (f"* median time: calibrate {s['time_calibrate_s']:.1f} s, diff {s['time_diff_s']:.1f} s"
         + (" (with `--keep`: a profile already in the directory is reused and its calibration time not measured)"
            if args.keep else "")),
        "",
        *md_table(rows, cols),
    ])
    return text


if __name__ == "__main__":
    sys.exit(main())
