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


# ---------------------------------------------------------------------------------------------- sensor geometry
# A best-focus surface is defined in the z_ref geometry; during a sweep, sensor pixel p at stage position z sees
# the scene point warp^-1(p, z) (breathing, shift, distortion, lateral colour). Sweep windows are per sensor pixel.
SENSOR_GRID_PX = 16      # the correction is smooth (it follows the map and the surface): a coarse grid suffices
SENSOR_GRID_MIN_SAMPLES = 24  # ...with at least this many samples across the ROI's short side (small sensors)
SENSOR_Z_LEVELS = 9      # stage positions the inverse map is tabulated at (it changes slowly and smoothly with z)


def _warp(profile, x, y, z_um: float, ch: str):
    """``profile.warp_px`` where the model has one (maps or the scalar model), else its scalar m(z), s(z) model."""
    if hasattr(profile, "warp_px"):
        return profile.warp_px(x, y, float(z_um), ch)
    cx, cy = profile.optical_centre_px()
    m = float(np.asarray(profile.magnification(z_um, ch))) * float(profile.lateral_colour_scale(ch))
    sx, sy = (float(np.asarray(v)) for v in profile.shift_px(z_um, ch))
    return cx + m * (x - cx) + sx, cy + m * (y - cy) + sy


def inverse_warp_px(profile, x, y, z_um: float, ch: str, tol_px: float = 1e-6, max_iter: int = 50):
    """The z_ref-geometry point that sensor pixel(s) (x, y) of channel ``ch`` see at stage position ``z_um``.

    Fixed-point iteration ``q <- q - (warp(q, z) - p)``: it converges because the map's derivative is within a
    few per cent of the identity (breathing and distortion are small per pixel).
    """
    px, py = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    qx, qy = px.copy(), py.copy()
    for _ in range(max_iter):
        wx, wy = _warp(profile, qx, qy, z_um, ch)
        ex, ey = np.asarray(wx) - px, np.asarray(wy) - py
        qx, qy = qx - ex, qy - ey
        if max(float(np.max(np.abs(ex), initial=0.0)), float(np.max(np.abs(ey), initial=0.0))) < tol_px:
            break
    return qx, qy


def sensor_focus_um(profile, xs, ys, ch: str, refocus_um: float = 0.0, levels: int = SENSOR_Z_LEVELS,
                    iterations: int = 30) -> np.ndarray:
    """Best focus (stage µm, refocused) of each sensor pixel of the lattice ``xs`` x ``ys``: the z at which the
    pixel is in focus for the scene point it images there, ``z = bf(warp^-1(p, z)) + refocus``.

    The inverse map is computed at ``levels`` stage positions spanning the surface's range (with a margin), and
    ``G(p, z) = bf(warp^-1(p, z)) + refocus`` interpolated between them (cubic, extrapolated beyond); the fixed
    point ``z <- G(p, z)`` then converges in a few steps because G changes with z only through breathing.
    Returns an array (len(ys), len(xs)); where the surface is not finite at the imaged point, the pixel's own.
    """
    gx, gy = np.meshgrid(np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64))
    z0 = _bf(profile, gx, gy, ch, refocus_um)
    lo, hi = float(np.nanmin(z0)), float(np.nanmax(z0))
    pad = max(0.25 * (hi - lo), 10.0)
    zl = np.linspace(lo - pad, hi + pad, max(4, int(levels)))
    g = np.empty((len(zl),) + gx.shape)
    for k, zk in enumerate(zl):
        qx, qy = inverse_warp_px(profile, gx, gy, float(zk), ch)
        g[k] = _bf(profile, qx, qy, ch, refocus_um)
    g = np.where(np.isfinite(g), g, z0[None])
    dz = zl[1] - zl[0]
    rows, cols = np.indices(gx.shape)
    z = np.where(np.isfinite(z0), z0, 0.5 * (lo + hi))
    for _ in range(int(iterations)):
        # cubic Lagrange through the 4 nearest levels (error ~dz^4; piecewise-linear left 0.7 µm at 8x breathing)
        i = np.clip(np.floor((z - zl[0]) / dz).astype(np.int64), 1, len(zl) - 3)
        t = (z - zl[i]) / dz  # unclipped: extrapolates the end cubic beyond the tabulated range
        w = (-t * (t - 1) * (t - 2) / 6, (t + 1) * (t - 1) * (t - 2) / 2, -(t + 1) * t * (t - 2) / 2,
             (t + 1) * t * (t - 1) / 6)
        z_new = sum(wk * g[i + k - 1, rows, cols] for k, wk in enumerate(w))
        done = float(np.max(np.abs(z_new - z), initial=0.0)) < 1e-6
        z = z_new
        if done:
            break
    return np.where(np.isfinite(z0), z, np.nan)


