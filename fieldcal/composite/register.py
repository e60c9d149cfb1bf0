"""Frame geometry measured from the stack itself, for compositing without a profile.

Between neighbouring frames (sorted by z) calibration's registration (:func:`fieldcal.measure.geometry.
register_step`: Gauss-Newton on scale and shift with cubic-spline resampling, unbiased where OpenCV's ECC is
biased by ~10 % of a small scale change) measures a scale and shift on a grey, downsampled copy (neighbours
differ little in focus, so it locks on). The lens model (docs/architecture.md) makes the magnification and
shift linear in z (``m(z) = 1 + a (z - z_ref)``, ``s(z) = b (z - z_ref)``), so the rates ``a`` and ``b`` are
the medians of the per-pair rates: robust to a failed pair, no drift from chaining. A handheld or rail stack
does not follow that model (the camera moves a little between frames): when the chained per-pair steps leave
the linear model by more than half a pixel at the image corner, each frame gets its own chained scale and shift
(:class:`ChainedGeometry`) instead. Either result answers the geometry part of the lens-profile interface.
"""

from __future__ import annotations

import numpy as np

from ..measure.geometry import register_step, registration_plane
from ..progress import progress
from .source import image_size, read_roi, z_positions


#: Chained per-frame geometry replaces the linear model when the two differ by more than this at the image
#: corner (px): below it the linear model's robustness (a median, no drift) is worth more.
CHAIN_DEVIATION_PX = 0.5


class EstimatedGeometry:
    """Geometry of the lens-profile interface, measured from a stack (``z_ref_um`` = a frame of the stack)."""

    has_measured_tolerance = False

    def __init__(self, z_ref_um: float, centre_px: tuple[float, float], scale_rate_per_um: float,
                 shift_rate_px_per_um: tuple[float, float], n_pairs: int):
        self.z_ref_um = float(z_ref_um)
        self.centre = (float(centre_px[0]), float(centre_px[1]))
        self.scale_rate_per_um = float(scale_rate_per_um)
        self.shift_rate_px_per_um = (float(shift_rate_px_per_um[0]), float(shift_rate_px_per_um[1]))
        self.n_pairs = int(n_pairs)

    def optical_centre_px(self) -> tuple[float, float]:
        return self.centre

    def magnification(self, z_um, channel=None):
        return 1.0 + self.scale_rate_per_um * (np.asarray(z_um, dtype=np.float64) - self.z_ref_um)

    def shift_px(self, z_um, channel=None):
        dz = np.asarray(z_um, dtype=np.float64) - self.z_ref_um
        return dz * self.shift_rate_px_per_um[0], dz * self.shift_rate_px_per_um[1]

    def lateral_colour_scale(self, channel) -> float:
        return 1.0

    def info(self) -> dict:
        return {"z_ref_um": self.z_ref_um, "scale_rate_per_um": self.scale_rate_per_um,
                "shift_rate_px_per_um": list(self.shift_rate_px_per_um), "pairs_used": self.n_pairs}


class ChainedGeometry(EstimatedGeometry):
    """Per-frame geometry from chained neighbour registrations (interpolated in z between frames)."""

    def __init__(self, z_ref_um, centre_px, z_um, magnification, shift_x_px, shift_y_px, linear: EstimatedGeometry,
                 deviation_px: float):
        super().__init__(z_ref_um, centre_px, linear.scale_rate_per_um, linear.shift_rate_px_per_um, linear.n_pairs)
        self.z_table = np.asarray(z_um, dtype=np.float64)
        self.m_table = np.asarray(magnification, dtype=np.float64)
        self.sx_table = np.asarray(shift_x_px, dtype=np.float64)
        self.sy_table = np.asarray(shift_y_px, dtype=np.float64)
        self.deviation_px = float(deviation_px)

    def magnification(self, z_um, channel=None):
        return np.interp(np.asarray(z_um, dtype=np.float64), self.z_table, self.m_table)

    def shift_px(self, z_um, channel=None):
        z = np.asarray(z_um, dtype=np.float64)
        return np.interp(z, self.z_table, self.sx_table), np.interp(z, self.z_table, self.sy_table)

    def info(self) -> dict:
        return {**super().info(), "model": "per-frame (chained)",
                "linear_model_deviation_px": round(self.deviation_px, 3)}


