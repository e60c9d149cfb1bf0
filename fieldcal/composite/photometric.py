"""Exposure and white-balance flicker between the frames of a stack, measured and removed.

A real stack's frames differ in brightness and colour: flash or mains flicker, auto exposure, auto white
balance, a shutter that is not quite repeatable. The focus measures that choose a frame per pixel are energies,
so a frame 10 % brighter has 21 % more of every one: it wins pixels it is not sharpest in, and its brightness
shows as patches in the composite. Each frame is therefore brought to the reference frame's exposure and
colour, per channel, by a gain and an offset about the black level: ``v' - b = g (v - b) + o``.

That model is exact for an exposure or white-balance change of linear data (a gain) and of gamma-encoded data
(a pure power law turns a gain into a gain; sRGB's ``1.055 L^(1/2.4) - 0.055`` into a gain and an offset), and
for a changed black level (an offset). It is fitted on the registered frames (already warped into the
reference geometry at full resolution), on cells of about 1/128 of the frame's long side, area means: at that
scale a frame's defocus moves light only within a cell, except along the few cells a strong edge crosses. The
line is fitted by total least squares (both frames' cells carry the same kinds of error) with Huber weights,
which put aside edge cells; cells near clipping or not wholly inside the frame's recorded area are left out.
A scene whose cells span too narrow a range to tell a gain from an offset (the gain's standard error above
:data:`MAX_GAIN_SE`) gets a gain alone, through the black level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Cells per long side of the frame, of at least ``MIN_CELL_PX`` px (the registration warp's own smoothing, a
#: pixel wide, stays inside a cell).
CELLS_PER_SIDE = 128
MIN_CELL_PX = 8
#: Cells within this share of the white level (or of the black level) are left out: clipping breaks the model.
CLIP_MARGIN = 0.03
#: A fit needs this many cells in a channel, and a gain inside these bounds, else the frame is left as it is.
MIN_CELLS = 32
GAIN_BOUNDS = (0.5, 2.0)
#: Above this standard error of the gain, the offset is not fitted (a gain through the black level alone).
MAX_GAIN_SE = 0.003


@dataclass(frozen=True)
class Correction:
    """Per-channel gain and offset (raw units, about the black level) taking a frame to the reference frame's
    exposure and colour."""

    gain: np.ndarray
    offset: np.ndarray
    cells: int


def cell_px(width: int, height: int) -> int:
    """Full-resolution px per cell side: :data:`CELLS_PER_SIDE` cells on the long side, at least
    :data:`MIN_CELL_PX`."""
    return max(MIN_CELL_PX, int(np.ceil(max(width, height) / CELLS_PER_SIDE)))


def cell_means(image: np.ndarray, cell: int, scale: float = 1.0) -> np.ndarray:
    """Area means over ``cell`` x ``cell`` px (OpenCV ``INTER_AREA``) divided by ``scale`` (a held frame's
    fixed point), float32 ``h x w x C``."""
    import cv2

    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    h, w = a.shape[:2]
    size = (max(1, w // cell), max(1, h // cell))
    out = np.empty((size[1], size[0], a.shape[2]), np.float32)
    for k in range(0, a.shape[2], 4):  # cv2 takes at most 4 channels a call
        part = np.ascontiguousarray(a[..., k:k + 4])
        if part.dtype not in (np.uint8, np.uint16, np.float32):
            part = part.astype(np.float32)
        res = cv2.resize(part, size, interpolation=cv2.INTER_AREA)
        out[..., k:k + 4] = res.reshape(size[1], size[0], -1)
    if scale != 1.0:
        out *= np.float32(1.0 / scale)
    return out


def cells_inside(mask: np.ndarray | None, cell: int) -> np.ndarray | None:
    """Cells wholly inside a registered frame's recorded area (``mask``: H x W bool; None: everywhere)."""
    if mask is None:
        return None
    return cell_means(mask.astype(np.float32), cell)[..., 0] > 0.999


def _huber(r: np.ndarray) -> np.ndarray:
    """Huber weights (threshold 1.345 robust sigmas, the sigma from the median absolute deviation)."""
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    if sigma <= 0:
        return np.ones_like(r)
    return np.minimum(1.0, 1.345 * sigma / np.maximum(np.abs(r), 1e-30))


