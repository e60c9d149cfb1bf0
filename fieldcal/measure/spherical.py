"""Through-focus contrast at one frequency of a lens with defocus and primary spherical aberration, and where it
peaks: the skewed curve model of the band-pass measure (docs/measurement.md "Asymmetric curves").

Geometric optics of a rotationally symmetric pupil (uniform illumination). A ray through normalised pupil
radius rho lands at ``eps(rho) = dz rho / (2N) - 8 N W040 rho^3`` from the chief ray (``W = W020 rho^2 +
W040 rho^4``, ``W020 = -dz / (8 N^2)``; the ray error is ``-2N dW/drho``), on a ring of that radius, whose
OTF is ``J0(2 pi f eps)``. So the OTF at f is

    O(dz) = int_0^1 J0(2 pi f eps(rho)) 2 rho drho = int_0^1 J0(x rho - s rho^3) 2 rho drho,

``x = pi f k dz`` (k = 1/N: the blur-disc diameter per µm of defocus) and ``s = 16 pi f N W040``. At s = 0
this is the disc OTF ``2 J1(x) / x`` of :mod:`fieldcal.optics.defocus` (the symmetric ``"otf"`` curve model);
with s != 0 the curve is skewed: a bright core on one side of focus, a rim on the other. At low f (blur
much wider than 1/f) O ~ 1 - pi^2 f^2 <eps^2>, so the peak tends to the minimum-RMS-spot focus x = 2 s / 3;
at higher f it is found numerically (:func:`peak_u`).

The integral is a fixed Gauss-Legendre rule in rho (:data:`N_RHO` nodes): the argument's phase changes by at
most |x| + |s| over the pupil, and at the window edges of a fitted curve (>= 15 % of the height) that stays
below ~15 rad, which 48 nodes integrate to < 1e-10.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import j0, j1

N_RHO = 48
_x, _w = np.polynomial.legendre.leggauss(N_RHO)
RHO = 0.5 * (_x + 1.0)
# int_0^1 g(rho) 2 rho drho = sum W_i g(rho_i)
WEIGHT = _w * RHO
RHO3 = RHO ** 3


def sa_otf(x, s):
    """O(x, s) (same broadcast shape as x and s), with dO/dx and dO/ds."""
    x = np.asarray(x, dtype=np.float64)[..., None]
    s = np.asarray(s, dtype=np.float64)[..., None]
    arg = x * RHO - s * RHO3
    o = j0(arg) @ WEIGHT
    d = -j1(arg)
    return o, (d * RHO) @ WEIGHT, (d * -RHO3) @ WEIGHT


def sa_otf_dxx(x, s):
    """d2O/dx2 (for Newton steps on the peak): J0'' = J1(t)/t - J0(t)."""
    x = np.asarray(x, dtype=np.float64)[..., None]
    s = np.asarray(s, dtype=np.float64)[..., None]
    t = x * RHO - s * RHO3
    small = np.abs(t) < 1e-6
    ts = np.where(small, 1.0, t)
    j1_t = np.where(small, 0.5, j1(ts) / ts)
    return ((j1_t - j0(t)) * RHO * RHO) @ WEIGHT


def model(u, a, u0, kappa, s, b):
    """The skewed curve model ``E(u) = a O(kappa (u - u0), s)^2 + b`` and its Jacobian (..., 5).

    ``u`` in scan steps; ``kappa = pi fs k step`` and ``s = 16 pi fs N W040`` (dimensionless). ``O`` is even in
    (x, s) jointly, so (kappa, s) and (-kappa, -s) are the same curve; callers keep kappa > 0.
    """
    du = u - u0
    o, ox, os_ = sa_otf(kappa * du, s)
    f = a * o * o + b
    g = 2.0 * a * o
    jac = np.stack([o * o, -g * ox * kappa, g * ox * du, g * os_, np.ones_like(f)], axis=-1)
    return f, jac


def _peak_step(o, ox, oxx, kappa, h):
    """Newton step in u towards the maximum of O^2 (g = O O_x, g' = O_x^2 + O O_xx per unit x; no step where
    g' >= 0, i.e. off a maximum), clipped to one grid interval ``h``."""
    g, gp = o * ox, ox * ox + o * oxx
    with np.errstate(divide="ignore", invalid="ignore"):
        du = np.where(gp < 0, -g / gp / kappa, 0.0)
    return np.clip(np.nan_to_num(du), -h, h)


def peak_u(a, u0, kappa, s, u_lo, u_hi, n_grid: int = 81, n_newton: int = 8):
    """Where each curve ``a O(kappa (u - u0), s)^2`` peaks in [u_lo, u_hi] (arrays of curves, vectorised).

    A grid over the interval finds the global maximum (contrast reverses after the first zero, so O^2 has
    secondary maxima), Newton steps on d(O^2)/du = 2 O O' refine it, each step clipped to one grid spacing.
    Returns NaN where the maximum is at an end of the interval (not a peak inside it).
    """
    a, u0, kappa, s, u_lo, u_hi = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64)
                                                        for v in (a, u0, kappa, s, u_lo, u_hi)))
    t = np.linspace(0.0, 1.0, n_grid)
    ug = u_lo[..., None] + (u_hi - u_lo)[..., None] * t
    o, _, _ = sa_otf(kappa[..., None] * (ug - u0[..., None]), s[..., None])
    i = np.argmax(o * o, axis=-1)
    h = (u_hi - u_lo) / (n_grid - 1)
    u = np.take_along_axis(ug, i[..., None], axis=-1)[..., 0]
    for _ in range(n_newton):
        x = kappa * (u - u0)
        o, ox, _ = sa_otf(x, s)
        u = u + _peak_step(o, ox, sa_otf_dxx(x, s), kappa, h)
    edge = (i == 0) | (i == n_grid - 1) | (u <= u_lo) | (u >= u_hi)
    return np.where(edge, np.nan, u)


