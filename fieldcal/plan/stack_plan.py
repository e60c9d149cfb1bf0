"""Focal-stack plans (paper IV.B, generalised): fewest frames keeping every pixel of every requested channel
within its focus tolerance, in one direction of travel, with per-channel bands of best focus per frame.

How the cover is built (exact up to a bin width):
1. For each channel, sample the MAP surface on a lattice (scene.py) and refine its extremes at full resolution.
2. Cut the channel's whole range of best focus ``[z_min, z_max]`` into bins of width ``w`` (≤ δ_min/50). The
   surface is continuous over a connected ROI, so every value in the range occurs at some pixel — sampled or
   not — and every value must be served. Each bin carries a tolerance ``δ_b``: the smallest tolerance of the
   samples in it and its two neighbours each side, shrunk by the credible half-width under ``--confidence``.
3. The fewest frames serving every value of every bin of every channel is the greedy cover over the continuum
   (cover.min_cover_values): exact for piecewise-constant δ, so with a uniform tolerance N = ceil(D / 2δ);
   a tolerance that varies over the field loses at most its variation across a bin.
4. Uncertainty (docs/planning.md "Coverage under uncertainty"): each sample's true best focus is N(MAP, σ_z²)
   (σ_z from the profile's credible band) and its true δ is N(δ̂, σ_δ²) (the width fit's standard error and the
   measurement's lens-to-lens systematic). For a given N the frames are placed to maximise the smallest margin
   in units of sqrt(σ_z² + σ_δ²) (bisection on t in δ̂ - t·sqrt(...)); N grows from the fewest until the
   expected fraction of pixels within their true δ reaches ``coverage``.
5. Compositing assigns each pixel to the *nearest* frame along z (bands are the Voronoi cells between
   consecutive frames): if any frame is within a pixel's tolerance, the nearest one is too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from ..errors import ParameterError
from ..optics import LensModel, MTFCriterion
from . import cover as cv
from .scene import Scene
from .surfaces import SampledField, sample_field
from .tolerance import (band_halfwidth_um, check_confidence, coverage_probability, expected_mtf_loss,
                        lower_tolerance_um, mtf_loss, sigma_from_halfwidth, tolerance_sd_um, tolerance_um)

from .planfile import PLAN_FORMAT
MAX_BINS = 200_000
# No stage takes more frames than this; it also bounds the O(frames x bins) greedy cover (q -> 0 or fs beyond
# the lens's cut-off would otherwise ask for millions of frames and never return).
MAX_FRAMES = 2_000


@dataclass(frozen=True)
class StackRequest:
    fs_cyc_per_mm: float = 80.0
    q: float = 0.05
    confidence: float | None = None
    # expected fraction of pixels within tolerance the plan must reach under the profile's uncertainty (its
    # surface band and δ's sd): frames are added, one at a time, until it does (None: the fewest frames)
    coverage: float | None = 0.99
    scene: Scene = field(default_factory=Scene)
    max_frames: int | None = None
    max_time_ms: float | None = None
    exposure_ms: float = 20.0
    frame_overhead_ms: float = 0.0
    placement: str = "optimal"        # or "paper": first frame at the on-axis best focus
    direction: str = "+z"              # capture order: increasing z ("+z") or decreasing ("-z")
    grid_step_px: int = 8


@dataclass
class StackPlan:
    """A computed stack plan; :meth:`to_dict` gives the ``fieldcal-plan/1`` document."""

    request: StackRequest
    field: SampledField
    frames_um: np.ndarray            # ascending
    bands: dict[str, list]           # channel -> per ascending frame [lo, hi] or None
    q_used: float
    tolerance: dict[str, dict]
    lower_bound: int
    stats: dict[str, Any]
    warnings: list[str]

    @property
    def n_frames(self) -> int:
        return int(self.frames_um.size)

    def capture_order(self) -> np.ndarray:
        """Indices into the ascending frames, in capture order."""
        idx = np.arange(self.n_frames)
        return idx if self.request.direction == "+z" else idx[::-1]

    def to_dict(self, profile_info: dict | None = None) -> dict:
        r = self.request
        per_frame_ms = r.exposure_ms + r.frame_overhead_ms
        frames = []
        for k, i in enumerate(self.capture_order()):
            frames.append({
                "index": k,
                "z_um": round(float(self.frames_um[i]), 4),
                "exposure_ms": r.exposure_ms,
                "bands": {c: (None if self.bands[c][i] is None else [round(v, 4) for v in self.bands[c][i]])
                          for c in self.field.channels},
            })
        x, y, w, h = self.field.roi
        return {
            "format": PLAN_FORMAT,
            "kind": "stack",
            "profile": profile_info or {},
            "parameters": {
                "fs_cyc_per_mm": r.fs_cyc_per_mm, "q": r.q, "confidence": r.confidence, "coverage": r.coverage,
                "roi": [x, y, w, h], "channels": list(self.field.channels),
                "object_distance_mm": r.scene.object_distance_mm,
                "max_frames": r.max_frames, "max_time_ms": r.max_time_ms,
                "exposure_ms": r.exposure_ms, "frame_overhead_ms": r.frame_overhead_ms,
                "placement": r.placement, "direction": r.direction, "grid_step_px": r.grid_step_px,
            },
            "direction": r.direction,
            "band_rule": "nearest frame: channel c of a pixel takes the frame whose band [lo, hi) holds "
                         "best_focus_um(x, y, c) + refocus_um (the last band is closed)",
            "refocus_um": round(self.field.refocus_um, 4),
            "n_frames": self.n_frames,
            "frames": frames,
            "total_exposure_ms": round(self.n_frames * r.exposure_ms, 4),
            "total_time_ms": round(self.n_frames * per_frame_ms, 4),
            "q_used": round(self.q_used, 6),
            "q_achieved": round(self.stats["worst_mtf_loss"], 6),
            "range_um": {c: [round(s.z_min_um, 4), round(s.z_max_um, 4)] for c, s in self.field.samples.items()},
            "D_um": round(self.field.range_um, 4),
            "tolerance": self.tolerance,
            "lower_bound_frames": self.lower_bound,
            "coverage": {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v)
                         for k, v in self.stats.items()},
            "warnings": self.warnings,
        }


# ----------------------------------------------------------------------------------------- the cover
def _bins(z, dtol, zmin, zmax, width):
    """Bins of best-focus values over the channel's whole range, each with the smallest tolerance near it."""
    span = zmax - zmin
    nb = max(1, int(math.ceil(span / width))) if span > 0 else 1
    edges = zmin + (span / nb) * np.arange(nb + 1)
    edges[-1] = zmax
    b = np.clip(((z - zmin) / (span / nb)).astype(np.int64) if span > 0 else np.zeros(z.size, np.int64), 0, nb - 1)
    dmin = np.full(nb, np.inf)
    np.minimum.at(dmin, b, dtol)
    filled = np.isfinite(dmin)
    if not filled.all():  # empty bins (values between samples): take the smaller tolerance of the neighbours
        idx = np.arange(nb)
        fi = np.flatnonzero(filled)
        left = fi[np.clip(np.searchsorted(fi, idx, side="right") - 1, 0, fi.size - 1)]
        right = fi[np.clip(np.searchsorted(fi, idx, side="left"), 0, fi.size - 1)]
        dmin = np.where(filled, dmin, np.minimum(dmin[left], dmin[right]))
    dmin = ndimage.minimum_filter1d(dmin, size=5, mode="nearest")
    return edges[:-1], edges[1:], dmin