def fit_gain_offset(x: np.ndarray, y: np.ndarray, iterations: int = 8) -> tuple[float, float, float]:
    """``y ≈ g x + o`` (values above the black level) by total least squares with Huber weights on the
    orthogonal residuals; where the gain's standard error exceeds :data:`MAX_GAIN_SE`, ``y ≈ g x`` alone
    (weighted least squares). Returns ``(g, o, standard error of g)``."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    wts = np.ones_like(x)
    g, o, se = 1.0, 0.0, np.inf
    for _ in range(iterations):
        sw = wts.sum()
        mx, my = (wts * x).sum() / sw, (wts * y).sum() / sw
        dx, dy = x - mx, y - my
        cov = np.array([[(wts * dx * dx).sum(), (wts * dx * dy).sum()], [(wts * dx * dy).sum(), (wts * dy * dy).sum()]])
        vals, vecs = np.linalg.eigh(cov / sw)
        nx, ny = vecs[:, 0]  # the normal of the line: the direction of least spread
        if abs(ny) < 1e-12:
            break
        g, o = -nx / ny, my + nx / ny * mx
        r = (dx * nx + dy * ny)  # orthogonal residuals
        wts = _huber(r)
        # the slope's standard error: the orthogonal scatter over the spread along x, per effective sample
        var_x = cov[0, 0] / sw
        n_eff = sw * sw / max((wts * wts).sum(), 1e-30)
        se = float(np.sqrt(max(vals[0], 0.0) * (1 + g * g) / max(var_x * n_eff, 1e-30)))
    if se <= MAX_GAIN_SE and np.isfinite(g):
        return float(g), float(o), se
    wts = np.ones_like(x)
    for _ in range(iterations):
        g = float((wts * x * y).sum() / max((wts * x * x).sum(), 1e-30))
        r = y - g * x
        wts = _huber(r)
    sw = (wts * x * x).sum()
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return g, 0.0, float(sigma / np.sqrt(max(sw, 1e-30)))


def fit_correction(frame_cells: np.ndarray, ref_cells: np.ndarray, inside: np.ndarray | None, black: float,
                   white: float) -> Correction | None:
    """The gain and offset per channel taking a registered frame's cells (:func:`cell_means`, raw units) to the
    reference frame's; ``inside``: cells wholly in the frame's recorded area (None: all). None when fewer than
    :data:`MIN_CELLS` cells are usable or a gain is implausible (the frame is then left as it is)."""
    span = max(float(white) - float(black), 1e-12)
    lo, hi = CLIP_MARGIN * span, (1.0 - CLIP_MARGIN) * span
    f = frame_cells - np.float32(black)
    r = ref_cells - np.float32(black)
    ok = np.all((f > lo) & (f < hi) & (r > lo) & (r < hi), axis=2)
    if inside is not None:
        ok &= inside
    if int(ok.sum()) < MIN_CELLS:
        return None
    fits = [fit_gain_offset(f[..., c][ok], r[..., c][ok]) for c in range(f.shape[2])]
    gain = np.array([v[0] for v in fits])
    if not np.all(np.isfinite(gain) & (gain > GAIN_BOUNDS[0]) & (gain < GAIN_BOUNDS[1])):
        return None
    return Correction(gain, np.array([v[1] for v in fits]), int(ok.sum()))


def apply_correction(held: np.ndarray, corr: Correction, scale: float = 1.0, black: float = 0.0) -> np.ndarray:
    """A held frame (``H x W x C``, samples ``value * scale``) corrected about the ``black`` level, in its own
    dtype (integers rounded and saturated, by OpenCV ``transform``; a new array)."""
    import cv2

    held = np.asarray(held)
    offset = (corr.offset + float(black) * (1.0 - corr.gain)) * scale  # v' = g v + (o + b (1 - g))
    if held.dtype.kind == "f":
        return (held * corr.gain.astype(held.dtype) + offset.astype(held.dtype)).astype(held.dtype, copy=False)
    def transform(k: int, n: int) -> np.ndarray:
        m = np.zeros((n, n + 1))
        m[np.arange(n), np.arange(n)] = corr.gain[k:k + n]
        m[:, n] = offset[k:k + n]
        return cv2.transform(np.ascontiguousarray(held[..., k:k + n]), m).reshape(*held.shape[:2], n)

    if held.shape[2] <= 4:  # one call: OpenCV's array is the result (not copied into another)
        return transform(0, held.shape[2])
    out = np.empty_like(held)
    for k in range(0, held.shape[2], 4):  # cv2 takes at most 4 channels a call
        n = min(4, held.shape[2] - k)
        out[..., k:k + n] = transform(k, n)
    return out


def summary(corr: dict[int, Correction | None], channels) -> dict:
    """For metadata: the range of the gains and offsets over the frames, per channel, and how many frames were
    corrected and left as they are (the reference frame is in neither)."""
    fitted = [c for c in corr.values() if c is not None]
    if not fitted:
        return {"frames_corrected": 0}
    gains = np.array([c.gain for c in fitted])
    offs = np.array([c.offset for c in fitted])
    return {"frames_corrected": len(fitted), "frames_left": sum(1 for c in corr.values() if c is None),
            "gain_range": {ch: [round(float(gains[:, k].min()), 4), round(float(gains[:, k].max()), 4)]
                           for k, ch in enumerate(channels)},
            "offset_range": {ch: [round(float(offs[:, k].min()), 3), round(float(offs[:, k].max()), 3)]
                             for k, ch in enumerate(channels)}}
