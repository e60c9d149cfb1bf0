"""Per-pixel frame weights from a best-focus position: stack blending and sweep emulation.

Both kernels are functions of the pixel's best-focus position ``z_b`` only, so a frame's weight over a region
is computed from the region's best-focus map, and the weights of all frames add up to exactly 1 everywhere.

* :class:`BlendKernel` (stacks): each pixel takes the frame nearest its best focus. Between two frames the
  weight crosses over smoothly (a smoothstep) inside the band where *both* frames are within the focus
  tolerance, so seams have no steps and cost no sharpness; the band never shrinks below ``min_band`` of the
  frame spacing (an under-sampled stack still gets soft seams).
* :class:`SweepKernel` (sweep emulation, paper Fig. 8d): each frame stands for the sensor travel half-way to
  its neighbours; its weight is the overlap of that travel with ``[z_b - alpha, z_b + alpha]``, i.e. the
  exposure a per-pixel-exposure sweep would have given it.
"""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError


def _sorted_positions(z_sorted_um) -> np.ndarray:
    z = np.asarray(z_sorted_um, dtype=np.float64)
    if z.ndim != 1 or len(z) == 0:
        raise ParameterError("no frame positions", field="z_um", fix="give at least one frame")
    if np.any(np.diff(z) <= 0):
        raise ParameterError("frame positions must be strictly increasing", field="z_um",
                             fix="sort frames by z and drop duplicates")
    return z


