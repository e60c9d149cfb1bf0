"""The gain exponent k that sensor-fixed MTFs leave on a breathing lens's SML curves, from the stack's own spectrum.

The SML is taken with its operator dilated by each frame's image scale ``m`` (:func:`fieldcal.measure.focus.sml`),
so it sees the same *scene* frequencies ``u`` in every frame, at the sensor frequencies ``u / m``. Every MTF
that is fixed at the sensor (the pixel aperture, the pupil's diffraction, a camera's own filters) is then read
at a different frequency in every frame: the tile's SML energy changes as ``m^(2k)`` with

    k = -< f . grad ln M(f) >_W ,    W(f) = the SML's energy density over sensor frequency near focus,

(``f . grad`` the log-slope along the frequency's own direction: for the separable pixel aperture
``sinc(fx p) sinc(fy p)`` it is ``h(fx p) + h(fy p)``, ``h(x) = pi x cot(pi x) - 1``; for the radial
diffraction-limited MTF ``rho M'(rho) / M(rho)``). The gain ``m^k`` on the curve moves a tile's best focus by
at most ``k x z_dgamma_um`` (:func:`fieldcal.measure.tiles._exponent_sensitivity`): 0.15-0.45 µm on the wave
renderer's breathing lenses at F/3-F/7 (k 0.50-0.67: the SML's energy sits near Nyquist, where ``h`` is -0.5 to -1).

``W`` is measured on the stack: the 2-D power spectrum of the sharpest frame (largest SML) less that of the most
blurred one (what remains is the in-focus texture's; the noise's power is the same in both and cancels), times
the SML's own response ``|H(fx)|^2 + |H(fy)|^2``, ``H(f) = 4 sin^2(pi f)`` of the 3-tap second difference, on a
:data:`WINDOW_PX` window where that frame's SML energy is largest (its in-focus zone).

Which MTFs a stack's frames carry is its own to say (``stack.json`` ``"sensor_mtf"``,
:func:`fieldcal.measure.breathing_mtf.declared_factors`): k is that of the declared factors, 0 for a stack that
declares none (fieldcal's geometric renderer: a blur disc at the sensor on a scene sampled at its own scale),
and a camera's (100 % fill-factor pixel aperture, the diffraction-limited pupil at the stack's F-number) for a
stack that does not say.

**Why a bound and not a correction.** This k is the gain at best focus; away from it the blur has taken the
high frequencies where ``|f . grad ln M|`` is large, and the gain falls towards 1, so the fitted peak moves by
less than ``k x z_dgamma_um``. On the wave renderer's five breathing lenses without spherical aberration
(s9 band-coverage run, 15 channels, k 0.50-0.67 here) the pistons the SML left were 0.0-0.8 x k x dz/dk
(F/3.2-F/3.3: ~1; F/4.1-F/6.7: 0-0.3): dividing k out would have put lenses 23, 35 and 39 -0.3 to -0.4 µm
off (RMS 0.17 -> 0.24 µm). The exponent lies between 0 and k, so the band carries it as
:func:`exponent_sd` ``= sqrt(SCALE_KERNEL_SD^2 + k^2 / 3)`` (the RMS about 0 of a k anywhere in [0, k]) and no
correction is made.
"""
from __future__ import annotations

import math

import numpy as np

from fieldcal.optics.defocus import default_wavelength_nm, diffraction_mtf

#: sd of the exponent the SML's dilated operator itself leaves (second order in m - 1, and the first-order
#: dilation on textures whose spectrum is not stationary): 0.03-0.13 measured on the closed-form textures of
#: tests/test_measure_maps.py (docs/fitting.md "Breathing systematic"); 0.1 is that range's middle.
SCALE_KERNEL_SD = 0.1
_EPS = 1e-3  # relative frequency step of the numerical log-slope


def _log_mtf(fx_cyc_per_mm, fy_cyc_per_mm, pitch_um: float | None, f_number: float | None,
             wavelength_nm: float) -> np.ndarray:
    """ln of the sensor-fixed MTF (pixel aperture x diffraction-limited pupil) at 2-D sensor frequencies."""
    out = np.zeros(np.broadcast(fx_cyc_per_mm, fy_cyc_per_mm).shape)
    if pitch_um is not None:
        p = float(pitch_um) * 1e-3
        out = out + np.log(np.maximum(np.abs(np.sinc(fx_cyc_per_mm * p) * np.sinc(fy_cyc_per_mm * p)), 1e-300))
    if f_number is not None and math.isfinite(float(f_number)) and float(f_number) > 0:
        f = np.hypot(fx_cyc_per_mm, fy_cyc_per_mm)
        out = out + np.log(np.maximum(diffraction_mtf(f, wavelength_nm, float(f_number)), 1e-300))
    return out


