"""Deconvolving a *captured* focal sweep: per-zone kernels with the image motion during the sweep, then geometry.

A physically captured sweep is recorded in the sensor's geometry, and while the stage moves the image of a scene
point moves too: its scale ``m(z)`` (focus breathing of a non-telecentric lens) and shift ``s(z)`` (stage axis
not parallel to the optical axis) change with z (the profile's :class:`~fieldcal.optics.FrameGeometry`). A
pixel at ``p`` exposed while the stage is within ±alpha of its window centre ``z_c(p)`` therefore records

* the scene at the position that lands on ``p`` at ``z_c(p)`` (a smooth per-pixel warp of the ``z_ref``
  image: up to D / exit pupil x the image radius, 25 px in the corners of the paper's triplet at 4K), and
* blurred by the defocus discs of the window, each displaced by ``v t`` (``t`` the stage's distance from
  ``z_c``, ``v = dp/dz`` the image velocity): a radial streak of ``2 alpha |v|`` px that grows with the image
  height, plus the shift's constant streak.

The kernel therefore varies over the field. :func:`deconvolve_zones` cuts the image into overlapping zones
(``zone_px`` square, half overlap, blended with sin² weights that sum to one), Wiener-deconvolves each with the
exact moving-sweep OTF of its centre (:func:`fieldcal.optics.sweep.moving_sweep_otf`: defocus and motion
integrated jointly) to the lens's in-focus image, and :func:`register_to_reference` then maps the result to the
``z_ref`` geometry (where stacks are composited and the simulator's truth lives). ``breathing="blind"`` keeps the
zones and the registration but drops the motion from the kernel: the comparison ``benchmarks/bench_sweep_vs_stack.py``
measures.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError
from ..optics import LensModel
from ..optics.sweep import integrated_otf, moving_sweep_otf, radial_on_grid, rfft_radial_grid

BREATHING = ("aware", "blind")
DEFAULT_ZONE_PX = 64


_CENTRE_CACHE: dict = {}  # (id(model), channel, refocus) -> (model, correction): one lattice solve per sweep


def _sensor_correction(model: LensModel, channel: str, refocus_um: float):
    from ..plan.surfaces import sensor_focus_correction

    size = getattr(model, "image_size_px", None)
    if size is None:
        return None
    key = (id(model), channel, float(refocus_um))
    hit = _CENTRE_CACHE.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    if len(_CENTRE_CACHE) > 16:
        _CENTRE_CACHE.clear()
    w, h = (int(v) for v in size)
    corr = sensor_focus_correction(model, (0, 0, w, h), channel, float(refocus_um))
    _CENTRE_CACHE[key] = (model, corr)
    return corr


def window_centres_um(model: LensModel, x, y, channel: str, refocus_um: float = 0.0) -> np.ndarray:
    """Stage position (µm) at the centre of the exposure window of sensor pixel(s) (x, y): the sweep plan opens
    each pixel α before its best focus (:func:`fieldcal.plan.masks.window_starts`), that of the scene point the
    sensor pixel images there through the profile's geometry (:func:`fieldcal.plan.surfaces.sensor_focus_um`)."""
    z = np.asarray(model.best_focus_um(x, y, channel), dtype=np.float64) + float(refocus_um)
    corr = _sensor_correction(model, channel, refocus_um)
    return z if corr is None else z + corr(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))


def _geometry(model: LensModel, z_um, channel: str):
    m = np.asarray(model.magnification(z_um, channel), dtype=np.float64)
    sx, sy = model.shift_px(z_um, channel)
    return m, np.asarray(sx, dtype=np.float64), np.asarray(sy, dtype=np.float64)


