"""Calibration from slanted-edge stacks against the simulator's truth: surfaces, T/S, bands, plans, cost.

For each lens: ``simulate_stack(..., scene="slanted-edge")`` over the focus range ± 50 µm in ``--step`` µm steps,
``fieldcal.calibrate`` (CPU time and peak RSS of this process), then against ``TruthProfile`` (same optics):

* mean-surface RMS / scan step and 90 % band coverage (``validation.run.surface_metrics``);
* tangential and sagittal surfaces (``profile.best_focus_um(..., orientation=...)`` vs the truth's) on a 15x9 grid;
* a stack plan at (fs, q = 0.05) from the profile (its measured tolerance when it has one): fraction of pixels
  whose nearest frame is within the *true* tolerance, and N against the plan drawn from the truth;
* what an exactly honest band would give (:func:`honest_coverage_odds`): one calibration's field coverage is a
  random number, spread by the surface's field-correlated errors, so the count of lens x channels in 85-95 %
  is compared with the count the profiles' own error model expects there.

Usage::

    python benchmarks/bench_edge_calibration.py --lens models/triplet-astigmatic.json --optics wave \\
        --size 640x360 --step 10
    python benchmarks/bench_edge_calibration.py --random 10 --size 480x270 --step 20 --cache /tmp/edge-stacks

Prints one line per lens and a markdown table (docs/benchmarks.md "bench_edge_calibration" with ``--docs``).
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _ts_errors(profile, truth, w: int, h: int) -> dict[str, float]:
    """Worst-channel RMS / max error (µm) of the tangential and sagittal surfaces on a 15x9 grid."""
    gx, gy = np.meshgrid(np.linspace(0.05, 0.95, 15) * (w - 1), np.linspace(0.05, 0.95, 9) * (h - 1))
    out = {"t_rms_um": 0.0, "s_rms_um": 0.0, "ts_max_um": 0.0}
    for c in profile.channels:
        for o, key in (("tangential", "t_rms_um"), ("sagittal", "s_rms_um")):
            e = profile.best_focus_um(gx, gy, c, orientation=o) - truth.best_focus_um(gx, gy, c, orientation=o)
            out[key] = max(out[key], float(np.sqrt(np.mean(e * e))))
            out["ts_max_um"] = max(out["ts_max_um"], float(np.max(np.abs(e))))
    return out


def honest_coverage_odds(prof, x_px: np.ndarray, y_px: np.ndarray, channel: str, lo: float = 0.85,
                         hi: float = 0.95, seed: int = 0, n_draws: int = 500) -> tuple[float, float, float]:
    """P(field coverage in [lo, hi]), P(above), P(below) of the profile's 90 % band if the band were exactly
    honest: the truth drawn from the profile's own error model — the posterior surface samples (coefficients,
    centre, model average; scaled by the self-check's band scale), one field-wide draw of the common-mode and
    stage terms, and the local discrepancy as a Gaussian field with the fit's Matérn 3/2 kernel at its fitted
    length — and the band's coverage of each draw counted on the grid. Field-correlated errors make one
    calibration cover nearly all or much less than 90 % however honest the band: this is the count the target
    can be judged against (``bench_band_coverage.p_coverage_in_range`` counts the field-wide share alone)."""
    from fieldcal.fit.discrepancy import matern32

    s = prof.surfaces
    d = s.discrepancy
    xf, yf = np.ravel(x_px).astype(np.float64), np.ravel(y_px).astype(np.float64)
    z, _ = s._eval(s.samples[:n_draws], xf, yf, channel, model=s.sample_model)
    z0, _ = s._eval(s.theta_map, xf, yf, channel)
    c = float(s.band_scale)
    draws = s.z_scale_um * c * (z - z0[None, :])
    rng = np.random.default_rng(seed)
    if d is not None:
        ci = s._ch(channel)
        xh, yh = s.geometry.normalise(xf, yf)
        _, extra = s._kriged(xh, yh, ci)
        common = float(d.common_sd[ci]) ** 2 if d.common_sd is not None and ci < d.common_sd.size else 0.0
        stage = 0.0 if d.has_stage else float(s.stage_sd_um.get(channel, 0.0)) / s.z_scale_um
        local = s.z_scale_um * np.sqrt(c * c * np.clip(extra - common, 0.0, None) + s._window_var(xf, yf, channel))
        corr = matern32(np.hypot(xh[:, None] - xh[None, :], yh[:, None] - yh[None, :]) / d.length_scale)
        chol = np.linalg.cholesky(local[:, None] * local[None, :] * corr + 1e-9 * np.eye(xf.size))
        n = draws.shape[0]
        draws = (draws + s.z_scale_um * math.sqrt(common + stage ** 2) * rng.standard_normal((n, 1))
                 + (chol @ rng.standard_normal((xf.size, n))).T)
    blo, bhi = (np.ravel(a) for a in prof.best_focus_interval_um(xf, yf, channel))
    zmap = np.ravel(prof.best_focus_um(xf, yf, channel))
    cov = np.mean((zmap + draws >= blo) & (zmap + draws <= bhi), axis=1)
    return (float(np.mean((cov >= lo) & (cov <= hi))), float(np.mean(cov > hi)), float(np.mean(cov < lo)))


def run_lens(spec, name: str, size, step_um: float, optics: str, effort: str, seed: int, tmp: Path,
             scene: str = "slanted-edge", frames: int = 0) -> dict:
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.simulate.stackgen import simulate_stack, z_grid
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import plan_coverage, surface_metrics, true_tolerances

    w, h = size
    pitch_um = spec.sensor.pixel_pitch_um * spec.sensor.width_px / w
    fs = round(0.25 / (pitch_um / 1000.0), 2)  # 0.25 cycles/px
    lo, hi = spec.focus_range_um()
    if frames > 1:
        step_um = (hi - lo + 100.0) / (frames - 1)
    where = tmp / f"{name}-{optics}-{scene}-{w}x{h}-{step_um:g}um-seed{seed}"
    if (where / "stack.json").exists():  # --cache: the stack this lens, size, step and seed rendered before
        from fieldcal.formats.stack import Stack
        st = Stack.open(where)
    else:
        st = simulate_stack(spec, where, z_grid(lo - 50.0, hi + 50.0, step_um), scene=scene, seed=seed,
                            size=(w, h), progress=False, optics=optics)
    c0 = time.process_time()
    t0 = time.perf_counter()
    prof = calibrate(st.path, effort=effort, fs_cyc_per_mm=fs, seed=seed, quiet=True)
    row = {"lens": name, "frames": len(st), "cal_cpu_s": time.process_time() - c0,
           "cal_wall_s": time.perf_counter() - t0,
           "measurement": prof.calibration.get("measurement")}
    truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um, optics=optics, fs_cyc_per_mm=fs)
    metrics, _, _ = surface_metrics(prof, truth)
    row["rms_step"] = max(m["rms_um"] for m in metrics.values()) / step_um
    row["coverage_min"] = min(m["band_coverage"] for m in metrics.values())
    row["coverage_max"] = max(m["band_coverage"] for m in metrics.values())
    row["coverages"] = [float(m["band_coverage"]) for m in metrics.values()]
    row["hw_over_rms"] = max(m["band_halfwidth_um"] / max(m["rms_um"], 1e-9) for m in metrics.values())
    from fieldcal.validation.run import SURFACE_GRID_PX, _grid
    gxs, gys = _grid(w, h, SURFACE_GRID_PX)
    row["honest"] = [honest_coverage_odds(prof, gxs, gys, c) for c in metrics]
    row["bias_step"] = [float(m["bias_um"]) / step_um for m in metrics.values()]
    # the share of the band's variance that is one draw for the whole field, as the profile states it: one
    # calibration's coverage is a random quantity, spread by that draw (p_coverage_in_range)
    sc = (prof.diagnostics.get("surface") or {}).get("self_check") or {}
    row["field_share"] = float(sc.get("field_wide_share", float("nan")))
    row.update(_ts_errors(prof, truth, w, h))
    q = 0.05
    gx, gy = np.meshgrid(np.linspace(0.05, 0.95, 15) * (w - 1), np.linspace(0.05, 0.95, 9) * (h - 1))
    true_tol = true_tolerances(truth.spec, fs, q)
    # the profile's tolerance (measured widths, or the model) against the true δ(fs, q): > 1 is too wide
    row["tol_ratio"] = float(np.median(np.concatenate(
        [np.ravel(prof.focus_tolerance_um(gx, gy, c, fs, q)) / true_tol[c] for c in prof.channels])))
    row["measured_tol"] = bool(prof.has_measured_tolerance)
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=fs, q=q))
    n_opt = plan_stack(truth, StackRequest(fs_cyc_per_mm=fs, q=q)).n_frames
    cov, _ = plan_coverage(np.asarray(plan.frames_um), truth, true_tol, plan.field.refocus_um)
    row.update(plan_n=plan.n_frames, n_opt=n_opt, plan_within=min(v["coverage"] for v in cov.values()),
               tol_source=next(iter(plan.tolerance.values())).get("source", "") if plan.tolerance else "")
    return row


COLS = [("lens", "lens", ""), ("calibration CPU (s)", "cal_cpu_s", ".1f"), ("surface RMS / step", "rms_step", ".3f"),
        ("90% band coverage per channel", "cov", ""), ("field-wide share", "field_share", ".2f"), ("T RMS (µm)", "t_rms_um", ".2f"), ("S RMS (µm)", "s_rms_um", ".2f"),
        ("T/S max (µm)", "ts_max_um", ".2f"), ("plan N / optimum", "n", ""),
        ("δ profile / true (median)", "tol_ratio", ".3f"), ("pixels within true δ", "plan_within", ".4f")]


def table(rows) -> str:
    lines = ["| " + " | ".join(c for c, _, _ in COLS) + " |", "|" + " --- |" * len(COLS)]
    for r in rows:
        r = dict(r, cov=" / ".join(f"{c:.2f}" for c in r["coverages"]), n=f"{r['plan_n']} / {r['n_opt']}")
        lines.append("| " + " | ".join(format(r[k], f) for _, k, f in COLS) + " |")
    return "\n".join(lines)


def summary(rows, lo: float = 0.85, hi: float = 0.95) -> str:
    """Band coverage over every lens x channel: mean, how many in [lo, hi] against the number an honest band
    with the profiles' stated field-wide shares would put there, and the worst surface and tolerance."""
    from bench_band_coverage import p_coverage_in_range

    cov = np.concatenate([r["coverages"] for r in rows])
    honest = sum(len(r["coverages"]) * p_coverage_in_range(r["field_share"], lo, hi)
                 for r in rows if np.isfinite(r["field_share"]))
    odds = np.sum([o for r in rows for o in r.get("honest", [])], axis=0) if rows[0].get("honest") else None
    joint = (f"; an exactly honest band, the profiles' own joint error model: {odds[0]:.1f} in range, {odds[1]:.1f} "
             f"above, {odds[2]:.1f} below" if odds is not None else "")
    tol = [r["tol_ratio"] for r in rows]
    return (f"{len(rows)} lenses x channels = {cov.size}: 90 % band coverage mean {cov.mean():.3f}, median "
            f"{np.median(cov):.3f}, {int(np.sum((cov >= lo) & (cov <= hi)))} in [{lo}, {hi}] (an honest band "
            f"with these field-wide shares: {honest:.1f}), {int(np.sum(cov < lo))} below, "
            f"{int(np.sum(cov > hi))} above{joint}; surface RMS / step worst {max(r['rms_step'] for r in rows):.3f}, "
            f"mean {np.mean([r['rms_step'] for r in rows]):.3f}; band half-width / RMS worst "
            f"{max(r.get('hw_over_rms', float('nan')) for r in rows):.2f}; δ profile / true "
            f"{min(tol):.3f}-{max(tol):.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lens", action="append", default=[], help="lens spec(s) (default models/triplet-astigmatic.json)")
    ap.add_argument("--random", type=int, default=0, help="also this many random_lens(optics=True) lenses")
    ap.add_argument("--optics", default="geometric", choices=("geometric", "wave"))
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--step", type=float, default=20.0, help="scan step (µm)")
    ap.add_argument("--frames", type=int, default=0,
                    help="instead of --step: this many frames over the focus range ± 50 µm")
    ap.add_argument("--effort", default="standard")
    ap.add_argument("--scene", default="slanted-edge", help="slanted-edge, or chart for the texture path")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default="", help="keep the rendered stacks in this folder and reuse them "
                                                 "(keyed by lens name, optics, scene, size, step and seed)")
    args = ap.parse_args(argv)
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.simulate.lens import LensSpec

    size = tuple(int(v) for v in args.size.split("x"))
    lenses = [(Path(p).stem, LensSpec.load(p)) for p in (args.lens or [REPO / "models" / "triplet-astigmatic.json"])]
    rng = np.random.default_rng(args.seed)
    lenses += [(f"random-{i}", random_lens(rng, optics=True)) for i in range(args.random)]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-edge-") as tmp:
        where = Path(args.cache) if args.cache else Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for name, spec in lenses:
            r = run_lens(spec, name, size, args.step, args.optics, args.effort, args.seed, where, args.scene,
                        args.frames)
            rows.append(r)
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    # the whole process: rendering the stack included (an upper bound for the calibration)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    print(table(rows))
    print(summary(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
