"""Absolute distortion from a planar board: the z_ref geometry against the board's ideal (pinhole) image.

The geometry maps (:mod:`fieldcal.fit.geometry_map`) are *relative*: they map the z_ref geometry to the frame at
z, so at z_ref they are the identity whatever the lens does. A planar board measures the absolute part: its
ideal image is a homography ``H`` of the board's coordinates, and what is left is distortion. In coordinates
``w = (p - centre) / R`` (``R`` = half the image diagonal) the reference channel's z_ref frame shows the board
point ``X`` at::

    q = centre + R D(w),  w = (H X - centre) / R,  D(w) = w + sum_j a_j B_j(w)

with OpenCV's Brown-Conrady fields ``B``: ``k1`` w r^2, ``k2`` w r^4, ``k3`` w r^6, ``p1`` (2 wx wy, r^2 + 2 wy^2),
``p2`` (r^2 + 2 wx^2, 2 wx wy). ``D`` has no linear part (``H`` takes it), so the undistorted image has the
distorted one's scale and position at the centre. The centre is the image centre: radial distortion about
an off-centre axis is the same field as tangential terms to first order (p1, p2 carry it), and a free centre
beside them is degenerate. ``H`` and ``a`` are fitted together by ``scipy.optimize.least_squares`` (OpenCV's
``findHomography`` starts it); the terms are chosen by BIC (error scale profiled out, as for the surfaces and
maps); the covariance of ``a`` is the Gauss-Newton one, marginal over ``H``, scaled by the residual variance.

Other channels and other stage positions compose with the maps (docs/geometry.md, "Absolute distortion"):
:func:`distortion_at` normalises ``warp_px(D(p), z, c)`` by the reference channel's linear part at the centre.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..formats import documents
from .data import FitError

DISTORTION_FORMAT = documents.format_id("distortion")

#: Brown-Conrady terms (OpenCV's names and signs)
TERMS = ("k1", "k2", "k3", "p1", "p2")
#: candidate term sets, chosen by BIC
TERM_SETS = ((), ("k1",), ("k1", "k2"), ("k1", "k2", "k3"), ("k1", "p1", "p2"), ("k1", "k2", "p1", "p2"),
             ("k1", "k2", "k3", "p1", "p2"))


def brown_basis(term: str, wx, wy):
    """The displacement field of one term at normalised positions (wx, wy): (bx, by)."""
    r2 = wx * wx + wy * wy
    if term == "k1":
        return wx * r2, wy * r2
    if term == "k2":
        return wx * r2 * r2, wy * r2 * r2
    if term == "k3":
        return wx * r2 ** 3, wy * r2 ** 3
    if term == "p1":
        return 2.0 * wx * wy, r2 + 2.0 * wy * wy
    if term == "p2":
        return r2 + 2.0 * wx * wx, 2.0 * wx * wy
    raise ValueError(f"unknown distortion term {term!r}")


def _design(terms, wx, wy) -> tuple[np.ndarray, np.ndarray]:
    if not terms:
        z = np.zeros(np.shape(wx) + (0,))
        return z, z
    bs = [brown_basis(t, wx, wy) for t in terms]
    return np.stack([b[0] for b in bs], axis=-1), np.stack([b[1] for b in bs], axis=-1)


@dataclass
class AbsoluteDistortion:
    """The reference channel's distortion at ``z_um`` (the maps' z_ref): undistorted pixel -> distorted pixel."""

    z_um: float
    reference_channel: str
    centre_px: tuple[float, float]
    norm_px: float
    terms: tuple[str, ...]
    coef: np.ndarray
    cov: np.ndarray
    rms_px: float
    n_points: int
    source: str = "charuco"
    diagnostics: dict[str, Any] = field(default_factory=dict)
    hull_px: np.ndarray | None = None  # convex hull of the board's corners in undistorted px: the measured field

    def _w(self, x, y):
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return (x - self.centre_px[0]) / self.norm_px, (y - self.centre_px[1]) / self.norm_px

    def distort_px(self, x_u, y_u):
        """Distorted pixel of undistorted pixel(s) (x_u, y_u)."""
        wx, wy = self._w(x_u, y_u)
        ax, ay = _design(self.terms, wx, wy)
        return (self.centre_px[0] + self.norm_px * (wx + ax @ self.coef),
                self.centre_px[1] + self.norm_px * (wy + ay @ self.coef))

    def distort_sd_px(self, x_u, y_u):
        """1-sigma (px, x and y) of :meth:`distort_px` from the coefficients' covariance (exact: D is linear in
        them)."""
        wx, wy = self._w(x_u, y_u)
        ax, ay = _design(self.terms, wx, wy)
        vx = np.einsum("...i,ij,...j->...", ax, self.cov, ax)
        vy = np.einsum("...i,ij,...j->...", ay, self.cov, ay)
        return self.norm_px * np.sqrt(np.clip(vx, 0, None)), self.norm_px * np.sqrt(np.clip(vy, 0, None))

    def undistort_px(self, x_d, y_d, iterations: int = 100, tol_px: float = 1e-9):
        """Undistorted pixel of distorted pixel(s): Newton's method on :meth:`distort_px`."""
        return invert_map(self.distort_px, x_d, y_d, iterations, tol_px)

    def to_dict(self) -> dict[str, Any]:
        return {"format": DISTORTION_FORMAT, "z_um": float(self.z_um), "reference_channel": self.reference_channel,
                "centre_px": [float(v) for v in self.centre_px], "norm_px": float(self.norm_px),
                "terms": list(self.terms), "coef": [float(v) for v in self.coef],
                "cov": np.asarray(self.cov, dtype=np.float64).reshape(len(self.terms), len(self.terms)).tolist(),
                "rms_px": float(self.rms_px), "n_points": int(self.n_points), "source": self.source,
                **({"hull_px": np.asarray(self.hull_px, dtype=np.float64).tolist()} if self.hull_px is not None else {}),
                "diagnostics": self.diagnostics}

    @classmethod
    def from_dict(cls, d: dict[str, Any], path=None) -> "AbsoluteDistortion":
        from ..errors import SpecError
        if not isinstance(d, dict) or d.get("format") != DISTORTION_FORMAT:
            raise SpecError(f"not a {DISTORTION_FORMAT} block", path=path, field="absolute_distortion",
                            fix="write it with AbsoluteDistortion.to_dict() (or recalibrate)")
        try:
            terms = tuple(str(t) for t in d["terms"])
            if any(t not in TERMS for t in terms):
                raise ValueError(f"unknown term in {terms}")
            n = len(terms)
            return cls(float(d["z_um"]), str(d["reference_channel"]), tuple(float(v) for v in d["centre_px"]),
                       float(d["norm_px"]), terms, np.asarray(d["coef"], dtype=np.float64).reshape(n),
                       np.asarray(d["cov"], dtype=np.float64).reshape(n, n), float(d["rms_px"]),
                       int(d["n_points"]), str(d.get("source", "charuco")), dict(d.get("diagnostics", {})),
                       None if d.get("hull_px") is None else np.asarray(d["hull_px"], dtype=np.float64).reshape(-1, 2))
        except (KeyError, TypeError, ValueError) as e:
            raise SpecError(f"malformed absolute distortion ({e})", path=path, field="absolute_distortion",
                            fix="regenerate the profile with `fieldcal calibrate`") from None


