"""Per-frame geometry from the chart itself: magnification about the optical centre and shift, per channel.

Method: frames are taken in z order and each is registered to its *neighbour*, whose blur is almost the
same (registering far-apart frames compares sharp texture with blurred texture, and a blur disc's OTF
changes sign). Both frames are downsampled (``cv2.resize`` INTER_AREA: low-pass and fast) and the
neighbour-to-neighbour scale ratio ``r`` about the optical centre c and the translation ``t`` are fitted by
Gauss-Newton with cubic-spline resampling (:func:`register_step`). The step uncertainty is the
step-to-step scatter (MAD of second differences), or the Gauss-Newton covariance when there are few
steps. Steps are composed outward from the reference frame (``m_k = r m_{k-1}``, ``s_k = r s_{k-1} + t``),
and their variances add along the way.

The geometry convention (docs/architecture.md): a point at pixel p of the reference frame appears at ``c + m (p - c) + s`` in frame k.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy import ndimage

from ..errors import ParameterError


@dataclass(frozen=True)
class StepFit:
    """One neighbour-to-neighbour registration: scale ratio r, translation t (px, about ``centre``)."""

    r: float
    tx: float
    ty: float
    cov: np.ndarray  # 3x3 covariance of (r - 1, tx, ty)
    n_patches: int  # pixels (or patches) that support the fit; 0 for a bridged (missing) step


@dataclass
class GeometryMeasurements:
    """Per-frame, per-channel geometry relative to the reference frame (frames sorted by z).

    Attributes
    ----------
    z_um : (n,) stage positions, increasing.
    channels : channel names (columns of the 2-D arrays).
    magnification, mag_sigma : (n, C) image scale about ``centre_px`` relative to the reference frame, 1-sigma.
    shift_x_px, shift_y_px, shift_sigma_px : (n, C) shift (px) relative to the reference frame, 1-sigma.
    ref_index : index (into ``z_um``) of the reference frame; ``z_ref_um = z_um[ref_index]``.
    centre_px : (cx, cy) centre of the magnification (the optical centre if known, else the image centre).
    image_size_px : (W, H).
    frame_index : (n,) index of each row's frame in the stack's file order.
    lateral_colour_scale : optional per-channel scale relative to the first channel at the reference frame.
    """

    z_um: np.ndarray
    channels: tuple[str, ...]
    magnification: np.ndarray
    mag_sigma: np.ndarray
    shift_x_px: np.ndarray
    shift_y_px: np.ndarray
    shift_sigma_px: np.ndarray
    ref_index: int
    centre_px: tuple[float, float]
    image_size_px: tuple[int, int]
    frame_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    lateral_colour_scale: dict[str, float] | None = None

    @property
    def z_ref_um(self) -> float:
        return float(self.z_um[self.ref_index])

    def channel_index(self, channel: str) -> int:
        try:
            return self.channels.index(channel)
        except ValueError:
            raise ParameterError(f"no channel {channel!r} in the geometry (it has {', '.join(self.channels)})",
                                 field="channel", fix=f"use one of {', '.join(self.channels)}") from None

    def map_points(self, k: int, channel: str, x_px, y_px):
        """Where reference-frame points (x, y) appear in frame row ``k`` of channel ``channel``."""
        c = self.channel_index(channel)
        cx, cy = self.centre_px
        m = self.magnification[k, c]
        return (cx + m * (np.asarray(x_px, dtype=np.float64) - cx) + self.shift_x_px[k, c],
                cy + m * (np.asarray(y_px, dtype=np.float64) - cy) + self.shift_y_px[k, c])

    def unmap_points(self, k: int, channel: str, x_px, y_px):
        """Where points (x, y) of frame row ``k`` of channel ``channel`` lie in the reference frame (the inverse
        of :meth:`map_points`)."""
        c = self.channel_index(channel)
        cx, cy = self.centre_px
        m = self.magnification[k, c]
        return (cx + (np.asarray(x_px, dtype=np.float64) - cx - self.shift_x_px[k, c]) / m,
                cy + (np.asarray(y_px, dtype=np.float64) - cy - self.shift_y_px[k, c]) / m)

    def recentred(self, centre_px: tuple[float, float]) -> "GeometryMeasurements":
        """The same geometry with magnification about another centre (shifts change, scales do not)."""
        (cx, cy), (nx, ny) = self.centre_px, centre_px
        m = self.magnification
        return replace(self, shift_x_px=self.shift_x_px + (m - 1.0) * (nx - cx),
                       shift_y_px=self.shift_y_px + (m - 1.0) * (ny - cy), centre_px=(float(nx), float(ny)))

    def max_displacement_px(self) -> float:
        """Largest movement of an image corner over the scan (px): how far tiles must follow the image."""
        w, h = self.image_size_px
        xs = np.array([0.0, w - 1.0, 0.0, w - 1.0])
        ys = np.array([0.0, 0.0, h - 1.0, h - 1.0])
        best = 0.0
        for k in range(len(self.z_um)):
            for ch in self.channels:
                x, y = self.map_points(k, ch, xs, ys)
                best = max(best, float(np.max(np.hypot(x - xs, y - ys))))
        return best

    def to_dict(self) -> dict:
        """JSON-ready columns (for reports and profiles)."""
        return {"z_um": self.z_um.tolist(), "channels": list(self.channels), "ref_index": int(self.ref_index),
                "centre_px": list(self.centre_px), "image_size_px": list(self.image_size_px),
                "magnification": self.magnification.tolist(), "mag_sigma": self.mag_sigma.tolist(),
                "shift_x_px": self.shift_x_px.tolist(), "shift_y_px": self.shift_y_px.tolist(),
                "shift_sigma_px": self.shift_sigma_px.tolist(),
                "lateral_colour_scale": self.lateral_colour_scale}

    @classmethod
    def identity(cls, z_um, channels, image_size_px, centre_px=None, ref_index=None) -> "GeometryMeasurements":
        """No breathing and no shift (e.g. a telecentric lens), with zero uncertainty."""
        z = np.sort(np.asarray(z_um, dtype=np.float64))
        n, c = z.size, len(channels)
        w, h = image_size_px
        centre = centre_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        zeros = np.zeros((n, c))
        return cls(z, tuple(channels), np.ones((n, c)), zeros.copy(), zeros.copy(), zeros.copy(), zeros.copy(),
                   int(n // 2 if ref_index is None else ref_index), centre, (int(w), int(h)),
                   np.arange(n))


# ------------------------------------------------------------------------------------------ registration
def downsample(plane: np.ndarray, factor: int) -> np.ndarray:
    """Area-average downsampling by an integer factor (float32): low-pass and smaller."""
    if factor <= 1:
        return np.ascontiguousarray(plane, dtype=np.float32)
    h, w = plane.shape
    hs, ws = h // factor, w // factor
    return cv2.resize(plane[:hs * factor, :ws * factor], (ws, hs), interpolation=cv2.INTER_AREA)


# A mild low-pass (sigma 1 px of the registration grid) before registering: the highest frequencies carry the
# most noise and the most blur change between neighbouring frames.
REGISTRATION_BLUR_PX = 1.0


def registration_plane(plane: np.ndarray, factor: int, blur_px: float = REGISTRATION_BLUR_PX) -> np.ndarray:
    """A plane ready for :func:`register_step`: area-downsampled by ``factor`` and lightly blurred (float32).

    Calibration (chart planes) and compositing (grey scene frames) both register through this.
    """
    small = downsample(plane, factor)
    return cv2.GaussianBlur(small, (0, 0), blur_px) if blur_px > 0 else small


def _spline_taps(q: np.ndarray, n: int):
    """The cubic B-spline's weights at positions ``q`` (px) on a line of ``n`` coefficients: a sparse
    ``len(q) x n`` matrix, four taps a row, indices beyond the line clamped to its ends (``mode="nearest"``)."""
    from scipy import sparse

    f = np.floor(q)
    t = q - f
    # (a diverged step's positions may be huge or NaN: clipped before the cast, their weights stay NaN)
    idx = np.clip(np.clip(np.nan_to_num(f), -2.0, n + 1.0).astype(np.intp)[:, None] + np.arange(-1, 3), 0, n - 1)
    t2, t3 = t * t, t * t * t
    w = np.stack([(1.0 - t) ** 3 / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
                  (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0], axis=1)
    return sparse.csr_matrix((w.ravel(), (np.repeat(np.arange(len(q)), 4), idx.ravel())), shape=(len(q), n))


def _cubic_on_grid(coeffs: np.ndarray, qy: np.ndarray, qx: np.ndarray,
                   coeffs_t: np.ndarray | None = None) -> np.ndarray:
    """``ndimage.map_coordinates(coeffs, [Y, X], order=3, prefilter=False, mode="nearest")`` at the product grid
    ``Y, X = meshgrid(qy, qx, indexing="ij")``, raveled (row-major): the B-spline is a product of 1-D splines, so
    one pass along the rows and one along the columns (two sparse products, 4 taps each) give the same numbers
    (to float64 rounding) at ~2x less cost than 16 taps per point. ``coeffs_t``: ``coeffs.T`` made contiguous,
    for a caller resampling the same coefficients many times (SciPy's sparse product copies a transposed
    operand into row order on every call: a whole plane per Gauss-Newton iteration); the same numbers."""
    if coeffs_t is None:
        coeffs_t = coeffs.T
    along_x = (_spline_taps(qx, coeffs.shape[1]) @ coeffs_t).T  # H x len(qx)
    return np.asarray(_spline_taps(qy, coeffs.shape[0]) @ along_x).ravel()


def register_step(prev: np.ndarray, cur: np.ndarray, centre_xy: tuple[float, float],
                  init: tuple[float, float, float] | None = None, subsample: int = 2,
                  iterations: int = 8, tol_px: float = 1e-5) -> StepFit | None:
    """Scale ratio and translation of ``cur`` relative to ``prev`` (same plane grid, px of that grid).

    Model: a point at p in ``prev`` is at ``c + r (p - c) + t`` in ``cur``. Solved by Gauss-Newton on the
    three parameters with ``cur`` resampled by cubic B-splines (separable, :func:`_cubic_on_grid`): OpenCV's
    warps quantise sub-pixel positions to 1/32 px and bilinear resampling smooths by a phase-dependent
    amount, which biased ``cv2.findTransformECC`` by ~10 % of a small scale change in our tests. ECC (affine)
    gives the start when ``init`` (e.g. the previous step) does not converge. ``cov`` is the Gauss-Newton
    covariance of (r - 1, tx, ty) scaled by the residual variance (a lower bound: residuals are spatially
    correlated; :func:`compose_steps` uses the scatter of the steps when there are enough).
    ``tol_px`` is the convergence threshold on the last update (px at the image's half diagonal): the default
    suits charts; real photographs with defocus differences between neighbours settle at noise level nearer
    1e-3 px (compositing passes that, with more iterations). Returns None on failure.
    """
    if prev.shape != cur.shape:
        raise ParameterError(f"frames to register differ in size: {prev.shape} vs {cur.shape}", field="frames",
                             fix="all frames of a stack must have the same size")
    h, w = prev.shape
    b = 4
    if min(h, w) < 4 * b + 8:
        return None
    c = np.asarray(centre_xy, dtype=np.float64)
    # the samples form a product grid (rows ``yg`` x columns ``xg``), and a scale-and-shift maps it to another
    # product grid: the cubic B-spline resampling below is separable (:func:`_cubic_on_grid`)
    yg = np.arange(b, h - b, subsample, dtype=np.float64)
    xg = np.arange(b, w - b, subsample, dtype=np.float64)
    ys, xs = np.meshgrid(yg, xg, indexing="ij")
    xs, ys = xs.ravel(), ys.ravel()
    # central differences at the samples only (np.gradient's interior, the same numbers: the samples are >= b px
    # from the edge), not over the whole plane
    rows, cols = slice(b, h - b, subsample), slice(b, w - b, subsample)
    gx = ((prev[rows, b + 1:w - b + 1:subsample].astype(np.float64)
           - prev[rows, b - 1:w - b - 1:subsample].astype(np.float64)) / 2.0).ravel()
    gy = ((prev[b + 1:h - b + 1:subsample, cols].astype(np.float64)
           - prev[b - 1:h - b - 1:subsample, cols].astype(np.float64)) / 2.0).ravel()
    lev = max(float(np.hypot(w, h)) / 2.0, 1.0)  # normalised lever arm: a well-conditioned system
    J = np.stack([(gx * (xs - c[0]) + gy * (ys - c[1])) / lev, gx, gy], axis=1)
    # einsum, not J.T @ J: a multi-threaded BLAS spins its threads after every such product, which cost ~40 %
    # extra CPU over a measurement pass (the pass already runs its own threads)
    H = np.einsum("ni,nj->ij", J, J)
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e12:
        return None
    target = prev[b:h - b:subsample, b:w - b:subsample].astype(np.float64).ravel()
    coeffs = ndimage.spline_filter(cur.astype(np.float64), order=3)
    coeffs_t = np.ascontiguousarray(coeffs.T)  # once, not copied by every iteration's sparse product

    def solve(theta):
        res = None
        for _ in range(iterations):
            rr = 1.0 + theta[0] / lev
            back = _cubic_on_grid(coeffs, c[1] + rr * (yg - c[1]) + theta[2], c[0] + rr * (xg - c[0]) + theta[1],
                                  coeffs_t)
            res = back - target
            d = np.linalg.solve(H, np.einsum("ni,n->i", J, res))
            theta = theta - d
            if np.max(np.abs(d)) < tol_px:
                return theta, res, True
        return theta, res, False

    theta0 = np.zeros(3) if init is None else np.array([(init[0] - 1.0) * lev, init[1], init[2]])
    theta, res, ok = solve(theta0)
    if not ok:  # a poor start: ask ECC for one
        warp = np.eye(2, 3, dtype=np.float32)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-6)
        try:
            _, warp = cv2.findTransformECC(prev, cur, warp, cv2.MOTION_AFFINE, crit, None, 1)
        except cv2.error:
            return None
        A = warp[:, :2].astype(np.float64)
        r0 = 0.5 * (A[0, 0] + A[1, 1])
        t0 = A @ c + warp[:, 2].astype(np.float64) - c
        theta, res, ok = solve(np.array([(r0 - 1.0) * lev, t0[0], t0[1]]))
        if not ok:
            return None
    r = 1.0 + theta[0] / lev
    if not (np.all(np.isfinite(theta)) and 0.5 < r < 2.0 and np.all(np.abs(theta[1:]) < 0.25 * min(h, w))):
        return None
    res = res - res.mean()
    s2 = float(np.einsum("n,n->", res, res)) / max(res.size - 3, 1)
    scale = np.diag([1.0 / lev, 1.0, 1.0])
    cov = scale @ (np.linalg.inv(H) * s2) @ scale
    return StepFit(float(r), float(theta[1]), float(theta[2]), cov, int(res.size))


def compose_steps(steps: list[StepFit | None], ref_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                         np.ndarray, np.ndarray]:
    """Compose neighbour steps (``steps[k]``: frame k -> k+1) into per-frame geometry about the reference.

    Returns (m, mag_sigma, sx, sy, shift_sigma), each (n,). A missing step (None) is bridged with the mean
    of the others and a large uncertainty.
    """
    n = len(steps) + 1
    good = [s for s in steps if s is not None]
    if good:
        fill = StepFit(float(np.mean([s.r for s in good])), float(np.mean([s.tx for s in good])),
                       float(np.mean([s.ty for s in good])),
                       np.diag([1e-6, 1.0, 1.0]) + np.mean([s.cov for s in good], axis=0) * 100.0, 0)
    else:
        fill = StepFit(1.0, 0.0, 0.0, np.diag([1e-6, 1.0, 1.0]), 0)
    steps = [s if s is not None else fill for s in steps]
    # The Gauss-Newton covariance ignores correlated residuals (blur changes, texture); with enough steps use
    # the step-to-step scatter instead: second differences remove any smooth trend of r(z) and t(z).
    if len(good) >= 5:
        arr = np.array([[s.r, s.tx, s.ty] for s in steps])
        d2 = arr[2:] - 2.0 * arr[1:-1] + arr[:-2]
        emp = (1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / math.sqrt(6.0)) ** 2
        steps = [replace(s, cov=np.diag(np.maximum(emp, np.diag(s.cov)))) if s.n_patches else s for s in steps]
    # Relative to frame 0: x_k = c + M_k (p0 - c) + S_k.
    M = np.ones(n)
    S = np.zeros((n, 2))
    for k, s in enumerate(steps):
        M[k + 1] = s.r * M[k]
        S[k + 1] = s.r * S[k] + (s.tx, s.ty)
    # Re-reference: p0 - c = (p - c - S_ref) / M_ref.
    m = M / M[ref_index]
    sx = S[:, 0] - m * S[ref_index, 0]
    sy = S[:, 1] - m * S[ref_index, 1]
    var_m = np.zeros(n)
    var_s = np.zeros(n)
    for k in range(n):
        lo, hi = (k, ref_index) if k < ref_index else (ref_index, k)
        for j in range(lo, hi):
            var_m[k] += steps[j].cov[0, 0]
            var_s[k] += 0.5 * (steps[j].cov[1, 1] + steps[j].cov[2, 2])
    return m, np.sqrt(var_m), sx, sy, np.sqrt(var_s)


def lateral_colour_scales(planes: dict[str, np.ndarray], centre_xy: tuple[float, float],
                          reference: str) -> dict[str, float]:
    """Scale of each channel about ``centre_xy`` relative to ``reference`` in one frame (same plane grid).

    Approximate: channels focus at different z (longitudinal colour), so their blur differs in one frame;
    the registration is unbiased for symmetric blur but noisier. NaN where the registration fails.
    """
    out = {reference: 1.0}
    ref = planes[reference]
    for name, p in planes.items():
        if name == reference:
            continue
        st = register_step(ref, p, centre_xy)
        out[name] = float(st.r) if st is not None else math.nan
    return out