#: side (plane px) of the window the spectrum is taken on: 256 px hold ~65 000 frequency bins, enough for W's
#: mean, and cost ~1 ms where a 1080p plane's periodograms cost ~1 s of CPU per channel
WINDOW_PX = 256


def window(plane: np.ndarray, centre_yx: tuple[float, float], size: int = WINDOW_PX) -> np.ndarray:
    """A ``size`` x ``size`` window of ``plane`` (float64) about ``centre_yx`` (plane px), moved inside the
    plane (the whole plane when smaller)."""
    a = np.asarray(plane)
    out = []
    for n, c in zip(a.shape[:2], centre_yx):
        m = min(int(size), n)
        lo = int(np.clip(round(float(c) - m / 2.0), 0, n - m))
        out.append(slice(lo, lo + m))
    return np.asarray(a[out[0], out[1]], dtype=np.float64)


def sml_weights(sharp: np.ndarray, blurred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fx, fy, W): plane frequencies (cycles per plane pixel, FFT layout) and the SML's in-focus energy density
    ``(P_sharp - P_blurred) (|H(fx)|^2 + |H(fy)|^2)`` (Hann-windowed periodograms, means removed).

    Signed, not clipped at 0: a periodogram bin of noise scatters by 100 %, so clipping keeps the half of the
    noise difference that is positive (a noise-only 0.05 sd added to a 16-cycle stripe raised k from 0.05 to 0.27,
    the noise's weight being at Nyquist); the signed sums over many bins cancel it (tests/test_sml_gain.py)."""
    a = np.asarray(sharp, dtype=np.float64)
    b = np.asarray(blurred, dtype=np.float64)
    win = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    pa = np.abs(np.fft.fft2((a - a.mean()) * win)) ** 2
    pb = np.abs(np.fft.fft2((b - b.mean()) * win)) ** 2
    fy = np.fft.fftfreq(a.shape[0])[:, None]
    fx = np.fft.fftfreq(a.shape[1])[None, :]
    h = lambda f: 16.0 * np.sin(np.pi * f) ** 4  # |H|^2 of [1, -2, 1]
    return fx, fy, (pa - pb) * (h(fx) + h(fy))


def gain_exponent(sharp: np.ndarray, blurred: np.ndarray, plane_pitch_um: float, pitch_um: float | None,
                  f_number: float | None, channel: str) -> float:
    """k of the SML curves of one plane (see the module): ``-<f . grad ln M>_W`` for the pixel aperture
    ``pitch_um`` (None: none) and the diffraction of ``f_number`` (None: none) in the channel's default band.

    Parameters
    ----------
    sharp, blurred : ndarray
        The plane in the frame of largest and of smallest SML (same shape).
    plane_pitch_um : float
        The plane's sample spacing at the sensor (the pitch x a Bayer sub-lattice's stride).
    """
    if pitch_um is None and (f_number is None or not math.isfinite(float(f_number)) or float(f_number) <= 0):
        return 0.0
    fx, fy, w = sml_weights(sharp, blurred)
    tot = float(w.sum())
    if not tot > 0:
        return 0.0
    to_mm = 1e3 / float(plane_pitch_um)
    lam = default_wavelength_nm(channel)
    hi = _log_mtf(fx * to_mm * (1 + _EPS), fy * to_mm * (1 + _EPS), pitch_um, f_number, lam)
    lo = _log_mtf(fx * to_mm * (1 - _EPS), fy * to_mm * (1 - _EPS), pitch_um, f_number, lam)
    g = (hi - lo) / (2.0 * _EPS)
    # a mean over the signed weights: bounded by the log-slopes' own range (0 to the steepest in the band)
    return float(np.clip(-np.sum(w * g) / tot, 0.0, float(np.max(-g))))


def exponent_sd(k_max: float) -> float:
    """sd of the SML's uncorrected gain exponent: the dilated operator's own (:data:`SCALE_KERNEL_SD`) and a k
    anywhere between 0 (wings of the curve, no high frequencies) and ``k_max`` (at best focus): RMS
    ``k_max / sqrt(3)`` about 0."""
    return math.sqrt(SCALE_KERNEL_SD ** 2 + float(k_max) ** 2 / 3.0)
