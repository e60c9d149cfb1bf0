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


# --- Through focus (the closed form of a slanted edge's MTF(fs) curve; docs/benchmarks.md bench_edge_bias_s15) ---

def defocus_disc_px(dz_um, f_number: float, pitch_um: float):
    """Geometric blur-circle diameter (px) of a defocus ``dz_um`` at ``f_number``: ``|dz| / (N p)``."""
    return np.abs(np.asarray(dz_um, dtype=np.float64)) / (float(f_number) * float(pitch_um))


def render_edge_rows(rows: int, width_px: int, *, normal_deg: float, x_mid_px: float, sigma_px: float,
                     defocus_d_px, dark: float = 0.2, light: float = 0.8) -> np.ndarray:
    """A ``rows`` x ``width_px`` near-vertical edge whose defocus disc may change from row to row.

    The edge passes through (``x_mid_px``, (rows - 1) / 2) with its normal at ``normal_deg`` from +x (|normal_deg|
    < 45: the light side is to the right). ``defocus_d_px``: one diameter, or one per row. Each row is the exact
    1-D edge spread of its own blur (:func:`render_edge`'s), i.e. the local-PSF model of a field whose focus
    changes along the edge slowly against the blur: the edge's ESF is then the mean of its rows' ESFs and its
    OTF the mean of theirs, and a row's MTF(fs) peaks where its disc vanishes.
    """
    d = np.broadcast_to(np.asarray(defocus_d_px, dtype=np.float64), (int(rows),))
    th = math.radians(normal_deg)
    xx = np.arange(width_px, dtype=np.float64)
    out = np.empty((int(rows), int(width_px)))
    cache: dict = {}
    yc = (rows - 1) / 2.0
    for r in range(int(rows)):
        key = round(float(d[r]), 4)
        if key not in cache:
            cache[key] = _esf_table(sigma_px, key, normal_deg)
        s, esf = cache[key]
        dist = (xx - x_mid_px) * math.cos(th) + (r - yc) * math.sin(th)
        out[r] = dark + (light - dark) * np.interp(dist, s, esf)
    return out


def edge_focus_rows(rows: int, *, z_focus_um: float, slant_deg: float, gradient_um_per_px: float = 0.0,
                    curvature_um_per_px2: float = 0.0) -> np.ndarray:
    """Best focus (µm) of each row of a near-vertical edge: ``z_focus + g t + curvature t² / 2``, t the distance
    along the edge from its middle row (``(r - (rows - 1) / 2) / cos(slant)``)."""
    t = (np.arange(int(rows)) - (rows - 1) / 2.0) / math.cos(math.radians(slant_deg))
    return float(z_focus_um) + gradient_um_per_px * t + 0.5 * curvature_um_per_px2 * t * t


def through_focus_edge(z_um, *, z_focus_um: float, f_number: float, pitch_um: float, sigma_px: float = 0.5,
                       slant_deg: float = 5.0, rows: int = 13, width_px: int = 17, x_phase_px: float = 0.0,
                       gradient_um_per_px: float = 0.0, curvature_um_per_px2: float = 0.0,
                       noise_sd: float = 0.0, seed=None) -> list[np.ndarray]:
    """One near-vertical edge's region at every sensor position in ``z_um``: exact Gaussian x geometric defocus
    disc x pixel aperture (:func:`render_edge_rows`), the rows' best foci from :func:`edge_focus_rows`, additive
    Gaussian noise of ``noise_sd`` (signal units, step 0.6). The edge crosses the middle row at column
    ``(width_px - 1) / 2 + x_phase_px``."""
    zf = edge_focus_rows(rows, z_focus_um=z_focus_um, slant_deg=slant_deg, gradient_um_per_px=gradient_um_per_px,
                         curvature_um_per_px2=curvature_um_per_px2)
    rng = np.random.default_rng(seed)
    out = []
    for z in np.asarray(z_um, dtype=np.float64):
        img = render_edge_rows(rows, width_px, normal_deg=slant_deg, x_mid_px=(width_px - 1) / 2.0 + x_phase_px,
                               sigma_px=sigma_px, defocus_d_px=defocus_disc_px(z - zf, f_number, pitch_um))
        if noise_sd > 0:
            img = img + rng.normal(0.0, noise_sd, img.shape)
        out.append(img)
    return out


def edge_mtf_fs_curve(z_um, fs_cy_per_px: float, *, f_number: float, pitch_um: float, sigma_px: float = 0.5,
                      slant_deg: float = 5.0, z_focus_rows_um=None, z_focus_um: float = 0.0) -> np.ndarray:
    """The exact MTF(fs) through focus of an edge rendered by :func:`through_focus_edge`: the mean of its rows'
    OTFs along the normal (``z_focus_rows_um`` the rows' foci, :func:`edge_focus_rows`; default one focus)."""
    zf = np.atleast_1d(np.asarray(z_focus_um if z_focus_rows_um is None else z_focus_rows_um, dtype=np.float64))
    z = np.asarray(z_um, dtype=np.float64)
    d = defocus_disc_px(z[:, None] - zf[None, :], f_number, pitch_um)
    base = float(analytic_otf(np.array([fs_cy_per_px]), sigma_px=sigma_px, normal_deg=slant_deg)[0])
    otf = base * disc_otf(float(fs_cy_per_px) * d, 1.0)  # 2 J1(pi d f) / (pi d f) for every (frame, row)
    return np.abs(otf.mean(axis=1))
