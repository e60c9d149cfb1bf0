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

import numpy as np

from ..errors import ParameterError
from . import noise as _noise

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
        frame = np.asarray(render_float(float(z_of_t_ms(0.5 * (t0 + t1)))), dtype=np.float32)
        if weights is not None:
            frame = frame * np.asarray(weights(float(t0), float(t1)), dtype=np.float32)
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


__all__ = ["Weights", "n_sub_for", "render_sweep_exposure", "sub_exposure_edges_ms", "sweep_signal"]
