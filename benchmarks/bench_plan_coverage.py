"""Stack plans from calibrated profiles against the simulator's truth: stated vs delivered coverage, N vs optimum,
and the measured tolerance against the true δ(fs, q), for slanted-edge (e-SFR) and texture profiles.

Two stages (the first is the costly one and is cached in ``--work``):

1. ``prepare``: for each lens (the triplet, plus random lenses with F/1.4-F/8, both simulator paths
   ``--optics geometric`` and ``wave``, spherical aberration on some wave lenses) render a ``slanted-edge`` and
   a ``chart`` (texture) stack over the focus range ± 2 δ at 0.5 δ steps and ``fieldcal.calibrate`` each; the
   profile and the lens spec are stored as ``WORK/NAME-SCENE/lens.json`` and ``spec.json``.
2. ``evaluate``: for each stored profile, against ``TruthProfile`` (same optics; on the wave path the true δ is
   the pupil's own through-focus MTF):

   * ``raw δ / true``: the profile's own ``focus_tolerance_um`` (the width as measured, before the plan's
     corrections) over the true δ(fs, q), median over the field and channels;
   * ``plan δ / true``: the tolerance the plan used (after the texture-width correction), same median;
   * the plan at (fs, q = 0.05) with its default coverage target: N against the optimum (the plan drawn from
     the truth: true surfaces and true δ), the stated expected fraction (``coverage.expected_fraction``), and
     the measured fraction of pixels (every pixel, every channel) whose nearest frame is within the true δ.

Usage::

    python benchmarks/bench_plan_coverage.py prepare --work /tmp/plancov --random 6
    python benchmarks/bench_plan_coverage.py evaluate --work /tmp/plancov [--docs]

``--docs`` writes the table into docs/benchmarks.md (section "bench_plan_coverage").
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

LOG_F_RANGE = (math.log(1.4), math.log(8.0))
SA_WAVES = (0.25, 0.8)
Q = 0.05


def lens_set(n_random: int, seed: int, width_px: int):
    """(name, spec, optics) of the triplet on both paths and ``n_random`` random lenses (alternating paths)."""
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.simulate.aberrations import Aberrations
    from fieldcal.simulate.lens import LensSpec

    h = int(round(width_px * 9 / 16))
    out = [("triplet-geo", LensSpec.load(REPO / "models" / "triplet-astigmatic.json").with_sensor_size(width_px, h),
            "geometric"),
           ("triplet-wave", LensSpec.load(REPO / "models" / "triplet-astigmatic.json").with_sensor_size(width_px, h),
            "wave")]
    for k in range(n_random):
        rng = np.random.default_rng(seed + k)
        spec = random_lens(rng, channels=("R", "G", "B") if k % 3 else ("Y",), optics=True)
        rng2 = np.random.default_rng(seed + 7919 * (k + 1))
        spec = replace(spec, f_number=float(math.exp(rng2.uniform(*LOG_F_RANGE))))
        optics = "geometric" if k % 2 == 0 else "wave"
        sa = optics == "wave" and k % 4 == 1
        if sa:
            spec = replace(spec, aberrations=Aberrations(spherical=(float(rng2.uniform(*SA_WAVES)),)))
        spec = spec.with_sensor_size(width_px, int(round(width_px * 3 / 4)))
        out.append((f"random-{k}{'-wave' if optics == 'wave' else '-geo'}{'-sa' if sa else ''}", spec, optics))
    return out


def prepare(work: Path, n_random: int, seed: int, width_px: int, scenes, effort: str, fs_px: float = 0.0,
            step_frac: float = 0.5, min_frames_planned: int = 0, only: str = "") -> None:
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.validation.run import chart_positions_um, default_fs

    work.mkdir(parents=True, exist_ok=True)
    for name, spec, optics in lens_set(n_random, seed, width_px):
        if only and not any(o in name for o in only.split(",")):
            continue
        fs = (default_fs(spec.sensor.pixel_pitch_um) if fs_px <= 0
              else float(round(fs_px / (spec.sensor.pixel_pitch_um / 1000.0))))
        tol = min(spec.focus_tolerance_um(fs, Q, c) for c in spec.channel_names)
        lo, hi = spec.focus_range_um()
        if (hi - lo) / (2.0 * tol) < min_frames_planned - 1:
            print(f"{name}: skipped (D / 2δ = {(hi - lo) / (2 * tol):.1f})", flush=True)
            continue
        z = chart_positions_um(spec, tol, step_frac, 2.0)
        for scene in scenes:
            d = work / f"{name}-{scene}"
            if (d / "lens.json").exists():
                continue
            t0 = time.perf_counter()
            st = simulate_stack(spec, d / "stack", z, scene=scene, seed=seed, progress=False, overwrite=True,
                                optics=optics, fs_cyc_per_mm=fs)
            try:
                prof = calibrate(st.path, effort=effort, fs_cyc_per_mm=fs, q=Q, seed=seed, quiet=True)
            except Exception as e:  # noqa: BLE001 - a benchmark records the failure and goes on
                print(f"{name} {scene}: calibration failed: {e}", flush=True)
                continue
            spec.save(d / "spec.json")
            (d / "meta.json").write_text(json.dumps({"optics": optics, "fs": fs, "scene": scene,
                                                     "step_um": float(z[1] - z[0]), "frames": int(z.size),
                                                     "f_number": spec.f_number,
                                                     "sa": spec.aberrations is not None}))
            prof.save(d / "lens.json")
            print(f"{name} {scene}: {z.size} frames, {time.perf_counter() - t0:.0f} s, "
                  f"{prof.calibration.get('measurement')}", flush=True)


def recalibrate(src: Path, work: Path, effort: str, seed: int, only: str = "") -> None:
    """Calibrate the stacks stored by ``prepare`` in ``src`` again with this code into ``work`` (the stack, spec
    and meta are linked, not copied): the same renders, today's measurement and fit."""
    from fieldcal.calibration.pipeline import calibrate

    for d in sorted(p.parent for p in src.glob("*/meta.json")):
        if only and not any(o in d.name for o in only.split(",")):
            continue
        out = work / d.name
        if (out / "lens.json").exists():
            continue
        out.mkdir(parents=True, exist_ok=True)
        for name in ("stack", "spec.json", "meta.json"):
            if not (out / name).exists():
                (out / name).symlink_to((d / name).resolve())
        meta = json.loads((d / "meta.json").read_text())
        t0 = time.perf_counter()
        try:
            prof = calibrate(d / "stack", effort=effort, fs_cyc_per_mm=float(meta["fs"]), q=Q, seed=seed, quiet=True)
        except Exception as e:  # noqa: BLE001 - a benchmark records the failure and goes on
            print(f"{d.name}: calibration failed: {e}", flush=True)
            continue
        prof.save(out / "lens.json")
        print(f"{d.name}: {time.perf_counter() - t0:.0f} s", flush=True)


