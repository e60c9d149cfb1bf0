"""Sampled best-focus surfaces of the requested channels over the ROI (refocused), with refined extremes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import scene as sc
from .tolerance import band_halfwidth_um


@dataclass
class ChannelSamples:
    name: str
    x: np.ndarray           # sample pixel coordinates (flat)
    y: np.ndarray
    z_um: np.ndarray        # MAP best focus + refocus shift
    u_um: np.ndarray        # credible half-width at the requested level (0 without --confidence)
    z_min_um: float         # range over the ROI, extremes refined at full resolution
    z_max_um: float
    grid_error_bound_um: float  # |grad z|max * step / sqrt(2): worst first-order gap between samples


@dataclass
class SampledField:
    roi: tuple[int, int, int, int]
    channels: tuple[str, ...]
    refocus_um: float
    step_px: int
    samples: dict[str, ChannelSamples]

    @property
    def z_min_um(self) -> float:
        return min(s.z_min_um for s in self.samples.values())

    @property
    def z_max_um(self) -> float:
        return max(s.z_max_um for s in self.samples.values())

    @property
    def range_um(self) -> float:
        return self.z_max_um - self.z_min_um


def _bf(profile, x, y, ch, shift):
    return np.asarray(profile.best_focus_um(x, y, ch), dtype=np.float64) + shift


def _refine(profile, ch, shift, roi, xs, ys, zs, step, pick):
    """Evaluate the full-resolution window of +-step px around the extreme sample."""
    i = int(pick(zs))
    x0, y0, w, h = roi
    cx, cy = xs.flat[i], ys.flat[i]
    xa = np.arange(max(x0, int(cx) - step), min(x0 + w, int(cx) + step + 1), dtype=np.float64)
    ya = np.arange(max(y0, int(cy) - step), min(y0 + h, int(cy) + step + 1), dtype=np.float64)
    gx, gy = np.meshgrid(xa, ya)
    return _bf(profile, gx, gy, ch, shift)


def sample_field(profile, scene: sc.Scene, step_px: int = 8, confidence: float | None = None) -> SampledField:
    roi = sc.resolve_roi(profile, scene.roi)
    channels = sc.resolve_channels(profile, scene.channels)
    shift = sc.refocus_shift_um(profile, scene.object_distance_mm)
    gx, gy = sc.sample_grid(profile, roi, step_px)
    out = {}
    for ch in channels:
        z = _bf(profile, gx, gy, ch, shift)
        if not np.all(np.isfinite(z)):
            from ..errors import SpecError
            raise SpecError(f"the profile's best-focus surface of channel {ch} is not finite inside the ROI",
                            field="surfaces", fix="recalibrate, or restrict --roi to the calibrated field")
        u = (band_halfwidth_um(profile, gx, gy, ch, z - shift, confidence) if confidence is not None
             else np.zeros_like(z))
        zmin = min(float(z.min()), float(_refine(profile, ch, shift, roi, gx, gy, z, step_px, np.argmin).min()))
        zmax = max(float(z.max()), float(_refine(profile, ch, shift, roi, gx, gy, z, step_px, np.argmax).max()))
        gmax = 0.0
        if z.shape[1] > 1:
            gmax = max(gmax, float(np.max(np.abs(np.diff(z, axis=1)) / np.diff(gx, axis=1))))
        if z.shape[0] > 1:
            gmax = max(gmax, float(np.max(np.abs(np.diff(z, axis=0)) / np.diff(gy, axis=0))))
        out[ch] = ChannelSamples(ch, gx.ravel(), gy.ravel(), z.ravel(), u.ravel(), zmin, zmax,
                                 gmax * max(1, step_px) / math.sqrt(2.0))
    return SampledField(roi, channels, shift, int(step_px), out)
