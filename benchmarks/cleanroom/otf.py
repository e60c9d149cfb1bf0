"""The OTF of a circular pupil with defocus, astigmatism (along T/S) and primary spherical aberration.

Two independent ways, so each checks the other (and both are checked against closed forms in
tests/test_cleanroom.py):

* :func:`otf_native` — the rendering path: pupil sampled on a grid (edge cells grey by their covered area),
  PSF = |FFT(pupil)|², OTF = FFT(PSF) normalised at 0 (Goodman §6.2). Real, because every aberration here is
  even in the pupil coordinate (the PSF is centro-symmetric).
* :func:`otf_quadrature` — the truth path: the OTF as the pupil's normalised autocorrelation,
  ``(1/π) ∫ exp(i 2π [W(ρ + s/2) − W(ρ − s/2)]) dρ`` over the two discs' overlap, by Gauss–Legendre
  quadrature with exact boundaries, vectorised over many sensor positions at once.

Wavefront (waves): ``W_T (ρ·r̂)² + W_S (ρ·â)² + W040 |ρ|⁴``. Frequencies: the lag ``s`` (pupil radii) of a
frequency f is ``2 f / f_c`` with the incoherent cut-off ``f_c = 1 / (λ N)``.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import sparse
from scipy.ndimage import map_coordinates


def _pupil_area_fraction(n_pupil: int, size: int, sub: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pupil transmission on a size² grid with n_pupil cells across the diameter: each cell's fraction inside
    the unit disc (sub² samples), and the cell-centre coordinates (ρx, ρy)."""
    d = 2.0 / n_pupil
    c = (np.arange(size) - size // 2) * d
    off = (np.arange(sub) + 0.5) / sub - 0.5
    fx = (c[None, :, None] + off[None, None, :] * d)   # (1, size, sub)
    inside = np.zeros((size, size))
    for oy in off:
        yy = c[:, None] + oy * d
        inside += ((fx[0][None, :, :] ** 2 + yy[:, :, None] ** 2) <= 1.0).sum(axis=2)
    amp = inside / sub ** 2
    rx, ry = np.meshgrid(c, c)
    return amp, rx, ry


_PUPIL_CACHE: dict = {}


def otf_native(w_t: float, w_s: float, w040: float, r_hat: tuple[float, float], n_pupil: int = 96) -> np.ndarray:
    """Centred real OTF on a (2 n_pupil)² lag grid; lag index l (from the centre) is frequency l·f_c/n_pupil.

    Parameters
    ----------
    w_t, w_s, w040 : float
        Tangential and sagittal defocus and spherical aberration (waves).
    r_hat : (float, float)
        Radial unit vector (x, y) of the field point in sensor axes.
    n_pupil : int
        Pupil samples across its diameter.
    """
    size = 2 * n_pupil   # the autocorrelation's support is twice the pupil: no wrap-around
    key = (n_pupil, size)
    if key not in _PUPIL_CACHE:
        _PUPIL_CACHE[key] = _pupil_area_fraction(n_pupil, size)
    amp, rx, ry = _PUPIL_CACHE[key]
    pr = rx * r_hat[0] + ry * r_hat[1]
    pa = -rx * r_hat[1] + ry * r_hat[0]
    rho2 = rx * rx + ry * ry
    phase = 2.0 * np.pi * (w_t * pr * pr + w_s * pa * pa + w040 * rho2 * rho2)
    p = amp * np.exp(1j * phase)
    psf = np.abs(sfft.fft2(sfft.ifftshift(p), workers=1)) ** 2
    otf = sfft.fft2(psf, workers=1).real
    otf = sfft.fftshift(otf / otf[0, 0])
    return otf


def otf_on_frequencies(native: np.ndarray, n_pupil: int, fc_cyc_per_px: float, fx: np.ndarray,
                       fy: np.ndarray) -> np.ndarray:
    """The native OTF interpolated (bilinear) at frequencies fx, fy (cycles/px); 0 beyond the cut-off."""
    size = native.shape[0]
    scale = n_pupil / fc_cyc_per_px
    ix = size // 2 + fx * scale
    iy = size // 2 + fy * scale
    shape = np.broadcast(ix, iy).shape
    out = map_coordinates(native, [np.broadcast_to(iy, shape).ravel(), np.broadcast_to(ix, shape).ravel()],
                          order=1, mode="constant", cval=0.0, prefilter=False)
    return out.reshape(shape)


def _gl_overlap(s: float, n: int = 64):
    """Gauss–Legendre nodes (a, b) and weights over the overlap of two unit discs offset by s along a."""
    t, wt = np.polynomial.legendre.leggauss(n)
    th = 0.5 * np.pi * t
    wth = 0.5 * np.pi * wt
    bmax = np.sqrt(max(1.0 - 0.25 * s * s, 0.0))
    b = bmax * np.sin(th)
    X = np.sqrt(np.maximum(1.0 - b * b, 0.0)) - 0.5 * s
    X = np.maximum(X, 0.0)
    a = X[:, None] * t[None, :]
    w = (wth * bmax * np.cos(th) * X)[:, None] * wt[None, :]
    return a.ravel(), np.broadcast_to(b[:, None], a.shape).ravel(), w.ravel()


def otf_quadrature(w_t, w_s, w040: float, r_hat: tuple[float, float], s: float, direction: tuple[float, float],
                   n: int = 64) -> np.ndarray:
    """OTF (real part) at lag ``s`` (pupil radii, 0 ≤ s < 2) along unit ``direction`` (sensor axes), for
    arrays of (W_T, W_S) in waves (one value per sensor position), W040 in waves."""
    w_t = np.atleast_1d(np.asarray(w_t, dtype=np.float64))
    w_s = np.atleast_1d(np.asarray(w_s, dtype=np.float64))
    if s >= 2.0:
        return np.zeros(np.broadcast(w_t, w_s).shape)
    a, b, w = _gl_overlap(float(s), n)
    ux, uy = direction
    vx, vy = -uy, ux
    px, py = a * ux + b * vx, a * uy + b * vy
    rr = px * r_hat[0] + py * r_hat[1]          # ρ·r̂
    ra = -px * r_hat[1] + py * r_hat[0]         # ρ·â
    sr = s * (ux * r_hat[0] + uy * r_hat[1])
    sa = s * (-ux * r_hat[1] + uy * r_hat[0])
    rho2 = px * px + py * py
    base_sa = 2.0 * a * s * (2.0 * rho2 + 0.5 * s * s)   # W(ρ+s/2) − W(ρ−s/2) of ρ⁴, per unit W040
    phase = 2.0 * np.pi * (np.outer(w_t, 2.0 * rr * sr) + np.outer(w_s, 2.0 * ra * sa) + w040 * base_sa[None, :])
    return (np.cos(phase) @ w) / np.pi


def interpolation_matrix(f_cyc_per_px: np.ndarray, n_pupil: int, fc_cyc_per_px: float) -> sparse.csr_matrix:
    """Sparse linear-interpolation matrix from the native lag grid (2 n_pupil samples) to frequencies f along
    one axis; rows beyond the grid are zero. ``A_y @ native @ A_x.T`` is the bilinear interpolation of
    :func:`otf_on_frequencies` on a separable frequency grid, at a fraction of the cost."""
    size = 2 * n_pupil
    idx = size // 2 + np.asarray(f_cyc_per_px, dtype=np.float64).ravel() * (n_pupil / fc_cyc_per_px)
    i0 = np.floor(idx).astype(np.int64)
    t = idx - i0
    rows, cols, vals = [], [], []
    for j, w in ((i0, 1.0 - t), (i0 + 1, t)):
        ok = (j >= 0) & (j < size)
        rows.append(np.nonzero(ok)[0])
        cols.append(j[ok])
        vals.append(w[ok])
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(idx.size, size))
