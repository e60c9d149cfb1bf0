"""Dense per-channel geometry maps as a function of (x, y, z): a linear model fitted to point correspondences.

A correspondence says: the scene point at pixel ``p`` of the z_ref geometry (the reference channel's frame at
``z_ref``) is seen at ``q`` in channel ``c`` of the frame at ``z``. The map (docs/geometry.md), in coordinates
normalised about the image centre ``u = (p - centre) / R`` (``R`` the half diagonal in px) and
``t = (z - z_ref) / z_scale``::

    q = p + R sum_j sum_k theta[c, j, k] t^k B_j(u)

with the vector fields ``B_j``: ``scale`` (u), ``shift_x`` (1, 0), ``shift_y`` (0, 1), ``k1`` (u r^2), ``k2``
(u r^4), ``p1`` (2 ux uy, r^2 + 2 uy^2), ``p2`` (r^2 + 2 ux^2, 2 ux uy): magnification (focus breathing), shift,
radial and tangential distortion, each a polynomial in z. The reference channel has no ``k = 0`` term (its
z_ref frame *is* the geometry); the other channels do (lateral colour: a constant scale, plus any constant
difference of distortion or shift). Radial distortion about an off-centre optical axis appears as tangential
terms to first order, so the centre need not be known.

The model is linear in theta: weighted least squares gives the exact Gauss-Markov covariance, scaled by the
residual variance (the per-point sigmas are relative weights), so :meth:`GeometryMap.warp_sd_px` answers every query with an uncertainty. Terms and the degree in
z are chosen per channel by BIC over nested models (error scale profiled out), as for the surfaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..formats import documents
from .data import FitError

GEOMETRY_MAP_FORMAT = documents.format_id("geometry-map")

#: basis vector fields, in nesting order
TERMS = ("scale", "shift_x", "shift_y", "k1", "k2", "p1", "p2")
#: nested term sets tried by model selection
TERM_SETS = (("scale", "shift_x", "shift_y"), ("scale", "shift_x", "shift_y", "k1"),
             ("scale", "shift_x", "shift_y", "k1", "k2"), TERMS)


def basis(term: str, ux, uy):
    """The vector field of one term at normalised positions (ux, uy): (bx, by)."""
    r2 = ux * ux + uy * uy
    if term == "scale":
        return ux, uy
    if term == "shift_x":
        return np.ones_like(ux), np.zeros_like(uy)
    if term == "shift_y":
        return np.zeros_like(ux), np.ones_like(uy)
    if term == "k1":
        return ux * r2, uy * r2
    if term == "k2":
        return ux * r2 * r2, uy * r2 * r2
    if term == "p1":
        return 2.0 * ux * uy, r2 + 2.0 * uy * uy
    if term == "p2":
        return r2 + 2.0 * ux * ux, 2.0 * ux * uy
    raise ValueError(f"unknown geometry term {term!r}")


@dataclass(frozen=True)
class ChannelMap:
    """One channel's map: ``columns`` are (term, power of t); ``coef`` and ``cov`` over them."""

    columns: tuple[tuple[str, int], ...]
    coef: np.ndarray
    cov: np.ndarray
    chi2_dof: float
    n_points: int

    def design(self, ux, uy, t) -> tuple[np.ndarray, np.ndarray]:
        """(..., P) design rows for the x and y displacements (normalised units)."""
        cache = {}
        xs, ys = [], []
        for term, k in self.columns:
            if term not in cache:
                cache[term] = basis(term, ux, uy)
            bx, by = cache[term]
            tk = t ** k
            xs.append(bx * tk)
            ys.append(by * tk)
        return np.stack(xs, axis=-1), np.stack(ys, axis=-1)

    def to_dict(self) -> dict[str, Any]:
        return {"columns": [[t, int(k)] for t, k in self.columns], "coef": self.coef.tolist(),
                "cov": self.cov.tolist(), "chi2_dof": float(self.chi2_dof), "n_points": int(self.n_points)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ChannelMap":
        cols = tuple((str(t), int(k)) for t, k in d["columns"])
        coef = np.asarray(d["coef"], dtype=np.float64).reshape(len(cols))
        cov = np.asarray(d["cov"], dtype=np.float64).reshape(len(cols), len(cols))
        return cls(cols, coef, cov, float(d["chi2_dof"]), int(d.get("n_points", 0)))


@dataclass
class GeometryMap:
    """Per-channel dense geometry maps (z_ref geometry -> frame at z), with covariance."""

    z_ref_um: float
    z_scale_um: float
    centre_px: tuple[float, float]
    norm_px: float
    reference_channel: str
    channels: dict[str, ChannelMap]
    source: str = "charuco"  # "charuco" or "texture": what the correspondences came from
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def _prep(self, x, y, z_um, channel: str):
        if channel not in self.channels:
            raise FitError(f"no geometry map for channel {channel!r} (have {', '.join(self.channels)})",
                           field="channel", fix=f"use one of {', '.join(self.channels)}")
        x, y, z = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64),
                                      np.asarray(z_um, dtype=np.float64))
        ux = (x - self.centre_px[0]) / self.norm_px
        uy = (y - self.centre_px[1]) / self.norm_px
        t = (z - self.z_ref_um) / self.z_scale_um
        return x, y, ux, uy, t, self.channels[channel]

    def warp_px(self, x, y, z_um, channel: str):
        """Where the point at pixel (x, y) of the z_ref geometry appears in ``channel`` of the frame at z."""
        x, y, ux, uy, t, cm = self._prep(x, y, z_um, channel)
        dx, dy = cm.design(ux, uy, t)
        return x + self.norm_px * (dx @ cm.coef), y + self.norm_px * (dy @ cm.coef)

    def warp_sd_px(self, x, y, z_um, channel: str):
        """1-sigma uncertainty (px) of :meth:`warp_px` in x and y, from the fit's covariance."""
        x, y, ux, uy, t, cm = self._prep(x, y, z_um, channel)
        dx, dy = cm.design(ux, uy, t)
        vx = np.einsum("...i,ij,...j->...", dx, cm.cov, dx)
        vy = np.einsum("...i,ij,...j->...", dy, cm.cov, dy)
        return self.norm_px * np.sqrt(np.clip(vx, 0, None)), self.norm_px * np.sqrt(np.clip(vy, 0, None))

    def to_dict(self) -> dict[str, Any]:
        return {"format": GEOMETRY_MAP_FORMAT, "z_ref_um": float(self.z_ref_um), "z_scale_um": float(self.z_scale_um),
                "centre_px": [float(v) for v in self.centre_px], "norm_px": float(self.norm_px),
                "reference_channel": self.reference_channel, "source": self.source,
                "channels": {c: m.to_dict() for c, m in self.channels.items()}, "diagnostics": self.diagnostics}

    @classmethod
    def from_dict(cls, d: dict[str, Any], path=None) -> "GeometryMap":
        from ..errors import SpecError
        if not isinstance(d, dict) or d.get("format") != GEOMETRY_MAP_FORMAT:
            raise SpecError(f"not a {GEOMETRY_MAP_FORMAT} block", path=path, field="geometry_map",
                            fix="write it with GeometryMap.to_dict() (or recalibrate)")
        try:
            chans = {c: ChannelMap.from_dict(v) for c, v in d["channels"].items()}
            return cls(float(d["z_ref_um"]), float(d["z_scale_um"]), tuple(float(v) for v in d["centre_px"]),
                       float(d["norm_px"]), str(d["reference_channel"]), chans, str(d.get("source", "charuco")),
                       dict(d.get("diagnostics", {})))
        except (KeyError, TypeError, ValueError) as e:
            raise SpecError(f"malformed geometry map ({e})", path=path, field="geometry_map",
                            fix="regenerate the profile with `fieldcal calibrate`") from None