def sensor_focus_correction(profile, roi, ch: str, refocus_um: float = 0.0, step_px: int | None = None):
    """``(x, y) -> sensor focus - z_ref-geometry focus`` (µm) over the ROI, as a callable on pixel coordinates:
    :func:`sensor_focus_um` on a coarse lattice (borders included; every 16 px, finer on small sensors),
    interpolated with a bicubic spline.
    None when the geometry does not move any pixel's focus (no breathing, shift or distortion): then the
    z_ref-geometry surface is the sensor's, exactly."""
    from scipy.interpolate import RectBivariateSpline

    x0, y0, w, h = roi
    if step_px is None:
        step_px = int(np.clip(min(w, h) // SENSOR_GRID_MIN_SAMPLES, 2, SENSOR_GRID_PX))
    xs = sc.sample_axes(x0, w, step_px)
    ys = sc.sample_axes(y0, h, step_px)
    gx, gy = np.meshgrid(xs, ys)
    d = sensor_focus_um(profile, xs, ys, ch, refocus_um) - _bf(profile, gx, gy, ch, refocus_um)
    d = np.nan_to_num(d, nan=0.0)
    if float(np.max(np.abs(d), initial=0.0)) < 1e-6:
        return None
    spline = RectBivariateSpline(ys, xs, d, kx=min(3, len(ys) - 1), ky=min(3, len(xs) - 1))
    return lambda x, y: spline(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64), grid=False)


def _refine(profile, ch, shift, roi, xs, ys, zs, step, pick, corr=None):
    """Evaluate the full-resolution window of +-step px around the extreme sample."""
    i = int(pick(zs))
    x0, y0, w, h = roi
    cx, cy = xs.flat[i], ys.flat[i]
    xa = np.arange(max(x0, int(cx) - step), min(x0 + w, int(cx) + step + 1), dtype=np.float64)
    ya = np.arange(max(y0, int(cy) - step), min(y0 + h, int(cy) + step + 1), dtype=np.float64)
    gx, gy = np.meshgrid(xa, ya)
    return _bf(profile, gx, gy, ch, shift) + (corr(gx, gy) if corr is not None else 0.0)


def sample_field(profile, scene: sc.Scene, step_px: int = 8, confidence: float | None = None,
                 sensor_geometry: bool = False) -> SampledField:
    """Best focus sampled over the ROI. ``sensor_geometry``: per sensor pixel, at the scene point it images at
    that stage position (:func:`sensor_focus_um`, what a sweep's per-pixel windows need); otherwise in the z_ref
    geometry the compositor registers frames to (what a stack's frames cover)."""
    roi = sc.resolve_roi(profile, scene.roi)
    channels = sc.resolve_channels(profile, scene.channels)
    shift = sc.refocus_shift_um(profile, scene.object_distance_mm)
    gx, gy = sc.sample_grid(profile, roi, step_px)
    out = {}
    for ch in channels:
        z = _bf(profile, gx, gy, ch, shift)
        corr = sensor_focus_correction(profile, roi, ch, shift) if sensor_geometry else None
        if corr is not None:
            z = z + corr(gx, gy)
        if not np.all(np.isfinite(z)):
            from ..errors import SpecError
            raise SpecError(f"the profile's best-focus surface of channel {ch} is not finite inside the ROI",
                            field="surfaces", fix="recalibrate, or restrict --roi to the calibrated field")
        u = (band_halfwidth_um(profile, gx, gy, ch, z - shift, confidence) if confidence is not None
             else np.zeros_like(z))
        zmin = min(float(z.min()), float(_refine(profile, ch, shift, roi, gx, gy, z, step_px, np.argmin, corr).min()))
        zmax = max(float(z.max()), float(_refine(profile, ch, shift, roi, gx, gy, z, step_px, np.argmax, corr).max()))
        gmax = 0.0
        if z.shape[1] > 1:
            gmax = max(gmax, float(np.max(np.abs(np.diff(z, axis=1)) / np.diff(gx, axis=1))))
        if z.shape[0] > 1:
            gmax = max(gmax, float(np.max(np.abs(np.diff(z, axis=0)) / np.diff(gy, axis=0))))
        out[ch] = ChannelSamples(ch, gx.ravel(), gy.ravel(), z.ravel(), u.ravel(), zmin, zmax,
                                 gmax * max(1, step_px) / math.sqrt(2.0))
    return SampledField(roi, channels, shift, int(step_px), out)
