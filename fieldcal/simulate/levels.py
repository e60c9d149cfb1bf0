"""Blur levels shared by both image-formation paths: the defocus ladder each pixel interpolates on.

Levels are spaced geometrically in blur-disc diameter above a floor, with an in-focus level at zero, so the
interpolation error is a bounded fraction of the local blur change (docs/simulator.md).
"""

from __future__ import annotations

import math

import numpy as np


def level_diameters_px(max_diameter_px: float, ratio: float, floor_px: float) -> np.ndarray:
    """Blur-level diameters (px): 0, then ``floor * ratio**k`` until ``max_diameter_px`` is covered (plus one
    spare level, so that a diameter exactly on the last level still has an upper neighbour)."""
    n = 0 if max_diameter_px <= floor_px else math.ceil(math.log(max_diameter_px / floor_px) / math.log(ratio))
    return np.concatenate([[0.0], floor_px * ratio ** np.arange(n + 2)])


def fractional_level(diameter_px: np.ndarray, ratio: float, floor_px: float) -> np.ndarray:
    """Continuous level index of each blur diameter: integer at a level, between two levels the weight that
    gives the blend the disc's own second moment.

    A blend ``(1 - t) disc(b_k) + t disc(b_k+1)`` has the variance ``((1 - t) b_k^2 + t b_k+1^2) / 16`` per
    axis: with ``t = (b^2 - b_k^2) / (b_k+1^2 - b_k^2)`` it is the disc ``b``'s, so the blend's OTF,
    ``1 - 2 pi^2 var f^2 + O(f^4)``, agrees with the disc's to second order in f at every diameter. Linear in b (as
    before) it did not: between the in-focus level and the 0.5 px floor the blend's MTF fell *linearly* with
    |dz| (a cusp at best focus) where a disc's falls quadratically, 0.008 of MTF(fs) too low half a floor from
    focus at 1/3 cycle/px, so a through-focus curve sampled near its peak read 4-9 % wide and its width
    depended on where the scan's steps fell (issue 13; docs/simulator.md "Blur levels").
    """
    b = np.asarray(diameter_px, dtype=np.float32)
    safe = np.maximum(b, floor_px)  # the log below is only used above the floor
    k = np.floor(np.log(safe / floor_px) / np.float32(math.log(ratio))).astype(np.float32)
    lo = floor_px * np.power(np.float32(ratio), k)
    frac = (safe * safe - lo * lo) / (lo * lo * np.float32(ratio * ratio - 1.0))
    above = 1.0 + k + np.clip(frac, 0.0, 1.0)
    return np.where(b < floor_px, (b / np.float32(floor_px)) ** 2, above).astype(np.float32)


def fractional_level_lut(max_diameter_px: float, ratio: float, floor_px: float, n: int = 32000):
    """A table of :func:`fractional_level` for ``cv2.remap`` (1 x n, float32) and its step (px).

    ``cv2.remap(table, b / step, 0, INTER_LINEAR)`` evaluates the level of diameters b up to
    ``max_diameter_px`` in one multithreaded pass. The level is piecewise quadratic in b with breakpoints at the
    level diameters, so the table is exact to its linear interpolation of a quadratic (< step^2 levels) except within one step of a breakpoint (error <= slope jump x
    step / 4 <= 1.5 step levels) and the position rounding of remap (1/32 step, <= step / 4 levels).
    """
    step = max(float(max_diameter_px), floor_px) * 1.001 / (n - 2)
    b = np.arange(n, dtype=np.float64) * step
    return fractional_level(b.astype(np.float32), ratio, floor_px)[None, :], step


# int16 steps of a compact stack (LevelStack(compact=True)): 2**-14, range +-2.
_COMPACT_SCALE = 16384.0
# cv2.remap addresses at most 32767 rows: levels are stacked in pages of that height.
_REMAP_MAX_ROWS = 32766