# --------------------------------------------------------------------------- diffraction (wave optics)
#: Where the ray model above stops finding the wave-optics peak. Fitted (free kappa and s) to the exact
#: pupil-autocorrelation curves (:mod:`fieldcal.optics.pupil`, noise-free, 4 sampling phases, steps of half the
#: q = 0.05 tolerance), its peak is within 0.005 step of the true one for W040 <= 1.2 waves at nu = fs lambda N
#: in 0.05-0.6 (0.013 at nu = 0.3), and <= 0.02 step at 1.6 waves for nu <= 0.15; beyond (1.6 waves at nu 0.2-0.3)
#: it is off by 0.06-0.1 step: the fitted s can no longer absorb the diffraction, and comes out small (0.4-0.7
#: waves for 1.6 true). Curves whose ray fit lands past these thresholds (with evidence for the skew,
#: ``throughfocus.WAVE_MIN_CHI2``) are refitted with the exact model (:func:`wave_model`); elsewhere the ray
#: model stays. Set where the 1080p quick calibration of the (geometric) triplet, whose band-pass curves carry a
#: slight skew, does not cross them (0.1 / 0.15 waves: +1.1 s of profiled CPU there, for no gain). Skewed
#: slanted-edge channels read through the e-SFR's window take the exact model at any nu
#: (:func:`fieldcal.measure.esfr_focus.channel_shape`): the window's taps need the law at other frequencies.
WAVE_MIN_NU = 0.15
WAVE_MIN_W040_WAVES = 0.4


def wave_nu(kappa, fs_cyc_per_um: float, step_um: float, wavelength_um: float):
    """``nu = fs lambda N`` of curves with blur scale ``kappa`` (per step): ``kappa = pi fs step / N``; the model's
    ``c_nu`` is ``nu kappa``."""
    kappa = np.abs(np.asarray(kappa, dtype=np.float64))
    with np.errstate(divide="ignore"):
        return np.pi * fs_cyc_per_um ** 2 * wavelength_um * step_um / kappa


def w040_waves(s, nu):
    """W040 in waves of a ray-model ``s = 16 pi fs N W040`` at ``nu = fs lambda N``."""
    return np.asarray(s, dtype=np.float64) / (16.0 * np.pi * np.asarray(nu, dtype=np.float64))


def _rules(nu: np.ndarray, x_max: float, s_max: np.ndarray):
    """Per-curve quadrature (T, K) arrays alpha = c2 / (4 nu), beta = c4 / (8 nu), weights / their sum."""
    from fieldcal.optics import pupil

    rng = float(np.max(x_max + np.abs(s_max) * (1.0 + nu * nu)))
    n = int(min(max(math.ceil(rng / 2.0) + 14, 20), 80))
    al, be, wt = [], [], []
    for v in np.atleast_1d(nu):
        c2, c4, w = pupil.quadrature(float(v), n)
        al.append(c2 / (4.0 * v))
        be.append(c4 / (8.0 * v))
        wt.append(w / w.sum())
    return np.array(al), np.array(be), np.array(wt)


