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

``--decompose`` also splits each lens x channel's band against the truth, term by term (:func:`band_terms`,
with ``bench_band_coverage.decompose`` / ``decomposition_summary`` for the piston, tilt and rest), and
``--docs SECTION`` writes the tables into docs/benchmarks.md section ``bench_SECTION``.

Prints one line per lens and a markdown table.
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
    """P(field coverage in [lo, hi]), P(above), P(below) of the profile's 90 % band on one channel if the band were
    exactly honest: the truth drawn from the profile's own joint error model (``selfcheck.coverage_draws`` at
    kappa = 1 on these points) and the band's coverage of each draw counted. Field-correlated errors make one
    calibration cover nearly all or much less than 90 % however honest the band: this is the count the target
    can be judged against (``bench_band_coverage.p_coverage_in_range`` counts the field-wide share alone)."""
    from fieldcal.fit.selfcheck import coverage_draws

    cov, _, _ = coverage_draws(prof, kappa=1.0, n_draws=n_draws, seed=seed, points_px=(x_px, y_px),
                               channels=(channel,))
    return (float(np.mean((cov >= lo) & (cov <= hi))), float(np.mean(cov > hi)), float(np.mean(cov < lo)))


TERMS = ("samples", "gp_local", "kriging_excess", "jackknife_excess", "misfit", "common", "window")


def band_terms(prof, x_px: np.ndarray, y_px: np.ndarray, channel: str) -> dict[str, np.ndarray]:
    """The variance (µm², per point) each term puts into the profile's band, as ``SurfaceFit._sample_surfaces``
    assembles it: the posterior samples about the MAP (coefficients, centre, model average, Student-t),
    the discrepancy GP's local variance, the kriging coefficient variance beyond the independent-row one, what
    the block jackknife adds where it exceeds the kriging variance (the pointwise maximum), the misfit term,
    the common mode and the tile-window systematic. Their sum is the band's variance at the points (to the
    sampling of the band's quantiles)."""
    from scipy.linalg import solve_triangular

    s = prof.surfaces
    d = s.discrepancy
    ci = s._ch(channel)
    xf, yf = np.ravel(x_px).astype(np.float64), np.ravel(y_px).astype(np.float64)
    xh, yh = s.geometry.normalise(xf, yf)
    zs2, c2 = float(s.z_scale_um) ** 2, float(s.band_scale) ** 2
    z, _ = s._eval(s.samples, xf, yf, channel, model=s.sample_model)
    z0, _ = s._eval(s.theta_map, xf, yf, channel)
    out = {t: np.zeros(xf.size) for t in TERMS}
    out["samples"] = c2 * zs2 * np.var(z - z0, axis=0)
    if d is None:
        return out
    st = d._state()
    p = st["p"]
    H = d._design(xh, yh, ci)
    Ha = np.hstack([H, np.zeros((H.shape[0], st["beta"].size - p))])
    kc = np.einsum("mp,pq,mq->m", H, st["bare_cov"], H)
    local = np.zeros(xf.size)
    if ci in st["chol"] and d.tau[ci] > 0:
        m = d.ch_index == ci
        ks = d._kernel_rows(xh, yh, ci)
        v = solve_triangular(st["chol"][ci][0], ks.T, lower=True)
        r = (Ha - ks @ st["kinv_x"][m])[:, :p]
        local = d.gp_identified() * np.clip(d.tau[ci] ** 2 - np.sum(v * v, axis=0), 0.0, None)
        kc = np.einsum("mp,pq,mq->m", r, st["bare_cov"], r)
    jk = np.einsum("mp,pq,mq->m", H, d.jk_cov, H) if d.jk_cov is not None else np.zeros(xf.size)
    iid = np.einsum("mp,pq,mq->m", H, d.iid_cov, H)
    mis = np.zeros(xf.size)
    if d.rich_model is not None and d.misfit_scale > 0:
        hr = d.rich_model.design(xh, yh, np.full(xh.size, ci), np.zeros(xh.size, np.int64), d.centre)
        mis = d.misfit_scale * np.clip(np.einsum("mp,pq,mq->m", hr, d.rich_cov, hr) - iid, 0.0, None)
        covered = s.model_average_covered(z, xh, yh, ci)  # what the model average states already (predict)
        if covered is not None:
            mis = np.clip(mis - covered, 0.0, None)
    # predict(): clip(max(local + kc, local + jk) - iid, 0), split in the order local, kriging, jackknife
    tot = np.clip(np.maximum(local + kc, local + jk) - iid, 0.0, None)
    out["gp_local"] = np.minimum(local, tot)
    out["kriging_excess"] = np.minimum(np.clip(kc - iid, 0.0, None), tot - out["gp_local"])
    out["jackknife_excess"] = tot - out["gp_local"] - out["kriging_excess"]
    out = {k: (c2 * zs2 * v if k in ("gp_local", "kriging_excess", "jackknife_excess") else v) for k, v in out.items()}
    out["misfit"] = c2 * zs2 * mis
    out["common"] = np.full(xf.size, zs2 * float(d.common_sd[ci]) ** 2 if d.common_sd is not None else 0.0)
    out["window"] = zs2 * np.broadcast_to(s._window_var(xf, yf, channel), xf.shape)
    return out