def image_velocity_px_per_um(model: LensModel, x, y, z_um, alpha_um: float, channel: str):
    """(vx, vy): image motion (px per µm of stage travel) at sensor pixel (x, y) over the window ``z ± alpha``.

    A z_ref pixel q lands at ``c + m(z) (q - c) + s(z)``; the derivative is the mean slope over the window
    (exact for the linear m and s of a thin-lens model), with q recovered from the sensor pixel at z.
    """
    cx, cy = model.optical_centre_px()
    a = max(float(alpha_um), 1e-3)
    z = np.asarray(z_um, dtype=np.float64)
    m, sx, sy = _geometry(model, z, channel)
    m1, sx1, sy1 = _geometry(model, z + a, channel)
    m0, sx0, sy0 = _geometry(model, z - a, channel)
    qx = (np.asarray(x, dtype=np.float64) - cx - sx) / m
    qy = (np.asarray(y, dtype=np.float64) - cy - sy) / m
    dm = (m1 - m0) / (2 * a)
    return dm * qx + (sx1 - sx0) / (2 * a), dm * qy + (sy1 - sy0) / (2 * a)


def _tile_starts(n: int, core: int) -> list[int]:
    step = max(1, core // 2)
    starts = list(range(0, max(n - core, 0) + 1, step))
    if starts[-1] + core < n:
        starts.append(n - core)
    return starts


def _blend_weight(core: int) -> np.ndarray:
    # sin² over the tile: two tiles half a tile apart sum to one; never exactly zero at the image border
    return np.sin(np.pi * (np.arange(core) + 0.5) / core) ** 2


def deconvolve_zones(channel_image: np.ndarray, model: LensModel, alpha_um: float, channel: str, *,
                     noise_sigma: float, signal_model: tuple[float, float], centre_um: np.ndarray,
                     widen_um: np.ndarray | None = None, breathing: str = "aware",
                     zone_px: int = DEFAULT_ZONE_PX) -> tuple[np.ndarray, dict]:
    """Wiener-deconvolve one channel of a captured sweep zone by zone (sensor geometry in, sensor geometry out).

    Parameters
    ----------
    channel_image : (H, W) array
        Black-subtracted or raw sweep image (the mean is kept).
    noise_sigma : float
        Pixel noise (image units).
    signal_model : (A, beta)
        Power-law signal spectrum ``A f^-beta`` (per-pixel power), fitted once on the whole image.
    centre_um : (H, W) array
        Window centre of each pixel (:func:`window_centres_um`).
    widen_um : (H, W) array, optional
        Per-pixel widening of the half-range (a plan made with ``--confidence``): the zone's half-range is
        ``alpha_um + widen_um`` at its centre.
    breathing : {"aware", "blind"}
        Include the image motion in each zone's kernel, or not.
    """
    from scipy import fft

    if breathing not in BREATHING:
        raise ParameterError(f"unknown breathing mode {breathing!r}", field="breathing",
                             fix=f"use one of {', '.join(BREATHING)}")
    img = np.asarray(channel_image, dtype=np.float64)
    h, w = img.shape
    pitch = float(model.pixel_pitch_um)
    mean = float(img.mean())
    a_max = float(alpha_um) + (float(np.max(widen_um)) if widen_um is not None else 0.0)
    corners_x, corners_y = np.array([0, w - 1, 0, w - 1.0]), np.array([0, 0, h - 1, h - 1.0])
    zc = window_centres_um(model, corners_x, corners_y, channel)
    vx, vy = image_velocity_px_per_um(model, corners_x, corners_y, zc, a_max, channel)
    v_max = float(np.max(np.hypot(vx, vy))) if breathing == "aware" else 0.0
    # halo: the whole kernel (streak + defocus disc) plus a margin for the Wiener filter's ringing
    halo = int(math.ceil(a_max * v_max + a_max / float(model.f_number) / pitch)) + 16
    core_y, core_x = min(int(zone_px), h), min(int(zone_px), w)
    padded = np.pad(img - mean, halo, mode="symmetric")
    ny = fft.next_fast_len(core_y + 2 * halo, real=True)
    nx = fft.next_fast_len(core_x + 2 * halo, real=True)
    fy = (fft.fftfreq(ny) / (pitch * 1e-3))[:, None]
    fx = (fft.rfftfreq(nx) / (pitch * 1e-3))[None, :]
    fr = rfft_radial_grid((ny, nx), pitch)
    a_sig, beta = signal_model
    fmin = 4.0 / (max(ny, nx) * pitch * 1e-3)
    px = a_sig * np.maximum(fr, fmin) ** (-beta)
    h0 = radial_on_grid(lambda t: integrated_otf(model, t, 0.0, channel), fr)
    noise_power = float(noise_sigma) ** 2
    wy, wx = _blend_weight(core_y), _blend_weight(core_x)
    acc = np.zeros((h, w))
    wsum = np.zeros((h, w))
    gains, streaks = [], []
    for y0 in _tile_starts(h, core_y):
        for x0 in _tile_starts(w, core_x):
            yc, xc = y0 + core_y // 2, x0 + core_x // 2
            a = float(alpha_um) + (float(widen_um[yc, xc]) if widen_um is not None else 0.0)
            v = (0.0, 0.0)
            if breathing == "aware":
                vxi, vyi = image_velocity_px_per_um(model, float(xc), float(yc), centre_um[yc, xc], a, channel)
                v = (float(vxi), float(vyi))
            streaks.append(2.0 * a * math.hypot(*v))
            block = padded[y0:y0 + core_y + 2 * halo, x0:x0 + core_x + 2 * halo]
            block = np.pad(block, ((0, ny - block.shape[0]), (0, nx - block.shape[1])), mode="symmetric")
            y = fft.rfft2(block, workers=-1)
            hs = moving_sweep_otf(model, fx, fy, a, channel, velocity_px_per_um=v, pitch_um=pitch)
            g = h0 * np.conj(hs) * px / ((hs.real ** 2 + hs.imag ** 2) * px + noise_power)
            g[0, 0] = 1.0
            out = fft.irfft2(y * g, s=(ny, nx), workers=-1)[halo:halo + core_y, halo:halo + core_x]
            wt = wy[:, None] * wx[None, :]
            acc[y0:y0 + core_y, x0:x0 + core_x] += wt * out
            wsum[y0:y0 + core_y, x0:x0 + core_x] += wt
            gains.append(float(np.sqrt(np.mean(np.abs(g) ** 2))))
    res = acc / wsum + mean
    return res.astype(np.float32), {"noise_sigma": float(noise_sigma), "noise_gain": float(np.max(gains)),
                                    "signal_beta": float(beta), "zones": len(gains),
                                    "max_streak_px": round(float(max(streaks)), 3)}


def register_to_reference(channel_image: np.ndarray, model: LensModel, channel: str,
                          refocus_um: float = 0.0, iterations: int = 3) -> np.ndarray:
    """Map one channel of a sweep image from the sensor's geometry to the ``z_ref`` frame's.

    Sensor pixel p saw the scene point q with ``p = c + m(z_c(p)) (q - c) + s(z_c(p))``, z_c its window centre;
    for each output pixel q this solves for p by fixed-point iteration (the map is within a few per cent of
    the identity) and samples the image there (Lanczos-4, mirrored edges: cubic interpolation cost 0.85 dB PSNR on
    the sweep benchmark's chart).
    """
    import cv2

    img = np.asarray(channel_image, dtype=np.float32)
    h, w = img.shape
    cx, cy = model.optical_centre_px()
    qy, qx = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = qx.copy(), qy.copy()
    for _ in range(int(iterations)):
        z = window_centres_um(model, px, py, channel, refocus_um)
        m, sx, sy = _geometry(model, z, channel)
        px = cx + m * (qx - cx) + sx
        py = cy + m * (qy - cy) + sy
    return cv2.remap(img, px.astype(np.float32), py.astype(np.float32), interpolation=cv2.INTER_LANCZOS4,
                     borderMode=cv2.BORDER_REFLECT)