def _cover(fieldd: SampledField, eff: dict, placement: str, anchor: float | None, width: float | None = None,
           limit: int | None = None):
    """Fewest frames serving every bin with the effective tolerances ``eff`` (µm, per sample, > 0).

    ``width``: the bin width (default: a 50th of the smallest tolerance); ``limit``: stop the greedy once it
    needs more than that many frames."""
    if width is None:
        dmin_all = min(float(eff[c].min()) for c in fieldd.samples)
        width = max(dmin_all / 50.0, fieldd.range_um / MAX_BINS, 1e-9)
    parts = [_bins(s.z_um, eff[c], s.z_min_um, s.z_max_um, width) for c, s in fieldd.samples.items()]
    b0, b1, d = (np.concatenate([p[i] for p in parts]) for i in range(3))
    if placement == "paper":
        return cv.anchored_cover_values(b0, b1, d, anchor, limit), width
    return cv.min_cover_values(b0, b1, d, limit), width


def _needs_too_many(fieldd: SampledField, eff: dict) -> float | None:
    """A lower bound on the frames of any cover when it exceeds MAX_FRAMES, else None.

    One frame serves at most ``2 max(δ)`` of a channel's range of best focus, so every cover needs at least
    ``range / (2 max δ)`` frames (compared in floats: a tolerance near 0 must not overflow an int).
    """
    worst = 0.0
    for c, s in fieldd.samples.items():
        dmax = float(np.max(eff[c]))  # > 0: solve() checked that every tolerance exceeds its band
        span = s.z_max_um - s.z_min_um
        if span > 2.0 * dmax * MAX_FRAMES:
            worst = max(worst, span / (2.0 * dmax))
    return worst or None


