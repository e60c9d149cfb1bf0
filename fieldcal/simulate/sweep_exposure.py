"""One exposure over a focal sweep, physically: the scene integrated while the sensor moves, pixel by pixel
gated by a per-pixel exposure device, with the sensor's noise applied once to the total.

A real sensor accumulates photo-electrons over the whole exposure and is read out once, so photon noise is that
of the total charge and read noise enters once. Emulating a sweep by summing noisy frames would count the read
noise N times (and quantise N times); here the *noise-free* signal of ``n_sub`` sub-exposures is integrated —
each rendered at the sensor's position at the sub-exposure's mid-time and multiplied by the fraction of that
sub-interval each pixel was open — and :func:`fieldcal.simulate.noise.to_dn` is applied to the sum.

Units: the signal is in fractions of the full well, scaled by exposure time relative to the lens spec's
nominal ``sensor.exposure_ms`` (the renderer's frames are metered for it): a pixel open for ``t`` ms collects
``t / exposure_ms`` times the frame signal, averaged over where the sensor was while it was open.
"""

from __future__ import annotations

import math
from typing import Callable

from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError
from . import noise as _noise
from .render import Renderer

#: ``weights(t0_ms, t1_ms)``: the fraction (0..1) of ``[t0, t1)`` (ms from the exposure's start) each pixel was
#: open, broadcastable to the frame's H x W x C (or H x W for a Bayer mosaic); None = every pixel always open.
Weights = Callable[[float, float], np.ndarray]


def sub_exposure_edges_ms(duration_ms: float, n_sub: int) -> np.ndarray:
    """``n_sub + 1`` equally spaced instants from 0 to ``duration_ms``."""
    if not (math.isfinite(duration_ms) and duration_ms > 0):
        raise ParameterError(f"exposure {duration_ms!r} ms must be finite and > 0", field="duration_ms",
                             fix="give the sweep's exposure time in ms")
    if isinstance(n_sub, bool) or not isinstance(n_sub, (int, np.integer)) or not 1 <= n_sub <= 100000:
        raise ParameterError(f"n_sub = {n_sub!r} must be an integer in 1..100000", field="n_sub",
                             fix="e.g. one sub-exposure per micrometre of the sweep")
    return np.linspace(0.0, float(duration_ms), int(n_sub) + 1)


def sweep_signal(render_float: Callable[[float], np.ndarray], z_of_t_ms: Callable[[float], float],
                 duration_ms: float, nominal_exposure_ms: float, *, n_sub: int,
                 weights: Weights | None = None) -> np.ndarray:
    """Noise-free integrated signal (fraction of full well, float32) of one exposure over a sweep.

    Parameters
    ----------
    render_float : ``z_um -> H x W x C`` linear frame signal at the nominal exposure (``Renderer.render_float``).
    z_of_t_ms : sensor position (µm) at time ``t`` ms after the exposure opened.
    duration_ms : how long the exposure lasts.
    nominal_exposure_ms : the exposure ``render_float``'s frames are metered for.
    n_sub : sub-exposures (the sum is a midpoint rule in time).
    weights : per-pixel open fraction of each sub-interval (see :data:`Weights`).

    Returns
    -------
    numpy.ndarray
        ``sum_k frame(z(t_k)) * w_k * dt / nominal`` — the mean of the masked frames times
        ``duration / nominal``.
    """
    edges = sub_exposure_edges_ms(duration_ms, n_sub)
    if not (math.isfinite(nominal_exposure_ms) and nominal_exposure_ms > 0):
        raise ParameterError(f"nominal exposure {nominal_exposure_ms!r} ms must be > 0", field="sensor.exposure_ms",
                             fix="set the lens spec's sensor.exposure_ms")
    acc = None
    for t0, t1 in zip(edges[:-1], edges[1:]):
        w = None if weights is None else np.asarray(weights(float(t0), float(t1)), dtype=np.float32)
        if w is not None and acc is not None and not w.any():
            continue   # no pixel open in this sub-interval: nothing to render
        frame = np.asarray(render_float(float(z_of_t_ms(0.5 * (t0 + t1)))), dtype=np.float32)
        if w is not None:
            frame = frame * w
        acc = frame.astype(np.float64) if acc is None else acc + frame
    return (acc * (float(duration_ms) / n_sub / float(nominal_exposure_ms))).astype(np.float32)


