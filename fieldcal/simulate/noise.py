"""The simulated sensor: exposure, Bayer mosaic, photon and read noise, gain, black level, quantisation.

Signals here are in units of the full well (0..1 = 0..full_well_e electrons). The gain maps the full well to
the white level above black, ``g = (white - black) / full_well`` DN per electron, so a noise-free frame is
``black + g * e`` and the photon-noise variance of a pixel is ``g * (DN - black) + (g * read_noise_e)**2``.
Large frames draw photon noise above 100 e- from a moment-matched normal approximation (:func:`add_noise_e`).
"""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from fieldcal.simulate.lens import SensorSpec

# (row, col) of each colour in the 2x2 Bayer tile, in the order (0,0), (0,1), (1,0), (1,1).
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


HEADROOM = 0.9


def exposure_scale(scene: np.ndarray, signal_fraction: float) -> float:
    """Scene value -> fraction of full well: a metered exposure.

    The mean scene value reaches ``signal_fraction`` of the full well, unless that would push the brightest
    scene value past 90% of the full well, in which case the brightest value is put there (headroom for photon
    noise and blur overshoot, as a lab exposes a chart).
    """
    mean = float(np.mean(scene, dtype=np.float64))
    peak = float(np.max(scene))
    if peak <= 0.0:  # a black scene: nothing to meter on
        return float(signal_fraction)
    # Headroom: the brightest scene value at 90% of full well, so that photon noise and the blur's overshoot
    # do not clip it (a lab exposes a chart the same way; clipped tiles are rejected as saturated).
    return min(float(signal_fraction) / max(mean, 1e-12), HEADROOM / peak)


def frame_rng(seed: int, z_um: float) -> np.random.Generator:
    """A generator that depends only on (seed, z): frames are identical whatever the render order."""
    bits = int(np.float64(z_um).view(np.uint64))
    return np.random.default_rng(np.random.SeedSequence([int(seed), bits >> 32, bits & 0xFFFFFFFF]))


def mosaic(signal: np.ndarray, channels: tuple[str, ...], cfa: str) -> np.ndarray:
    """H x W x 3 (channels named R, G, B in any order) -> H x W raw mosaic for a 2x2 CFA pattern."""
    if cfa not in CFA_PATTERNS:
        raise ParameterError(f"unknown CFA pattern {cfa!r}", field="sensor.cfa", fix=f"use one of {CFA_PATTERNS}")
    out = np.empty(signal.shape[:2], dtype=signal.dtype)
    for k, colour in enumerate(cfa):
        r, c = divmod(k, 2)
        out[r::2, c::2] = signal[r::2, c::2, channels.index(colour)]
    return out


def gain_dn_per_e(sensor: SensorSpec) -> float:
    return (sensor.white_level_dn - sensor.black_level_dn) / sensor.full_well_e


def check_levels(sensor: SensorSpec) -> None:
    if not sensor.black_level_dn < sensor.white_level_dn:
        raise ParameterError(
            f"black level {sensor.black_level_dn} DN is not below the white level {sensor.white_level_dn} DN "
            f"of a {sensor.bit_depth}-bit sensor", field="sensor.black_level_dn",
            fix="lower black_level_dn (for bit_depth 32 the levels are in [0, 1])")


def to_dn(signal: np.ndarray, sensor: SensorSpec, rng: np.random.Generator | None,
          exact: bool = True) -> np.ndarray:
    """Signal (fraction of full well, float32) -> recorded frame in the sensor's dtype.

    With ``rng``: Poisson photon noise in electrons plus Gaussian read noise (e-); ``exact=False`` draws the
    photon noise above 100 e- from the moment-matched normal approximation of :func:`add_noise_e` (3-5x faster,
    a different realisation of the same statistics). Then gain, black level, clipping to [0, white] and
    quantisation: uint8 for 8 bits, uint16 holding 0..2**bit-1 for 10-16 bits (not rescaled), float32 for 32
    bits (white = 1.0, not rounded).
    """
    check_levels(sensor)
    g = np.float32(gain_dn_per_e(sensor))
    fw = np.float32(sensor.full_well_e)
    flat = signal.reshape(signal.shape[0], signal.shape[1], -1)
    dn = np.empty(flat.shape, dtype=np.float32)
    for i in range(flat.shape[2]):  # one plane at a time: Poisson needs float64 / int64 temporaries
        e = np.maximum(flat[:, :, i], 0.0) * fw
        if rng is not None and not exact:
            e = add_noise_e(e, float(sensor.read_noise_e), rng)
        elif rng is not None:
            e = rng.poisson(e).astype(np.float32)
            if sensor.read_noise_e > 0:
                e += np.float32(sensor.read_noise_e) * rng.standard_normal(e.shape, dtype=np.float32)
        e *= g
        e += np.float32(sensor.black_level_dn)
        dn[:, :, i] = e
    dn = dn.reshape(signal.shape)
    white = sensor.white_level_dn
    np.clip(dn, 0.0, white, out=dn)
    if sensor.bit_depth == 32:
        return dn
    out_dtype = np.uint8 if sensor.bit_depth == 8 else np.uint16
    return np.rint(dn).astype(out_dtype)


#: below this mean (electrons) photon noise is drawn from the Poisson distribution itself; above it from the
#: skewness-corrected normal approximation of :func:`add_noise_e` (several times faster; the skewness of
#: Poisson(100) is 0.1).
POISSON_EXACT_BELOW_E = 100.0


def add_noise_e(e: np.ndarray, read_noise_e: float, rng: np.random.Generator) -> np.ndarray:
    """Electrons ``e`` (float32, >= 0, modified in place) plus photon and read noise; float32.

    Where ``e >= POISSON_EXACT_BELOW_E``: one standard normal Z per pixel, ``e + s Z + (Z^2 - 1) / 6`` with
    ``s^2 = e + r^2 - 1/18``: mean e, variance ``e + r^2`` and third cumulant ``e + r^2 - 1/54``, against
    ``e`` for Poisson(e) + N(0, r^2) (a first-order Cornish-Fisher expansion; the skewness differs by
    ``r^2 / (e + r^2)^1.5``, < 0.01 for r <= 3 e-, and the kurtosis by 1/e < 0.01). Below it: Poisson(e) plus
    r Z, exactly.
    """
    z = rng.standard_normal(e.shape, dtype=np.float32)
    low = e < np.float32(POISSON_EXACT_BELOW_E)
    exact = e[low] if low.any() else None
    s = e + np.float32(read_noise_e * read_noise_e - 1.0 / 18.0)
    np.maximum(s, 0.0, out=s)  # only below the threshold (those pixels are drawn exactly below)
    np.sqrt(s, out=s)
    s *= z
    e += s
    z2 = np.square(z, out=s)
    z2 *= np.float32(1.0 / 6.0)
    e += z2
    e -= np.float32(1.0 / 6.0)
    if exact is not None:
        e[low] = rng.poisson(exact).astype(np.float32) + np.float32(read_noise_e) * z[low]
    return e
