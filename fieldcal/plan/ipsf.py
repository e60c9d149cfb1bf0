"""Sweep planning figures: the MTF and Wiener noise gain of a sweep's integrated PSF vs its half-range α.

The integrated OTF/PSF itself (paper eq. 2) is :mod:`fieldcal.optics.sweep` (one implementation, shared with
the compositor's deconvolution).

Wiener deconvolution with noise-to-signal ratio K uses ``W = H / (H² + K)``; white noise of standard
deviation σ comes out with standard deviation ``g σ``, ``g² = mean |W(f)|²`` over the sampled frequency square
(|fx|, |fy| ≤ Nyquist of the pixel pitch): the noise gain. With a fixed K this gain can *fall* as α grows
(where H < √K the filter stops restoring and the image stays blurred), so the trade table also gives the noise
gain of restoring the in-focus MTF over the band the plan preserves (|f| ≤ fs): RMS of ``H_0 / H_α`` there,
which always grows with α (``noise_gain_to_in_focus``), and the restored MTF at fs.
"""

from __future__ import annotations

import math

import numpy as np

from ..optics import LensModel
from ..optics.sweep import integrated_otf


def frequency_grid(pixel_pitch_um: float, n: int = 65) -> np.ndarray:
    """Radial frequencies (cycles/mm) of an n x n grid spanning ±Nyquist in x and y."""
    nyq = 1000.0 / (2.0 * pixel_pitch_um)
    a = np.linspace(-nyq, nyq, n)
    fx, fy = np.meshgrid(a, a)
    return np.hypot(fx, fy)


def wiener_noise_gain(otf_values, nsr: float) -> float:
    """RMS of the Wiener filter H/(H² + K) over the given frequency samples (white-noise amplification)."""
    h = np.asarray(otf_values, dtype=np.float64)
    w = h / (h * h + float(nsr))
    return float(math.sqrt(np.mean(w * w)))


def sweep_total_time_ms(D_um: float, alpha_um: float, pixel_exposure_ms: float) -> float:
    """Paper eq. 3: T = (D / 2α + 1) t_s."""
    return (D_um / (2.0 * alpha_um) + 1.0) * pixel_exposure_ms


def alpha_trade(profile: LensModel, D_um: float, pixel_exposure_ms: float, alphas_um, channel: str, fs_cyc_per_mm: float,
                nsr: float = 0.01, n_freq: int = 65) -> list[dict]:
    """Total time vs MTF and Wiener noise gain for a range of α (one row per α)."""
    fr = frequency_grid(float(profile.pixel_pitch_um), n_freq)
    band = np.linspace(0.0, fs_cyc_per_mm, 129)  # radial samples of the disc |f| <= fs, weighted by f
    h0 = integrated_otf(profile, band, 0.0, channel)
    floor = math.sqrt(nsr)
    rows = []
    for a in alphas_um:
        a = float(a)
        h = integrated_otf(profile, fr, a, channel)
        h_fs = float(integrated_otf(profile, np.array([fs_cyc_per_mm]), a, channel)[0])
        ratio = np.abs(h0) / np.maximum(np.abs(integrated_otf(profile, band, a, channel)), floor)
        to_focus = math.sqrt(float(np.trapezoid(ratio ** 2 * band, band) / np.trapezoid(band, band)))
        rows.append({
            "alpha_um": a,
            "total_time_ms": sweep_total_time_ms(D_um, a, pixel_exposure_ms),
            "velocity_um_per_ms": 2.0 * a / pixel_exposure_ms,
            "mtf_at_fs": abs(h_fs),
            "noise_gain": wiener_noise_gain(h, nsr),
            "noise_gain_to_in_focus": to_focus,
            "restored_mtf_at_fs": abs(h_fs * h_fs / (h_fs * h_fs + nsr)),
        })
    return rows