def _median_ratio(tol_fn, truth, w: int, h: int, channels, fs: float) -> float:
    gx, gy = np.meshgrid(np.linspace(0.05, 0.95, 15) * (w - 1), np.linspace(0.05, 0.95, 9) * (h - 1))
    return float(np.median(np.concatenate([np.ravel(tol_fn(gx, gy, c)) / np.ravel(
        truth.focus_tolerance_um(gx, gy, c, fs, Q)) for c in channels])))


def evaluate_one(d: Path, coverage: float | None = 0.99, confidence: float | None = None) -> dict:
    from fieldcal.optics import MTFCriterion
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.plan.tolerance import tolerance_um
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import plan_coverage, surface_metrics

    meta = json.loads((d / "meta.json").read_text())
    prof = LensProfile.load(d / "lens.json")
    spec = LensSpec.load(d / "spec.json")
    fs = float(meta["fs"])
    w, h = prof.image_size_px
    truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um, optics=meta["optics"], fs_cyc_per_mm=fs)
    crit = MTFCriterion(fs, Q)
    row = {"case": d.name, "optics": meta["optics"], "scene": meta["scene"], "f_number": float(meta["f_number"]),
           "sa": bool(meta["sa"]), "measurement": prof.calibration.get("measurement"), "fs": fs,
           "step_um": float(meta["step_um"])}
    metrics, _, _ = surface_metrics(prof, truth)
    row["rms_um"] = max(m["rms_um"] for m in metrics.values())
    row["band_cov"] = float(np.mean([m["band_coverage"] for m in metrics.values()]))
    row["raw_ratio"] = _median_ratio(lambda x, y, c: prof.focus_tolerance_um(x, y, c, fs, Q), truth, w, h,
                                     prof.channels, fs)
    row["plan_ratio"] = _median_ratio(lambda x, y, c: tolerance_um(prof, x, y, c, crit)[0], truth, w, h,
                                      prof.channels, fs)
    true_tol = {c: float(np.asarray(truth.focus_tolerance_um(0.0, 0.0, c, fs, Q))) for c in truth.channels}
    row["true_tol_um"] = min(true_tol.values())
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=fs, q=Q, coverage=coverage, confidence=confidence))
    opt = plan_stack(truth, StackRequest(fs_cyc_per_mm=fs, q=Q, coverage=None))
    cov, _ = plan_coverage(np.asarray(plan.frames_um), truth, true_tol, plan.field.refocus_um)
    row.update(n=plan.n_frames, n_fewest=int(plan.stats["fewest_frames"]), n_opt=opt.n_frames,
               stated=float(plan.stats["expected_fraction"]), worst_p=float(plan.stats["probability"]),
               effort=prof.calibration.get("effort", ""),
               measured=float(np.mean([v["coverage"] for v in cov.values()])),
               measured_min=min(v["coverage"] for v in cov.values()))
    return row


