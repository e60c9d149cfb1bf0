"""Slanted edges whose MTF is known in closed form: the reference for e-SFR tests and benchmarks.

A straight edge blurred by a Gaussian (sigma) and a uniform defocus disc (diameter d) and integrated over
square pixels has, along the edge normal n = (cos θ, sin θ), the transfer function

    OTF(f) = exp(-2 π² σ² f²) · 2 J1(π d f) / (π d f) · sinc(f cos θ) · sinc(f sin θ)

(the last two factors are the unit pixel box projected onto n). Everything is a function of the signed
distance to the edge along n only, so each pixel's value is the 1-D ESF (the integral of the inverse
transform of the OTF, computed on a fine grid) at its centre's distance: exact up to a 1/64 px interpolation.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import j1


def disc_otf(f, d_px: float) -> np.ndarray:
    """OTF of a uniform disc of diameter ``d_px`` (2 J1(π d f) / (π d f); 1 at f = 0)."""
    x = np.pi * float(d_px) * np.abs(np.asarray(f, dtype=np.float64))
    out = np.ones_like(x)
    nz = x > 1e-12
    out[nz] = 2.0 * j1(x[nz]) / x[nz]
    return out


def analytic_otf(f, *, sigma_px: float = 0.0, defocus_d_px: float = 0.0, normal_deg: float = 0.0,
                 pixel_aperture: bool = True) -> np.ndarray:
    """Signed OTF along an edge normal at ``normal_deg`` from the x axis, f in cycles/px."""
    f = np.asarray(f, dtype=np.float64)
    out = np.exp(-2.0 * np.pi ** 2 * sigma_px ** 2 * f ** 2) * disc_otf(f, defocus_d_px)
    if pixel_aperture:
        th = math.radians(normal_deg)
        out = out * np.sinc(f * math.cos(th)) * np.sinc(f * math.sin(th))
    return out


def analytic_mtf(f, **kw) -> np.ndarray:
    """``|analytic_otf|``: the reference e-SFR of an edge rendered by :func:`render_edge`."""
    return np.abs(analytic_otf(f, **kw))


def analytic_mtf50(**kw) -> float:
    """Frequency (cy/px) where :func:`analytic_mtf` first falls to 0.5 (bisection on a fine grid)."""
    from scipy.optimize import brentq
    f = np.linspace(0.0, 2.0, 4001)
    m = analytic_mtf(f, **kw)
    i = int(np.flatnonzero(m < 0.5)[0])
    return float(brentq(lambda x: analytic_mtf(np.array([x]), **kw)[0] - 0.5, f[i - 1], f[i]))


def _esf_table(sigma_px: float, defocus_d_px: float, normal_deg: float, ds: float = 1.0 / 64,
               period_px: float = 512.0) -> tuple[np.ndarray, np.ndarray]:
    """(s, ESF(s)) on a fine grid, ESF rising from 0 to 1 across s = 0."""
    n = int(round(period_px / ds))
    f = np.fft.rfftfreq(n, d=ds)
    lsf = np.fft.irfft(analytic_otf(f, sigma_px=sigma_px, defocus_d_px=defocus_d_px, normal_deg=normal_deg), n=n)
    lsf = np.fft.fftshift(lsf)  # centred at index n // 2
    esf = np.cumsum(lsf)
    esf /= esf[-1]
    s = (np.arange(n) - n // 2 + 0.5) * ds  # cumulative sum: value at the right end of each sample
    return s, esf


def render_edge(height_px: int, width_px: int, *, normal_deg: float, point_px=None, sigma_px: float = 0.0,
                defocus_d_px: float = 0.0, dark: float = 0.2, light: float = 0.8) -> np.ndarray:
    """An H x W float64 image of a straight edge through ``point_px`` (default the centre) whose normal points
    at ``normal_deg`` from the +x axis (y down) towards the light side; the blur is Gaussian x disc x pixel."""
    if point_px is None:
        point_px = ((width_px - 1) / 2.0, (height_px - 1) / 2.0)
    th = math.radians(normal_deg)
    yy, xx = np.mgrid[0:height_px, 0:width_px].astype(np.float64)
    dist = (xx - point_px[0]) * math.cos(th) + (yy - point_px[1]) * math.sin(th)
    s, esf = _esf_table(sigma_px, defocus_d_px, normal_deg)
    return dark + (light - dark) * np.interp(dist, s, esf)