def _chain(zs, steps, linear: EstimatedGeometry, cs, factor: int, z_ref_um: float):
    """Per-frame (m, sx, sy) relative to the frame at ``z_ref_um`` from neighbour steps (None: the linear model's
    step for that pair). A step maps p in frame k-1 to cs + r (p - cs) + t in frame k (downsampled px)."""
    R, T = [1.0], [np.zeros(2)]
    for k in range(1, len(zs)):
        s = steps[k - 1]
        dz = float(zs[k] - zs[k - 1])
        if s is None:
            r = float(np.exp(linear.scale_rate_per_um * dz))
            tt = np.array(linear.shift_rate_px_per_um) * dz / factor
        else:
            r, tt = float(s.r), np.array([s.tx, s.ty])
        R.append(R[-1] * r)
        T.append(r * T[-1] + tt)
    R, T = np.array(R), np.array(T)
    kr = int(np.argmin(np.abs(np.asarray(zs) - z_ref_um)))
    m = R / R[kr]
    shift = (T - m[:, None] * T[kr]) * factor
    return m, shift[:, 0], shift[:, 1]


def _ecc_start(prev: np.ndarray, cur: np.ndarray, cs) -> tuple[float, float, float] | None:
    """(r, tx, ty) about ``cs`` from OpenCV's ECC (affine, Gaussian-smoothed), or None when it fails."""
    import cv2

    warp = np.eye(2, 3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    try:
        _, warp = cv2.findTransformECC(prev.astype(np.float32), cur.astype(np.float32), warp, cv2.MOTION_AFFINE,
                                       crit, None, 5)
    except cv2.error:
        return None
    a = warp[:, :2].astype(np.float64)
    r = 0.5 * (a[0, 0] + a[1, 1])
    t = a @ np.asarray(cs, dtype=np.float64) + warp[:, 2].astype(np.float64) - np.asarray(cs, dtype=np.float64)
    return (float(r), float(t[0]), float(t[1])) if 0.5 < r < 2.0 else None


def _grey(stack, i: int, factor: int) -> np.ndarray:
    w, h = image_size(stack)
    return registration_plane(read_roi(stack, i, 0, 0, w, h).astype(np.float32).mean(axis=2), factor)


def estimate_geometry(stack, frames=None, z_ref_um: float | None = None, max_side_px: int = 1024,
                      quiet: bool = False) -> EstimatedGeometry:
    """Measure focus breathing and stage-axis shift from neighbouring frames (one or two in memory).

    ``z_ref_um`` (the output geometry) defaults to the frame at the middle of the z range.
    """
    w, h = image_size(stack)
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    zs = z_all[order]
    if z_ref_um is None:
        z_ref_um = float(zs[len(zs) // 2])
    factor = max(1, int(np.ceil(max(w, h) / max_side_px)))
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    cs = ((w // factor - 1) / 2.0, (h // factor - 1) / 2.0)
    rates_m, rates_x, rates_y = [], [], []
    steps = []
    prev, step = None, None
    for k, i in enumerate(progress(order, total=len(order), desc="registering", quiet=quiet, unit="frame")):
        cur = _grey(stack, int(i), factor)
        cur = (cur - cur.mean()) / max(float(cur.std()), 1e-12)
        if prev is not None:
            dz = float(zs[k] - zs[k - 1])
            # a point at p in prev is at cs + r (p - cs) + t in cur (downsampled px, about the centre)
            init = (step.r, step.tx, step.ty) if step is not None else None
            # photographs (not charts): neighbours differ in focus, so the update settles at noise level; a
            # handheld step can be several px, beyond Gauss-Newton's reach from the previous step: ECC (on a
            # smoothed copy, robust to the focus change) gives the start
            ecc = _ecc_start(prev, cur, cs)
            step = register_step(prev, cur, cs, init=ecc or init, iterations=20, tol_px=1e-3)
            steps.append(step)
            if step is not None:
                rates_m.append(np.log(step.r) / dz)
                rates_x.append(step.tx * factor / dz)
                rates_y.append(step.ty * factor / dz)
        prev = cur
    if not rates_m:
        return EstimatedGeometry(z_ref_um, c, 0.0, (0.0, 0.0), 0)
    linear = EstimatedGeometry(z_ref_um, c, float(np.median(rates_m)),
                               (float(np.median(rates_x)), float(np.median(rates_y))), len(rates_m))
    if len(zs) < 3:
        return linear
    m, sx, sy = _chain(zs, steps, linear, cs, factor, float(z_ref_um))
    # how far the chained positions of the image corner leave the linear model, in full-resolution px
    corner = float(np.hypot(w / 2.0, h / 2.0))
    lm = np.asarray(linear.magnification(zs))
    lx, ly = linear.shift_px(zs)
    dev = float(np.max(np.abs(m - lm) * corner + np.hypot(sx - lx, sy - ly)))
    if dev <= CHAIN_DEVIATION_PX:
        return linear
    return ChainedGeometry(z_ref_um, c, zs, m, sx, sy, linear, dev)