@dataclass
class _Tolerances:
    """Per channel, per sample: δ̂ (µm), its sd, the tolerance the cover uses (``eff``: δ̂, or its lower credible
    bound under --confidence, minus the band's half-width) and where δ came from."""

    tol: dict
    sd: dict
    eff: dict
    src: dict


def _tolerances(profile, fieldd, crit: MTFCriterion, confidence) -> _Tolerances:
    tols, sds, eff, src = {}, {}, {}, {}
    for c, s in fieldd.samples.items():
        tols[c], src[c] = tolerance_um(profile, s.x, s.y, c, crit)
        sds[c] = tolerance_sd_um(profile, s.x, s.y, c, crit, tols[c])
        low = lower_tolerance_um(tols[c], sds[c], confidence) if confidence is not None else tols[c]
        eff[c] = low - s.u_um
    return _Tolerances(tols, sds, eff, src)


def _surface_sd(profile, fieldd: SampledField, confidence) -> dict:
    """Per channel, per sample: sd (µm) of the true best focus about the MAP (Gaussian matched to the
    profile's credible band at the --confidence level, else at 0.9); 0 for models without a band."""
    level = 0.9 if confidence is None else confidence
    out = {}
    for c, s in fieldd.samples.items():
        u = s.u_um if confidence is not None else band_halfwidth_um(profile, s.x, s.y, c, s.z_um - fieldd.refocus_um,
                                                                    level)
        # float noise of z ± 0 about a refocused z is no uncertainty (it would make the margin bisection move frames)
        u = np.where(np.isfinite(u) & (u > 1e-9 * (1.0 + np.abs(s.z_um))), u, 0.0)
        out[c] = np.asarray(sigma_from_halfwidth(u, level), dtype=np.float64)
    return out


def _expected_fraction(fieldd: SampledField, frames, T: _Tolerances, sig: dict) -> float:
    p_sum, n_px = 0.0, 0
    for c, s in fieldd.samples.items():
        zf = frames[cv.nearest_index(frames, s.z_um)]
        p = coverage_probability(zf, s.z_um, T.tol[c], sig[c], T.sd[c])
        p_sum, n_px = p_sum + float(np.sum(p)), n_px + int(p.size)
    return p_sum / max(n_px, 1)


BISECTION_STEPS = 24


def _balanced_cover(fieldd, T: _Tolerances, spread: dict, n: int, placement: str, anchor, width: float):
    """N frames placed to maximise t, the smallest margin in units of ``spread`` (bisection on t: the cover of
    ``eff - t * spread`` needs at most n frames). Returns (cover, t, bin width, saturated: t reached its top,
    so more frames cannot widen the margin).

    t stops where the smallest tolerance would fall to a quarter of its value (beyond that no cover of n frames
    exists anyway once n is below ~4x the fewest); the bins keep the width of the fewest cover."""
    ratios = [0.75 * T.eff[c][spread[c] > 0] / spread[c][spread[c] > 0] for c in fieldd.samples]
    ratios = [r for r in ratios if r.size]
    if not ratios:
        cov, width = _cover(fieldd, T.eff, placement, anchor, width)
        return cov, 0.0, width, True
    t_hi = min(float(r.min()) for r in ratios)

    def at(t):
        return _cover(fieldd, {c: T.eff[c] - t * spread[c] for c in fieldd.samples}, placement, anchor,
                      width, limit=n)

    top = at(t_hi)
    if top[0].n <= n:
        return top[0], t_hi, top[1], True
    lo, hi = 0.0, t_hi
    best = at(0.0)
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        cm = at(mid)
        if cm[0].n <= n:
            lo, best = mid, cm
        else:
            hi = mid
    return best[0], lo, best[1], False


