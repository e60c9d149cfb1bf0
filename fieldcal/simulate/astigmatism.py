"""The geometric path's astigmatic blur: an elliptical defocus PSF, oriented radially, by orientation wedges.

Geometry. With astigmatism ``A(rho)`` (tangential - sagittal focus, ``LensSpec``) a field point at signed
defocus ``dz`` from its mean focus and azimuth ``theta`` (direction from the optical centre, image axes x right,
y down) images the pupil's uniform disc through an anisotropic scaling: a uniform **ellipse** with diameter
``b_T = |dz - A/2| / N`` along the radial (tangential/meridional) direction and ``b_S = |dz + A/2| / N`` along
the azimuthal (sagittal) one. So the blur across a tangential edge (normal radial, the e-SFR classifier's
"tangential", :func:`fieldcal.measure.mtf.classify`) vanishes at the tangential focus ``z_c + A/2``, as in the
wave path (``simulate.wave.terms_at``) and the truth (``TruthProfile.best_focus_um(orientation=...)``).
Its OTF at spatial frequency ``f`` in direction ``alpha`` is the disc's at the diameter

    q(alpha)^2 = b_T^2 cos^2(alpha - theta) + b_S^2 sin^2(alpha - theta)
               = dz^2 + h^2 - 2 dz (h cos 2theta cos 2alpha + h sin 2theta sin 2alpha),   h = A/2,

times the (radial) diffraction and residual-Gaussian OTFs.

Rendering. The renderer's blur levels are isotropic images, one per disc diameter. The spectrum is split into
K orientation **wedges** by a partition of unity over ``alpha`` (trigonometric interpolation on K equispaced
nodes ``alpha_k = k pi / K``, period pi, K odd: the Dirichlet kernel, rotation-equivariant); wedge k has its own
level stack, and each pixel blends wedge k's levels at its own ``q(alpha_k)``. The sum over wedges has, at
every frequency, the OTF ``sum_k w_k(alpha) D(|f| q(alpha_k))``: the trigonometric interpolant of the pixel's
own OTF over orientation. It is exact for the second moments (``q^2`` is a pure second harmonic, so any
K >= 3 interpolates it exactly) and converges fast in K; :func:`wedge_count` picks the smallest odd K whose
worst OTF error over the band is below a tolerance for the lens's largest ``|A| / (N pitch)``.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import j1

# Worst OTF error (absolute, any orientation, defocus and field azimuth, |f| <= _BAND_CYC_PER_PX) allowed from
# the orientation interpolation: the level ladder's own interpolation error is of this order (docs/simulator.md).
WEDGE_TOLERANCE = 0.02
_BAND_CYC_PER_PX = 0.5  # up to Nyquist along an axis: the band the e-SFR and the focus measures use
MAX_WEDGES = 11  # memory: K level stacks per channel (docs/simulator.md, "Astigmatism")


def _disc_otf(x: np.ndarray) -> np.ndarray:
    """``2 J1(pi x) / (pi x)``: the OTF of a uniform disc of diameter b at frequency f, x = b f."""
    x = np.abs(np.asarray(x, dtype=np.float64))
    out = np.ones_like(x)
    m = x > 1e-12
    px = np.pi * x[m]
    out[m] = 2.0 * j1(px) / px
    return out


def node_angles(k: int) -> np.ndarray:
    """The K wedge directions ``alpha_k = k pi / K`` (rad)."""
    return np.arange(int(k), dtype=np.float64) * (math.pi / int(k))


def wedge_weights(alpha, k: int) -> np.ndarray:
    """Weights ``w_j(alpha)`` (shape ``alpha.shape + (K,)``) of the K-node trigonometric interpolation in alpha
    (period pi; K odd): ``w_j = (1 + 2 sum_{m=1}^{(K-1)/2} cos 2m (alpha - alpha_j)) / K``. They sum to 1 at
    every alpha and reproduce any function of alpha with harmonics up to ``2 (K - 1) / 2`` exactly."""
    k = int(k)
    if k < 1 or k % 2 == 0:
        raise ValueError(f"the wedge count must be odd and >= 1, got {k}")
    a = np.asarray(alpha, dtype=np.float64)[..., None] - node_angles(k)
    w = np.ones_like(a)
    for m in range(1, (k - 1) // 2 + 1):
        w += 2.0 * np.cos(2.0 * m * a)
    return w / k


def node_diameters(dz, half, cos2t, sin2t, k: int):
    """Blur diameter ``q(alpha_j)`` of each wedge node j (module docstring), in the units of dz and half.

    dz: signed defocus from the mean focus; half: ``A/2`` (signed); (cos2t, sin2t): ``cos 2 theta``,
    ``sin 2 theta`` of the field azimuth. Arrays broadcast; returns a list of K arrays (float32)."""
    dz = np.asarray(dz, dtype=np.float32)
    hc = np.asarray(half * cos2t, dtype=np.float32)
    hs = np.asarray(half * sin2t, dtype=np.float32)
    return diameters_from_parts(dz, hc, hs, k)


def diameters_from_parts(dz: np.ndarray, hc: np.ndarray, hs: np.ndarray, k: int) -> list[np.ndarray]:
    """:func:`node_diameters` from the smooth parts ``dz``, ``h cos 2 theta``, ``h sin 2 theta`` (float32 maps)."""
    base = np.square(dz) + np.square(hc) + np.square(hs)
    two_dz = dz * np.float32(2.0)
    out = []
    for a in node_angles(k):
        q2 = base - two_dz * (hc * np.float32(math.cos(2.0 * a)) + hs * np.float32(math.sin(2.0 * a)))
        # rounding can leave q^2 = (b_T cos)^2 + (b_S sin)^2 slightly below 0
        out.append(np.sqrt(np.maximum(q2, np.float32(0.0))))
    return out


@functools.lru_cache(maxsize=64)
def interpolation_error(k: int, astig_px: float) -> float:
    """Worst absolute OTF error of K wedges for T - S = ``astig_px`` blur-disc pixels (``|A| / (N pitch)``).

    Evaluated on a grid: defocus over +-(3 astig + 2) px about the mean focus, field azimuths over a quarter turn
    (the error has that period), frequency directions over a half turn, |f| up to 0.5 cycles/px."""
    a = float(astig_px)
    if a == 0.0:
        return 0.0
    dz = np.linspace(-3.0 * a - 2.0, 3.0 * a + 2.0, 97)[:, None, None, None]
    theta = np.linspace(0.0, 0.5 * math.pi, 7)[None, :, None, None]
    alpha = np.linspace(0.0, math.pi, 37, endpoint=False)[None, None, :, None]
    f = np.linspace(0.0, _BAND_CYC_PER_PX, 11)[None, None, None, :]
    half = 0.5 * a
    d = alpha - theta
    q_true = np.sqrt((dz - half) ** 2 * np.cos(d) ** 2 + (dz + half) ** 2 * np.sin(d) ** 2)
    want = _disc_otf(f * q_true)
    w = wedge_weights(alpha[0, 0, :, 0], k)  # (alpha, K)
    got = np.zeros_like(want)
    qs = node_diameters(dz, half, np.cos(2.0 * theta), np.sin(2.0 * theta), k)
    for j, qj in enumerate(qs):
        got = got + w[None, None, :, j, None] * _disc_otf(f * qj.astype(np.float64))
    return float(np.max(np.abs(got - want)))


def wedge_count(astig_px: float, tolerance: float = WEDGE_TOLERANCE, max_wedges: int = MAX_WEDGES) -> int:
    """Smallest odd K (>= 3) whose :func:`interpolation_error` is within ``tolerance``, at most ``max_wedges``.

    ``astig_px`` is the largest ``|A| / (N pitch)`` over the sensor (T - S as a blur-disc diameter in pixels)."""
    k = 3
    while k < max_wedges and interpolation_error(k, round(float(astig_px), 3)) > tolerance:
        k += 2
    return k
