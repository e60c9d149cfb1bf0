"""The integrated PSF of a focal sweep (paper eq. 2): its OTF, its radial profile and its pixel kernel.

A pixel exposed while the sensor moves through ``[z_b + offset - alpha, z_b + offset + alpha]`` records the scene
blurred by the integrated PSF. The OTF is linear in the PSF, so the integrated OTF is the mean of the *signed*
through-focus OTF over the defocus range (contrast reversals partly cancel)::

    H_s(f) = 1/(2 alpha) * integral_{-alpha}^{alpha} OTF(f, offset + dz) d dz        (H_s(0) = 1)

One implementation serves the planner (alpha trade, plan summaries) and the compositor (deconvolution). The
OTF is the lens model's own :meth:`~fieldcal.optics.model.LensModel.defocus_otf` (a calibrated profile's
defocus x diffraction model, a simulated lens's exact model with its residual blur), integrated by
Gauss-Legendre quadrature with enough nodes for the highest frequency asked (the integrand oscillates about
``x / pi`` times over the range, ``x = pi alpha f / N``). For the geometric blur disc alone the integral has
a closed form, :func:`disc_sweep_otf`, which the tests pin the quadrature against.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import special

from .model import LensModel

_MIN_NODES = 48
# Beyond ~1300 rad of the disc argument (where |H_s| < 2e-3 anyway) the capped rule is good to ~1e-3 absolute.
_MAX_NODES = 1024


@functools.lru_cache(maxsize=32)
def _legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    # scipy's banded eigen-solver: numpy's leggauss builds a dense n x n matrix (130 MB at n = 4096)
    x, w = special.roots_legendre(n)
    return x, w


def disc_sweep_otf(f_cyc_per_mm, alpha_um: float, f_number: float):
    """Closed form of the sweep OTF of the geometric blur disc alone (no diffraction), centred sweep.

    With ``X = pi alpha f / N``: ``H_s = (1/X) int_0^X 2 J1(t)/t dt = 2 (int_0^X J0(t) dt - J1(X)) / X``
    (``J1(t)/t = J0(t) - J1'(t)``), ``int_0^X J0`` from :func:`scipy.special.itj0y0`.
    """
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    x = np.pi * float(alpha_um) / float(f_number) / 1000.0 * np.abs(f)
    small = x < 1e-3
    xs = np.where(small, 1.0, x)
    ij0 = special.itj0y0(xs)[0]
    return np.where(small, 1.0 - x * x / 24.0, 2.0 * (ij0 - special.j1(xs)) / xs)


def _n_nodes(f: np.ndarray, alpha_um: float, offset_um: float, f_number: float | None) -> int:
    """Gauss-Legendre nodes for the range: 0.75 per radian of the disc argument over a floor (converged to
    1e-10 at 250 µm and 250 cycles/mm, tests/test_optics.py), at most ``_MAX_NODES``."""
    if not f_number or f.size == 0:
        return 64
    x_max = math.pi * (alpha_um + abs(offset_um)) / float(f_number) / 1000.0 * float(np.max(np.abs(f)))
    return int(min(_MAX_NODES, max(_MIN_NODES, math.ceil(0.75 * x_max) + 32)))


def integrated_otf(model: LensModel, f_cyc_per_mm, alpha_um: float, channel: str, *, offset_um: float = 0.0,
                   n_nodes: int | None = None) -> np.ndarray:
    """Sweep OTF ``H_s(f)`` for a sweep of ±alpha about best focus (+ ``offset_um``); alpha = 0: the OTF there.

    Parameters
    ----------
    model : LensModel
        Supplies ``defocus_otf(f, dz_um, channel)`` (signed) and ``f_number`` (node count).
    f_cyc_per_mm : array_like
        Radial spatial frequencies at the sensor.
    alpha_um : float
        Half-range of the sweep (µm of stage travel).
    n_nodes : int, optional
        Gauss-Legendre nodes (default: enough for the highest frequency).
    """
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    if alpha_um <= 0:
        return np.asarray(model.defocus_otf(f, np.full_like(f, offset_um), channel), dtype=np.float64)
    n = int(n_nodes) if n_nodes else _n_nodes(f, float(alpha_um), float(offset_um), model.f_number)
    t, w = _legendre(n)
    acc = np.zeros_like(f)
    for ti, wi in zip(t, w):
        acc += 0.5 * wi * np.asarray(model.defocus_otf(f, np.full_like(f, offset_um + alpha_um * ti), channel),
                                     dtype=np.float64)
    return acc


def integrated_psf_radial(model: LensModel, r_um, alpha_um: float, channel: str, n_f: int = 2048) -> np.ndarray:
    """Radial integrated PSF (1/µm², integrates to 1 over the plane): Hankel transform of the sweep OTF up to
    the diffraction cut-off."""
    fc = 1.0 / (float(model.wavelength_nm(channel)) * 1e-6 * float(model.f_number))  # cycles/mm
    f = np.linspace(0.0, fc, n_f)
    h = integrated_otf(model, f, alpha_um, channel)
    r_mm = np.asarray(r_um, dtype=np.float64)[:, None] / 1000.0
    integrand = h[None, :] * special.j0(2.0 * np.pi * f[None, :] * r_mm) * f[None, :]
    psf_per_mm2 = 2.0 * np.pi * np.trapezoid(integrand, f, axis=1)
    return psf_per_mm2 / 1e6


def rfft_radial_grid(shape: tuple[int, int], pitch_um: float, dtype=np.float64) -> np.ndarray:
    """|f| (cycles/mm) on the ``scipy.fft.rfft2`` grid of an image of ``shape`` (rows, cols), in ``dtype``
    (float32: half the memory and time of a whole image's grid)."""
    from scipy import fft  # imported when needed: ~0.15 s saved on stack composites

    fy = fft.fftfreq(shape[0])[:, None]
    fx = fft.rfftfreq(shape[1])[None, :]
    if np.dtype(dtype) == np.float64:
        return np.sqrt(fy * fy + fx * fx) / (pitch_um * 1e-3)
    scale = 1.0 / (pitch_um * 1e-3)
    fy, fx = (fy * scale).astype(dtype), (fx * scale).astype(dtype)
    return np.sqrt(fy * fy + fx * fx)


def radial_table(fn_1d, f_grid: np.ndarray, n: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """The fine 1-D table ``(f, fn_1d(f))`` through which :func:`radial_on_grid` evaluates ``fn_1d`` on
    ``f_grid`` (``np.interp(f_grid, *table)``: the grid may then be interpolated in parts)."""
    fmax = float(f_grid.max())
    ft = np.linspace(0.0, fmax * (1 + 1e-9), n)
    return ft, fn_1d(ft)


def radial_on_grid(fn_1d, f_grid: np.ndarray, n: int = 4096) -> np.ndarray:
    """Evaluate a radial function on a 2-D frequency grid through a fine 1-D table (Bessel calls stay 1-D)."""
    return np.interp(f_grid, *radial_table(fn_1d, f_grid, n))


def sweep_psf_kernel(model: LensModel, alpha_um: float, channel: str, pitch_um: float,
                     size_px: int = 33) -> np.ndarray:
    """Pixel PSF (``size_px`` square, odd, non-negative, sums to 1) of a sweep over ±alpha about best focus;
    alpha = 0 gives the in-focus PSF. Sampled from the sweep OTF on a 4x larger grid, so it is band-limited
    at the pixel Nyquist frequency as the sensor samples it."""
    from scipy import fft

    size_px = int(size_px) | 1
    n = 4 * size_px
    f = rfft_radial_grid((n, n), pitch_um)
    h = radial_on_grid(lambda t: integrated_otf(model, t, alpha_um, channel), f)
    psf = fft.fftshift(fft.irfft2(h, s=(n, n)))
    c, r = n // 2, size_px // 2
    k = np.clip(psf[c - r:c + r + 1, c - r:c + r + 1], 0.0, None)
    return k / k.sum()


def moving_sweep_otf(model: LensModel, fx_cyc_per_mm, fy_cyc_per_mm, alpha_um: float, channel: str, *,
                     velocity_px_per_um: tuple[float, float] = (0.0, 0.0), pitch_um: float,
                     offset_um: float = 0.0, n_nodes: int | None = None) -> np.ndarray:
    """2-D sweep OTF when the image also moves with the stage (focus breathing, stage-axis shift): complex.

    A scene point whose image moves by ``v t`` pixels when the stage is ``t`` µm from the window centre
    records, during a sweep of ±alpha at constant velocity, the defocus disc of each t *displaced* by ``v t``.
    Its OTF is the mean over the window of the defocus OTF times the displacement's phase::

        H(f) = 1/(2 alpha) integral_{-alpha}^{alpha} OTF(|f|, offset + t) exp(-2 pi i f . v t p) dt

    (p the pixel pitch in mm/px). With ``v = 0`` it is :func:`integrated_otf`; with a defocus OTF constant in t
    it is that OTF times ``sinc(2 alpha p f . v)``, the uniform streak of length ``2 alpha |v|`` px. Defocus and
    motion are integrated jointly (the streak is not convolved with the integrated disc: at each t the disc
    has the size belonging to that t), by Gauss-Legendre quadrature with enough nodes for both oscillations.

    Parameters
    ----------
    fx_cyc_per_mm, fy_cyc_per_mm : array_like
        Frequency grid (broadcastable), cycles/mm at the sensor.
    velocity_px_per_um : (float, float)
        Image motion (px) per µm of stage travel at this field position.
    pitch_um : float
        Pixel pitch (µm), converting the motion in pixels to mm.
    """
    fx = np.asarray(fx_cyc_per_mm, dtype=np.float64)
    fy = np.asarray(fy_cyc_per_mm, dtype=np.float64)
    fx, fy = np.broadcast_arrays(fx, fy)
    fr = np.hypot(fx, fy)
    vx, vy = (float(v) for v in velocity_px_per_um)
    # phase per µm of stage travel: 2 pi f . v p (f in cycles/mm, v p / 1000 in mm per µm)
    k = 2.0 * np.pi * (fx * vx + fy * vy) * float(pitch_um) / 1000.0
    if alpha_um <= 0:
        return np.asarray(model.defocus_otf(fr, np.full_like(fr, offset_um), channel), dtype=np.complex128)
    if n_nodes:
        n = int(n_nodes)
    else:
        n = _n_nodes(fr, float(alpha_um), float(offset_um), model.f_number)
        n = int(min(_MAX_NODES, n + math.ceil(0.75 * float(alpha_um) * float(np.max(np.abs(k), initial=0.0)))))
    t, w = _legendre(n)
    # the defocus OTF is radial: tabulate it once per node on a fine 1-D table, then interpolate
    fmax = float(fr.max()) if fr.size else 0.0
    ft = np.linspace(0.0, fmax * (1 + 1e-9) + 1e-12, 2048)
    pos = fr / ft[-1] * (ft.size - 1)
    i0 = np.minimum(pos.astype(np.int64), ft.size - 2)
    a = pos - i0
    acc = np.zeros(fr.shape, dtype=np.complex128)
    for ti, wi in zip(t, w):
        dz = alpha_um * ti
        tab = np.asarray(model.defocus_otf(ft, np.full_like(ft, offset_um + dz), channel), dtype=np.float64)
        otf = tab[i0] * (1.0 - a) + tab[i0 + 1] * a
        acc += (0.5 * wi) * otf * np.exp(-1j * k * dz)
    return acc