def _reach_coverage(fieldd, T: _Tolerances, sig: dict, fewest, width, target: float, placement: str, anchor,
                    max_frames: int | None):
    """Add frames to the fewest cover until the expected fraction within the true δ reaches ``target``.

    Returns (cover, bin width, margin t in sd units, expected fraction, warning or None)."""
    spread = {c: np.hypot(sig[c], T.sd[c]) for c in fieldd.samples}
    ef = _expected_fraction(fieldd, fewest.points_um, T, sig)
    if not any(np.any(v > 0) for v in spread.values()):
        return fewest, width, 0.0, ef, None
    limit = min(MAX_FRAMES, max_frames if max_frames is not None else MAX_FRAMES, 2 * fewest.n + 2)
    n, best = fewest.n, None
    while True:
        # the fraction is not monotone in n on a coarse sample grid (clustered values can sit on a band's
        # edge), so every n is tried until the target, the budget or the largest margin is reached
        cov_n, t, w, saturated = _balanced_cover(fieldd, T, spread, n, placement, anchor, width)
        ef = _expected_fraction(fieldd, cov_n.points_um, T, sig)
        if best is None or ef > best[3]:
            best = (cov_n, w, t, ef)
        if ef >= target or n >= limit or saturated:
            break
        n += 1
    warn = None
    if best[3] < target:
        why = (f"the frame budget ({max_frames})" if max_frames is not None and n >= max_frames
               else "the profile's uncertainty (credible band and δ's sd) against its tolerance")
        warn = (f"expected fraction of pixels within tolerance {best[3]:.4f} < the target {target} with "
                f"{best[0].n} frames: limited by {why}")
    return best[0], best[1], best[2], best[3], warn


def _check_request(r: StackRequest):
    crit = MTFCriterion(r.fs_cyc_per_mm, r.q)
    check_confidence(r.confidence)
    if r.coverage is not None:
        try:
            cfr = float(r.coverage)
        except (TypeError, ValueError):
            cfr = math.nan
        if not (0.0 < cfr < 1.0):
            raise ParameterError(f"coverage target {r.coverage!r} must be in (0, 1)", field="coverage",
                                 fix="give the expected fraction of pixels within tolerance, e.g. --coverage 0.99")
    if r.placement not in ("optimal", "paper"):
        raise ParameterError(f"placement {r.placement!r} unknown", field="placement", fix="use optimal or paper")
    if r.direction not in ("+z", "-z"):
        raise ParameterError(f"direction {r.direction!r} unknown", field="direction",
                             fix="use +z (increasing stage position) or -z")
    if not (math.isfinite(r.exposure_ms) and r.exposure_ms > 0):
        raise ParameterError(f"exposure {r.exposure_ms} ms must be > 0", field="exposure_ms", fix="e.g. --exposure-ms 20")
    if not (math.isfinite(r.frame_overhead_ms) and r.frame_overhead_ms >= 0):
        raise ParameterError(f"frame overhead {r.frame_overhead_ms} ms must be >= 0", field="frame_overhead_ms",
                             fix="e.g. --frame-overhead-ms 50 (stage move and settle)")
    max_frames = r.max_frames
    if max_frames is not None and int(max_frames) < 1:
        raise ParameterError(f"max frames {max_frames} must be >= 1", field="max_frames", fix="e.g. --max-frames 20")
    if r.max_time_ms is not None:
        per = r.exposure_ms + r.frame_overhead_ms
        if not (math.isfinite(r.max_time_ms) and r.max_time_ms >= per):
            raise ParameterError(f"max time {r.max_time_ms} ms is shorter than one frame ({per} ms)",
                                 field="max_time_ms", fix=f"allow at least {per} ms or shorten --exposure-ms")
        by_time = int(math.floor(r.max_time_ms / per + 1e-9))
        max_frames = by_time if max_frames is None else min(int(max_frames), by_time)
    return crit, max_frames