def smoothstep(u):
    """``3u^2 - 2u^3`` on [0, 1], 0 below, 1 above: continuous with a continuous slope."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


class _FrameKernel:
    """What both kernels share: frames sorted by z (``self.z``) and a vectorised ``supports``."""

    def __len__(self) -> int:
        return len(self.z)

    def support(self, zmin: float, zmax: float) -> tuple[int, int]:
        """Inclusive range of sorted frame indices that can weigh anything for ``z_b`` in [zmin, zmax]."""
        lo, hi = self.supports(np.array([zmin]), np.array([zmax]))
        return int(lo[0]), int(hi[0])


class BlendKernel(_FrameKernel):
    """Nearest-frame selection with tolerance-wide smooth seams.

    Parameters
    ----------
    z_sorted_um : array
        Frame positions (µm), strictly increasing.
    tolerance_um : float
        Half-width of the in-focus range (MTF within q of its peak) at the reference frequency.
    min_band : float
        Smallest cross-over width as a fraction of the frame spacing (0 gives hard seams).
    """

    def __init__(self, z_sorted_um, tolerance_um: float, min_band: float = 0.25):
        self.z = _sorted_positions(z_sorted_um)
        if not (np.isfinite(tolerance_um) and tolerance_um >= 0):
            raise ParameterError(f"focus tolerance must be >= 0, got {tolerance_um}", field="tolerance_um",
                                 fix="use a positive tolerance (µm)")
        if not 0.0 <= min_band <= 1.0:
            raise ParameterError(f"min_band must be in [0, 1], got {min_band}", field="min_band",
                                 fix="use e.g. 0.25")
        dz = np.diff(self.z)
        # Both neighbours are in focus for t in [1 - tol/dz, tol/dz]: a band of half-width tol/dz - 1/2.
        self.half_band = np.clip(tolerance_um / np.where(dz > 0, dz, 1.0) - 0.5, 0.5 * min_band, 0.5)
        pad = 1e-4 * dz + 1e-6 * (np.abs(self.z[:-1]) + np.abs(self.z[1:]))  # >> float32 rounding of the ramp
        # A seam stops a few pads short of the frames it joins, so that on a frame only that frame weighs even
        # with a full-width band (padded supports of both neighbours reached it: 3 frames at one point).
        self.half_band = np.clip(self.half_band, 0.0, np.maximum(0.5 - 3.0 * pad / np.where(dz > 0, dz, 1.0), 0.0))
        # Where each frame's weight can be non-zero: (seam below starts, seam above ends), see supports().
        h = np.maximum(self.half_band, 1e-6)
        seam_lo = self.z[:-1] + (0.5 - h) * dz - pad
        seam_hi = self.z[:-1] + (0.5 + h) * dz + pad
        self._edges = (np.concatenate([[-np.inf], seam_lo]), np.concatenate([seam_hi, [np.inf]]))

    def supports(self, zmin: np.ndarray, zmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`support` for arrays of ranges (e.g. every tile at once): ``(lo, hi)`` int32 arrays.

        Frame ``k`` weighs only for ``z_b`` in ``(a_k, b_k)``, from the start of the seam below it to the end of
        the seam above it; these open intervals are widened (1e-4 of a spacing plus 1e-6 of ``|z|``) so float32
        rounding of the ramps can never give weight outside them. So only the frames a pixel really blends are
        read: with the usual narrow seams one frame per pixel, not two.
        """
        lo_edge, hi_edge = self._edges
        n = len(self.z)
        zmin = np.asarray(zmin, dtype=np.float64)
        zmax = np.asarray(zmax, dtype=np.float64)
        lo = np.clip(np.searchsorted(hi_edge, zmin, side="right"), 0, n - 1)
        hi = np.clip(np.searchsorted(lo_edge, zmax, side="left") - 1, 0, n - 1)
        return lo.astype(np.int32), np.maximum(hi, lo).astype(np.int32)

    def unit_range(self, k: int) -> tuple[float, float]:
        """The ``z_b`` range where frame ``k`` weighs exactly 1 (between the seams around it, inclusive).

        Regions inside it need no weights at all: the frame is copied (warped) as it is.
        """
        lo_edge, hi_edge = self._edges
        below = hi_edge[k - 1] if k > 0 else -np.inf  # end of the seam below (padded outwards: ramp is 1 there)
        above = lo_edge[k + 1] if k + 1 < len(self.z) else np.inf  # start of the seam above (ramp is 0)
        return float(below), float(above)

    def _rise(self, j: int, zb):
        """Weight of frame j+1 for z_b between frames j and j+1."""
        t = (zb - self.z[j]) / (self.z[j + 1] - self.z[j])
        h = self.half_band[j]
        # below ~1e-6 of a spacing a seam is hard anyway (and 1/h would overflow)
        return smoothstep((t - (0.5 - h)) / (2.0 * h)) if h > 1e-6 else (t > 0.5).astype(np.float64)

    def _ramp(self, j: int, zb: np.ndarray) -> np.ndarray:
        """Smoothstep from 0 to 1 across the seam band between frames j and j+1 (float32, a new array)."""
        d = self.z[j + 1] - self.z[j]
        h = max(float(self.half_band[j]), 1e-6)  # 1e-6 of a spacing: a hard seam
        a = 1.0 / (2.0 * h * d)
        b = -(self.z[j] + (0.5 - h) * d) * a
        u = zb * np.float32(a)
        u += np.float32(b)
        np.clip(u, 0.0, 1.0, out=u)
        s = u * np.float32(-2.0)
        s += np.float32(3.0)
        u *= u
        u *= s
        return u

    def weight(self, k: int, zb, below: bool = True, above: bool = True) -> np.ndarray:
        """Weight of sorted frame ``k`` at best-focus positions ``zb`` (float32, same shape).

        ``w_k = r_{k-1} (1 - r_k)`` with ``r_j`` the ramp across seam j: where ``r_k > 0``, ``r_{k-1} = 1``,
        so the sum over k telescopes to exactly 1. A few float32 passes, no masks. ``below=False`` /
        ``above=False`` skip the seam below / above frame k, for regions known to lie past its end / before its
        start (see :meth:`unit_range`), where that factor is exactly 1: the result is the same, for half the work.
        """
        zb = np.asarray(zb, dtype=np.float32)
        n = len(self.z)
        w = None
        if k > 0 and below:
            w = self._ramp(k - 1, zb)
        if k < n - 1 and above:
            r = self._ramp(k, zb)
            np.subtract(np.float32(1.0), r, out=r)
            if w is None:
                w = r
            else:
                w *= r
        return np.ones(zb.shape, dtype=np.float32) if w is None else w

    def weight_exact(self, k: int, zb) -> np.ndarray:
        """The same weight written piecewise with masks, in float64 (a reference for :meth:`weight`)."""
        zb = np.asarray(zb, dtype=np.float64)
        n = len(self.z)
        w = np.zeros(zb.shape, dtype=np.float64)
        if n == 1:
            w[...] = 1.0
            return w.astype(np.float32)
        if k == 0:
            w[zb <= self.z[0]] = 1.0
        else:
            m = (zb > self.z[k - 1]) & (zb <= self.z[k])
            w[m] = self._rise(k - 1, zb[m])
        if k == n - 1:
            w[zb > self.z[-1]] = 1.0
        else:
            m = (zb > self.z[k]) & (zb < self.z[k + 1])
            w[m] = 1.0 - self._rise(k, zb[m])
        return w.astype(np.float32)