def rows_piston(prof, truth, channel: str) -> tuple[float, float]:
    """(inverse-variance mean of the fitted rows' error against the truth at their own positions, its sd from
    the rows' fitted noise alone) in µm: a field-wide error of the measurement shows as the first exceeding
    the second, before any surface is fitted."""
    s = prof.surfaces
    d = s.discrepancy
    ci = s._ch(channel)
    m = d.ch_index == ci
    g = s.geometry
    x = d.x_hat[m] * g.half_diagonal_px + g.centre_px[0]
    y = d.y_hat[m] * g.half_diagonal_px + g.centre_px[1]
    err = s.z_centre_um + s.z_scale_um * d.target[m] - np.asarray(truth.best_focus_um(x, y, channel))
    w = 1.0 / (d.noise_var[m] * float(s.z_scale_um) ** 2)
    return float(np.sum(w * err) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w)))


def run_lens(spec, name: str, size, step_um: float, optics: str, effort: str, seed: int, tmp: Path,
             scene: str = "slanted-edge", frames: int = 0, decompose_band: bool = False) -> dict:
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.simulate.stackgen import simulate_stack, z_grid
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import plan_coverage, surface_metrics, true_tolerances

    w, h = size
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
    # 0.25 cycles per pixel of the stack as rendered: its pitch keeps the sensor's field at this size (a 4:3
    # sensor rendered 16:9 has a coarser pitch than width / w says; until session 10 the bench used the latter,
    # and its random lenses were calibrated at 0.333 cycles/px)
    fs = round(0.25 / (float(st.pixel_pitch_um) / 1000.0), 2)
    c0 = time.process_time()
    t0 = time.perf_counter()
    prof = calibrate(st.path, effort=effort, fs_cyc_per_mm=fs, seed=seed, quiet=True)
    row = {"lens": name, "frames": len(st), "cal_cpu_s": time.process_time() - c0, "step_um": float(step_um),
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
    if decompose_band and prof.surfaces.discrepancy is not None:
        from bench_band_coverage import decompose
        lens = {"spec": spec, "fs": fs, "optics": optics, "stage_backlash_um": 0.0, "stage_scale_error": 0.0}
        row.update(decompose(prof, lens))
        terms = [band_terms(prof, gxs, gys, c) for c in prof.channels]
        row["term_sd_um"] = {t: [float(np.sqrt(np.mean(v[t]))) for v in terms] for t in TERMS}
        row["rows_piston"] = [rows_piston(prof, truth, c) for c in prof.channels]
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


def decomposition_table(rows) -> str:
    """Per lens (channels averaged): the band's sd by term (grid RMS, µm), the true error's piston / tilt / rest
    against the sd the profile states for each (``bench_band_coverage.decompose``), and the rows' own
    field-wide error (:func:`rows_piston`); then the pooled summary (``decomposition_summary``: piston z RMS,
    median |tilt| z, median rest / local sd, ML multiplier of the common mode) and the rows' field-wide error
    split into the part the channels share (frame-level) and the part each channel has alone."""
    from bench_band_coverage import decomposition_summary

    dec = [r for r in rows if "term_sd_um" in r]
    if not dec:
        return ""
    lines = ["| lens | coverage | worst-channel error RMS (µm) | " + " | ".join(f"{t} sd" for t in TERMS)
             + " | piston error (µm) | piston stated sd | rows' field-wide error ± noise se (µm) | rest RMS / local sd |",
             "|" + " --- |" * (len(TERMS) + 7)]
    for r in dec:
        n = len(r["dec_piston_um"])
        ps = [math.sqrt(r["dec_coef_piston_var"][i] + sum(r[f"dec_{t}_var"][i] for t in ("frames", "common", "breathing", "offset"))) for i in range(n)]
        cells = [r["lens"], " / ".join(f"{c:.2f}" for c in r["coverages"]), f"{r['rms_step'] * r['step_um']:.2f}"]
        cells += [f"{np.mean(r['term_sd_um'][t]):.2f}" for t in TERMS]
        cells += [" / ".join(f"{v:+.2f}" for v in r["dec_piston_um"]), " / ".join(f"{v:.2f}" for v in ps),
                  " / ".join(f"{a:+.2f}±{b:.2f}" for a, b in r["rows_piston"]),
                  " / ".join(f"{a / math.sqrt(max(b, 1e-12)):.2f}" for a, b in zip(r["dec_rest_um"], r["dec_local_var"]))]
        lines.append("| " + " | ".join(cells) + " |")
    sm = decomposition_summary(dec)
    rp = np.array([v for r in dec for v in r["rows_piston"]])
    # the rows' field-wide errors: shared by a lens's channels (the frames) or each channel's own
    per_lens = [np.array(r["rows_piston"]) for r in dec]
    shared = np.array([a[:, 0].mean() for a in per_lens])
    own = np.concatenate([a[:, 0] - a[:, 0].mean() for a in per_lens])
    se2 = np.mean(rp[:, 1] ** 2)
    k = np.mean([len(a) for a in per_lens])
    common = np.array([v for r in dec for v in r["term_sd_um"]["common"]])
    excess = math.sqrt(max(np.mean(rp[:, 0] ** 2) - se2, 0.0))
    lines += ["", (f"Pooled ({sm['n']} lens x channels): piston error / stated sd RMS {sm['piston_z_rms']:.2f} (honest 1), "
                   f"median |piston| z {sm['piston_z_med']:.2f} (0.67), median |tilt| z {sm['tilt_z_med']:.2f} (0.67), "
                   f"median rest RMS / local sd {sm['rest_local_med']:.2f} (~1); ML multiplier of the common mode's "
                   f"variance {sm.get('ml_common', float('nan')):.2f} (1 honest, < 1 overstated). The rows' own field-wide "
                   f"error (before any surface): RMS {math.sqrt(np.mean(rp[:, 0] ** 2)):.3f} µm against a noise se of "
                   f"{math.sqrt(se2):.3f} µm, an excess of {excess:.3f} µm (stated common mode {common.mean():.3f} µm); "
                   f"shared by a lens's channels RMS {math.sqrt(np.mean(shared ** 2)):.3f} µm (noise alone "
                   f"{math.sqrt(se2 / k):.3f}), each channel's own RMS {math.sqrt(np.mean(own ** 2) * k / max(k - 1, 1)):.3f} µm "
                   f"(noise alone {math.sqrt(se2):.3f}).")]
    return "\n".join(lines)


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
    ap.add_argument("--decompose", action="store_true", help="split each band against the truth, term by term")
    ap.add_argument("--docs", default="", help="write the tables into docs/benchmarks.md section bench_DOCS")
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
                         args.frames, decompose_band=args.decompose)
            rows.append(r)
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()
                   if not k.startswith("dec_") and k != "term_sd_um"}, flush=True)
    # the whole process: rendering the stack included (an upper bound for the calibration)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    print(table(rows))
    print(summary(rows))
    dec = decomposition_table(rows) if args.decompose else ""
    if dec:
        print(dec)
    if args.docs:
        from _common import write_docs_section
        cmd = "python benchmarks/bench_edge_calibration.py " + " ".join(argv if argv is not None else sys.argv[1:])
        write_docs_section(args.docs, "\n\n".join(x for x in (f"`{cmd}`", table(rows), summary(rows), dec) if x))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