@dataclass(frozen=True)
class Correspondences:
    """Point correspondences: reference position ``p`` (z_ref geometry) seen at ``q`` in ``channel`` at ``z_um``.

    ``point_id``: the same scene point across observations (ChArUco corner id), or -1 (texture grid points
    whose reference position is exact by construction). ``sigma_px``: 1-sigma of each q (x and y).
    """

    p_px: np.ndarray
    q_px: np.ndarray
    z_um: np.ndarray
    channel: np.ndarray
    sigma_px: np.ndarray
    point_id: np.ndarray

    def __post_init__(self):
        n = len(self.z_um)
        for name in ("p_px", "q_px"):
            a = getattr(self, name)
            if a.shape != (n, 2) or not np.all(np.isfinite(a)):
                raise FitError(f"'{name}' must be finite and N x 2 with N = {n}", field=name,
                               fix="drop correspondences that were not measured")
        if not (np.all(np.isfinite(self.sigma_px)) and np.all(self.sigma_px > 0)):
            raise FitError("correspondence uncertainties must be finite and > 0", field="sigma_px",
                           fix="give each point a positive 1-sigma (px)")


def _fit_columns(ux, uy, t, dx, dy, w, columns, clusters=None):
    """Weighted LS for one column set; returns (coef, cov, chi2, cond, residuals).

    ``clusters`` (one label per point): the covariance is the cluster-robust sandwich (CR1) over them -- the
    observations of one scene point share its estimator error across frames and channels -- or the classical
    one where that is larger (few clusters make the sandwich itself noisy)."""
    cm = ChannelMap(columns, np.zeros(len(columns)), np.zeros((len(columns),) * 2), 0.0, 0)
    Ax, Ay = cm.design(ux, uy, t)
    A = np.concatenate([Ax, Ay]) * np.concatenate([w, w])[:, None]
    b = np.concatenate([dx, dy]) * np.concatenate([w, w])
    # column equilibration: the conditioning check and the solve see unit-norm columns
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    An = A / norms
    coef_n, *_ = np.linalg.lstsq(An, b, rcond=None)
    r = b - An @ coef_n
    chi2 = float(r @ r)
    dof = max(1, b.size - len(columns))
    cond = float(np.linalg.cond(An))
    # the sigmas are relative weights (corner noise is not known a priori): scale by the residual variance
    bread = np.linalg.pinv(An.T @ An)
    cov_n = bread * (chi2 / dof)
    if clusters is not None:
        cl = np.concatenate([clusters, clusters])
        uniq, inv = np.unique(cl, return_inverse=True)
        g = uniq.size
        if g > len(columns) + 1:
            score = np.zeros((g, An.shape[1]))
            np.add.at(score, inv, An * r[:, None])
            meat = score.T @ score
            cr = bread @ meat @ bread * (g / (g - 1.0)) * ((b.size - 1.0) / dof)
            cov_n = _psd_max(cov_n, cr)
    coef = coef_n / norms
    cov = cov_n / np.outer(norms, norms)
    return coef, cov, chi2, cond, r