def wave_otf(x, s, nu, x_max: float | None = None):
    """The exact OTF in the ray model's variables, over the diffraction-limited MTF: O, dO/dx, dO/ds, d2O/dx2.

    ``x`` (T, n) and ``s`` (T, 1) as in :func:`model`, ``nu`` (T,) per curve. The wavefront is ``W020 = -x / (8 pi
    nu)``, ``W040 = s / (16 pi nu)`` waves, so the phase is ``-x c2 / (4 nu) + s c4 / (8 nu)``
    (:func:`fieldcal.optics.pupil.quadrature`); as nu -> 0 this is :func:`sa_otf`.
    """
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    s = np.asarray(s, dtype=np.float64).reshape(-1, 1)
    nu = np.asarray(nu, dtype=np.float64).reshape(-1)
    al, be, wt = _rules(nu, float(np.max(np.abs(x))) if x_max is None else x_max, s[:, 0])
    ph = -x[..., None] * al[:, None, :] + s[..., None] * be[:, None, :]
    c, sn = np.cos(ph), np.sin(ph)
    w = wt[:, None, :]
    o = np.sum(c * w, axis=-1)
    ox = np.sum(sn * (al[:, None, :] * w), axis=-1)
    os_ = -np.sum(sn * (be[:, None, :] * w), axis=-1)
    oxx = -np.sum(c * (al[:, None, :] ** 2 * w), axis=-1)
    return o, ox, os_, oxx


def wave_model(u, a, u0, kappa, s, b, c_nu):
    """:func:`model` with the exact (wave-optics) OTF: value and Jacobian (T, n, 5).

    ``c_nu`` (T,) per curve is ``nu kappa = pi fs^2 lambda step`` (:func:`wave_nu`): the blur scale kappa measures
    the F-number, so ``nu = c_nu / |kappa|`` moves with it (its share of d/dkappa by a central difference in nu).
    """
    du = u - u0
    k1 = np.abs(kappa[:, 0])
    nu = np.asarray(c_nu, dtype=np.float64) / k1
    x = kappa * du
    o, ox, os_, _ = wave_otf(x, s, nu)
    h = 1e-4 * nu
    o_nu = (wave_otf(x, s, nu + h)[0] - wave_otf(x, s, nu - h)[0]) / (2.0 * h[:, None])
    f = a * o * o + b
    g = 2.0 * a * o
    dk = ox * du - o_nu * (nu / kappa[:, 0])[:, None]  # d nu / d kappa = -nu / kappa
    jac = np.stack([o * o, -g * ox * kappa, g * dk, g * os_, np.ones_like(f)], axis=-1)
    return f, jac


def wave_peak_u(a, u0, kappa, s, u_lo, u_hi, c_nu, n_grid: int = 81, n_newton: int = 8, u_start=None):
    """:func:`peak_u` of the exact model (:func:`wave_model`'s ``c_nu`` per curve). ``u_start``: Newton steps from
    these peaks, no grid (the peak of slightly perturbed parameters, for the delta method)."""
    a, u0, kappa, s, u_lo, u_hi, c_nu = (np.atleast_1d(np.asarray(v, dtype=np.float64))
                                         for v in (a, u0, kappa, s, u_lo, u_hi, c_nu))
    nu = c_nu / np.abs(kappa)
    h = (u_hi - u_lo) / (n_grid - 1)
    x_max = float(np.max(np.abs(kappa) * np.maximum(np.abs(u_lo - u0), np.abs(u_hi - u0))))
    if u_start is None:
        ug = u_lo[:, None] + (u_hi - u_lo)[:, None] * np.linspace(0.0, 1.0, n_grid)
        o, _, _, _ = wave_otf(kappa[:, None] * (ug - u0[:, None]), s, nu, x_max)
        i = np.argmax(o * o, axis=-1)
        u = np.take_along_axis(ug, i[:, None], axis=-1)[:, 0]
    else:
        u = np.asarray(u_start, dtype=np.float64).copy()
        i = np.ones(u.shape, dtype=int)
    for _ in range(n_newton):
        o, ox, _, oxx = wave_otf((kappa * (u - u0))[:, None], s, nu, x_max)
        u = u + _peak_step(o[:, 0], ox[:, 0], oxx[:, 0], kappa, h)
    edge = (i == 0) | (i == n_grid - 1) | (u <= u_lo) | (u >= u_hi)
    return np.where(edge, np.nan, u)
