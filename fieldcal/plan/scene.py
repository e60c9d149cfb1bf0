"""What a scene asks of a plan: a region of interest, channels, an object distance; and the sample grid.

Surfaces are evaluated on a subsampled pixel lattice (every ``step_px`` pixels, plus the ROI's last row and
column and the optical centre's row and column, so the corners, the border and the on-axis point are always
samples). Between samples the best focus can differ from the nearest sample by at most
``|grad z| * step_px / sqrt(2)``; the planners do not rely on that bound for the range of best focus (they
refine the extremes at full resolution and cover the whole range of values in between, see stack_plan.py),
and they report it as ``grid_error_bound_um``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..optics import LensModel


@dataclass(frozen=True)
class Scene:
    """ROI ``(x, y, w, h)`` in px (None = whole image), channel names (None = all), object distance (None = as calibrated)."""

    roi: tuple[int, int, int, int] | None = None
    channels: tuple[str, ...] | None = None
    object_distance_mm: float | None = None

    def __post_init__(self):
        d = self.object_distance_mm
        if d is not None and (isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d)):
            raise ParameterError(f"object distance must be a finite number of mm, got {d!r}",
                                 field="object_distance_mm", fix="e.g. 500")


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """``"X,Y,W,H"`` in pixels -> tuple, with a clear error."""
    try:
        parts = [int(round(float(v))) for v in str(text).replace(" ", "").split(",")]
    except ValueError:
        parts = []
    if len(parts) != 4:
        raise ParameterError(f"ROI {text!r} is not four numbers X,Y,W,H", field="roi",
                             fix="give the region as X,Y,W,H in pixels, e.g. --roi 0,0,640,480")
    return tuple(parts)  # type: ignore[return-value]


def resolve_roi(profile, roi) -> tuple[int, int, int, int]:
    """Clip the ROI to the image; an empty result is an error."""
    w_img, h_img = (int(v) for v in profile.image_size_px)
    if roi is None:
        return (0, 0, w_img, h_img)
    x, y, w, h = (int(v) for v in roi)
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + w, w_img), min(y + h, h_img)
    if w <= 0 or h <= 0 or x1 <= x0 or y1 <= y0:
        raise ParameterError(f"ROI {x},{y},{w},{h} is empty inside the {w_img}x{h_img} image", field="roi",
                             fix=f"give X,Y,W,H with W, H > 0 overlapping 0..{w_img - 1} x 0..{h_img - 1}")
    return (x0, y0, x1 - x0, y1 - y0)


def resolve_channels(profile, channels) -> tuple[str, ...]:
    have = tuple(profile.channels)
    if channels is None or len(channels) == 0:
        return have
    out = []
    for c in channels:
        c = str(c).strip()
        if c not in have:
            raise ParameterError(f"channel {c!r} is not in the profile (it has {', '.join(have)})", field="channels",
                                 fix=f"use a subset of {','.join(have)}")
        if c not in out:
            out.append(c)
    return tuple(out)


def refocus_shift_um(profile: LensModel, object_distance_mm) -> float:
    """Stage shift (µm, +z away from the lens) that refocuses the surfaces from the calibration distance.

    Thin-lens image distance ``v = f u / (u - f)``; a change of object distance moves every best-focus point by
    the same ``v(u') - v(u)`` to first order (the paper notes the curved surface's shape hardly changes with
    object distance).
    """
    if object_distance_mm is None:
        return 0.0
    u_new = float(object_distance_mm)
    f, u_cal = profile.focal_length_mm, profile.object_distance_mm
    if f is None or u_cal is None:
        raise ParameterError("the profile does not record its calibration object distance and focal length, "
                             "so it cannot be refocused", field="object_distance_mm",
                             fix="drop --object-distance-mm, or calibrate at the scene's distance")
    f = float(f)
    if not math.isfinite(u_new) or u_new <= f or float(u_cal) <= f:
        raise ParameterError(f"object distance {u_new} mm must be finite and beyond the focal length {f} mm",
                             field="object_distance_mm", fix=f"give a distance > {f} mm")
    v = lambda u: f * u / (u - f)  # noqa: E731
    return float((v(u_new) - v(float(u_cal))) * 1000.0)


def sample_axes(lo: int, n: int, step_px: int, extra: float | None = None) -> np.ndarray:
    """Sample coordinates along one axis: every ``step_px`` from ``lo``, the last pixel, and ``extra`` if inside."""
    hi = lo + n - 1
    v = list(range(lo, hi + 1, max(1, int(step_px))))
    v.append(hi)
    if extra is not None and lo <= extra <= hi:
        v += [int(math.floor(extra)), int(math.ceil(extra))]
    return np.unique(np.asarray(v, dtype=np.float64))


def sample_grid(profile, roi, step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Lattice of sample pixels (x, y) inside the ROI, including its border, corners and the optical centre."""
    if int(step_px) < 1:
        raise ParameterError(f"grid step {step_px} px must be >= 1", field="grid_step_px", fix="use e.g. 8")
    x0, y0, w, h = roi
    cx, cy = profile.optical_centre_px()
    xs = sample_axes(x0, w, step_px, cx)
    ys = sample_axes(y0, h, step_px, cy)
    return np.meshgrid(xs, ys)


def full_grid(roi) -> tuple[np.ndarray, np.ndarray]:
    x0, y0, w, h = roi
    return np.meshgrid(np.arange(x0, x0 + w, dtype=np.float64), np.arange(y0, y0 + h, dtype=np.float64))