def invert_map(forward: Callable, x, y, iterations: int = 100, tol_px: float = 1e-9, step_px: float = 0.5):
    """Solve ``forward(u) = (x, y)`` for u (Newton's method with a central-difference Jacobian per point)."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    ux, uy = x.copy(), y.copy()
    err = np.inf
    for _ in range(iterations):
        fx, fy = forward(ux, uy)
        ex, ey = np.asarray(fx) - x, np.asarray(fy) - y
        err = float(np.max(np.hypot(ex, ey), initial=0.0))
        if not err > tol_px:
            break
        xp, yp = forward(ux + step_px, uy)
        xm, ym = forward(ux - step_px, uy)
        a, c = (xp - xm) / (2 * step_px), (yp - ym) / (2 * step_px)
        xp, yp = forward(ux, uy + step_px)
        xm, ym = forward(ux, uy - step_px)
        b, d = (xp - xm) / (2 * step_px), (yp - ym) / (2 * step_px)
        det = a * d - b * c
        ux = ux - (d * ex - b * ey) / det
        uy = uy - (-c * ex + a * ey) / det
    if not (np.isfinite(err) and err < 1e-6):
        raise FitError(f"the distortion could not be inverted (residual {err:.3g} px): it folds the image there",
                       field="distortion", fix="query points inside the calibrated field")
    return ux, uy


def distortion_at(forward: Callable, forward_ref: Callable, centre_px: tuple[float, float], x_u, y_u,
                  step_px: float = 1e-2):
    """The distortion of one channel at one stage position, in the unit-derivative convention.

    ``forward(x, y)``: where the ideal-image point (x, y) of the reference geometry lands in the channel's frame
    (e.g. ``warp_px(*D(x, y), z, c)``); ``forward_ref`` the same for the reference channel at that z. The
    undistorted coordinates at z are those in which the reference channel's map is the identity to first order
    at the centre (breathing and shift taken out): ``forward(c + J^-1 (p_u - f_ref(c)))`` with ``J`` the
    reference map's Jacobian at the centre.
    """
    cx, cy = centre_px
    f0 = np.array([float(np.ravel(v)[0]) for v in forward_ref(np.array([cx]), np.array([cy]))])
    xs = np.array([cx + step_px, cx - step_px, cx, cx])
    ys = np.array([cy, cy, cy + step_px, cy - step_px])
    fx, fy = (np.asarray(v, dtype=np.float64).ravel() for v in forward_ref(xs, ys))
    J = np.array([[fx[0] - fx[1], fx[2] - fx[3]], [fy[0] - fy[1], fy[2] - fy[3]]]) / (2 * step_px)
    Ji = np.linalg.inv(J)
    x_u, y_u = np.broadcast_arrays(np.asarray(x_u, dtype=np.float64), np.asarray(y_u, dtype=np.float64))
    dx, dy = x_u - f0[0], y_u - f0[1]
    return forward(cx + Ji[0, 0] * dx + Ji[0, 1] * dy, cy + Ji[1, 0] * dx + Ji[1, 1] * dy)


# ------------------------------------------------------------------------------------------------- the fit
def _norm_points(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation (mean 0, mean distance sqrt 2): the 3x3 T and the normalised points."""
    m = xy.mean(axis=0)
    s = math.sqrt(2.0) / max(float(np.mean(np.hypot(*(xy - m).T))), 1e-12)
    T = np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1.0]])
    return T, (xy - m) * s