def _anchor(profile, fieldd: SampledField) -> float:
    """The paper's first frame: on-axis best focus of G (else the first channel), kept inside the range."""
    ch = "G" if "G" in fieldd.channels else fieldd.channels[0]
    cx, cy = profile.optical_centre_px()
    z = float(np.asarray(profile.best_focus_um(np.array([cx]), np.array([cy]), ch)).ravel()[0]) + fieldd.refocus_um
    s = fieldd.samples[ch]
    return float(np.clip(z, s.z_min_um, s.z_max_um))


def plan_stack(profile: LensModel, request: StackRequest) -> StackPlan:
    """Compute a stack plan for ``profile`` (any :class:`fieldcal.optics.LensModel`)."""
    r = request
    crit, max_frames = _check_request(r)
    fs, q = crit.fs_cyc_per_mm, crit.q
    fieldd = sample_field(profile, r.scene, r.grid_step_px, r.confidence)
    anchor = _anchor(profile, fieldd) if r.placement == "paper" else None
    warnings: list[str] = []

    def solve(qq):
        T = _tolerances(profile, fieldd, replace(crit, q=qq), r.confidence)
        short = {c: float(np.max(-T.eff[c])) for c in fieldd.samples}
        if any(v >= 0 for v in short.values()):
            return None, T, short, None
        if _needs_too_many(fieldd, T.eff) is not None:
            return None, T, short, None
        cov, width = _cover(fieldd, T.eff, r.placement, anchor)
        return cov, T, short, width

    cov, T, short, width = solve(q)
    q_used = q
    if cov is None and max_frames is None and all(v < 0 for v in short.values()):
        need = _needs_too_many(fieldd, T.eff)
        tmax = min(float(np.max(t)) for t in T.tol.values())
        raise ParameterError(
            f"an MTF loss of at most q = {q:g} at fs = {fs:g} cycles/mm leaves a focus tolerance of only "
            f"{tmax:.3g} µm, so covering the {fieldd.range_um:.1f} µm range of best focus needs at least "
            f"{need:.3g} frames (more than {MAX_FRAMES})", field="q",
            fix="allow a larger --q or a lower --fs (below the lens's cut-off), or cap the plan with --max-frames")
    if cov is None:
        if max_frames is None:
            worst = max(short, key=short.get)
            raise ParameterError(
                f"the credible band of channel {worst} is wider than the tolerance (by up to {short[worst]:.2f} µm): "
                f"no frame placement covers every pixel with probability {r.confidence}", field="confidence",
                fix="lower --confidence, allow a larger --q, or recalibrate with a finer stack")
    if max_frames is not None and (cov is None or cov.n > max_frames):
        q_hi = 0.99
        c_hi = solve(q_hi)[0]
        if c_hi is None or c_hi.n > max_frames:
            raise ParameterError(f"even a {q_hi:.0%} MTF loss needs more than {max_frames} frames",
                                 field="max_frames", fix="allow more frames or time, narrow --roi or --channels")
        lo_q, hi_q = q, q_hi
        for _ in range(40):  # smallest q whose cover fits: N(q) is non-increasing in q
            mid = 0.5 * (lo_q + hi_q)
            cm = solve(mid)[0]
            if cm is not None and cm.n <= max_frames:
                hi_q = mid
            else:
                lo_q = mid
            if hi_q - lo_q < 1e-5:
                break
        q_used = hi_q
        cov, T, short, width = solve(q_used)
        warnings.append(f"{max_frames} frames allow an MTF loss of {q_used:.4f} at {fs} cycles/mm, not {q}")

    sig = _surface_sd(profile, fieldd, r.confidence)
    fewest, t_margin = cov.n, 0.0
    if r.coverage is not None:
        chosen, width, t_margin, _, warn = _reach_coverage(fieldd, T, sig, cov, width, float(r.coverage),
                                                           r.placement, anchor, max_frames)
        if warn:
            warnings.append(warn)
    else:
        chosen = cov
    frames = chosen.points_um
    # per-channel bands: Voronoi cells along z clipped to the channel's range
    mids = 0.5 * (frames[1:] + frames[:-1])
    edges = np.concatenate([[-np.inf], mids, [np.inf]])
    bands = {}
    for c, s in fieldd.samples.items():
        bl = []
        for i in range(frames.size):
            lo_b, hi_b = max(edges[i], s.z_min_um), min(edges[i + 1], s.z_max_um)
            flat = s.z_max_um == s.z_min_um and edges[i] <= s.z_min_um < edges[i + 1]
            bl.append([float(lo_b), float(hi_b)] if (lo_b < hi_b or flat) else None)
        bands[c] = bl
    stats = _stats(profile, fieldd, frames, T, sig, replace(crit, q=q_used))
    stats["target_fraction"] = None if r.coverage is None else float(r.coverage)
    stats["fewest_frames"] = int(fewest)
    stats["margin_sd"] = float(t_margin)
    stats["grid_error_bound_um"] = max(s.grid_error_bound_um for s in fieldd.samples.values())
    stats["bin_width_um"] = width
    tol_info = {c: {"source": T.src[c], "min_um": float(T.tol[c].min()), "max_um": float(T.tol[c].max()),
                    "sd_max_um": float(T.sd[c].max())}
                for c in fieldd.channels}
    return StackPlan(r, fieldd, frames, bands, q_used, tol_info, cov.lower_bound, stats, warnings)


