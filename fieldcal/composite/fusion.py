"""Depth from focus for scenes with depth: multi-scale selection in a Laplacian pyramid.

A chart is flat, so its best focus is a smooth surface and :mod:`.dff` fits one. A real scene has depth
steps, slopes and thin things in front of a background: a smooth surface blurs them. Here every pixel, at every
scale, takes the frame in which it is sharpest, and the pyramid blends the choices without seams
(Burt & Kolczynski 1993, "Enhanced image capture through fusion"; the method of enfuse's contrast-weighted
hard mask and of focus stackers, with the selection made per scale rather than once per pixel):

1. each frame, warped to the output geometry, is split into a Laplacian pyramid (``levels`` band-pass levels
   and a low-pass base);
2. at each band-pass level the *salience* of a frame is the local energy of its luminance's coefficients (the
   channels' mean; squared, Gaussian-weighted over ``window_px`` at that level's scale), and every channel takes
   its coefficient from the most salient frame (one choice per place: the colours come from one frame). Deciding per level keeps fine detail at a depth edge from the frame where the edge
   is sharp, while the coarse levels follow the larger object: no halo wider than the finest levels' support;
3. the base (the coarsest, low-pass level, nearly the same in every frame) is the mean over frames, which
   averages its noise;
4. the pyramid is collapsed.

Frames stream through one at a time (the next read while one is added): memory holds the running best
coefficients and saliences (about twice one frame) and two frames' planes, never the whole stack. The selected frame at the finest level that carries signal is kept as a
depth index (frame order by z) for plots and for deciding, elsewhere, whether a scene is flat.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np

from ..errors import ParameterError
from ..progress import progress
from .source import default_workers, image_size, z_positions
from .dff import frame_planes

_BORDER = cv2.BORDER_REFLECT101
#: Element types OpenCV's masked copy takes (:func:`masked_copy`).
_CV_TYPES = frozenset(np.dtype(t) for t in (np.uint8, np.int8, np.uint16, np.int16, np.int32, np.float32, np.float64))


def masked_copy(dst: np.ndarray, src, mask: np.ndarray) -> np.ndarray:
    """``np.copyto(dst, src, where=mask)`` (a scalar ``src`` cast as ``casting="unsafe"`` does), through OpenCV's
    masked copy where it applies: the same values (a copy), but NumPy's masked loop took 16x longer (20.6 against
    1.25 ms) on a 2048 x 1536 float32 plane with a random mask, and twice as long (0.25 against 0.12 s) over the
    188 masked copies of the per-frame selections (the fusion's, the depth map's peak, the fine detail's) of the
    7-frame board (docs/benchmarks.md ``bench_composite_speed_s16``). OpenCV's applies to a C-contiguous ``H x W`` or ``H x W x C`` (C <= 4)
    ``dst`` of a type it holds, an ``H x W`` C-contiguous bool ``mask`` and a ``src`` of ``dst``'s shape and type
    (or a scalar); anything else goes to ``np.copyto`` (an ``H x W`` mask applying to every channel). Returns
    ``dst``."""
    if (dst.size and dst.dtype in _CV_TYPES and dst.flags.c_contiguous and mask.dtype == np.bool_
            and mask.flags.c_contiguous and mask.shape == dst.shape[:2]
            and (dst.ndim == 2 or (dst.ndim == 3 and dst.shape[2] <= 4))):
        if np.ndim(src) == 0:
            src = np.full(dst.shape, src, dst.dtype)  # cast as np.copyto casts a scalar
        if (isinstance(src, np.ndarray) and src.shape == dst.shape and src.dtype == dst.dtype
                and src.flags.c_contiguous):
            got = cv2.copyTo(src, mask.view(np.uint8), dst)
            if got is dst or got.__array_interface__["data"][0] == dst.__array_interface__["data"][0]:
                return dst
    where = mask.reshape(mask.shape + (1,) * (dst.ndim - mask.ndim)) if mask.ndim < dst.ndim else mask
    np.copyto(dst, src, where=where, casting="unsafe" if np.ndim(src) == 0 else "same_kind")
    return dst


@dataclass
class FusionResult:
    """A fused image (``H x W x C`` float32, in the frames' units) and where its detail came from.

    ``depth_index`` (``H x W`` float32) is the frame (position in z order) chosen at the finest pyramid level
    with signal, median-filtered; ``z_um`` the frames' positions in that order.
    """

    image: np.ndarray
    depth_index: np.ndarray
    z_um: np.ndarray
    levels: int
    #: How far (full-resolution px) what lies beside a pixel can decide its ``depth_index``: the chosen level's
    #: salience window (two sigmas) and the median's half-width, at that level's scale (:func:`index_reach_px`).
    index_reach_px: float = 0.0


def default_levels(width: int, height: int) -> int:
    """Band-pass levels down to a base of ~16 px on the short side (at most 8)."""
    return int(np.clip(np.floor(np.log2(max(min(width, height), 2) / 16.0)), 1, 8))


#: The median filter (px at the index level) that cleans :attr:`FusionResult.depth_index` of single-coefficient noise.
INDEX_MEDIAN_PX = 5


def index_reach_px(window_px: float, index_level: int) -> float:
    """The radius (full-resolution px) over which the scene decides a pixel's fused frame choice
    (:attr:`FusionResult.depth_index`): the salience window's two sigmas (``window_px / 2`` each) plus the median's
    half-width, at level ``index_level``'s scale (``2 ** index_level`` px). A structure narrower than that (a thin
    bar, a wire) is not resolved by the choice: it takes the frame of what surrounds it, or lends its own to it."""
    return float(2 ** int(index_level)) * (max(float(window_px), 1.0) + (INDEX_MEDIAN_PX - 1) // 2)


def _level_shapes(h: int, w: int, levels: int) -> list[tuple[int, int]]:
    """``(rows, cols)`` of each pyramid level (as ``cv2.pyrDown`` halves them), finest first, base last."""
    shapes = [(h, w)]
    for _ in range(levels):
        hh, ww = shapes[-1]
        shapes.append(((hh + 1) // 2, (ww + 1) // 2))
    return shapes


#: A level's row bands (:class:`_Selection`) are at least this high: below, a thread's hand-over costs more
#: than the band's work.
_BAND_MIN_ROWS = 64


class _Selection:
    """Per-scale selection for all channels at once, frame by frame: the running best coefficients of each
    channel, and the saliences that chose them.

    One choice per coefficient for every channel, made on the luminance: its coefficients are the channels' mean
    (the pyramid is linear), so a frame's salience is computed once, not once per channel, and the colours of a
    place come from one frame (no colour fringes where channels would pick different frames on their noise; as
    the fine detail's choice, :mod:`.detail`).

    All scratch (the frame's pyramids, its saliences, the selection mask) is allocated once and reused, every
    operation writes in place: a frame costs no new full-size arrays (at 2048 x 1536 a fresh array costs as
    much in page faults as the arithmetic on it).
    """

    def __init__(self, h: int, w: int, n_channels: int, levels: int, sigma: float, index_level: int,
                 pool=None, workers: int = 1):
        self.shapes = _level_shapes(h, w, levels)
        self.levels, self.sigma, self.index_level = levels, sigma, index_level
        self.gauss = [[np.empty(s, np.float32) for s in self.shapes[1:]] for _ in range(n_channels)]
        self.lap = [[np.empty(s, np.float32) for s in self.shapes[:-1]] for _ in range(n_channels)]
        self.best = [[np.empty(s, np.float32) for s in self.shapes[:-1]] for _ in range(n_channels)]
        self.best_sal = [np.empty(s, np.float32) for s in self.shapes[:-1]]
        self.best_idx = np.zeros(self.shapes[index_level], np.int16)
        self._sal = np.empty(h * w, np.float32)
        self._take = np.empty(h * w, bool)
        self.base_sum = [np.zeros(self.shapes[-1], np.float64) for _ in range(n_channels)]
        # Row bands: the per-coefficient work (the coefficients, the salience, its window, the choice and the
        # masked copies) split across ``workers`` threads (``pool`` runs all bands but the first, which the
        # caller's thread takes). Every step is per coefficient except the window, which each band filters over
        # its rows plus a halo of the Gaussian's support (OpenCV's kernel radius for float: 4 sigma): the same
        # sums, so the same values bit for bit as on the whole plane, whatever the number of bands.
        self._pool = pool if workers > 1 else None
        self._workers = max(1, int(workers)) if pool is not None else 1
        self._halo = int(np.ceil(4.0 * sigma)) + 2
        size = [0] * self._workers  # each band's window with its halo, the largest over the levels
        for hh, ww in self.shapes[:-1]:
            for i, (a, b) in enumerate(self._bands(hh)):
                size[i] = max(size[i], (min(hh, b + self._halo) - max(0, a - self._halo)) * ww)
        self._window = [np.empty(n, np.float32) for n in size]

    def _bands(self, hh: int) -> list[tuple[int, int]]:
        """Row bands of a level ``hh`` rows high: one per worker, none under :data:`_BAND_MIN_ROWS` rows."""
        n = max(1, min(self._workers, hh // _BAND_MIN_ROWS))
        edges = [hh * i // n for i in range(n + 1)]
        return list(pairwise(edges))

    def _each_band(self, fn, bands: list[tuple[int, int]]) -> None:
        """``fn(i, a, b)`` for every band ``i`` (rows ``a:b``): the first on this thread, the others on the pool;
        returns when all are done."""
        futures = [self._pool.submit(fn, i, a, b) for i, (a, b) in enumerate(bands) if i > 0]
        try:
            fn(0, *bands[0])
        finally:
            for f in futures:
                f.result()

    def add(self, planes: list[np.ndarray], k: int, support: np.ndarray | None = None) -> None:
        """Take frame ``k``'s (in z order) coefficients where it is more salient than the frames before (never
        outside ``support``, where the frame holds recorded pixels, when given)."""
        curs = list(planes)
        n_ch = len(curs)
        for lev in range(self.levels):
            hh, ww = self.shapes[lev]
            laps = [self.best[c][lev] if k == 0 else self.lap[c][lev] for c in range(n_ch)]

            def pyramid(i: int, a: int, b: int, curs=curs, laps=laps, lev=lev, hh=hh, ww=ww) -> None:
                for c in range(a, b):  # channels a:b, each on its own (OpenCV's pyramids run on one thread)
                    down = cv2.pyrDown(curs[c], dst=self.gauss[c][lev], borderType=_BORDER)
                    # the first frame's coefficients are written straight into the running selection
                    cv2.pyrUp(down, dst=laps[c], dstsize=(ww, hh), borderType=_BORDER)

            n_split = min(len(self._bands(hh)), n_ch)
            self._each_band(pyramid, [(n_ch * j // n_split, n_ch * (j + 1) // n_split) for j in range(n_split)])
            if support is not None and support.shape != (hh, ww):
                support = cv2.resize(support.view(np.uint8), (ww, hh), interpolation=cv2.INTER_NEAREST) > 0
            raw = self._sal[:hh * ww].reshape(hh, ww)
            bands = self._bands(hh)

            def salience(i: int, a: int, b: int, curs=curs, laps=laps, raw=raw) -> None:
                for c in range(n_ch):  # the band-pass coefficients
                    np.subtract(curs[c][a:b], laps[c][a:b], out=laps[c][a:b])
                sal = raw[a:b]
                if n_ch == 1:
                    np.multiply(laps[0][a:b], laps[0][a:b], out=sal)
                else:  # the luminance's coefficients, squared
                    np.add(laps[0][a:b], laps[1][a:b], out=sal)
                    for lap in laps[2:]:
                        sal += lap[a:b]
                    sal *= np.float32(1.0 / n_ch)
                    np.multiply(sal, sal, out=sal)

            def choose(i: int, a: int, b: int, lev=lev, laps=laps, raw=raw, support=support, hh=hh, ww=ww) -> None:
                a0, b0 = max(0, a - self._halo), min(hh, b + self._halo)
                window = self._window[i][:(b0 - a0) * ww].reshape(b0 - a0, ww)
                cv2.GaussianBlur(raw[a0:b0], (0, 0), self.sigma, dst=window, borderType=_BORDER)
                sal = window[a - a0:b - a0]
                if support is not None:
                    sal[~support[a:b]] = -1.0
                best_sal = self.best_sal[lev][a:b]
                if k == 0:
                    np.copyto(best_sal, sal)
                    return
                take = np.greater(sal, best_sal, out=self._take[a * ww:b * ww].reshape(b - a, ww))
                for c in range(n_ch):
                    masked_copy(self.best[c][lev][a:b], laps[c][a:b], take)
                np.maximum(best_sal, sal, out=best_sal)
                if lev == self.index_level:
                    masked_copy(self.best_idx[a:b], k, take)

            self._each_band(salience, bands)
            self._each_band(choose, bands)  # after every band's salience: a band's window reads its neighbours'
            curs = [self.gauss[c][lev] for c in range(n_ch)]
        for c in range(n_ch):
            self.base_sum[c] += curs[c]

    def collapse(self, c: int, n_frames: int) -> np.ndarray:
        """Channel ``c`` fused: the selected pyramid over the mean base, collapsed (overwrites the
        coefficients)."""
        img = (self.base_sum[c] / n_frames).astype(np.float32)
        for lev in range(self.levels - 1, -1, -1):
            hh, ww = self.shapes[lev]
            up = cv2.pyrUp(img, dstsize=(ww, hh), borderType=_BORDER)
            img = np.add(self.best[c][lev], up, out=self.best[c][lev])
        return img


def _select(selection: _Selection, read, n_frames: int, n_channels: int, shape: tuple[int, int],
            support=None) -> None:
    """Add ``n_frames`` frames to ``selection`` in z order: ``read(k, planes)`` fills one float32 plane per channel
    with frame ``k`` on a thread of its own, the next frame read while one is added (two sets of planes, reused);
    OpenCV's own threads share the pyramids' and saliences' filtering. ``support(k)``, when given, is frame
    ``k``'s mask of recorded pixels (or ``None``: everywhere)."""

    h, w = shape
    sets = [[np.empty((h, w), np.float32) for _ in range(n_channels)] for _ in range(2 if n_frames > 1 else 1)]
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="fieldcal-fuse-read") as pool:
        pending = pool.submit(read, 0, sets[0])
        for k in range(n_frames):
            pending.result()
            if k + 1 < n_frames:
                pending = pool.submit(read, k + 1, sets[(k + 1) % 2])
            selection.add(sets[k % 2], k, support(k) if support is not None else None)


def fuse_pyramid(stack, geometry=None, frames=None, *, levels: int | None = None, window_px: float = 5.0,
                 quiet: bool = False) -> FusionResult:
    """All-in-focus image of a scene with depth, by per-scale selection of the sharpest frame.

    Parameters
    ----------
    stack : fieldcal.Stack or ArrayStack
        The frames (any dtype; output is float32 in the frames' units).
    geometry : lens profile, estimated geometry or None
        Warps each frame to the output geometry (``magnification``/``shift_px`` about ``optical_centre_px``);
        ``None`` takes the frames as registered.
    frames : array of int, optional
        File indices to use; default all.
    levels : int, optional
        Band-pass levels; default :func:`default_levels`.
    window_px : float
        Width of the salience window at each level (in that level's pixels); 5 px follows local contrast
        without letting one frame's noise decide a pixel.
    quiet : bool
        No progress bar.

    Returns
    -------
    FusionResult

    Notes
    -----
    Float32 throughout: the running selection (the best coefficients and saliences) and one frame's scratch
    pyramid, reused; each level's selection split in row bands over the compositor's threads (the same values
    as on the whole plane).

    Examples
    --------
    >>> from fieldcal.composite.source import ArrayStack
    >>> import numpy as np
    >>> sharp = np.random.default_rng(0).random((64, 64, 1)).astype(np.float32)
    >>> blurred = np.full_like(sharp, sharp.mean())
    >>> st = ArrayStack([blurred, sharp], [0.0, 10.0], ["Y"])
    >>> out = fuse_pyramid(st, quiet=True)
    >>> bool(np.abs(out.image - sharp).mean() < 0.1 * np.abs(blurred - sharp).mean())
    True
    """
    w, h = image_size(stack)
    channels = tuple(stack.channels)
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    if len(idx) < 1:
        raise ParameterError("no frames to fuse", field="frames", fix="give at least one frame")
    order = idx[np.argsort(z_all[idx], kind="stable")]
    n_levels = int(levels) if levels is not None else default_levels(w, h)
    if n_levels < 1 or (min(w, h) >> n_levels) < 2:
        raise ParameterError(f"{n_levels} pyramid levels do not fit a {w}x{h} image", field="levels",
                             fix="use fewer levels")
    sigma = max(float(window_px), 1.0) / 2.0
    # Level 1 (half resolution) is less noise-driven than level 0 and still follows edges within 2 px.
    index_level = 1 if n_levels > 1 else 0
    bar = iter(progress(order, total=len(order), desc="fusing", quiet=quiet, unit="frame"))

    def read(k: int, planes: list[np.ndarray]) -> None:
        i = next(bar)
        frame_planes(stack, geometry, float(z_all[i]), int(i), channels, w, h, out=planes)

    cover = getattr(stack, "support", None)  # registered frames: where each holds recorded pixels
    workers = default_workers()
    fused = np.empty((h, w, len(channels)), dtype=np.float32)
    # the selection's row bands run on this thread and the pool's (the compositor's threads, less this one): it
    # was serial on this thread, one core idle, ~0.6 s of the board's 1 s of fusion (bench_composite_speed_s17_overlap)
    with ThreadPoolExecutor(max_workers=max(1, workers - 1), thread_name_prefix="fieldcal-fuse-band") as pool:
        sel = _Selection(h, w, len(channels), n_levels, sigma, index_level, pool=pool, workers=workers)
        _select(sel, read, len(order), len(channels), (h, w),
                (lambda k: cover(int(order[k]))) if cover is not None else None)
        next(bar, None)  # closes the progress bar

        def collapse(c: int) -> None:
            fused[..., c] = sel.collapse(c, len(order))

        later = [pool.submit(collapse, c) for c in range(1, len(channels))] if workers > 1 else []
        for c in range(len(channels) if not later else 1):
            collapse(c)
        depth = _depth_index(sel.best_idx, w, h)
        for f in later:
            f.result()
    return FusionResult(fused, depth, z_all[order], n_levels, index_reach_px(2.0 * sigma, index_level))


def _depth_index(choice: np.ndarray, w: int, h: int) -> np.ndarray:
    """Frame choice per pixel at one level (every channel's), median-filtered, upsampled (nearest) to ``w x h``."""
    d = cv2.medianBlur(choice.astype(np.uint8) if choice.max() < 256 else choice.astype(np.float32), INDEX_MEDIAN_PX)
    return cv2.resize(d.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)


@dataclass
class DepthMap:
    """Per-pixel best focus measured from the stack: ``z_um`` (H x W float32, µm), ``confidence``
    (H x W, peak over mean focus measure minus 1, ~0 where there is no texture)."""

    z_um: np.ndarray
    confidence: np.ndarray


class _GuidedFilter:
    """He et al.'s guided filter (2013) with a grey guide, the guide's statistics computed once for all the
    inputs filtered with it (OpenCV ``ximgproc.guidedFilter`` recomputes them on every call). Box windows with
    ``BORDER_REFLECT``, as ximgproc's: the output is ximgproc's to float32 rounding. Calls may run concurrently.

    ``subsample`` > 1: He and Sun's fast guided filter (2015): the linear coefficients ``a``, ``b`` are computed on
    the guide and input area-averaged by that factor, with a box of ``radius / subsample`` there, and
    interpolated back (bilinear) to be applied to the full-resolution guide. The coefficients are box means over
    ``2 radius + 1`` px, smooth at the scale of the box, so a sampling of a few points per box width keeps them;
    the guide's edges, where the output must follow it, still come from the full-resolution guide.
    """

    def __init__(self, guide: np.ndarray, radius: int, eps: float, subsample: int = 1):
        self.guide = np.ascontiguousarray(guide, dtype=np.float32)
        self.s = max(1, int(subsample))
        h, w = self.guide.shape
        self.low = (-(-w // self.s), -(-h // self.s))  # cv2's (width, height) of the subsampled planes
        low_guide = self._down(self.guide)
        r = max(1, int(round(radius / self.s))) if self.s > 1 else int(radius)
        self.ksize = (2 * r + 1, 2 * r + 1)
        self.low_guide = low_guide
        self.mean = self._box(low_guide)
        var = self._box(low_guide * low_guide)
        var -= self.mean * self.mean
        var += np.float32(eps)
        self.inv_var = np.divide(np.float32(1.0), var, out=var)

    def _down(self, a: np.ndarray) -> np.ndarray:
        if self.s == 1:
            return a
        return cv2.resize(a, self.low, interpolation=cv2.INTER_AREA)

    def _box(self, a: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        return cv2.boxFilter(a, cv2.CV_32F, self.ksize, dst=out, normalize=True, borderType=cv2.BORDER_REFLECT)

    def __call__(self, src: np.ndarray) -> np.ndarray:
        p = self._down(np.asarray(src, dtype=np.float32))
        mean_p = self._box(p)
        a = self._box(np.multiply(self.low_guide, p))  # mean of guide x input
        tmp = np.multiply(self.mean, mean_p)
        a -= tmp  # covariance of guide and input
        a *= self.inv_var
        b = np.subtract(mean_p, np.multiply(a, self.mean, out=tmp), out=mean_p)
        a = self._box(a, out=a)
        b = self._box(b, out=b)
        if self.s > 1:
            size = self.guide.shape[::-1]
            a = cv2.resize(a, size, interpolation=cv2.INTER_LINEAR)
            b = cv2.resize(b, size, interpolation=cv2.INTER_LINEAR)
        a *= self.guide
        a += b
        return a


class _PeakTracker:
    """The per-pixel maximum over a focus volume streamed frame by frame (z order) and, for the sub-frame
    parabola, the values at the frames on either side of it: the volume itself is never held.

    Matches ``argmax`` over the volume (the first frame wins ties) and its neighbours clipped to the stack's
    ends (at the first or last frame the missing neighbour is the peak itself).
    """

    def __init__(self, first: np.ndarray):
        self.peak = first.copy()
        self.before = first.copy()
        self.after = first.copy()
        self.total = first.copy()
        self.index = np.zeros(first.shape, np.int16)
        self._prev = first
        self._mask = np.empty(first.shape, bool)
        self.n = 1

    def add(self, f: np.ndarray) -> None:
        k = self.n
        # the frame after a peak found at the previous frame
        masked_copy(self.after, f, np.equal(self.index, k - 1, out=self._mask))
        take = np.greater(f, self.peak, out=self._mask)
        masked_copy(self.before, self._prev, take)
        masked_copy(self.after, f, take)  # the peak's own value until a frame follows (clipped at the end)
        masked_copy(self.peak, f, take)
        masked_copy(self.index, k, take)
        self.total += f
        self._prev = f
        self.n += 1


def depth_map(stack, geometry=None, frames=None, *, guide: np.ndarray | None = None, window_px: float = 1.0,
              radius_px: int | None = None, eps: float = 1e-3, quiet: bool = False) -> DepthMap:
    """Per-pixel depth from focus with edge-aware aggregation (for scenes with depth).

    1. Per frame (warped to the output geometry): the modified Laplacian of the luminance, squared, Gaussian-
       smoothed over ``window_px``.
    2. Each frame's focus map is guided-filtered (He et al. 2013; :class:`_GuidedFilter`, OpenCV ``ximgproc``'s
       filter with the guide's statistics computed once; exact: its subsampled form lost 0.06-0.10 dB on the
       simulated thin bars at 960 x 720, bench_composite_speed_s15) with ``guide``, an
       all-in-focus image of the same scene (e.g. :func:`fuse_pyramid`'s), so the aggregation follows the
       scene's edges: a sharp foreground edge does not lend its focus energy to the blurred background beside
       it (no halo), yet textureless stretches inherit the depth of the object they belong to.
    3. Per pixel: the frame of peak focus, refined by a parabola through its neighbours (sub-frame), and a
       confidence.

    Frames are measured on a few threads and the peak is tracked as they come (:class:`_PeakTracker`): memory
    holds a few planes, not the focus volume.

    Parameters
    ----------
    stack, geometry, frames
        As :func:`fuse_pyramid`.
    guide : H x W x C array, optional
        All-in-focus guide; default: a pyramid fusion of the stack.
    window_px : float
        Focus-measure window (Gaussian sigma, px).
    radius_px : int, optional
        Guided-filter radius; default 1/200 of the image diagonal (at least 2 px): wider lets a sharp edge's
        energy decide pixels that belong to the object behind it.
    eps : float
        Guided-filter regularisation, in units of the guide's normalised range squared.
    """
    from .dff import map_in_order, modified_laplacian

    w, h = image_size(stack)
    channels = tuple(stack.channels)
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    if len(order) < 1:
        raise ParameterError("no frames for depth from focus", field="frames", fix="give at least one frame")
    if guide is None:
        guide = fuse_pyramid(stack, geometry, frames, quiet=quiet).image
    g = _grey(np.asarray(guide, dtype=np.float32))
    r = int(radius_px) if radius_px is not None else max(2, int(round(np.hypot(w, h) / 200)))

    def normalised_guide() -> _GuidedFilter:
        lo, hi = np.percentile(g, [0.5, 99.5])
        g[...] -= np.float32(g.min())
        g[...] *= np.float32(1.0 / max(float(hi - lo), 1e-12))
        return _GuidedFilter(g, r, eps)

    # The guide's normalisation and both guided filters' statistics on a thread of their own (they were serial
    # on this one, ~0.1 s with a core idle): the frames' focus measures start meanwhile and wait for the first
    # filter only where they need it; the smoothing's filter is ready by the end of the frames.
    aux = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fieldcal-depth-aux")
    gf_ready = aux.submit(normalised_guide)
    smooth_ready = aux.submit(lambda: _GuidedFilter(g, max(1, r // 2), 1e-2))  # after the normalisation (one thread)
    cover = getattr(stack, "support", None)  # registered frames: where each holds recorded pixels

    def focus(i: int) -> np.ndarray:
        planes = frame_planes(stack, geometry, float(z_all[i]), int(i), channels, w, h)
        lum = planes[0]
        for plane in planes[1:]:
            lum += plane
        if len(planes) > 1:
            lum /= np.float32(len(planes))
        e = modified_laplacian(lum)
        del planes, lum
        np.multiply(e, e, out=e)
        e = cv2.GaussianBlur(e, (0, 0), window_px, dst=e, borderType=_BORDER)
        q = gf_ready.result()(e)
        # an energy is >= 0: the guided filter's undershoot beside strong edges is not focus, and negative
        # values would make the mean below (the confidence's denominator) meaningless
        q = np.maximum(q, np.float32(0.0), out=q)
        mask = cover(int(i)) if cover is not None else None
        if mask is not None:  # a registered frame's repeated edge pixels are streaks, not focus
            q[~mask] = 0.0
        return q

    try:
        track = None
        for f in progress(map_in_order(focus, order), total=len(order), desc="depth from focus", quiet=quiet,
                          unit="frame"):
            if track is None:
                track = _PeakTracker(f)
            else:
                track.add(f)
        gf_ready.result()  # (an error of the normalisation raised here even without frames to wait for it)
        del gf_ready
        smooth = smooth_ready.result()
    except BaseException:
        aux.shutdown(wait=True, cancel_futures=True)
        raise
    zs = z_all[order].astype(np.float64)
    n = len(zs)
    k = track.index
    peak = track.peak
    mean = np.multiply(track.total, np.float32(1.0 / n), out=track.total)
    # a floor relative to the stack's strongest focus: where nothing is textured, confidence 0, not noise/noise
    floor = np.float32(max(1e-6 * float(mean.max()), 1e-30))
    conf = np.divide(peak, np.maximum(mean, floor, out=mean), out=mean)
    conf -= np.float32(1.0)
    np.maximum(conf, np.float32(0.0), out=conf)
    zb = zs.astype(np.float32)[k]
    if n >= 3:
        fm, fp = track.before, track.after
        den = peak * np.float32(-2.0)
        den += fm
        den += fp
        inner = (k > 0) & (k < n - 1) & (den < 0)
        off = np.subtract(fm, fp, out=fm)
        off *= np.float32(0.5)
        np.divide(off, den, out=off, where=inner)
        off[~inner] = 0.0
        np.clip(off, -0.5, 0.5, out=off)
        up = np.diff(zs, append=zs[-1]).astype(np.float32)  # z[k + 1] - z[k], 0 at the last frame
        down = np.diff(zs, prepend=zs[0]).astype(np.float32)  # z[k] - z[k - 1], 0 at the first
        step = np.where(off >= 0, up[k], down[k])
        off *= step
        zb += off
        del fm, fp, den, off, step, inner
    del track
    # Confidence-weighted, edge-aware smoothing: a pixel with little texture takes the depth of the confident
    # pixels of its own object (the guide's edges bound the averaging); confident pixels barely move.
    # the two filterings at once, one on each core (a guided filter's calls may run concurrently)
    den_ready = aux.submit(smooth, conf)
    aux.shutdown(wait=False)
    num = smooth(zb * conf)
    den = den_ready.result()
    ok = den > 1e-6
    np.divide(num, den, out=zb, where=ok)
    # the guided filter is not a convex average: where the confidence nearly vanishes its ratio can leave the
    # stack; no depth from focus lies beyond the frames
    np.clip(zb, np.float32(zs[0]), np.float32(zs[-1]), out=zb)
    return DepthMap(zb, conf)


def _grey(img: np.ndarray) -> np.ndarray:
    """Mean over channels of an ``H x W x C`` float32 image, ``H x W`` (OpenCV's ``transform``: one pass)."""
    c = img.shape[2] if img.ndim == 3 else 1
    if c == 1:
        return np.array(img.reshape(img.shape[:2]), dtype=np.float32)
    if c <= 4:
        return cv2.transform(img, np.full((1, c), 1.0 / c, np.float32))
    return img.mean(axis=2, dtype=np.float32)