COLS = [("case", "case", ""), ("optics", "optics", ""), ("F", "f_number", ".1f"), ("SA", "sa", ""),
        ("surface RMS (µm)", "rms_um", ".2f"), ("90% band cov.", "band_cov", ".2f"), ("true δ (µm)", "true_tol_um", ".1f"),
        ("raw δ / true", "raw_ratio", ".3f"), ("plan δ / true", "plan_ratio", ".3f"),
        ("N / fewest / optimum", "ns", ""), ("stated", "stated", ".4f"), ("worst pixel p", "worst_p", ".4f"),
        ("measured", "measured", ".4f"),
        ("worst channel", "measured_min", ".4f")]


def table(rows) -> str:
    lines = ["| " + " | ".join(c for c, _, _ in COLS) + " |", "|" + " --- |" * len(COLS)]
    for r in rows:
        r = dict(r, ns=f"{r['n']} / {r['n_fewest']} / {r['n_opt']}", sa="yes" if r["sa"] else "")
        lines.append("| " + " | ".join(format(r[k], f) for _, k, f in COLS) + " |")
    return "\n".join(lines)


def width_summary(rows) -> str:
    """Median and spread of the raw width ratio per measurement and optics path."""
    out = ["| measurement | optics | lenses | raw δ / true: median | min-max | relative sd |", "|" + " --- |" * 6]
    for meas in ("esfr", "focus-measure"):
        for optics in ("geometric", "wave", "all"):
            v = np.array([r["raw_ratio"] for r in rows if r["measurement"] == meas
                          and (optics == "all" or r["optics"] == optics)])
            if v.size:
                sd = float(np.std(v, ddof=1) / np.median(v)) if v.size > 1 else math.nan
                out.append(f"| {meas} | {optics} | {v.size} | {np.median(v):.3f} | {v.min():.3f}-{v.max():.3f} | "
                           f"{sd:.3f} |")
    return "\n".join(out)


def write_docs(text: str) -> None:
    doc = REPO / "docs" / "benchmarks.md"
    s = doc.read_text()
    head = "## bench_plan_coverage"
    block = head + "\n\n" + text.strip() + "\n"
    if head in s:
        a = s.index(head)
        # the next section: its heading, or the marker comment some sections open with
        ends = [e for e in (s.find("\n## ", a + len(head)), s.find("\n<!-- bench_", a + len(head))) if e >= 0]
        b = min(ends) if ends else -1
        s = s[:a] + block + ("\n" + s[b + 1:] if b >= 0 else "")
    else:
        s = s.rstrip() + "\n\n" + block
    doc.write_text(s)


