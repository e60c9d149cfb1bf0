"""fieldcal's profile against the clean-room truth, with the calls a user makes (LensProfile methods and the
stack plan). Every figure is over the truth's nodes x channels (the nodes include the frame's corners)."""

from __future__ import annotations

import numpy as np


def truth_mean(truth: dict, ch: str, chart: str) -> tuple[np.ndarray, np.ndarray]:
    """(best focus, δ) the profile's mean surface claims: the isotropic MTF(fs) peak on texture; on edges
    fieldcal's mean surface is the midpoint of the T and S peaks (docs/measurement.md), δ the narrower."""
    t = truth[ch]
    if chart == "texture":
        return t["iso"]["z_best_um"], t["iso"]["delta_um"]
    return 0.5 * (t["T"]["z_best_um"] + t["S"]["z_best_um"]), np.minimum(t["T"]["delta_um"], t["S"]["delta_um"])


def greedy_cover_count(lo: np.ndarray, hi: np.ndarray) -> int:
    """Fewest points that hit every interval [lo, hi] (interval stabbing: sort by right end, greedy)."""
    order = np.argsort(hi)
    n, last = 0, -np.inf
    for i in order:
        if lo[i] > last:
            n += 1
            last = hi[i]
    return n


def evaluate_profile(prof, truth: dict, xs: np.ndarray, ys: np.ndarray, chart: str, step_um: float,
                     fs_cyc_per_mm: float, q: float) -> dict:
    """Surface error, band coverage, self-check, tolerance ratio and a stack plan's true coverage."""
    from fieldcal.plan import StackRequest, plan_stack

    X, Y = np.meshgrid(xs, ys)
    chans = list(prof.channels)
    err, inside, half, tol_ratio, ts_err = [], [], [], [], []
    per_ch = {}
    for c in chans:
        zt, dt = truth_mean(truth, c, chart)
        z = np.asarray(prof.best_focus_um(X, Y, c), dtype=np.float64)
        lo, hi = prof.best_focus_interval_um(X, Y, c, level=0.9)
        e = z - zt
        err.append(e.ravel())
        inside.append(((zt >= lo) & (zt <= hi)).ravel())
        half.append((0.5 * (np.asarray(hi) - np.asarray(lo))).ravel())
        tol = np.asarray(prof.focus_tolerance_um(X, Y, c, fs_cyc_per_mm, q), dtype=np.float64)
        tol_ratio.append((tol / truth[c]["iso"]["delta_um"]).ravel())
        per_ch[c] = {"rms_step": float(np.sqrt(np.mean(e ** 2)) / step_um), "coverage": float(inside[-1].mean()),
                     "bias_um": float(e.mean())}
        if chart == "edges":
            for o, name in (("T", "tangential"), ("S", "sagittal")):
                zo = np.asarray(prof.best_focus_um(X, Y, c, orientation=name), dtype=np.float64)
                ts_err.append((zo - truth[c][o]["z_best_um"]).ravel())
    err = np.concatenate(err)
    inside = np.concatenate(inside)
    half = np.concatenate(half)
    rms = float(np.sqrt(np.mean(err ** 2)))
    sc = ((prof.diagnostics or {}).get("surface") or {}).get("self_check") or {}
    row = {
        "rms_um": rms, "rms_step": rms / step_um, "max_err_step": float(np.abs(err).max() / step_um),
        "bias_step": float(err.mean() / step_um),
        "worst_ch_rms_step": max(v["rms_step"] for v in per_ch.values()),
        "coverage": float(inside.mean()),
        "coverage_ch": [per_ch[c]["coverage"] for c in chans],
        "half_over_rms": float(half.mean() / rms) if rms > 0 else float("nan"),
        "self_check": sc.get("coverage"), "self_check_range": sc.get("coverage_range"),
        "tol_ratio": float(np.median(np.concatenate(tol_ratio))),
        "tol_ratio_min": float(np.min(np.concatenate(tol_ratio))),
        "ts_rms_um": float(np.sqrt(np.mean(np.concatenate(ts_err) ** 2))) if ts_err else None,
        "per_channel": per_ch,
    }
    # a stack plan at (fs, q) with the default coverage target, judged by the isotropic truth
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=fs_cyc_per_mm, q=q))
    frames = np.sort(np.asarray(plan.frames_um, dtype=np.float64))
    ok, los, his = [], [], []
    for c in chans:
        zt, dt = truth[c]["iso"]["z_best_um"].ravel(), truth[c]["iso"]["delta_um"].ravel()
        near = np.min(np.abs(frames[None, :] - zt[:, None]), axis=1)
        ok.append(near <= dt)
        los.append(zt - dt)
        his.append(zt + dt)
    row.update(plan_n=int(plan.n_frames), plan_within=float(np.concatenate(ok).mean()),
               plan_stated=float(plan.stats.get("expected_fraction", float("nan"))),
               plan_opt=greedy_cover_count(np.concatenate(los), np.concatenate(his)))
    return row
