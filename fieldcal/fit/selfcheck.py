"""Leave-tiles-out predictive check: calibrate the band's field terms on the stack itself, and say how well.

Why: the band's terms (kriging discrepancy, block jackknife, misfit F test, common mode) were tuned on
fieldcal's own simulator; on curves it did not make (another renderer, a real lens) they were 1.7x too wide
where the physics was simple and too narrow where it was not. A band that must hold on unknown lenses has to
be checked against the data it came from, with data the fit did not see.

Procedure (all in normalised z units, focus rows of the chosen model):

1. The tiles are split into spatial blocks (the 4 x 3 blocks of the block jackknife). For each block, the
   universal-kriging posterior with the same hyperparameters is rebuilt from the *other* blocks' tiles and
   predicts the block's tiles: mean ``mu_i`` and the variance of the surface there, ``v_i`` (coefficients,
   discrepancy, block jackknife, misfit term; without the common-mode term, which shifts held-out and kept
   tiles alike and so cancels in a tile-to-tile check).
2. A held-out tile is ``y_i ~ N(mu_i, c^2 v_i + n_i)`` with ``n_i = s^2 sigma_i^2 / u_i`` its own noise (the
   fitted scale s and Student-t weight u of the full fit) plus the part of the discrepancy GP that is too
   short to be surface (``(1 - Discrepancy.gp_identified()) tau^2``: a nugget, which the band leaves out). The band scale ``c`` maximises this likelihood with
   a weak log-normal prior on c (sd 1 in ln c: where the tile noise dominates, c stays near 1), c in [1, 8]:
   c > 1 means the surface model misses structure between tiles. (c < 1 is not allowed: see SCALE_BOUNDS.)
3. Self-check: for each block, c is re-estimated *without* that block and its tiles are tested against
   their 90 % predictive interval: the fraction inside is the cross-validated coverage of the calibrated
   band, stored in the profile (``diagnostics.surface.self_check``) and reported; outside 0.8-0.97 warns.

The scale multiplies the non-common part of the surface band (:class:`fieldcal.fit.result.SurfaceFit`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize
from scipy.special import ndtr, ndtri  # not scipy.stats: its import alone is ~0.35 s of a quick calibration

from .discrepancy import JK_BLOCKS, Discrepancy

LEVEL = 0.9
# The scale only widens. A held-out tile's predictive variance is mostly its own noise (REML fitted the noise
# scale to these residuals), so c < 1 is weakly identified: on a random lens whose band already held the truth
# at only 0.74 the check asked for c = 0.62 (coverage 0.74 -> 0.66). c > 1 (held-out blocks predicted worse
# than noise + band allow) is what the check sees reliably: structure the surface model misses.
SCALE_BOUNDS = (1.0, 8.0)
LOG_SCALE_PRIOR_SD = 1.0
WARN_RANGE = (0.8, 0.97)
MIN_BLOCKS = 4
# What the held-out tiles can test, and what they cannot (stored with the check, so a reader of the profile knows
# what its self-check vouches for). Measured on the 40 benchmark lenses (docs/fitting.md "Field-wide terms, term
# by term"): the tiles identify the fitted stage frames on 6 of 40 lenses only (standard effort; on the others
# every frame's posterior sd is above 95 % of its prior), so the stage term is the stated repeatability
# propagated through the fit, not checked.
SEES = "structure between tiles that the band's field-varying terms miss, edge blocks predicted from the interior"
CANNOT_SEE = ("errors shared by every tile of a channel: the fitted stage frames' unidentified part, the breathing "
              "systematic, the sml@fs offset and any bias of the peak estimator; the surface beyond the last tiles "
              "(corners); these are stated as field_wide_share and coverage_range instead")


@dataclass
class SelfCheck:
    """Result of :func:`predictive_check` (JSON-ready via :meth:`to_dict`)."""

    band_scale: float
    coverage: float            # cross-validated: fraction of held-out tiles inside their 90 % interval
    coverage_unscaled: float   # the same with c = 1 (the band terms as estimated before the check)
    n_tiles: int
    n_blocks: int
    z_rms: float               # RMS of the standardised held-out residuals at the final scale
    time_s: float
    status: str = "ok"

    @property
    def warning(self) -> str | None:
        if self.status != "ok":
            return None
        lo, hi = WARN_RANGE
        if not (lo <= self.coverage <= hi):
            side = "narrow" if self.coverage < lo else "wide"
            return (f"held-out tile check: {100 * self.coverage:.0f} % of left-out tiles fall in their 90 % "
                    f"band (expected {100 * lo:.0f}-{100 * hi:.0f} %): the credible bands may be too {side} "
                    "for this lens; use a finer tile grid / more frames, or treat the bands with care")
        return None

    def to_dict(self) -> dict:
        return {"method": "leave-blocks-out predictive check (docs/fitting.md 'Self-checked coverage')",
                "level": LEVEL, "coverage": float(self.coverage), "coverage_unscaled": float(self.coverage_unscaled),
                "band_scale": float(self.band_scale), "n_tiles": int(self.n_tiles), "n_blocks": int(self.n_blocks),
                "z_rms": float(self.z_rms), "time_s": round(float(self.time_s), 4), "status": self.status,
                "warning": self.warning, "sees": SEES, "cannot_see": CANNOT_SEE}


def block_labels(x_hat: np.ndarray, y_hat: np.ndarray, blocks=JK_BLOCKS) -> np.ndarray:
    """Spatial block of each row: the same rectangles of the tile layout as the block jackknife."""
    def span(v, n):
        lo, hi = float(v.min()), float(v.max())
        return np.clip(((v - lo) / max(hi - lo, 1e-12) * n).astype(int), 0, n - 1)
    return span(x_hat, blocks[0]) * blocks[1] + span(y_hat, blocks[1])


def held_out_predictions(disc: Discrepancy) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(residual, surface variance, tile noise variance, block label) of every focus row predicted without its
    block; the tile noise includes the unidentified (sub-spacing) part of the discrepancy GP."""
    lab = block_labels(disc.x_hat, disc.y_hat)
    n = disc.target.size
    resid, v_surf = np.full(n, np.nan), np.full(n, np.nan)
    common = np.zeros(len(disc.model.channels))
    if disc.common_sd is not None:
        common[:disc.common_sd.size] = np.asarray(disc.common_sd, float) ** 2
    for k in np.unique(lab):
        out = lab == k
        keep = ~out
        sub = replace(disc, x_hat=disc.x_hat[keep], y_hat=disc.y_hat[keep], ch_index=disc.ch_index[keep],
                      target=disc.target[keep], noise_var=disc.noise_var[keep], _cache={},
                      stage_c=None if disc.stage_c is None else disc.stage_c[keep])
        for ci in np.unique(disc.ch_index[out]):
            m = out & (disc.ch_index == ci)
            if not np.any(keep & (disc.ch_index == ci)):
                continue
            try:
                # the frames' share moves held-out and kept tiles alike (most of it): left out, as the common mode
                mean, extra = sub.predict(disc.x_hat[m], disc.y_hat[m], int(ci), nuisance=False)
            except (np.linalg.LinAlgError, ValueError):
                continue
            H = sub._design(disc.x_hat[m], disc.y_hat[m], int(ci))
            iid = np.einsum("mp,pq,mq->m", H, disc.iid_cov, H)
            resid[m] = disc.target[m] - mean
            v_surf[m] = np.clip(extra - common[int(ci)], 0.0, None) + iid
    # A GP shorter than a tile spacing is tile noise, not surface (Discrepancy.predict leaves it out of the band):
    # a held-out *tile* still has it, so it joins the tile's noise here. Left out, the check blamed it on the
    # surface and widened the band (c = 2.3 on a random lens whose surface error was 1/7 of the band).
    nugget = (1.0 - disc.gp_identified()) * np.asarray(disc.tau, float)[disc.ch_index] ** 2
    return resid, v_surf, disc.noise_var + nugget, lab


