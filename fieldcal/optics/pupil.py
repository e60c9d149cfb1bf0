"""Exact (diffraction-included) OTF of a circular pupil with rotationally symmetric aberrations.

The incoherent OTF is the pupil's autocorrelation (Hopkins 1955). For a unit pupil with wavefront
``W(rho) = W020 rho^2 + W040 rho^4 + W060 rho^6`` (waves) and normalised frequency ``nu = f lambda N`` (cut-off
at nu = 1), the two pupils shifted by ``+-nu`` along p overlap where ``(p +- nu)^2 + q^2 <= 1`` and

    OTF(nu) = (1/pi) int int_overlap exp(2 pi i [W(p + nu, q) - W(p - nu, q)]) dp dq.

With ``A = p^2 + q^2 + nu^2`` and ``B = 2 p nu`` the radii squared are ``A +- B``, so the phase difference is
``2 pi (2 B W020 + 4 A B W040 + (6 A^2 B + 2 B^3) W060)``: odd in p (the OTF is real) and even in q, so

    OTF = (4/pi) int_0^Q dq int_0^{sqrt(1 - q^2) - nu} cos(phase) dp,    Q = sqrt(1 - nu^2).

Evaluated by Gauss-Legendre in p and in ``q = sin(t)`` (which takes the square root at the pupil's top out of
the limit, so both integrands are smooth); the node counts follow the phase range over the overlap. At
W040 = W060 = 0 this is Hopkins' defocus OTF (its closed 1-D form is in the tests); at nu -> 0 with
``x = 8 pi nu W020`` and ``s = 16 pi nu W040`` fixed it tends to the geometric-optics ray OTF of
:mod:`fieldcal.measure.spherical`. It is the same for every orientation, so it is the orientation-averaged MTF
of such a pupil (``abs``), which is what the wave-optics path's truth needs (:mod:`fieldcal.simulate.wave`).
"""

from __future__ import annotations

import functools
import math

import numpy as np


@functools.lru_cache(maxsize=64)
def _nodes(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(int(n))


def n_nodes(nu: float, w020, w040=0.0, w060=0.0) -> int:
    """Gauss-Legendre nodes per axis for a phase range ``2 pi |dW|`` over the overlap (<= 1e-10 relative).

    |dW| <= 2 nu (|W020| + 2 |W040| (1 + nu^2) + 3 |W060| (1 + nu^2)^2 + ...) over the unit pupil; a rule
    of n nodes integrates a phase range R exactly to ~1e-10 once n >= R / 2 + 16.
    """
    a2 = (1.0 + nu * nu)
    amp = 2.0 * nu * (np.max(np.abs(w020)) + 2.0 * np.max(np.abs(w040)) * a2
                      + 4.0 * np.max(np.abs(w060)) * a2 * a2)
    return int(min(max(math.ceil(2.0 * math.pi * amp / 2.0) + 16, 24), 400))


def otf(nu: float, w020_waves, w040_waves=0.0, w060_waves=0.0, n: int | None = None) -> np.ndarray:
    """OTF at normalised frequency ``nu`` (0 <= nu < 1) for wavefront coefficients in waves (broadcast arrays).

    Parameters
    ----------
    nu : float
        ``f lambda N``: spatial frequency over the incoherent cut-off ``1 / (lambda N)``.
    w020_waves, w040_waves, w060_waves : array_like
        Defocus, primary and secondary spherical aberration (waves at the wavelength of ``nu``).
    n : int, optional
        Nodes per axis (default :func:`n_nodes`).

    Returns
    -------
    ndarray
        The (real, signed) OTF, 1 at nu = 0; the diffraction-limited ``(2/pi)(acos nu - nu sqrt(1 - nu^2))``
        without aberration.
    """
    nu = float(nu)
    w2, w4, w6 = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (w020_waves, w040_waves, w060_waves)))
    if nu >= 1.0:
        return np.zeros(w2.shape)
    if nu <= 0.0:
        return np.ones(w2.shape)
    m = n or n_nodes(nu, w2, w4, w6)
    g, gw = _nodes(m)
    t_max = math.asin(math.sqrt(1.0 - nu * nu))
    t = 0.5 * t_max * (g + 1.0)
    q = np.sin(t)
    p_hi = np.cos(t) - nu                                 # the overlap's half-width at height q
    p = 0.5 * p_hi[:, None] * (g[None, :] + 1.0)          # (t node, p node)
    wt = (0.5 * t_max * gw * np.cos(t) * 0.5 * p_hi)[:, None] * gw[None, :]
    a = p * p + (q * q)[:, None] + nu * nu
    b = 2.0 * nu * p
    # phase / (2 pi) = W020 c2 + W040 c4 + W060 c6
    c2, c4, c6 = 2.0 * b, 4.0 * a * b, 6.0 * a * a * b + 2.0 * b ** 3
    ph = 2.0 * math.pi * (w2[..., None, None] * c2 + w4[..., None, None] * c4 + w6[..., None, None] * c6)
    return (4.0 / math.pi) * np.sum(np.cos(ph) * wt, axis=(-2, -1))


def quadrature(nu: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rule of :func:`otf` at ``nu`` with n nodes per axis, flattened: ``(c2, c4, weight)`` with
    ``OTF = sum(weight cos(2 pi (W020 c2 + W040 c4)))`` (``sum(weight)`` is the diffraction-limited MTF).

    For callers that evaluate many wavefronts at one frequency (the through-focus curve fits)."""
    g, gw = _nodes(int(n))
    t_max = math.asin(math.sqrt(max(1.0 - nu * nu, 0.0)))
    t = 0.5 * t_max * (g + 1.0)
    q = np.sin(t)
    p_hi = np.cos(t) - nu
    p = 0.5 * p_hi[:, None] * (g[None, :] + 1.0)
    wt = (4.0 / math.pi) * (0.5 * t_max * gw * np.cos(t) * 0.5 * p_hi)[:, None] * gw[None, :]
    a = p * p + (q * q)[:, None] + nu * nu
    b = 2.0 * nu * p
    return (2.0 * b).ravel(), (4.0 * a * b).ravel(), wt.ravel()
