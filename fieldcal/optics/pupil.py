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


def otf_radial(nu, w020_waves: float, w040_waves: float = 0.0, w060_waves: float = 0.0,
               chunk: int = 32) -> np.ndarray:
    """:func:`otf` of one wavefront at many normalised frequencies ``nu`` (any shape; 0 at nu >= 1, 1 at 0).

    For pixel kernels (:meth:`fieldcal.simulate.wave.ChannelOptics.kernel`), which need the OTF at every
    radius of the pixel grid's frequency block. The frequencies are taken in ascending chunks, each with the
    node count of its largest member (:func:`n_nodes` grows with nu), so each value has at least the accuracy
    :func:`otf` gives it alone; the rule is that of :func:`otf`, vectorised over nu.
    """
    nu = np.asarray(nu, dtype=np.float64)
    flat = nu.ravel()
    out = np.where(flat <= 0.0, 1.0, 0.0)
    inside = np.flatnonzero((flat > 0.0) & (flat < 1.0))
    order = inside[np.argsort(flat[inside], kind="stable")]
    w2, w4, w6 = float(w020_waves), float(w040_waves), float(w060_waves)
    for s in range(0, order.size, chunk):
        idx = order[s:s + chunk]
        v = flat[idx]                                              # (m,)
        g, gw = _nodes(n_nodes(float(v[-1]), w2, w4, w6))
        t_max = np.arcsin(np.sqrt(1.0 - v * v))                    # (m,)
        t = 0.5 * t_max[:, None] * (g[None, :] + 1.0)              # (m, t node)
        q2 = np.sin(t) ** 2
        p_hi = np.cos(t) - v[:, None]
        p = 0.5 * p_hi[:, :, None] * (g[None, None, :] + 1.0)      # (m, t node, p node)
        wt = (0.5 * t_max[:, None] * gw[None, :] * np.cos(t) * 0.5 * p_hi)[:, :, None] * gw[None, None, :]
        a = p * p + q2[:, :, None] + (v * v)[:, None, None]
        b = 2.0 * v[:, None, None] * p
        ph = 2.0 * math.pi * (w2 * 2.0 * b + w4 * 4.0 * a * b + w6 * (6.0 * a * a * b + 2.0 * b ** 3))
        out[idx] = (4.0 / math.pi) * np.sum(np.cos(ph) * wt, axis=(-2, -1))
    return out.reshape(nu.shape)


def otf_2d(nu_x, nu_y, wavefront_waves, slope_waves: float, n: int | None = None,
           chunk: int = 64) -> np.ndarray:
    """Complex OTF of a circular pupil with any smooth wavefront, at normalised frequencies ``(nu_x, nu_y)``.

    The pupil's autocorrelation (Hopkins 1955) as in :func:`otf`, without its symmetry: for a frequency of
    magnitude nu along the unit vector e (e' perpendicular), the pupils shifted by ``+-nu e`` overlap on
    ``|q| <= sqrt(1 - nu^2)``, ``|p| <= sqrt(1 - q^2) - nu`` (pupil point ``p e + q e'``), and

        OTF = (1/pi) int int_overlap exp(2 pi i [W(p e + q e' + nu e) - W(p e + q e' - nu e)]) dp dq,

    by Gauss-Legendre in p and in ``q = sin(t)``. The sign is that of the pupil function ``exp(-2 pi i W)``
    with numpy's FFT (:func:`fieldcal.simulate.wave.monochromatic_psf`): this OTF is the DFT of that PSF
    (``sum psf(x) exp(-2 pi i f x)``; checked against it in tests/test_simulate_wave.py).

    Parameters
    ----------
    nu_x, nu_y : array_like
        Frequency components over the incoherent cut-off ``1 / (lambda N)`` (broadcast together).
    wavefront_waves : callable
        ``W(u, v)`` in waves on normalised pupil coordinates (numpy arrays in, same shape out).
    slope_waves : float
        An upper bound of ``|grad W|`` (waves per pupil radius) over the pupil; sets the node count.
    n : int, optional
        Nodes per axis (default ``ceil(1.5 pi nu_max slope) + 12``: the phase range over the overlap is
        ``<= 8 pi nu slope``; errors measured <= 1e-8 against 300 nodes, tests/test_optics_pupil.py).

    Returns
    -------
    ndarray
        Complex OTF, 1 at nu = 0, 0 at nu >= 1; ``OTF(-nu) = conj(OTF(nu))``.
    """
    fx, fy = np.broadcast_arrays(np.asarray(nu_x, dtype=np.float64), np.asarray(nu_y, dtype=np.float64))
    nu_all = np.hypot(fx, fy).ravel()
    cx_all = np.divide(fx.ravel(), nu_all, out=np.ones_like(nu_all), where=nu_all > 0)
    sy_all = np.divide(fy.ravel(), nu_all, out=np.zeros_like(nu_all), where=nu_all > 0)
    out = np.where(nu_all <= 0.0, 1.0 + 0j, 0j)
    inside = np.flatnonzero((nu_all > 0.0) & (nu_all < 1.0))
    order = inside[np.argsort(nu_all[inside], kind="stable")]
    for s in range(0, order.size, chunk):
        idx = order[s:s + chunk]
        nu, c, sn = nu_all[idx], cx_all[idx], sy_all[idx]
        m = n or int(math.ceil(1.5 * math.pi * float(nu[-1]) * abs(slope_waves))) + 12
        g, gw = _nodes(m)
        t_max = np.arcsin(np.sqrt(1.0 - nu * nu))                  # (F,)
        t = t_max[:, None] * g[None, :]                             # (F, t node) over [-t_max, t_max]
        q = np.sin(t)
        p_hi = np.cos(t) - nu[:, None]
        p = p_hi[:, :, None] * g[None, None, :]                     # (F, t node, p node)
        wt = (t_max[:, None] * gw[None, :] * np.cos(t) * p_hi)[:, :, None] * gw[None, None, :]
        qq = q[:, :, None]
        # pupil points of the two shifted copies: (p +- nu) e + q e'
        ux, uy = c[:, None, None], sn[:, None, None]
        pa, pb = p + nu[:, None, None], p - nu[:, None, None]
        dw = (wavefront_waves(pa * ux - qq * uy, pa * uy + qq * ux)
              - wavefront_waves(pb * ux - qq * uy, pb * uy + qq * ux))
        out[idx] = np.sum(np.exp(2j * math.pi * dw) * wt, axis=(-2, -1)) / math.pi
    return out.reshape(fx.shape)