class LevelStack:
    """The blur levels of one scene channel, kept for the renderer's life, and their per-pixel blend.

    The scene is fixed, so each level image (the scene blurred by one defocus everywhere) is computed once and
    every frame only gathers, per pixel, the two levels that bracket its fractional level ``kf`` and
    interpolates linearly between them (the same blend :meth:`fieldcal.simulate.render.Renderer.blur_map`
    always did, now without an inverse FFT per level and frame).

    Levels are stacked vertically in pages (``cv2.remap`` gathers from one page; it addresses < 32767 rows).
    Consecutive pages overlap by one level, so both levels of a pixel's pair always lie in the same page.

    Parameters
    ----------
    height_px, width_px : int
        Level image size.

    compact : bool
        Store levels as int16 in steps of 2**-14 (range +-2: a [0, 1] scene and its ringing) instead of
        float32: half the memory, a rounding error of 1.8e-5 RMS (0.07 DN at 12 bits). The astigmatic renderer
        keeps K such stacks per channel (:mod:`fieldcal.simulate.astigmatism`).

    The methods that may compute levels take ``make_level(k) -> float32 (H, W)``; the stack keeps no reference
    to its owner (a renderer <-> stack cycle would hold hundreds of MB until the cyclic garbage collector ran).
    """

    def __init__(self, height_px: int, width_px: int, compact: bool = False):
        self.h, self.w = int(height_px), int(width_px)
        self.compact = bool(compact)
        self._dtype = np.int16 if self.compact else np.float32
        self.per_page = max(2, _REMAP_MAX_ROWS // self.h)  # levels per page (pages share one level)
        self._remap_ok = _REMAP_MAX_ROWS // self.h >= 2 and self.w < _REMAP_MAX_ROWS
        self._pages: dict[int, np.ndarray] = {}
        self._have: set[int] = set()
        self._grid = None

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self._pages.values())

    def _page_of(self, k: int) -> int:
        """Page holding the pair (k, k + 1)."""
        return k // (self.per_page - 1)

    def _slot(self, page: int, k: int) -> slice:
        j = k - page * (self.per_page - 1)
        return slice(j * self.h, (j + 1) * self.h)

    def _pages_with(self, k: int):
        """Pages that store level k (one, or two at a page boundary)."""
        p = self._page_of(k)
        out = [p]
        if k > 0 and k % (self.per_page - 1) == 0:
            out.append(p - 1)
        return out

    def ensure(self, k_max: int, make_level) -> None:
        """Compute (once) every level up to ``k_max`` that is missing."""
        for k in range(int(k_max) + 1):
            if k in self._have:
                continue
            img = np.asarray(make_level(k), dtype=np.float32)
            if self.compact:
                img = np.rint(np.clip(img * np.float32(_COMPACT_SCALE), -32767, 32767)).astype(np.int16)
            for p in self._pages_with(k):
                self._reserve(p, k, int(k_max))
                self._pages[p][self._slot(p, k)] = img
            self._have.add(k)

    def _reserve(self, page: int, k: int, k_max: int) -> None:
        """Make page ``page`` hold level k (rows for the page's levels up to k_max, at most a full page): a
        page grows only when a later frame needs more levels than the ones asked for so far."""
        first = page * (self.per_page - 1)
        need = min(self.per_page, max(k, k_max) - first + 1) * self.h
        old = self._pages.get(page)
        if old is not None and old.shape[0] >= need:
            return
        new = np.empty((need, self.w), dtype=self._dtype)
        if old is not None:
            new[:old.shape[0]] = old
        self._pages[page] = new

    def level(self, k: int) -> np.ndarray:
        """Level k (a view into its page, float32 for a compact stack; computed by ``ensure`` or ``blend``
        before)."""
        if k not in self._have:
            raise KeyError(f"level {k} has not been computed")
        p = self._page_of(k)
        v = self._pages[p][self._slot(p, k)]
        return v.astype(np.float32) * np.float32(1.0 / _COMPACT_SCALE) if self.compact else v

    def blend(self, kf: np.ndarray, make_level) -> np.ndarray:
        """Per pixel: ``(1 - t) level[floor(kf)] + t level[floor(kf) + 1]``, t = kf - floor(kf); float32 H x W."""
        kf = np.asarray(kf, dtype=np.float32)
        lo = np.floor(kf)
        t = kf - lo
        k0, k1 = int(lo.min()), int(lo.max())
        self.ensure(k1 + 1, make_level)
        p0, p1 = self._page_of(k0), self._page_of(k1)
        if not self._remap_ok:
            return self._blend_take(lo.astype(np.intp), t)
        import cv2
        if self._grid is None:
            self._grid = (np.broadcast_to(np.arange(self.w, dtype=np.float32)[None, :], (self.h, self.w)).copy(),
                          np.arange(self.h, dtype=np.float32)[:, None])
        mx, ys = self._grid
        out = None
        for p in range(p0, p1 + 1):
            if p not in self._pages:
                continue
            # row in the page: (lo - first level of the page) * H + y; pixels of other pages are clamped and
            # masked out below
            if p0 == p1 and p == 0:
                row = lo * np.float32(self.h)
            else:
                row = np.clip(lo - np.float32(p * (self.per_page - 1)), 0, self.per_page - 2) * np.float32(self.h)
            row += ys
            a = cv2.remap(self._pages[p], mx, row, cv2.INTER_NEAREST)
            b = cv2.remap(self._pages[p], mx, row + np.float32(self.h), cv2.INTER_NEAREST)
            if self.compact:
                a = a.astype(np.float32)
                a *= np.float32(1.0 / _COMPACT_SCALE)
                b = b.astype(np.float32)
                b *= np.float32(1.0 / _COMPACT_SCALE)
            b -= a
            b *= t
            b += a
            if p0 == p1:
                return b
            if out is None:
                out = b
            else:
                sel = np.floor(lo / np.float32(self.per_page - 1)) == p
                out[sel] = b[sel]
        return out

    def _blend_take(self, lo: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The same blend with numpy gathers (images too tall for cv2.remap's pages)."""
        out = np.empty((self.h, self.w), dtype=np.float32)
        for k in np.unique(lo):
            m = lo == k
            a = self.level(int(k))[m]
            out[m] = a + t[m] * (self.level(int(k) + 1)[m] - a)
        return out
