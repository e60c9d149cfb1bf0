"""A physically emulated focal-sweep exposure: one image integrated while the stage moves, per-pixel windows.

The stage moves at constant velocity from ``start_um`` for ``total_time_ms``; each pixel of each channel
integrates only inside its window ``[window_start_ms, window_stop_ms)`` (a pixel-wise exposure sensor, or an
LCoS whose slots the plan's windows describe). The exposure is cut into sub-exposures of ``step_um`` of stage
travel; in each the renderer's noise-free frame at the sub-exposure's middle position (defocus, focus breathing,
stage-axis shift, vignetting: everything :class:`~fieldcal.simulate.render.Renderer` models) is weighted by the
time each pixel is open within it (exact fractional overlap of the windows), and the sum is recorded once by the
sensor: photon and read noise, gain, clipping and quantisation are applied to the total, as a real exposure.

Radiometry: the renderer is metered for the sensor's ``exposure_ms`` (``render_float`` = fraction of full well
after that long), so a pixel open for ``t`` ms collects ``t / exposure_ms`` of it.

Unlike :func:`fieldcal.composite.emulate_sweep` (frames of a stack registered to ``z_ref`` and averaged, noise of
each frame averaged down), this image is in the sensor's geometry, moves with breathing during each window, and
carries the noise of one exposure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError
from . import noise as _noise
from .render import Renderer


@dataclass
class SweepExposure:
    """The recorded sweep (sensor dtype, H x W x C or an H x W mosaic) and how it was integrated."""

    image: np.ndarray
    info: dict = field(default_factory=dict)


def default_step_um(renderer: Renderer, max_change_px: float = 0.25) -> float:
    """Stage travel per sub-exposure such that neither the blur-disc diameter (``dz / (N p)`` px) nor the image
    position (breathing at the sensor corner, stage-axis shift) changes by more than ``max_change_px``."""
    spec = renderer.spec
    pitch = spec.sensor.pixel_pitch_um
    by_blur = max_change_px * spec.f_number * pitch
    cx, cy = renderer.centre_px
    r_max = math.hypot(max(cx, renderer.width_px - 1 - cx), max(cy, renderer.height_px - 1 - cy))
    v = 0.0 if not math.isfinite(spec.exit_pupil_mm) else r_max / (spec.exit_pupil_mm * 1000.0)
    v += float(np.hypot(*spec.shift_px(spec.z_ref_um + 1.0)) - np.hypot(*spec.shift_px(spec.z_ref_um)))
    return float(by_blur if v <= 0 else min(by_blur, max_change_px / v))


def render_sweep_exposure(renderer: Renderer, start_um: float, velocity_um_per_ms: float, total_time_ms: float,
                          window_start_ms: np.ndarray, window_stop_ms: np.ndarray, *, direction: str = "+z",
                          step_um: float | None = None, noise: bool = True, seed: int | None = None) -> SweepExposure:
    """Integrate the renderer's scene over a constant-velocity sweep with per-pixel exposure windows, then record
    the total once (noise, gain, clipping, quantisation).

    Parameters
    ----------
    renderer : Renderer
        The lens, sensor and scene.
    start_um, velocity_um_per_ms, total_time_ms : float
        The sweep: the stage is at ``start_um ± v t`` (sign from ``direction``) at time t in [0, total_time_ms].
    window_start_ms, window_stop_ms : (C, H, W) or (H, W) arrays
        Each pixel's exposure window per channel (one (H, W) map serves every channel, e.g. a CFA plan's single
        plane); NaN = never exposed. A plan's ``window_start_ms`` / ``window_stop_ms``.
    step_um : float, optional
        Stage travel per sub-exposure (default :func:`default_step_um`).
    noise : bool
        Photon and read noise on the total (once), from ``seed`` (default: the renderer's).

    Returns
    -------
    SweepExposure
        ``image`` in the sensor's dtype (a Bayer mosaic if the sensor has a CFA), ``info`` with the
        sub-exposure count, step and per-channel mean open time.
    """
    signal, info = integrate_sweep_signal(renderer, start_um, velocity_um_per_ms, total_time_ms, window_start_ms,
                                          window_stop_ms, direction=direction, step_um=step_um)
    return SweepExposure(record(signal, renderer, noise=noise, seed=seed), info)


def record(signal: np.ndarray, renderer: Renderer, *, noise: bool = True, seed: int | None = None) -> np.ndarray:
    """The sensor's recording of an integrated signal (fraction of full well, H x W x C): mosaic if the sensor
    has a CFA, photon and read noise once (seeded), gain, clipping, quantisation."""
    if renderer.spec.sensor.cfa:
        signal = _noise.mosaic(signal, renderer.channels, renderer.spec.sensor.cfa)
    rng = None
    if noise:
        rng = np.random.default_rng(np.random.SeedSequence([renderer.seed if seed is None else int(seed), 0x5EE9]))
    return _noise.to_dn(signal, renderer.spec.sensor, rng)


def integrate_sweep_signal(renderer: Renderer, start_um: float, velocity_um_per_ms: float, total_time_ms: float,
                           window_start_ms: np.ndarray, window_stop_ms: np.ndarray, *, direction: str = "+z",
                           step_um: float | None = None) -> tuple[np.ndarray, dict]:
    """The noise-free integrated signal of :func:`render_sweep_exposure` (float32 H x W x C, fraction of full
    well) and the integration's info."""
    if direction not in ("+z", "-z"):
        raise ParameterError(f"direction {direction!r} unknown", field="direction", fix="use +z or -z")
    for name, val in (("velocity_um_per_ms", velocity_um_per_ms), ("total_time_ms", total_time_ms)):
        if not (math.isfinite(float(val)) and float(val) > 0):
            raise ParameterError(f"{name} = {val!r} must be a finite number > 0", field=name,
                                 fix="pass the sweep plan's values")
    nc = len(renderer.channels)
    shape = (renderer.height_px, renderer.width_px)
    t0, t1 = (np.asarray(a, dtype=np.float32) for a in (window_start_ms, window_stop_ms))
    if t0.ndim == 2:
        t0, t1 = t0[None], t1[None]
    if t0.shape != t1.shape or t0.shape[1:] != shape or t0.shape[0] not in (1, nc):
        raise ParameterError(f"exposure windows of shape {t0.shape} do not fit a {nc}-channel "
                             f"{shape[1]}x{shape[0]} sensor", field="window_start_ms",
                             fix="give (C, H, W) or (H, W) windows at the sensor's size")
    t0 = np.nan_to_num(t0, nan=0.0)
    t1 = np.where(np.isfinite(t1), t1, 0.0).astype(np.float32)  # NaN: start = stop, never open
    step = float(step_um) if step_um is not None else default_step_um(renderer)
    if not (math.isfinite(step) and step > 0):
        raise ParameterError(f"sub-exposure step {step_um!r} µm must be > 0", field="step_um", fix="e.g. 2")
    travel = float(velocity_um_per_ms) * float(total_time_ms)
    n_sub = max(1, int(math.ceil(travel / step - 1e-9)))
    dt = float(total_time_ms) / n_sub
    sign = 1.0 if direction == "+z" else -1.0
    ref_ms = float(renderer.spec.sensor.exposure_ms)
    signal = np.zeros(shape + (nc,), dtype=np.float32)
    for k in range(n_sub):
        a, b = k * dt, (k + 1) * dt
        open_ms = np.clip(np.minimum(t1, np.float32(b)) - np.maximum(t0, np.float32(a)), 0.0, None)
        if not open_ms.any():
            continue
        frame = renderer.render_float(float(start_um) + sign * float(velocity_um_per_ms) * 0.5 * (a + b))
        wts = np.moveaxis(open_ms, 0, -1) / np.float32(ref_ms)   # (H, W, 1 or C)
        signal += frame * wts
    open_total = np.maximum(t1 - t0, 0.0)
    mean_open = open_total.reshape(open_total.shape[0], -1).mean(axis=1)
    return signal, {"sub_exposures": n_sub, "step_um": step, "reference_exposure_ms": ref_ms,
                    "mean_open_ms": [round(float(v), 4) for v in mean_open]}


def model_noise_sigma(image: np.ndarray, renderer: Renderer) -> list[float]:
    """RMS pixel noise (DN) per channel of a recorded image under the sensor's noise model (photon + read):
    ``sqrt(mean(g (DN - black) + (g read)^2))`` — what a camera's noise calibration gives a deconvolution
    instead of an estimate from the image (which texture inflates)."""
    s = renderer.spec.sensor
    g = _noise.gain_dn_per_e(s)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[..., None]
    var = g * np.clip(img - s.black_level_dn, 0.0, None) + (g * s.read_noise_e) ** 2
    return [float(np.sqrt(var[..., c].mean())) for c in range(img.shape[2])]