def _fit_scale(r: np.ndarray, v: np.ndarray, nv: np.ndarray) -> float:
    """ML (with a log-normal prior, sd LOG_SCALE_PRIOR_SD) scale c of the surface variance."""
    if r.size == 0:
        return 1.0

    def nlp(lc):
        tot = math.exp(2.0 * lc) * v + nv
        return 0.5 * float(np.sum(np.log(tot) + r * r / tot)) + 0.5 * (lc / LOG_SCALE_PRIOR_SD) ** 2

    lo, hi = (math.log(b) for b in SCALE_BOUNDS)
    res = optimize.minimize_scalar(nlp, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    return float(math.exp(res.x))


def predictive_check(disc: Discrepancy | None) -> SelfCheck:
    """Leave-blocks-out check of a fitted discrepancy's band; see the module docstring."""
    t0 = time.perf_counter()
    if disc is None or disc.target.size < 8:
        return SelfCheck(1.0, math.nan, math.nan, 0, 0, math.nan, 0.0, "skipped: too few tiles")
    r, v, nv, lab = held_out_predictions(disc)
    ok = np.isfinite(r) & np.isfinite(v) & (nv > 0)
    r, v, nv, lab = r[ok], v[ok], nv[ok], lab[ok]
    blocks = np.unique(lab)
    if blocks.size < MIN_BLOCKS:
        return SelfCheck(1.0, math.nan, math.nan, int(r.size), int(blocks.size), math.nan,
                         time.perf_counter() - t0, "skipped: too few blocks of tiles")
    zq = float(ndtri(0.5 + 0.5 * LEVEL))
    c = _fit_scale(r, v, nv)
    inside = np.zeros(r.size, dtype=bool)
    for k in blocks:  # cross-fitted: the scale that tests a block is learned without it
        m = lab == k
        ck = _fit_scale(r[~m], v[~m], nv[~m])
        inside[m] = np.abs(r[m]) <= zq * np.sqrt(ck * ck * v[m] + nv[m])
    unscaled = float(np.mean(np.abs(r) <= zq * np.sqrt(v + nv)))
    z_rms = float(np.sqrt(np.mean(r * r / (c * c * v + nv))))
    return SelfCheck(c, float(inside.mean()), unscaled, int(r.size), int(blocks.size), z_rms,
                     time.perf_counter() - t0)


# Above this share of the band's variance in one field-wide draw the truth coverage of one lens is near 0 or 1
# rather than near the level, however honest the band (docs/fitting.md "Self-checked coverage").
FIELD_WIDE_WARN_SHARE = 0.5
GRID = (16, 12)   # points across x and y of the image where the coverage range is evaluated


def coverage_given_shared(field_var: np.ndarray, shared_var: float, level: float = LEVEL,
                          quantiles=(0.05, 0.5, 0.95)) -> dict:
    """The field coverage a Gaussian band of variance ``field_var + shared_var`` gives when ``shared_var`` is
    one draw ``c`` for the whole field and ``field_var`` varies point to point.

    Coverage(c) = mean over points of P(|c + e_j| <= z sqrt(field_var_j + shared_var)), e_j ~ N(0, field_var_j):
    its mean over c ~ N(0, shared_var) is the level; it falls as |c| grows, so its quantiles are Coverage at the
    matching quantiles of |c|, and its mean is the average over 200 equal-probability values of |c| (a step in
    c when the field part is small, which Gauss-Hermite nodes would miss).
    """
    f = np.clip(np.asarray(field_var, dtype=np.float64).ravel(), 1e-30, None)
    s = max(float(shared_var), 0.0)
    zq = float(ndtri(0.5 + 0.5 * level))
    h = zq * np.sqrt(f + s)
    sf = np.sqrt(f)

    def cov(c):
        c = np.atleast_1d(np.asarray(c, dtype=np.float64))[:, None]
        return np.mean(ndtr((h - c) / sf) - ndtr((-h - c) / sf), axis=1)

    u = (np.arange(200) + 0.5) / 200.0
    mean = float(np.mean(cov(math.sqrt(s) * ndtri(0.5 + 0.5 * u))))
    # coverage at quantile q is coverage at the (1 - q) quantile of |c|
    qs = {f"p{int(round(100 * q)):02d}": float(cov(math.sqrt(s) * float(ndtri(1.0 - 0.5 * q)))[0])
          for q in quantiles}
    share = float(s / np.mean(f + s))
    return {"expected": mean, **qs, "field_wide_share": share}


def field_wide_coverage(surf, shared_extra_sd_um: dict | None = None, level: float = LEVEL) -> dict:
    """What the held-out check cannot see, as a range: the truth coverage this band gives on one lens, given the
    share of its variance that is one draw for the whole field (common mode, stage, breathing and other
    systematics, ``shared_extra_sd_um`` per channel in µm), on a regular grid over the whole image (corners
    included, where the field part is largest), channels pooled.

    Returns the record merged into ``diagnostics.surface.self_check``: ``coverage_expected``, the 5-95 %
    range ``coverage_range`` and ``field_wide_share``; a warning when the share is above
    ``FIELD_WIDE_WARN_SHARE`` (one lens's coverage is then near 0 or 1, not near the level).
    """
    d = getattr(surf, "discrepancy", None)
    if d is None or d.target.size == 0:
        return {}
    zs = float(surf.z_scale_um)
    c = float(getattr(surf, "band_scale", 1.0))
    g = surf.geometry
    gx, gy = np.meshgrid((np.arange(GRID[0]) + 0.5) * g.width_px / GRID[0] - 0.5,
                         (np.arange(GRID[1]) + 0.5) * g.height_px / GRID[1] - 0.5)
    xh, yh = g.normalise(gx.ravel(), gy.ravel())
    fvar, svar = [], []
    for ci, ch in enumerate(d.model.channels):
        if not np.any(d.ch_index == ci):
            continue
        _, extra = d.predict(xh, yh, ci)
        _, bare = d.without_nuisances().predict(xh, yh, ci)
        H = d._design(xh, yh, ci)
        iid = np.einsum("mp,pq,mq->m", H, d.iid_cov, H)
        common = float(d.common_sd[ci]) ** 2 if d.common_sd is not None and ci < d.common_sd.size else 0.0
        # fitted stage frames: one draw for the field, their share by difference
        nuisance = float(np.mean(np.clip(extra - bare, 0.0, None)))
        stage = 0.0 if d.has_stage else (float((getattr(surf, "stage_sd_um", None) or {}).get(ch, 0.0)) / zs) ** 2
        fvar.append((c * c * np.clip(bare - common, 0.0, None) + iid) * zs * zs)
        extra_sd = float((shared_extra_sd_um or {}).get(ch, 0.0))
        svar.append((common + stage + nuisance) * zs * zs + extra_sd ** 2)
    # channels pooled: each channel's points with its own shared variance, averaged over the shared draws
    parts = [coverage_given_shared(f, s, level) for f, s in zip(fvar, svar)]
    if not parts:
        return {}
    avg = lambda k: float(np.mean([p[k] for p in parts]))  # noqa: E731
    rec = {"coverage_expected": avg("expected"), "coverage_range": [avg("p05"), avg("p95")],
           "coverage_median": avg("p50"), "field_wide_share": avg("field_wide_share")}
    if rec["field_wide_share"] > FIELD_WIDE_WARN_SHARE:
        rec["field_wide_warning"] = (
            f"{100 * rec['field_wide_share']:.0f} % of the band's variance is one draw for the whole field "
            "(stage, breathing, common mode): on this lens the band will hold the truth at between "
            f"{100 * rec['coverage_range'][0]:.0f} % and {100 * rec['coverage_range'][1]:.0f} % of the field "
            f"(5-95 %), not at {100 * level:.0f} % everywhere")
    return rec