def render_sweep_exposure(renderer, z_of_t_ms: Callable[[float], float], duration_ms: float, *, n_sub: int,
                          weights: Weights | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
    """The frame a camera records over one sweep exposure, noise applied once (``rng`` None: noise-free).

    ``renderer`` is a :class:`fieldcal.simulate.Renderer`; a Bayer sensor (``spec.sensor.cfa``) is mosaicked
    before ``weights`` apply (a CFA mask plane is per photosite), so ``weights`` are then H x W. Returns the sensor's dtype, as :meth:`Renderer.render`.
    """
    spec = renderer.spec
    cfa = spec.sensor.cfa

    def frame(z_um: float) -> np.ndarray:
        sig = renderer.render_float(z_um)
        if cfa:
            sig = _noise.mosaic(sig, renderer.channels, cfa)
        return sig

    sig = sweep_signal(frame, z_of_t_ms, duration_ms, float(spec.sensor.exposure_ms), n_sub=n_sub, weights=weights)
    return _noise.to_dn(sig, spec.sensor, rng)


def n_sub_for(distance_um: float, step_um: float, *, at_least: int = 8) -> int:
    """Sub-exposures for a sweep over ``distance_um`` with at most ``step_um`` between renders."""
    if not (math.isfinite(step_um) and step_um > 0):
        raise ParameterError(f"sub-exposure step {step_um!r} um must be > 0", field="sub_step_um", fix="e.g. 1")
    return max(int(at_least), int(math.ceil(abs(float(distance_um)) / float(step_um))))


# --- constant-velocity sweeps with per-pixel windows (a plan's window_start_ms / window_stop_ms) ---


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


def render_windowed_sweep(renderer: Renderer, start_um: float, velocity_um_per_ms: float, total_time_ms: float,
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
    """The noise-free integrated signal of :func:`render_windowed_sweep` (float32 H x W x C, fraction of full
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
    sign = 1.0 if direction == "+z" else -1.0
    ref_ms = float(renderer.spec.sensor.exposure_ms)

    def open_fraction(a: float, b: float) -> np.ndarray:
        # exact fraction of [a, b) inside each pixel's window, as (H, W, 1 or C)
        open_ms = np.clip(np.minimum(t1, np.float32(b)) - np.maximum(t0, np.float32(a)), 0.0, None)
        return np.moveaxis(open_ms, 0, -1) / np.float32(b - a)

    signal = sweep_signal(renderer.render_float, lambda t: float(start_um) + sign * float(velocity_um_per_ms) * t,
                          float(total_time_ms), ref_ms, n_sub=n_sub, weights=open_fraction)
    open_total = np.maximum(t1 - t0, 0.0)
    mean_open = open_total.reshape(open_total.shape[0], -1).mean(axis=1)
    return signal, {"sub_exposures": n_sub, "step_um": step, "reference_exposure_ms": ref_ms,
                    "mean_open_ms": [round(float(v), 4) for v in mean_open]}


def model_noise_sigma(image: np.ndarray, renderer: Renderer) -> list[float]:
    """RMS pixel noise (DN) per channel of a recorded image under the simulated sensor's noise model (photon +
    read): :func:`fieldcal.composite.sweep.sensor_noise_sigma` with the sensor's gain, read noise and black
    level — what a camera's noise calibration gives a deconvolution instead of an estimate from the image."""
    from ..composite.sweep import sensor_noise_sigma

    s = renderer.spec.sensor
    return sensor_noise_sigma(image, _noise.gain_dn_per_e(s), s.read_noise_e, s.black_level_dn)


__all__ = ["SweepExposure", "Weights", "default_step_um", "integrate_sweep_signal", "model_noise_sigma", "n_sub_for",
           "record", "render_sweep_exposure", "render_windowed_sweep", "sub_exposure_edges_ms", "sweep_signal"]
