"""Integrated PSF of a focal sweep (paper eq. 2), its MTF, and the noise gain of Wiener deconvolution.

The sweep integrates the PSF over ``z0 - α .. z0 + α``; the OTF is linear in the PSF, so the integrated OTF is
the mean of the *signed* through-focus OTF over the defocus range (contrast reversals partly cancel):

    IOTF(f) = 1/(2α) ∫_{-α}^{α} OTF(f, dz) d(dz)        (normalised so IOTF(0) = 1)

evaluated with Gauss-Legendre quadrature on the profile's defocus model (fieldcal.simulate.lens.otf: geometric defocus
× diffraction × residual blur). The radial IPSF is the Hankel transform of the IOTF.

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
from scipy import special

from fieldcal.simulate.lens import otf as lens_otf


def _residual_blur_um(profile) -> float:
    v = getattr(profile, "residual_blur_um", None)
    if v is None:
        v = getattr(getattr(profile, "spec", None), "residual_blur_um", 0.0)
    return float(v or 0.0)


def through_focus_otf(profile, f_cyc_per_mm, dz_um, channel: str):
    """Signed OTF of the profile's defocus model (the profile's own ``defocus_otf`` when it has one)."""
    fn = getattr(profile, "defocus_otf", None)
    if callable(fn):
        return np.asarray(fn(f_cyc_per_mm, dz_um, channel), dtype=np.float64)
    return lens_otf(f_cyc_per_mm, dz_um, float(profile.f_number), float(profile.wavelength_nm(channel)),
                    _residual_blur_um(profile))


def integrated_otf(profile, f_cyc_per_mm, alpha_um: float, channel: str, n_nodes: int = 48, offset_um: float = 0.0):
    """IOTF at frequencies ``f`` for a sweep of ±α about best focus (+ ``offset_um``); α = 0 is the in-focus OTF."""
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    if alpha_um <= 0:
        return through_focus_otf(profile, f, np.full_like(f, offset_um), channel)
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    acc = np.zeros_like(f)
    for ti, wi in zip(t, w):
        acc += 0.5 * wi * through_focus_otf(profile, f, np.full_like(f, offset_um + alpha_um * ti), channel)
    return acc


def ipsf_profile(profile, r_um, alpha_um: float, channel: str, n_f: int = 2048):
    """Radial IPSF (1/µm², integrates to 1 over the plane) by the Hankel transform of the IOTF."""
    fc = 1.0 / (float(profile.wavelength_nm(channel)) * 1e-6 * float(profile.f_number))  # cycles/mm
    f = np.linspace(0.0, fc, n_f)
    h = integrated_otf(profile, f, alpha_um, channel)
    r_mm = np.asarray(r_um, dtype=np.float64)[:, None] / 1000.0
    integrand = h[None, :] * special.j0(2.0 * np.pi * f[None, :] * r_mm) * f[None, :]
    psf_per_mm2 = 2.0 * np.pi * np.trapezoid(integrand, f, axis=1)
    return psf_per_mm2 / 1e6


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


def alpha_trade(profile, D_um: float, pixel_exposure_ms: float, alphas_um, channel: str, fs_cyc_per_mm: float,
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