def _stats(profile, fieldd, frames, T: _Tolerances, sig: dict, crit: MTFCriterion):
    """Coverage probability and MTF losses on the sample grid under the profile's uncertainty."""
    fno = float(profile.f_number)
    p_min, e_loss, loss_map, margin = 1.0, 0.0, 0.0, np.inf
    p_sum, n_px = 0.0, 0
    for c, s in fieldd.samples.items():
        zf = frames[cv.nearest_index(frames, s.z_um)]
        p = coverage_probability(zf, s.z_um, T.tol[c], sig[c], T.sd[c])
        p_min = min(p_min, float(p.min()))
        p_sum, n_px = p_sum + float(np.sum(p)), n_px + int(p.size)
        loss_map = max(loss_map, float(mtf_loss(zf - s.z_um, T.tol[c], crit, fno).max()))
        e_loss = max(e_loss, float(expected_mtf_loss(zf, s.z_um, T.tol[c], sig[c], crit, fno).max()))
        margin = min(margin, float(np.min(T.tol[c] - np.abs(zf - s.z_um))))
    return {
        "probability": p_min,
        "probability_definition": "smallest per-pixel probability that the assigned frame is within the true "
                                  "tolerance: true best focus Gaussian, matched to the profile's credible band, "
                                  "and true δ Gaussian with the tolerance's sd (1 for a model without uncertainty)",
        # what a measured fraction of in-tolerance pixels is compared with (issue 14): the mean, not the worst
        "expected_fraction": p_sum / max(n_px, 1),
        "expected_fraction_definition": "mean over the sample grid and channels of the per-pixel probability: "
                                        "the expected fraction of pixels whose assigned frame is within tolerance",
        "expected_worst_mtf_loss": e_loss,
        "worst_mtf_loss": loss_map,
        "min_margin_um": margin,
    }


# ------------------------------------------------------------------------------------------ checking
def check_coverage(profile, plan: StackPlan, x, y, channels=None) -> dict[str, float]:
    """Smallest margin δ - |z_frame - z| (µm) per channel at the given pixels, using the *profile's* surfaces and
    tolerance at the plan's fs and q_used, with the nearest-frame rule (≥ 0 means every pixel is covered)."""
    out = {}
    for c in channels or plan.field.channels:
        z = np.asarray(profile.best_focus_um(x, y, c), dtype=np.float64) + plan.field.refocus_um
        zf = plan.frames_um[cv.nearest_index(plan.frames_um, z)]
        tol, _ = tolerance_um(profile, x, y, c, MTFCriterion(plan.request.fs_cyc_per_mm, plan.q_used))
        out[c] = float(np.min(tol - np.abs(zf - z)))
    return out


def paper_stack_count(D_um: float, d_um: float) -> int:
    """The paper's N = 1 + floor(D / 2d) (IV.B, with d the tolerance half-width)."""
    return 1 + int(math.floor(D_um / (2.0 * d_um) + 1e-12))


def optimal_uniform_count(D_um: float, d_um: float) -> int:
    """Fewest frames for a uniform half-width d over a range D: ceil(D / 2d), at least 1."""
    return max(1, int(math.ceil(D_um / (2.0 * d_um) - 1e-12)))
