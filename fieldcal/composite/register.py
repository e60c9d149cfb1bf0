"""Frame geometry measured from the stack itself, for compositing without a profile.

Between neighbouring frames (sorted by z) calibration's registration (:func:`fieldcal.measure.geometry.
register_step`: Gauss-Newton on scale and shift with cubic-spline resampling, unbiased where OpenCV's ECC is
biased by ~10 % of a small scale change) measures a scale and shift on a grey, downsampled copy (neighbours
differ little in focus, so it locks on). The lens model (docs/architecture.md) makes the magnification and
shift linear in z (``m(z) = 1 + a (z - z_ref)``, ``s(z) = b (z - z_ref)``), so the rates ``a`` and ``b`` are
the medians of the per-pair rates: robust to a failed pair, no drift from chaining.
The result answers the geometry part of the lens-profile interface.
"""

from __future__ import annotations

import numpy as np

from ..measure.geometry import register_step, registration_plane
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
    prev, step = None, None
    for k, i in enumerate(progress(order, total=len(order), desc="registering", quiet=quiet, unit="frame")):
        cur = _grey(stack, int(i), factor)
        cur = (cur - cur.mean()) / max(float(cur.std()), 1e-12)
        if prev is not None:
            dz = float(zs[k] - zs[k - 1])
            # a point at p in prev is at cs + r (p - cs) + t in cur (downsampled px, about the centre)
            init = (step.r, step.tx, step.ty) if step is not None else None
            step = register_step(prev, cur, cs, init=init)
            if step is not None:
                rates_m.append(np.log(step.r) / dz)
                rates_x.append(step.tx * factor / dz)
                rates_y.append(step.ty * factor / dz)
        prev = cur
    if not rates_m:
        return EstimatedGeometry(z_ref_um, c, 0.0, (0.0, 0.0), 0)
    return EstimatedGeometry(z_ref_um, c, float(np.median(rates_m)),
                             (float(np.median(rates_x)), float(np.median(rates_y))), len(rates_m))