def _project(h8: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    H = np.append(h8, 1.0).reshape(3, 3)
    den = H[2, 0] * b[:, 0] + H[2, 1] * b[:, 1] + H[2, 2]
    return ((H[0, 0] * b[:, 0] + H[0, 1] * b[:, 1] + H[0, 2]) / den,
            (H[1, 0] * b[:, 0] + H[1, 1] * b[:, 1] + H[1, 2]) / den)


def _fit_terms(b: np.ndarray, w_obs: np.ndarray, wt: np.ndarray, h0: np.ndarray, terms: tuple[str, ...]):
    """Joint homography + distortion least squares; returns (params, residuals (2N), J)."""
    from scipy.optimize import least_squares

    def resid(params):
        wx, wy = _project(params[:8], b)
        ax, ay = _design(terms, wx, wy)
        a = params[8:]
        return np.concatenate([(wx + ax @ a - w_obs[:, 0]) * wt, (wy + ay @ a - w_obs[:, 1]) * wt])

    x0 = np.concatenate([h0, np.zeros(len(terms))])
    sol = least_squares(resid, x0, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    return sol.x, sol.fun, sol.jac


def fit_absolute_distortion(board_xy, image_px, image_size_px: tuple[int, int], *, sigma_px=None,
                            shared_cov_px2=None, reference_channel: str = "G", z_um: float = 0.0,
                            clip_sigma: float = 5.0, source: str = "charuco", path=None) -> AbsoluteDistortion:
    """Absolute distortion of one view of a planar board (terms by BIC, covariance kept).

    Parameters
    ----------
    board_xy : (N, 2) array
        Corner positions on the board's plane (any unit).
    image_px : (N, 2) array
        Where the image shows them (px).
    image_size_px : (W, H)
        The frame's size: the centre and the normalisation radius come from it.
    sigma_px : (N,) array, optional
        Relative 1-sigma of each image point (weights; the scale comes from the residuals).
    shared_cov_px2 : (2N, 2N) array, optional
        A covariance of the image points (px^2, x of all points then y) that the residuals cannot show because
        it moves the points together (:func:`reference_points_map_cov`): propagated into the coefficients'
        covariance and added.
    """
    import cv2
    b_raw = np.asarray(board_xy, dtype=np.float64).reshape(-1, 2)
    q = np.asarray(image_px, dtype=np.float64).reshape(-1, 2)
    n = len(q)
    if len(b_raw) != n or n < 12 or not (np.all(np.isfinite(b_raw)) and np.all(np.isfinite(q))):
        raise FitError(f"{n} board corners: an absolute distortion needs at least 12 finite ones matched to the "
                       "board", path=path, field="points",
                       fix="show the whole board (ChArUco) near focus in the reference frame")
    sig = np.ones(n) if sigma_px is None else np.asarray(sigma_px, dtype=np.float64).reshape(n)
    if shared_cov_px2 is not None and np.shape(shared_cov_px2) != (2 * n, 2 * n):
        raise FitError(f"the shared covariance is {np.shape(shared_cov_px2)}, not (2N, 2N) for N = {n} points",
                       path=path, field="shared_cov_px2", fix="give it over x of all points, then y")
    w_px, h_px = image_size_px
    centre = ((w_px - 1) / 2.0, (h_px - 1) / 2.0)
    R = 0.5 * math.hypot(w_px - 1, h_px - 1)
    T, b = _norm_points(b_raw)
    w_obs = (q - np.array(centre)) / R
    H0, _ = cv2.findHomography(b, w_obs, 0)
    if H0 is None or not np.all(np.isfinite(H0)) or abs(H0[2, 2]) < 1e-12:
        raise FitError("the board's corners give no homography (collinear or repeated)", path=path,
                       field="points", fix="show the board's whole area, not a line of corners")
    h0 = (H0 / H0[2, 2]).ravel()[:8]
    keep = np.ones(n, bool)
    for it in range(2):
        wt = 1.0 / sig[keep] * np.median(sig[keep])
        best, table = None, []
        m = 2 * int(keep.sum())
        for terms in TERM_SETS:
            k = 8 + len(terms)
            if m <= k + 2:
                continue
            params, r, J = _fit_terms(b[keep], w_obs[keep], wt, h0, terms)
            rss = float(r @ r)
            bic = m * math.log(max(rss, 1e-300) / m) + k * math.log(m)
            table.append({"terms": list(terms), "bic": bic, "rms_px": R * math.sqrt(rss / m)})
            if best is None or bic < best[0]:
                cov = np.linalg.pinv(J.T @ J) * (rss / max(1, m - k))
                best = (bic, terms, params, cov, r, J)
        _, terms, params, cov, r, best_jac = best
        if it == 1:
            break
        # drop mis-detections (beyond clip_sigma robust sigmas of the first fit) and refit once
        wx, wy = _project(params[:8], b)
        ax, ay = _design(terms, wx, wy)
        pred = np.column_stack([wx + ax @ params[8:], wy + ay @ params[8:]])
        rn = np.hypot(*(pred - w_obs).T) / (sig / np.median(sig))
        # |residual| / sigma is Rayleigh for Gaussian errors: its median is sqrt(2 ln 2) robust sigmas
        s_hat = float(np.median(rn)) / math.sqrt(2.0 * math.log(2.0))
        new_keep = rn <= clip_sigma * max(s_hat, 1e-15)
        if new_keep.all() or new_keep.sum() < 12:
            break
        keep = new_keep
    na = len(terms)
    r_px = R * r / np.concatenate([wt, wt])  # unweighted residuals (px)
    rms = math.sqrt(float(r_px @ r_px) / r_px.size)
    for row in table:
        row["chosen"] = row["terms"] == list(terms)
    if shared_cov_px2 is not None:
        # d params = (J^T J)^-1 J^T diag(wt) d w_obs (the residuals are weighted, w_obs = (q - centre) / R)
        J = best_jac
        sens = (np.linalg.pinv(J.T @ J) @ J.T) * np.concatenate([wt, wt])[None, :] / R
        kk = np.concatenate([keep, keep])
        shared = np.asarray(shared_cov_px2, dtype=np.float64)[np.ix_(kk, kk)]
        cov = cov + sens @ shared @ sens.T
    hx, hy = _project(params[:8], b[keep])
    ideal = np.column_stack([centre[0] + R * hx, centre[1] + R * hy]).astype(np.float32)
    hull = cv2.convexHull(ideal).reshape(-1, 2).astype(np.float64)
    diag = {"model_selection": table, "n_rejected": int((~keep).sum()),
            "homography_normalised": np.append(params[:8], 1.0).tolist(), "board_normalisation": T.tolist()}
    return AbsoluteDistortion(float(z_um), reference_channel, centre, R, tuple(terms), params[8:].copy(),
                              cov[8:, 8:].reshape(na, na).copy(), rms, int(keep.sum()), source, diag, hull)


def reference_points(corr, gmap, iterations: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The z_ref-geometry position of every identified point from all its observations through the maps.

    Each observation ``q`` of point i (any channel, any frame) says ``warp_px(p_i, z, c) = q``; ``p_i`` moves by
    the weighted mean of ``q - warp_px(p_i)`` until it settles (the maps' derivative is the identity to ~1e-2).
    Returns (ids, positions (M, 2) px, 1-sigma (M,) px: the scatter of the observations over sqrt(count)).
    """
    ids_all = np.asarray(corr.point_id)
    sel = ids_all >= 0
    if not sel.any():
        raise FitError("the correspondences identify no points (texture tracks)", field="points",
                       fix="measure a ChArUco board for the absolute distortion")
    ids = ids_all[sel]
    ch = np.asarray(corr.channel).astype(str)[sel]
    z = np.asarray(corr.z_um, dtype=np.float64)[sel]
    q = corr.q_px[sel]
    w = 1.0 / corr.sigma_px[sel] ** 2
    uid, inv = np.unique(ids, return_inverse=True)
    # start: the mean reference-plane position given with each observation
    p = np.zeros((uid.size, 2))
    np.add.at(p, inv, corr.p_px[sel])
    p /= np.bincount(inv, minlength=uid.size)[:, None]
    res = np.zeros_like(q)
    for _ in range(iterations):
        pred = np.empty_like(q)
        for c in np.unique(ch):
            m = ch == c
            pred[m, 0], pred[m, 1] = gmap.warp_px(p[inv[m], 0], p[inv[m], 1], z[m], c)
        res = q - pred
        num = np.zeros((uid.size, 2))
        np.add.at(num, inv, res * w[:, None])
        den = np.bincount(inv, weights=w, minlength=uid.size)
        p += num / den[:, None]
    cnt = np.bincount(inv, minlength=uid.size)
    ss = np.bincount(inv, weights=np.sum(res ** 2, axis=1) / 2.0, minlength=uid.size)
    sd = np.sqrt(ss / np.maximum(cnt - 1, 1) / np.maximum(cnt, 1))
    sd = np.where(cnt > 1, sd, np.nan)
    sd = np.where(np.isfinite(sd) & (sd > 0), sd, np.nanmedian(sd) if np.isfinite(sd).any() else 1.0)
    return uid, p, np.maximum(sd, 1e-6)


def reference_points_map_cov(corr, gmap, ids: np.ndarray, p_px: np.ndarray) -> np.ndarray:
    """The covariance (px^2) the maps' own error gives the reference points of :func:`reference_points`.

    ``p_i`` is the weighted mean over its observations of ``q - (warp_px(p_i, z, c) - p_i)``, so an error
    ``d theta`` of the maps' coefficients moves every point at once: ``d p_i = -A_i d theta`` with ``A_i`` the
    weighted mean of the maps' design rows over point i's observations. In the joint fit of maps and
    positions the coefficients are estimated from within-point deviations, uncorrelated with the points'
    means (Frisch-Waugh-Lovell), so the points' covariance is their independent scatter plus this shared,
    low-rank part ``A Cov(theta) A^T`` -- which the board fit's residuals cannot show (it moves all corners
    together, into the distortion coefficients). Channels' coefficients are taken as uncorrelated (the joint
    fit keeps per-channel blocks). Returns a (2M, 2M) array over [x of the M points, then y], in ``ids``'s order.
    """
    sel = np.asarray(corr.point_id) >= 0
    pid = np.asarray(corr.point_id)[sel]
    ch = np.asarray(corr.channel).astype(str)[sel]
    z = np.asarray(corr.z_um, dtype=np.float64)[sel]
    w = 1.0 / corr.sigma_px[sel] ** 2
    lut = {int(v): k for k, v in enumerate(np.asarray(ids).tolist())}
    row = np.array([lut.get(int(v), -1) for v in pid])
    ok = row >= 0
    m = len(ids)
    den = np.bincount(row[ok], weights=w[ok], minlength=m)
    cov = np.zeros((2 * m, 2 * m))
    for c, cm in gmap.channels.items():
        k = ok & (ch == c)
        if not k.any():
            continue
        r = row[k]
        ux = (p_px[r, 0] - gmap.centre_px[0]) / gmap.norm_px
        uy = (p_px[r, 1] - gmap.centre_px[1]) / gmap.norm_px
        ax, ay = cm.design(ux, uy, (z[k] - gmap.z_ref_um) / gmap.z_scale_um)
        A = np.zeros((2 * m, ax.shape[1]))
        np.add.at(A, r, ax * w[k, None])
        np.add.at(A, m + r, ay * w[k, None])
        A /= np.concatenate([den, den])[:, None]
        cov += gmap.norm_px ** 2 * (A @ cm.cov @ A.T)
    return 0.5 * (cov + cov.T)


# ------------------------------------------------------------------------------ composition with the maps
def compose_distortion(dist: AbsoluteDistortion, warp: Callable, x_u, y_u, z_um: float, channel: str):
    """Channel ``channel``'s distortion at stage position ``z_um``: undistorted -> distorted pixel.

    ``warp(x, y, z, c)`` is the profile's ``warp_px`` (z_ref geometry -> frame at z). The chain is the board's
    ideal image -> ``dist`` (the z_ref geometry) -> ``warp`` (channel c at z), normalised by
    :func:`distortion_at` so the reference channel's distortion at z has no linear part at the centre;
    the other channels keep their lateral colour and any constant offset against it.
    """
    ref = dist.reference_channel
    fwd = lambda c: (lambda x, y: warp(*dist.distort_px(x, y), z_um, c))  # noqa: E731
    return distortion_at(fwd(channel), fwd(ref), dist.centre_px, x_u, y_u)


def compose_distortion_sd(dist: AbsoluteDistortion, warp_sd: Callable, x_u, y_u, z_um: float, channel: str):
    """1-sigma (px, x and y) of :func:`compose_distortion`: the board fit's and the maps' in quadrature (the
    maps' derivative is the identity to ~1e-2, so the board fit's sd passes through unchanged)."""
    dx, dy = dist.distort_px(x_u, y_u)
    sx, sy = dist.distort_sd_px(x_u, y_u)
    wx, wy = warp_sd(dx, dy, z_um, channel)
    return np.hypot(sx, wx), np.hypot(sy, wy)
