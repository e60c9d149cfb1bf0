"""Frame geometry measured from the stack itself, for compositing without a profile.

Between neighbouring frames (sorted by z) ``cv2.findTransformECC`` measures a scale and shift on a grey,
downsampled copy (neighbours differ little in focus, so ECC locks on). The lens model of DESIGN.md makes the
magnification and shift linear in z (``m(z) = 1 + a (z - z_ref)``, ``s(z) = b (z - z_ref)``), so the rates
``a`` and ``b`` are the medians of the per-pair rates: robust to a failed pair, no drift from chaining.
The result answers the geometry part of the lens-profile interface.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..progress import progress
from .source import image_size, read_roi, z_positions


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


def _grey(stack, i: int, factor: int) -> np.ndarray:
    w, h = image_size(stack)
    img = read_roi(stack, i, 0, 0, w, h).astype(np.float32).mean(axis=2)
    if factor > 1:
        img = cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    return img


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
    prev = None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-6)
    for k, i in enumerate(progress(order, total=len(order), desc="registering", quiet=quiet, unit="frame")):
        cur = _grey(stack, int(i), factor)
        cur = (cur - cur.mean()) / max(float(cur.std()), 1e-12)
        if prev is not None:
            dz = float(zs[k] - zs[k - 1])
            warp = np.eye(2, 3, dtype=np.float32)
            try:
                _, warp = cv2.findTransformECC(prev, cur, warp, cv2.MOTION_AFFINE, criteria, None, 5)
            except cv2.error:
                warp = None
            if warp is not None:
                s = 0.5 * float(warp[0, 0] + warp[1, 1])
                # q = s p + t in downsampled px -> shift about the centre, in full-resolution px
                sx = float(warp[0, 2]) + (s - 1.0) * cs[0]
                sy = float(warp[1, 2]) + (s - 1.0) * cs[1]
                rates_m.append(np.log(s) / dz)
                rates_x.append(sx * factor / dz)
                rates_y.append(sy * factor / dz)
        prev = cur
    if not rates_m:
        return EstimatedGeometry(z_ref_um, c, 0.0, (0.0, 0.0), 0)
    return EstimatedGeometry(z_ref_um, c, float(np.median(rates_m)),
                             (float(np.median(rates_x)), float(np.median(rates_y))), len(rates_m))