def widths(work: Path, fs_factors, scene: str, effort: str, seed: int, only: str = "") -> list[dict]:
    """Raw width ratio (profile δ / true δ) of each stored ``scene`` stack recalibrated at fs = factor x the
    stored fs: how the width-to-δ conversion depends on fs (and, across the stacks, on F-number and optics)."""
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile

    rows = []
    for d in sorted(p.parent for p in work.glob(f"*-{scene}/meta.json")):
        if only and not any(o in d.name for o in only.split(",")):
            continue
        meta = json.loads((d / "meta.json").read_text())
        spec = LensSpec.load(d / "spec.json")
        for k in fs_factors:
            fs = float(meta["fs"]) * k
            try:
                prof = calibrate(d / "stack", effort=effort, fs_cyc_per_mm=fs, q=Q, seed=seed, quiet=True)
            except Exception as e:  # noqa: BLE001 - a benchmark records the failure and goes on
                print(f"{d.name} fs x{k}: {e}", flush=True)
                continue
            w, h = prof.image_size_px
            truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um, optics=meta["optics"], fs_cyc_per_mm=fs)
            ratio = _median_ratio(lambda x, y, c: prof.focus_tolerance_um(x, y, c, fs, Q), truth, w, h,
                                  prof.channels, fs)
            pitch_mm = spec.sensor.pixel_pitch_um / 1000.0
            true_tol = float(np.min([truth.focus_tolerance_um(0.0, 0.0, c, fs, Q) for c in truth.channels]))
            r = {"case": d.name, "optics": meta["optics"], "f_number": float(meta["f_number"]), "sa": meta["sa"],
                 "fs_cyc_per_px": fs * pitch_mm, "step_over_tol": float(meta["step_um"]) / true_tol,
                 "raw_ratio": ratio, "measurement": prof.calibration.get("measurement")}
            rows.append(r)
            print({kk: (round(v, 4) if isinstance(v, float) else v) for kk, v in r.items()}, flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage", choices=("prepare", "recalibrate", "evaluate", "widths"))
    ap.add_argument("--from", dest="src", default=None, help="recalibrate: the prepared folder whose stacks to use")
    ap.add_argument("--work", default="/tmp/plancov", help="folder of the cached stacks and profiles")
    ap.add_argument("--random", type=int, default=6, help="random lenses besides the triplet")
    ap.add_argument("--width", type=int, default=480, help="render width (px)")
    ap.add_argument("--scenes", default="slanted-edge,chart")
    ap.add_argument("--effort", default="standard")
    ap.add_argument("--fs-px", type=float, default=0.0, help="fs in cycles/px (default 0.4 Nyquist)")
    ap.add_argument("--step-frac", type=float, default=0.5, help="scan step as a fraction of the true δ")
    ap.add_argument("--min-frames", type=int, default=0, help="skip lenses whose plan needs fewer frames")
    ap.add_argument("--seed", type=int, default=1300)
    ap.add_argument("--coverage", type=float, default=0.99, help="the plans' coverage target (0: fewest frames)")
    ap.add_argument("--confidence", type=float, default=0.0,
                    help="evaluate: plans with this --confidence (0: none); rows go to rows-cP.json")
    ap.add_argument("--fs-factors", default="0.5,1,1.5", help="widths: fs as multiples of the stored fs")
    ap.add_argument("--widths-scene", default="chart", help="widths: which stored stacks (chart or slanted-edge)")
    ap.add_argument("--only", default="",
                    help="prepare, widths, recalibrate: only lenses/stacks whose name holds one of these (comma list)")
    ap.add_argument("--docs", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args(argv)
    work = Path(args.work)
    if args.stage == "prepare":
        prepare(work, args.random, args.seed, args.width, args.scenes.split(","), args.effort, args.fs_px,
                args.step_frac, args.min_frames, args.only)
        return 0
    if args.stage == "recalibrate":
        recalibrate(Path(args.src), work, args.effort, args.seed, args.only)
        return 0
    if args.stage == "widths":
        rows = widths(work, [float(v) for v in args.fs_factors.split(",")], args.widths_scene, args.effort, args.seed,
                      args.only)
        (work / f"widths-{args.widths_scene}.json").write_text(json.dumps(rows, indent=1))
        return 0
    rows = []
    for d in sorted(p.parent for p in work.glob("*/lens.json")):
        r = evaluate_one(d, None if args.coverage <= 0 else args.coverage,
                         args.confidence if args.confidence > 0 else None)
        rows.append(r)
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    name = "rows.json" if args.confidence <= 0 else f"rows-c{args.confidence:g}.json"
    (work / name).write_text(json.dumps(rows, indent=1))
    conf = f", --confidence {args.confidence:g}" if args.confidence > 0 else ""
    text = (f"`python benchmarks/bench_plan_coverage.py prepare --work W --random {args.random}` then "
            f"`evaluate --work W`: {len(rows)} profiles, q = {Q}, coverage target "
            f"{args.coverage}{conf}.\n\n" + table(rows) + "\n\nWidths as measured (before the plan's correction):\n\n"
            + width_summary(rows))
    print(text)
    if args.docs:
        write_docs(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