def _psd_max(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A covariance at least as large as ``a`` and ``b`` in every direction (the upper envelope of their
    eigen-decomposition in the metric of ``a``)."""
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    ok = w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300)
    if not ok.any():
        return 0.5 * (b + b.T)
    # whiten by a: a -> I on its range, b -> M; the envelope keeps max(1, eig(M)) per direction
    s = v[:, ok] / np.sqrt(w[ok])
    m = s.T @ b @ s
    mw, mv = np.linalg.eigh(0.5 * (m + m.T))
    root = v[:, ok] * np.sqrt(w[ok])
    env = root @ (mv * np.maximum(mw, 1.0)) @ mv.T @ root.T
    return 0.5 * (env + env.T)


def _select_channel(ux, uy, t, dx, dy, w, reference: bool, max_order: int, clusters=None):
    """BIC over nested term sets and z degrees; returns (ChannelMap, table) (AIC is recorded too)."""
    n = 2 * ux.size
    best, table = None, []
    k0 = 1 if reference else 0
    for terms in TERM_SETS:
        for order in range(1, max_order + 1):
            cols = tuple((term, k) for term in terms for k in range(k0, order + 1))
            if n <= len(cols) + 2:
                continue
            coef, cov, chi2, cond, _ = _fit_columns(ux, uy, t, dx, dy, w, cols, clusters)
            fit_term = n * math.log(max(chi2, 1e-300) / n)
            bic = fit_term + len(cols) * math.log(n)
            aic = fit_term + 2.0 * len(cols)
            table.append({"terms": list(terms), "z_order": order, "bic": bic, "aic": aic,
                          "chi2_dof": chi2 / (n - len(cols)), "cond": cond})
            if best is None or bic < best[0]:
                best = (bic, ChannelMap(cols, coef, cov, chi2 / (n - len(cols)), ux.size))
    if best is None:
        raise FitError(f"too few correspondences ({ux.size}) for a geometry map", field="points",
                       fix="measure more chart corners or texture points")
    return best[1], table


def _joint_with_reference(gmap: GeometryMap, corr: Correspondences, p: np.ndarray, keep: np.ndarray, ch: np.ndarray,
                          chans: list[str], ids: np.ndarray) -> tuple[GeometryMap, np.ndarray]:
    """Errors in variables: refit every channel's chosen columns with each corner's reference position a free
    parameter (``p_i + delta_i``), linearised at the current ``p`` (the maps' derivative is within ~1e-2 of the
    identity). The deltas are fixed effects, projected out (Frisch-Waugh-Lovell: weighted demeaning of each
    corner's x and y rows), so the coefficients' covariance is the exact one of the joint problem, with the
    degrees of freedom the positions use. Ignoring the positions' error (they are measurements in the reference
    frame, as noisy as any other) made the maps' sd about half their error against truth."""
    norm, span, cx, cy = gmap.norm_px, gmap.z_scale_um, gmap.centre_px[0], gmap.centre_px[1]
    blocks, start = {}, 0
    for c in chans:
        blocks[c] = slice(start, start + len(gmap.channels[c].columns))
        start += len(gmap.channels[c].columns)
    A_rows, b_rows, w_rows, g_rows = [], [], [], []
    for c in chans:
        m = np.flatnonzero((ch == c) & keep)
        cm = gmap.channels[c]
        ux, uy = (p[m, 0] - cx) / norm, (p[m, 1] - cy) / norm
        dx, dy = cm.design(ux, uy, (corr.z_um[m] - gmap.z_ref_um) / span)
        # per-channel noise scale: the sigmas are relative weights within a channel
        w = norm / corr.sigma_px[m] / math.sqrt(max(cm.chi2_dof, 1e-300))
        for axis, dd in ((0, dx), (1, dy)):
            A = np.zeros((m.size, start))
            A[:, blocks[c]] = dd
            A_rows.append(A)
            b_rows.append((corr.q_px[m, axis] - p[m, axis]) / norm)
            w_rows.append(w)
            g_rows.append(np.where(ids[m] >= 0, 2 * ids[m] + axis, -1))
    A, b, w, grp = (np.concatenate(v) for v in (A_rows, b_rows, w_rows, g_rows))
    Aw, bw = A * w[:, None], b * w
    fe = grp >= 0
    uniq, inv = np.unique(grp[fe], return_inverse=True)
    den = np.bincount(inv, weights=w[fe] ** 2, minlength=uniq.size)

    def within(v):   # residual maker of the weighted group indicators
        v = v.copy()
        s = np.zeros((uniq.size,) + v.shape[1:])
        np.add.at(s, inv, v[fe] * w[fe].reshape((-1,) + (1,) * (v.ndim - 1)))
        v[fe] -= w[fe].reshape((-1,) + (1,) * (v.ndim - 1)) * (s / den.reshape((-1,) + (1,) * (v.ndim - 1)))[inv]
        return v

    At, bt = within(Aw), within(bw)
    norms = np.linalg.norm(At, axis=0)
    norms[norms == 0] = 1.0
    coef_n, *_ = np.linalg.lstsq(At / norms, bt, rcond=None)
    coef = coef_n / norms
    r = bt - At @ coef
    dof = max(1, b.size - start - uniq.size)
    cov = np.linalg.pinv((At / norms).T @ (At / norms)) / np.outer(norms, norms) * (float(r @ r) / dof)
    # the positions' corrections (normalised units), and the new p
    delta = np.zeros(uniq.size)
    np.add.at(delta, inv, w[fe] * (bw[fe] - Aw[fe] @ coef))
    delta /= den
    lut = dict(zip(uniq.tolist(), delta.tolist()))
    p = p.copy()
    for i in np.flatnonzero(ids >= 0):
        for axis in (0, 1):
            p[i, axis] += norm * lut.get(2 * int(ids[i]) + axis, 0.0)
    maps = {}
    for c in chans:
        sl, cm = blocks[c], gmap.channels[c]
        maps[c] = ChannelMap(cm.columns, coef[sl], 0.5 * (cov[sl, sl] + cov[sl, sl].T), cm.chi2_dof, cm.n_points)
    return GeometryMap(gmap.z_ref_um, span, gmap.centre_px, norm, gmap.reference_channel, maps, gmap.source), p


def lack_of_fit(gmap: GeometryMap, corr: Correspondences, p: np.ndarray, keep: np.ndarray,
                ch: np.ndarray) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Per channel, how far the frames depart from the maps' polynomial in z, and the covariance that adds.

    A saturated model gives each frame its own coefficients of the chosen terms (the reference channel none at
    z_ref). Their departures from the polynomial, beyond their own noise, are errors shared by all points of a
    frame that vary with z in a way the polynomial does not follow -- seen on rendered boards as a radial corner
    bias of up to 0.015 px where the field's edge is in focus, the same for every noise seed. Per-point
    residuals cannot show them, and they do not average out over a frame's points. Treated as a random effect
    per frame (method of moments): per term j, ``tau_j^2 = mean_z(delta_zj^2) n / (n - p) - mean_z(var_zj)``
    (``n`` frames, ``p`` powers of z); the polynomial's coefficients of term j then have the added covariance
    ``tau_j^2 (T^T T)^-1``, ``T`` the frames' powers of t. Partial: the frames' effects also reach the
    reference positions (averaged over all frames), which this does not model (synthetic test: error/sd
    RMS 1.4 with it, 1.7 without).

    Returns ``(F, added)``: the lack-of-fit F per channel (``((RSS_poly - RSS_sat) / (P_sat - P_poly)) /
    (RSS_sat / dof_sat)``, ~1 when the polynomial follows the frames within their noise; a diagnostic) and the
    covariance to add to each channel's coefficients (same column order).
    """
    f_out, add_out = {}, {}
    n_all = int(keep.sum())
    n_pts = np.unique(np.asarray(corr.point_id)[keep & (np.asarray(corr.point_id) >= 0)]).size
    for c, cm in gmap.channels.items():
        m = np.flatnonzero((ch == c) & keep)
        if m.size == 0:
            continue
        ux = (p[m, 0] - gmap.centre_px[0]) / gmap.norm_px
        uy = (p[m, 1] - gmap.centre_px[1]) / gmap.norm_px
        t = (corr.z_um[m] - gmap.z_ref_um) / gmap.z_scale_um
        w = np.concatenate([1.0 / corr.sigma_px[m]] * 2)
        b = np.concatenate([corr.q_px[m, 0] - p[m, 0], corr.q_px[m, 1] - p[m, 1]]) / gmap.norm_px * w
        ax, ay = cm.design(ux, uy, t)
        r_poly = b - np.concatenate([ax, ay]) @ cm.coef * w
        terms = tuple(dict.fromkeys(term for term, _ in cm.columns))
        flat = ChannelMap(tuple((term, 0) for term in terms), np.zeros(len(terms)), np.zeros((len(terms),) * 2),
                          0.0, 0)
        rss_sat, p_sat, frames = 0.0, 0, []
        for zz in np.unique(corr.z_um[m]):
            f = corr.z_um[m] == zz
            ff = np.concatenate([f, f])
            tz = (zz - gmap.z_ref_um) / gmap.z_scale_um
            if c == gmap.reference_channel and abs(tz) < 1e-12:
                rss_sat += float(b[ff] @ b[ff])
                continue
            fx, fy = flat.design(ux[f], uy[f], t[f])
            A = np.concatenate([fx, fy]) * w[ff][:, None]
            coef, *_ = np.linalg.lstsq(A, b[ff], rcond=None)
            r = b[ff] - A @ coef
            rss_sat += float(r @ r)
            p_sat += len(terms)
            dof_z = max(1, int(ff.sum()) - len(terms))
            var = np.diag(np.linalg.pinv(A.T @ A)) * float(r @ r) / dof_z
            pred = np.array([sum(cm.coef[i] * tz ** k for i, (tn, k) in enumerate(cm.columns) if tn == term)
                             for term in terms])
            frames.append((tz, coef - pred, var))
        # the points' positions are shared by all channels: their degrees of freedom by this channel's share
        dof_sat = 2 * m.size - p_sat - 2.0 * n_pts * m.size / max(n_all, 1)
        dp = p_sat - len(cm.columns)
        if dp <= 0 or dof_sat <= 0 or rss_sat <= 0:
            continue
        f_out[c] = float(((float(r_poly @ r_poly) - rss_sat) / dp) / (rss_sat / dof_sat))
        add = np.zeros((len(cm.columns),) * 2)
        tz = np.array([fr[0] for fr in frames])
        dev = np.array([fr[1] for fr in frames])
        var = np.array([fr[2] for fr in frames])
        for j, term in enumerate(terms):
            idx = [i for i, (tn, _) in enumerate(cm.columns) if tn == term]
            powers = [cm.columns[i][1] for i in idx]
            n_f = len(tz)
            if n_f <= len(powers):
                continue
            tau2 = float(np.mean(dev[:, j] ** 2)) * n_f / (n_f - len(powers)) - float(np.mean(var[:, j]))
            if tau2 > 0:
                T = tz[:, None] ** np.array(powers)[None, :]
                add[np.ix_(idx, idx)] = tau2 * np.linalg.pinv(T.T @ T)
        add_out[c] = add
    return f_out, add_out


def scene_points(corr: Correspondences) -> np.ndarray:
    """A label per observation naming its scene point: the ChArUco corner id, or for points without one (texture)
    the reference position they were measured at (one grid point, seen in every frame and channel)."""
    ids = np.asarray(corr.point_id, dtype=np.int64)
    out = ids.copy()
    free = ids < 0
    if free.any():
        _, inv = np.unique(np.round(corr.p_px[free], 3), axis=0, return_inverse=True)
        out[free] = int(ids.max(initial=-1)) + 1 + inv.ravel()
    return out


def fit_geometry_map(corr: Correspondences, z_ref_um: float, image_size_px: tuple[int, int],
                     reference_channel: str | None = None, max_order: int = 2, source: str = "charuco",
                     refine_reference: bool = True, clip_sigma: float = 5.0, path=None) -> GeometryMap:
    """Fit per-channel maps (model choice by BIC) to correspondences.

    ``refine_reference``: points with an id (ChArUco corners) have their z_ref position re-estimated from all
    their observations through the current maps (errors in variables: the measured reference corner is as noisy
    as any other), alternating with the fit. Observations further than ``clip_sigma`` robust sigmas from the
    fit are dropped (mis-detections). Where the frames depart from the polynomial in z beyond their noise, the
    coefficients' covariance takes that as a random effect per frame (:func:`lack_of_fit`; the lack-of-fit F in
    ``diagnostics["lack_of_fit_F"]``).
    """
    from threadpoolctl import threadpool_limits
    # ~100 small least-squares solves (thousands x ~20): multi-threaded BLAS only contends for the cores
    # (measured 20x slower on 2 loaded cores)
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit_geometry_map(corr, z_ref_um, image_size_px, reference_channel, max_order, source,
                                 refine_reference, clip_sigma, path)


def _fit_geometry_map(corr, z_ref_um, image_size_px, reference_channel, max_order, source, refine_reference,
                      clip_sigma, path) -> GeometryMap:
    chans = list(dict.fromkeys(np.asarray(corr.channel).astype(str).tolist()))
    if not chans:
        raise FitError("no correspondences for the geometry map", path=path, field="points",
                       fix="check that the chart was detected (ChArUco) or the frames are textured")
    ref = reference_channel or ("G" if "G" in chans else chans[0])
    w_px, h_px = image_size_px
    centre = ((w_px - 1) / 2.0, (h_px - 1) / 2.0)
    norm = 0.5 * math.hypot(w_px - 1, h_px - 1)
    span = float(np.max(np.abs(corr.z_um - z_ref_um)))
    if not span > 0:
        raise FitError("all frames are at z_ref", path=path, field="z_um", fix="measure frames across the scan")
    ch = np.asarray(corr.channel).astype(str)
    p = corr.p_px.copy()
    keep = np.ones(len(ch), bool)
    ids = np.asarray(corr.point_id)
    clusters = scene_points(corr)
    gmap = None
    n_iter = 4 if refine_reference and (ids >= 0).any() else 2
    for it in range(n_iter):
        maps, tables = {}, {}
        for c in chans:
            m = (ch == c) & keep
            ux = (p[m, 0] - centre[0]) / norm
            uy = (p[m, 1] - centre[1]) / norm
            t = (corr.z_um[m] - z_ref_um) / span
            d = (corr.q_px[m] - p[m]) / norm
            maps[c], tables[c] = _select_channel(ux, uy, t, d[:, 0], d[:, 1], norm / corr.sigma_px[m], c == ref,
                                                 max_order, clusters[m])
        gmap = GeometryMap(float(z_ref_um), span, centre, norm, ref, maps, source)
        # residuals of every observation through the current maps
        pred = np.empty_like(corr.q_px)
        for c in chans:
            m = ch == c
            pred[m, 0], pred[m, 1] = gmap.warp_px(p[m, 0], p[m, 1], corr.z_um[m], c)
        res = corr.q_px - pred
        rn = np.hypot(res[:, 0], res[:, 1]) / corr.sigma_px
        # |residual| / sigma is Rayleigh for Gaussian errors: its median is sqrt(2 ln 2) robust sigmas
        s_hat = float(np.median(rn[keep])) / math.sqrt(2.0 * math.log(2.0))
        if it == n_iter - 1:
            if refine_reference and (ids >= 0).any():
                # the chosen columns once more, jointly with every corner's z_ref position: its covariance then
                # holds the reference positions' own error (they are measured, not known)
                gmap, p = _joint_with_reference(gmap, corr, p, keep, ch, chans, ids)
                for c in chans:
                    m = ch == c
                    pred[m, 0], pred[m, 1] = gmap.warp_px(p[m, 0], p[m, 1], corr.z_um[m], c)
                res = corr.q_px - pred
            break
        keep = rn <= clip_sigma * max(s_hat, 1e-12)
        if refine_reference and (ids >= 0).any():
            # the maps are within ~1e-2 of the identity in their derivative: the mean residual moves p
            sel = keep & (ids >= 0)
            uid, inv = np.unique(ids[sel], return_inverse=True)
            wts = 1.0 / corr.sigma_px[sel] ** 2
            num = np.zeros((uid.size, 2))
            np.add.at(num, inv, res[sel] * wts[:, None])
            den = np.bincount(inv, weights=wts, minlength=uid.size)
            step = num / den[:, None]
            lut = {int(u): s for u, s in zip(uid, step)}
            move = np.array([lut.get(int(i), (0.0, 0.0)) for i in ids[ids >= 0]])
            p[ids >= 0] += move
    # errors shared by a frame's points that the polynomial in z does not follow: carried in the covariance
    lof, added = lack_of_fit(gmap, corr, p, keep, ch)
    for c, add in added.items():
        cm = gmap.channels[c]
        gmap.channels[c] = ChannelMap(cm.columns, cm.coef, cm.cov + add, cm.chi2_dof, cm.n_points)
    rms = {c: float(np.sqrt(np.mean(res[(ch == c) & keep] ** 2))) for c in chans}
    gmap.diagnostics = {"n_points": int(keep.sum()), "n_rejected": int((~keep).sum()), "residual_rms_px": rms,
                        "lack_of_fit_F": lof, "frame_cov": {c: a.tolist() for c, a in added.items()},
                        "model_selection": tables,
                        "chosen": {c: {"columns": [list(col) for col in gmap.channels[c].columns]} for c in chans}}
    return gmap