class SweepKernel(_FrameKernel):
    """Frame weights of an emulated focal sweep of half-range ``alpha_um`` centred on each pixel's best focus.

    Frame ``k`` covers the travel ``[e_k, e_{k+1}]`` between the midpoints to its neighbours (the end frames
    extend half a spacing outwards). Weights are normalised by the covered part of the window, so pixels near
    the ends of the stack still get a mean, and a window outside the stack takes the end frame.
    """

    def __init__(self, z_sorted_um, alpha_um: float):
        self.z = _sorted_positions(z_sorted_um)
        if not (np.isfinite(alpha_um) and alpha_um > 0):
            raise ParameterError(f"sweep half-range alpha must be > 0 µm, got {alpha_um}", field="alpha_um",
                                 fix="e.g. 20 µm (the paper's value)")
        self.alpha = float(alpha_um)
        z = self.z
        if len(z) == 1:
            e = np.array([z[0] - self.alpha, z[0] + self.alpha])
        else:
            mid = 0.5 * (z[1:] + z[:-1])
            e = np.concatenate([[z[0] - 0.5 * (z[1] - z[0])], mid, [z[-1] + 0.5 * (z[-1] - z[-2])]])
        self.edges = e

    def supports(self, zmin: np.ndarray, zmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive ranges of sorted frame indices whose travel meets the windows of ``z_b`` in [zmin, zmax]."""
        n = len(self.z)
        lo = np.asarray(zmin, dtype=np.float64) - self.alpha
        hi = np.asarray(zmax, dtype=np.float64) + self.alpha
        i0 = np.clip(np.searchsorted(self.edges, lo, side="right") - 1, 0, n - 1)
        i1 = np.clip(np.searchsorted(self.edges, hi, side="left") - 1, 0, n - 1)
        return i0.astype(np.int32), np.maximum(i1, i0).astype(np.int32)

    def weight(self, k: int, zb) -> np.ndarray:
        """Weight of sorted frame ``k`` at best-focus positions ``zb`` (float32, same shape)."""
        zb = np.asarray(zb, dtype=np.float64)
        e = self.edges
        lo = np.maximum(zb - self.alpha, e[0])
        hi = np.minimum(zb + self.alpha, e[-1])
        covered = hi - lo
        ov = np.clip(np.minimum(hi, e[k + 1]) - np.maximum(lo, e[k]), 0.0, None)
        inside = covered > 1e-9
        w = np.where(inside, ov / np.where(inside, covered, 1.0), 0.0)
        # Window entirely beyond an end of the stack: the end frame.
        if k == 0:
            w = np.where(~inside & (zb < e[0] + self.alpha), 1.0, w)
        if k == len(self.z) - 1:
            w = np.where(~inside & (zb >= e[0] + self.alpha), 1.0, w)
        return w.astype(np.float32)



