"""Depth from focus (paper Fig. 12): where is each pixel in focus, measured from the stack itself.

1. Focus volume: each frame (warped to the geometry of ``z_ref`` when a profile is known) is lightly smoothed
   and filtered with calibration's focus measure, the modified Laplacian ``|2I - I(x-1) - I(x+1)| +
   |2I - I(y-1) - I(y+1)|`` (:func:`fieldcal.measure.focus.sml`), per channel, and averaged over blocks
   (:func:`fieldcal.measure.focus.cell_sums`): the sum-modified-Laplacian. Only the small block volume
   (frames x blocks x channels) is kept.
2. Per block: the frame of peak focus, refined to sub-frame precision by a parabola through the peak and its
   neighbours; a confidence ``(peak - median) / median`` that is ~0 where there is no texture.
3. A smooth surface (a general quadratic plus radial r^4, r^6 terms, in normalised coordinates) is fitted to the block
   estimates by confidence-weighted, Tukey-reweighted least squares, so textureless regions and outliers
   follow the surface instead of noise. Composites then blend frames with this surface exactly as with a
   profile's (:mod:`.weights`).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np

from ..errors import ParameterError
from ..measure.focus import cell_sums, sml
from ..progress import progress
from .source import image_size, z_positions
from .surface import dense_map, output_best_focus_um
from .warp import frame_maps, warp_region

#: Bytes of one band when a frame is read into planes (:func:`frame_planes`): ~8 MB stays below glibc's 32 MB
#: ceiling for memory taken by ``mmap``, so band buffers are recycled rather than faulted in afresh per frame (a
#: whole 2048 x 1536 RGB float32 frame, 38 MB, costs as much in page faults as the arithmetic on it).
BAND_BYTES = 8 * 2 ** 20


def frame_planes(stack, geometry, z_um: float, i: int, channels, width: int, height: int, *,
                 lateral_colour: bool = False, out: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Frame ``i`` warped to the output geometry, one contiguous float32 ``H x W`` plane per channel.

    Read and warped in bands of rows (:data:`BAND_BYTES`), the same pixels as one whole-frame warp; written
    into ``out`` (a plane per channel) when given.
    """
    planes = out if out is not None else [np.empty((height, width), np.float32) for _ in channels]
    rows = max(16, BAND_BYTES // max(1, width * len(channels) * 4))
    held = getattr(stack, "read_rows_into", None)  # held frames: read, scaled and split in one pass
    for fmap in frame_maps(geometry, float(z_um), channels, lateral_colour):
        for y0 in range(0, height, rows):
            y1 = min(height, y0 + rows)
            if fmap.is_identity and held is not None and held(int(i), y0, y1, list(fmap.channels),
                                                              [planes[c][y0:y1] for c in fmap.channels]):
                continue
            part = warp_region(stack, int(i), fmap, 0, y0, width, y1)
            for j, c in enumerate(fmap.channels):
                planes[c][y0:y1] = part[..., j]
    return planes


def map_in_order(fn, items, workers: int | None = None, ahead: int | None = None):
    """``fn(item)`` for each item on ``workers`` threads (default: the compositor's), results yielded in order,
    at most ``ahead`` in flight (default ``2 * workers``; ``workers`` for items whose results are whole frames,
    where each one in flight is memory at the peak). OpenCV and NumPy release the GIL."""
    from concurrent.futures import ThreadPoolExecutor

    from .stream import default_workers

    items = list(items)
    workers = default_workers() if workers is None else max(1, int(workers))
    if workers == 1 or len(items) < 2:
        yield from map(fn, items)
        return
    ahead = 2 * workers if ahead is None else max(1, int(ahead))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fieldcal-frames") as pool:
        pending = [pool.submit(fn, it) for it in items[:ahead]]
        for k in range(len(items)):
            result = pending[k].result()
            pending[k] = None
            if k + ahead < len(items):
                pending.append(pool.submit(fn, items[k + ahead]))
            yield result


#: Row bands (:func:`row_bands`) are at least this high: below, a thread's hand-over costs more than the work.
BAND_MIN_ROWS = 64


def row_bands(fn, n_rows: int) -> list:
    """``[fn(a, b), ...]`` over row bands ``a:b`` of ``n_rows`` rows, in order, one band per compositor thread
    (:func:`.source.default_workers`; none under :data:`BAND_MIN_ROWS` rows), run on those threads. For per-pixel
    (per-row) work that would otherwise keep one core idle: each band's values are the whole array's."""
    from .source import default_workers

    n = max(1, min(default_workers(), n_rows // BAND_MIN_ROWS))
    if n == 1:
        return [fn(0, n_rows)]
    edges = [n_rows * i // n for i in range(n + 1)]
    return list(map_in_order(lambda ab: fn(*ab), list(pairwise(edges)), workers=n))


def default_block_px(width: int, height: int) -> int:
    """Blocks of 8-32 px, at least ~16 across the short side."""
    return int(np.clip(min(width, height) // 16, 8, 32))


def modified_laplacian(channel: np.ndarray) -> np.ndarray:
    """Calibration's modified Laplacian (:func:`fieldcal.measure.focus.sml`) of one float32 channel, lightly
    pre-smoothed: a scene (unlike a chart) has texture at the noise's frequencies, where the 1-px kernel would
    measure noise."""
    return sml(cv2.GaussianBlur(np.ascontiguousarray(channel, dtype=np.float32), (3, 3), 0.7,
                                borderType=cv2.BORDER_REFLECT_101))


@dataclass
class FocusVolume:
    """Block focus measure per frame: ``values[k, by, bx, c]`` for frames sorted by z (``z_um``)."""

    z_um: np.ndarray
    values: np.ndarray
    block_px: int
    x_px: np.ndarray  # block centres (px), shape (bx,)
    y_px: np.ndarray  # shape (by,)
    #: per pixel (every ``PIXEL_STRIDE``-th row and column): the frame (index in z order) where the focus measure,
    #: summed over channels and smoothed over ~1.5 px, peaks, and that peak; for telling a scene with thin or
    #: small things at another depth (which blocks average away) from a flat one
    pixel_peak_index: np.ndarray | None = None
    pixel_peak: np.ndarray | None = None


#: Subsampling of the per-pixel peak maps (rows and columns): enough pixels to count, a 16th of the memory.
PIXEL_STRIDE = 4
#: Smoothing of the per-pixel focus measure before its peak is taken (Gaussian sigma, px): a thin wire (2 px)
#: keeps its own peak, single-pixel noise does not make one.
PIXEL_SIGMA_PX = 1.5


def focus_volume(stack, profile=None, *, frames=None, block_px: int | None = None,
                 lateral_colour: bool = False, quiet: bool = False) -> FocusVolume:
    """Stream the frames once and measure focus per block and channel (a few frames in memory at a time,
    measured on the compositor's threads)."""
    w, h = image_size(stack)
    b = int(block_px or default_block_px(w, h))
    if b < 2 or b > min(w, h):
        raise ParameterError(f"block size {b} px does not fit a {w}x{h} image", field="block_px",
                             fix="use a block size between 2 px and the image's short side")
    nbx, nby = w // b, h // b
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    channels = tuple(stack.channels)
    vol = np.empty((len(order), nby, nbx, len(channels)), dtype=np.float32)
    s = PIXEL_STRIDE
    cover = getattr(stack, "support", None)  # registered frames: where each holds recorded pixels

    def measure(i: int) -> tuple[np.ndarray, np.ndarray]:
        cells = np.empty((nby, nbx, len(channels)), dtype=np.float32)
        pix = None
        mask = cover(int(i)) if cover is not None else None
        for ci, plane in enumerate(frame_planes(stack, profile, float(z_all[i]), int(i), channels, w, h,
                                                lateral_colour=lateral_colour)):
            ml = modified_laplacian(plane)
            if mask is not None:  # a registered frame's repeated edge pixels are streaks, not focus
                ml[~mask] = 0.0
            cells[..., ci] = cell_sums(ml, b) * np.float32(1.0 / (b * b))
            if pix is None:
                pix = ml
            else:
                pix += ml
        pix = cv2.GaussianBlur(pix, (0, 0), PIXEL_SIGMA_PX, dst=pix, borderType=cv2.BORDER_REFLECT_101)
        return cells, np.ascontiguousarray(pix[::s, ::s])

    best = np.full(((h + s - 1) // s, (w + s - 1) // s), -1.0, np.float32)
    best_k = np.zeros(best.shape, np.int16)
    results = map_in_order(measure, order)
    for k, (cells, pix) in enumerate(progress(results, total=len(order), desc="focus volume", quiet=quiet,
                                              unit="frame")):
        vol[k] = cells
        take = pix > best
        best[take] = pix[take]
        best_k[take] = k
    xs = (np.arange(nbx) + 0.5) * b - 0.5
    ys = (np.arange(nby) + 0.5) * b - 0.5
    return FocusVolume(z_all[order], vol, b, xs, ys, best_k, best)


def pixel_misfit_fraction(vol: FocusVolume, surfaces: list[SurfaceFit], spacing_um: float) -> float:
    """Fraction of the textured pixels (the upper half of per-pixel focus peaks) whose own peak frame lies a
    frame spacing, and a third of the blocks' median through-focus width (FWHM, about three focus tolerances), or
    more from the smooth surface (mean over channels) fitted to the blocks.

    Blocks average a thin wire or a small part away (it covers a few per cent of a block); pixels do not. On a
    flat scene a pixel's peak wanders with noise by a fraction of the curve's width (several frames in a fine
    stack: 8 % of pixels by a spacing at half a tolerance per frame, 0.2 % by a third of the width); a thin
    thing in front of a background sits that far off at every one of its pixels.
    """
    if vol.pixel_peak is None or len(vol.z_um) < 3 or not surfaces:
        return 0.0
    s = PIXEL_STRIDE
    hh, ww = vol.pixel_peak.shape
    yy, xx = np.mgrid[0:hh, 0:ww].astype(np.float64) * s
    z_surf = np.mean([f(xx, yy) for f in surfaces], axis=0)
    peak = vol.pixel_peak
    inner = (vol.pixel_peak_index > 0) & (vol.pixel_peak_index < len(vol.z_um) - 1)  # not beyond the stack
    textured = peak >= np.median(peak)
    if not np.any(textured):
        return 0.0
    v = vol.values
    half = 0.5 * (v.max(axis=0) + np.median(v, axis=0))
    fwhm = float(np.median(np.sum(v >= half[None], axis=0))) * spacing_um  # fine steps: peaks wander further
    off = np.abs(vol.z_um[vol.pixel_peak_index] - z_surf) >= max(spacing_um, fwhm / 3.0)
    return float(np.mean((off & inner)[textured]))


def peak_depth(vol: FocusVolume) -> tuple[np.ndarray, np.ndarray]:
    """Per block and channel: sub-frame best-focus z (µm) and confidence (>= 0).

    Returns arrays of shape (by, bx, C).
    """
    v = vol.values.astype(np.float64)
    z = vol.z_um
    n = len(z)
    k = np.argmax(v, axis=0)
    peak = np.take_along_axis(v, k[None], axis=0)[0]
    med = np.median(v, axis=0)
    conf = np.clip((peak - med) / np.maximum(med, 1e-12 * max(float(v.max()), 1e-30)), 0.0, None)
    if n < 3:
        return z[k], conf
    km = np.clip(k - 1, 0, n - 1)
    kp = np.clip(k + 1, 0, n - 1)
    fm = np.take_along_axis(v, km[None], axis=0)[0]
    fp = np.take_along_axis(v, kp[None], axis=0)[0]
    z0, zm, zp = z[k], z[km], z[kp]
    # Vertex of the parabola through (zm, fm), (z0, peak), (zp, fp); undefined at the ends of the stack.
    a1, a2 = (z0 - zm) * (peak - fp), (z0 - zp) * (peak - fm)
    den = a1 - a2
    inner = (k > 0) & (k < n - 1) & (np.abs(den) > 1e-30)
    num = (z0 - zm) * a1 - (z0 - zp) * a2
    zv = z0 - 0.5 * num / np.where(inner, den, 1.0)
    zbest = np.where(inner, np.clip(zv, zm, zp), z0)
    # A peak on the last/first frame may lie beyond the stack: trust it less.
    conf = np.where(inner, conf, 0.25 * conf)
    return zbest, np.where(peak_is_significant(v, k), conf, 0.0)


#: A block's peak counts when it stands this many noise sigmas above the curve's median (:func:`peak_is_significant`).
#: Pure Gaussian noise exceeds it with probability 2e-4 at 19 frames, 5e-3 at 11, 3e-2 at 9 (Monte Carlo); a peak
#: without noise, Gaussian or Lorentzian, 1-8 frames wide (FWHM), stands >= 13 of its own tails' "noise" high at
#: 9-19 frames, and the textured blocks of a simulated stack 15-80.
PEAK_SIGMA = 8.0
#: Fewer frames leave too few second differences outside the peak to estimate the noise: every peak counts.
PEAK_SIGMA_MIN_FRAMES = 9


def peak_is_significant(v: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Per block and channel: does the through-focus peak stand out of the curve's own noise?

    The noise of a block's focus measure is estimated from the curve itself: the RMS second difference
    ``v[j+1] - 2 v[j] + v[j-1]`` (variance 6 sigma^2 for independent noise) over the frames outside the peak's
    run above half height (``(max + median) / 2``) and one frame beyond it, where a real peak's own curvature is
    small. A textureless block's curve is that noise alone, and its maximum stands ~2 sigma above its median; the
    relative confidence ``(peak - median) / median`` cannot tell it (0.1-0.5 for a flat grey block of 10 px, as
    for a faint texture), so such blocks reached the surface fit, and which of them did changed with the noise's
    draw. Where fewer than 3 second differences remain (a peak as wide as the stack) the peak counts.

    ``v``: the focus volume (frames x ...; frames sorted by z); ``k``: the peak frame per block (shape ``...``).
    """
    n = v.shape[0]
    if n < PEAK_SIGMA_MIN_FRAMES:
        return np.ones(k.shape, dtype=bool)
    med = np.median(v, axis=0)
    excess = v.max(axis=0) - med
    frame = np.arange(n).reshape((-1,) + (1,) * k.ndim)
    below = v < (med + 0.5 * excess)[None]
    # the run of frames at or above half height that holds the peak: [first, last]
    first = np.max(np.where(below & (frame < k[None]), frame, -1), axis=0) + 1
    last = np.min(np.where(below & (frame > k[None]), frame, n), axis=0) - 1
    centre = frame[1:-1]
    away = (centre < first[None] - 1) | (centre > last[None] + 1)
    d2 = v[2:] - 2.0 * v[1:-1] + v[:-2]  # centred on frames 1 .. n-2
    count = np.sum(away, axis=0)
    sigma = np.sqrt(np.sum(np.where(away, d2 * d2, 0.0), axis=0) / (6.0 * np.maximum(count, 1)))
    return (count < 3) | (excess > PEAK_SIGMA * sigma)


@dataclass
class SurfaceFit:
    """A fitted best-focus surface ``z(x, y)`` (µm) in normalised coordinates about ``centre_px``.

    ``degree`` indexes the model: 0 constant, 1 plane, 2 quadratic, 3 + r^4, 4 + r^6.
    """

    coef: np.ndarray
    degree: int
    centre_px: tuple[float, float]
    scale_px: float
    rms_um: float
    n_used: int

    def __call__(self, x, y):
        u = (np.asarray(x, dtype=np.float64) - self.centre_px[0]) / self.scale_px
        v = (np.asarray(y, dtype=np.float64) - self.centre_px[1]) / self.scale_px
        return _design(u, v, self.degree) @ self.coef


# Surface models by number of terms: a constant, a plane (tilt), a general quadratic (field curvature about a
# decentred axis, tilt, astigmatism-like cylinder), and that plus the radial r^4 and r^6 of field curvature.
# Radial high orders extrapolate sanely into textureless corners; a full 2-D quartic does not.
_MODELS = {0: 1, 1: 3, 2: 6, 3: 7, 4: 8}


def _design(u, v, degree: int) -> np.ndarray:
    u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    r2 = u * u + v * v
    cols = [np.ones_like(u), u, v, u * u, u * v, v * v, r2 * r2, r2 * r2 * r2][:_MODELS[degree]]
    return np.stack(cols, axis=-1)


def fit_surface(x_px, y_px, z_um, weight, centre_px, scale_px: float, degree: int = 4,
                iterations: int = 10) -> SurfaceFit:
    """Robust weighted polynomial surface: Tukey biweight IRLS (c = 4.685 MAD) on top of ``weight``.

    The degree drops when there are fewer than 3 confident samples per coefficient.
    """
    x, y, z, w0 = (np.asarray(a, dtype=np.float64).ravel() for a in (x_px, y_px, z_um, weight))
    good = np.isfinite(z) & (w0 > 0)
    x, y, z, w0 = x[good], y[good], z[good], w0[good]
    if len(z) == 0:
        raise ParameterError("no block has any focus signal (a blank or saturated scene?)", field="stack",
                             fix="composite with a lens profile, or capture a textured scene")
    degree = int(np.clip(degree, 0, max(_MODELS)))
    while degree > 0 and len(z) < 3 * _MODELS[degree]:
        degree -= 1
    u = (x - centre_px[0]) / scale_px
    v = (y - centre_px[1]) / scale_px
    a = _design(u, v, degree)
    w = w0.copy()
    coef = np.zeros(a.shape[1])
    for _ in range(iterations):
        sw = np.sqrt(w)
        coef = _weighted_lstsq(a, z, sw)
        r = z - a @ coef
        s = 1.4826 * np.median(np.abs(r[w > 0])) if np.any(w > 0) else 0.0
        s = max(s, 1e-3)
        t = np.clip(r / (4.685 * s), -1.0, 1.0)
        w = w0 * (1.0 - t * t) ** 2
        if not np.any(w > 0):
            w = w0.copy()
            break
    r = z - a @ coef
    rms = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-30)))
    return SurfaceFit(coef, degree, (float(centre_px[0]), float(centre_px[1])), float(scale_px), rms,
                      int(np.count_nonzero(w > 0)))


def _weighted_lstsq(a: np.ndarray, z: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """Least squares of ``a @ coef ~ z`` with row weights ``sw``: by the normal equations when they are well
    conditioned (the design's columns are powers of coordinates within about +-1: always, in practice), 30x
    faster than LAPACK's SVD solver on a few thousand rows, else by that solver."""
    aw = a * sw[:, None]
    zw = z * sw
    ata = aw.T @ aw
    if np.linalg.cond(ata) < 1e10:
        return np.linalg.solve(ata, aw.T @ zw)
    return np.linalg.lstsq(aw, zw, rcond=None)[0]


def _block_weights(conf: np.ndarray) -> np.ndarray:
    """Fit weights from confidences: blocks below a tenth of the typical confident block carry nothing."""
    c = conf.ravel()
    ref = np.percentile(c, 75) if c.size else 0.0
    return np.where(conf >= 0.1 * ref, np.minimum(conf, 4.0 * max(ref, 1e-12)), 0.0)


def dff_surfaces(vol: FocusVolume, width: int, height: int, channels, centre_px=None,
                 degree: int = 4) -> list[SurfaceFit]:
    """One fitted surface per channel from a focus volume."""
    zbest, conf = peak_depth(vol)
    xx, yy = np.meshgrid(vol.x_px, vol.y_px)
    c = centre_px or ((width - 1) / 2.0, (height - 1) / 2.0)
    scale = 0.5 * float(np.hypot(width, height))
    return [fit_surface(xx, yy, zbest[..., ci], _block_weights(conf[..., ci]), c, scale, degree)
            for ci in range(len(channels))]


def hybrid_corrections(vol: FocusVolume, profile, width: int, height: int, channels, *,
                       lateral_colour: bool = False, degree: int = 2,
                       focus_offset_um: float = 0.0) -> list[tuple[SurfaceFit, float]]:
    """Per channel, a low-order correction to the profile's surface fitted to the DFF residuals, and the
    largest correction allowed (the profile's 90 % band half-width plus half a frame spacing)."""
    zbest, conf = peak_depth(vol)
    xx, yy = np.meshgrid(vol.x_px, vol.y_px)
    cx, cy = (float(v) for v in profile.optical_centre_px())
    scale = 0.5 * float(np.hypot(width, height))
    spacing = float(np.median(np.diff(vol.z_um))) if len(vol.z_um) > 1 else 0.0
    out = []
    for ci, ch in enumerate(channels):
        zp = output_best_focus_um(profile, xx, yy, ch, lateral_colour) + focus_offset_um
        lo, hi = profile.best_focus_interval_um(xx, yy, ch, level=0.9)
        band = 0.5 * float(np.median(np.asarray(hi) - np.asarray(lo)))
        fit = fit_surface(xx, yy, zbest[..., ci] - zp, _block_weights(conf[..., ci]), (cx, cy), scale, degree)
        out.append((fit, band + 0.5 * spacing))
    return out


def dff_focus_map(surfaces: list[SurfaceFit], width: int, height: int) -> np.ndarray:
    """The fitted surfaces at every pixel, ``H x W x C`` float32."""
    out = np.empty((height, width, len(surfaces)), np.float32)

    def channel(c: int) -> None:  # (the channels on the compositor's threads: was ~0.08 s serial on the board)
        out[..., c] = dense_map(surfaces[c], width, height)

    for _ in map_in_order(channel, range(len(surfaces))):
        pass
    return out
