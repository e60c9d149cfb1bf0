"""Undo focus breathing and stage-axis shift: map each frame (and channel) into the geometry of ``z_ref``.

docs/architecture.md: a point at pixel ``p`` of the frame at ``z_ref`` appears at ``c + m(z) (p - c) + s(z)`` in the frame
at ``z`` (``c`` the optical centre). With lateral-colour correction the channel's constant scale ``L_c`` about
``c`` is undone too, so every channel lands in the reference channel's geometry. The map from output pixel to
source pixel is affine, so a frame region is warped with one ``cv2.warpAffine`` call.

Profiles with dense geometry maps (``profile.has_geometry_map``: distortion that changes with z, docs/geometry.md)
add a non-affine part: the map ``profile.warp_px`` is split into its best scale-and-shift and a smooth residual
sampled on a coarse grid (:class:`ResidualGrid`), and such frames are warped with ``cv2.remap``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..optics import FrameGeometry
from .source import read_roi

if TYPE_CHECKING:
    from scipy import sparse

# Extra source pixels around a mapped region: the bicubic kernel reaches 2 px, plus rounding.
_MARGIN_PX = 3
_IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# Node spacing of a map's residual grid (px): distortion varies over hundreds of pixels, bicubic between nodes
# reproduces it to ~1e-3 px.
_RESIDUAL_STEP_PX = 16


@dataclass(frozen=True)
class ResidualGrid:
    """The non-affine part of a frame map, ``q - (A p + b)``, at nodes every ``step_px`` px (from pixel 0)."""

    step_px: int
    dx: np.ndarray
    dy: np.ndarray

    @cached_property
    def max_px(self) -> float:
        return float(max(np.max(np.abs(self.dx)), np.max(np.abs(self.dy))))

    def at(self, x, y):
        """Residual (dx, dy) at pixel positions (cubic-spline interpolation between nodes)."""
        from scipy import ndimage
        c = [np.asarray(y, dtype=np.float64) / self.step_px, np.asarray(x, dtype=np.float64) / self.step_px]
        return (ndimage.map_coordinates(self.dx, c, order=3, mode="nearest"),
                ndimage.map_coordinates(self.dy, c, order=3, mode="nearest"))


@dataclass(frozen=True)
class FrameMap:
    """Map output pixel (z_ref geometry) -> source pixel (frame at z) for a group of channels.

    ``matrix`` is the 2x3 ``[A | b]`` with ``q = A p + b``; ``channels`` are indices into the last image axis;
    ``residual`` the non-affine part of a dense geometry map (None: the map is affine).
    """

    matrix: np.ndarray
    channels: tuple[int, ...]
    residual: ResidualGrid | None = None

    @cached_property
    def is_identity(self) -> bool:
        return self.residual is None and _is_identity(self.matrix)

    @property
    def margin_px(self) -> int:
        """Source pixels to read around the affine footprint of an output box."""
        return _MARGIN_PX + (0 if self.residual is None else int(math.ceil(self.residual.max_px)))


def _is_identity(matrix: np.ndarray) -> bool:
    """Within 1e-6 of the identity (1e-6 px over a 10k px frame: far below interpolation error)."""
    return bool(np.max(np.abs(np.asarray(matrix, dtype=np.float64) - _IDENTITY)) <= 1e-6)


def affine_for(scale: float, centre_px: tuple[float, float], shift_px: tuple[float, float]) -> np.ndarray:
    """2x3 matrix of ``q = c + scale (p - c) + shift``."""
    cx, cy = centre_px
    dx, dy = shift_px
    return np.array([[scale, 0.0, cx * (1.0 - scale) + dx],
                     [0.0, scale, cy * (1.0 - scale) + dy]], dtype=np.float64)


def frame_maps(profile: FrameGeometry, z_um: float, channels, lateral_colour: bool = False) -> list[FrameMap]:
    """Maps of one frame, one per group of channels that share a transform (usually a single group).

    Parameters
    ----------
    profile : lens profile (docs/architecture.md) or None
        ``None`` means no geometry correction (identity).
    z_um : float
        Stage position of the frame.
    channels : sequence of str
        Channel names in image order.
    lateral_colour : bool
        Also undo the per-channel scale ``profile.lateral_colour_scale(ch)``.
    """
    if profile is None:
        return [FrameMap(affine_for(1.0, (0.0, 0.0), (0.0, 0.0)), tuple(range(len(channels))))]
    if getattr(profile, "has_geometry_map", False):
        return [dense_frame_map(profile, z_um, ch, ci, lateral_colour) for ci, ch in enumerate(channels)]
    centre = tuple(float(v) for v in profile.optical_centre_px())
    groups: list[FrameMap] = []
    for ci, ch in enumerate(channels):
        m = float(np.asarray(profile.magnification(z_um, ch)))
        if lateral_colour:
            m *= float(profile.lateral_colour_scale(ch))
        dx, dy = profile.shift_px(z_um, ch)
        mat = affine_for(m, centre, (float(np.asarray(dx)), float(np.asarray(dy))))
        for k, g in enumerate(groups):
            if np.array_equal(g.matrix, mat):
                groups[k] = FrameMap(g.matrix, g.channels + (ci,))
                break
        else:
            groups.append(FrameMap(mat, (ci,)))
    return groups


def dense_frame_map(profile, z_um: float, channel: str, ci: int, lateral_colour: bool) -> FrameMap:
    """One channel's map from ``profile.warp_px``: its least-squares scale and shift, plus the residual grid."""
    w, h = (int(v) for v in profile.image_size_px)
    gx, gy = np.meshgrid(np.arange(0, w - 1 + _RESIDUAL_STEP_PX, _RESIDUAL_STEP_PX, dtype=np.float64),
                         np.arange(0, h - 1 + _RESIDUAL_STEP_PX, _RESIDUAL_STEP_PX, dtype=np.float64))
    qx, qy = profile.warp_px(gx, gy, float(z_um), channel, lateral_colour=lateral_colour)
    # q = a p + t in the least-squares sense (about the frame centre: a well-conditioned 3-parameter fit)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    u, v = (gx - cx).ravel(), (gy - cy).ravel()
    A = np.concatenate([np.column_stack([u, np.ones_like(u), np.zeros_like(u)]),
                        np.column_stack([v, np.zeros_like(v), np.ones_like(v)])])
    b = np.concatenate([(qx - cx).ravel(), (qy - cy).ravel()])
    a, tx, ty = np.linalg.lstsq(A, b, rcond=None)[0]
    mat = affine_for(float(a), (cx, cy), (float(tx), float(ty)))
    res = ResidualGrid(_RESIDUAL_STEP_PX, qx - (mat[0, 0] * gx + mat[0, 2]), qy - (mat[1, 1] * gy + mat[1, 2]))
    return FrameMap(mat, (ci,), res if res.max_px > 1e-3 else None)


def source_box(matrix: np.ndarray, x0: int, y0: int, x1: int, y1: int, width: int, height: int,
               margin: int = _MARGIN_PX) -> tuple[int, int, int, int]:
    """Bounding box (half-open, clipped to the frame) of the source pixels an output box needs.

    The identity map (within 1e-6, as :attr:`FrameMap.is_identity`) needs exactly the box itself. Plain float
    arithmetic: this runs for every run of tiles of every frame.
    """
    (a, b, c), (d, e, f) = (float(v) for v in matrix[0]), (float(v) for v in matrix[1])
    if margin <= _MARGIN_PX and max(abs(a - 1.0), abs(b), abs(c), abs(d), abs(e - 1.0), abs(f)) <= 1e-6:
        return int(x0), int(y0), int(x1), int(y1)
    xa, xb, ya, yb = float(x0), float(x1 - 1), float(y0), float(y1 - 1)
    qx = [a * x + b * y + c for x, y in ((xa, ya), (xb, ya), (xa, yb), (xb, yb))]
    qy = [d * x + e * y + f for x, y in ((xa, ya), (xb, ya), (xa, yb), (xb, yb))]
    sx0 = min(max(math.floor(min(qx)) - margin, 0), width - 1)
    sy0 = min(max(math.floor(min(qy)) - margin, 0), height - 1)
    sx1 = min(max(math.ceil(max(qx)) + margin + 1, sx0 + 1), width)
    sy1 = min(max(math.ceil(max(qy)) + margin + 1, sy0 + 1), height)
    return int(sx0), int(sy0), int(sx1), int(sy1)


def _keys(x: np.ndarray) -> np.ndarray:
    """Keys (1981) cubic convolution kernel, a = -0.5 (reproduces quadratics: no centroid bias)."""
    x = np.abs(x)
    near = (1.5 * x - 2.5) * x * x + 1.0
    far = ((-0.5 * x + 2.5) * x - 4.0) * x + 2.0
    return np.where(x <= 1.0, near, np.where(x < 2.0, far, 0.0))


def axis_matrix(n_out: int, positions: np.ndarray, n_src: int) -> sparse.csr_matrix:
    """Sparse (n_out x n_src) matrix sampling a 1-D signal at ``positions`` (source px) with Keys' cubic;
    samples beyond the source repeat its edge pixels."""
    base = np.floor(positions).astype(np.int64)
    k = np.arange(-1, 3)
    idx = base[:, None] + k[None, :]
    w = _keys(positions[:, None] - idx)
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(n_out), k.size)
    from scipy import sparse  # here: importing it costs ~0.2 s on every run that never needs it

    m = sparse.coo_matrix((w.ravel().astype(np.float32), (rows, np.clip(idx, 0, n_src - 1).ravel())),
                          shape=(n_out, n_src))
    return m.tocsr()


def warp_region(stack, i: int, fmap: FrameMap, x0: int, y0: int, x1: int, y1: int,
                interpolation: str = "cv2") -> np.ndarray:
    """Output pixels ``[y0:y1, x0:x1]`` (z_ref geometry) of frame ``i``, channels ``fmap.channels``, float32.

    Only the source region the output box maps to is read (``stack.read(i, roi=...)``) and warped.
    Outside the frame the nearest edge pixel is repeated. ``interpolation``: ``"cv2"`` (default:
    ``cv2.warpAffine`` bicubic, a = -0.75, positions quantised to 1/32 px; fastest, and its slight
    high-frequency boost offsets the low-pass of the capture-side resampling: +0.6 dB against the simulator's
    truth) or ``"keys"`` (exact positions, separable Keys cubic a = -0.5, the simulator's own kernel; the
    better inverse in a round trip, ~1.5x slower).
    """
    h, w = stack.shape[:2]
    if fmap.is_identity:
        a = read_roi(stack, i, x0, y0, x1, y1)
        chans = list(fmap.channels)
        if chans != list(range(a.shape[2])):
            return a[..., chans].astype(np.float32, copy=False)  # the selection is already a copy
        # one copy at most: a source that hands out new float32 arrays (held fixed-point frames) needs none;
        # any other may return its own pixels, which the caller must not get to modify
        fresh = getattr(stack, "reads_new_float32", False) and a.dtype == np.float32
        return a if fresh else a.astype(np.float32)
    sx0, sy0, sx1, sy1 = source_box(fmap.matrix, x0, y0, x1, y1, w, h, fmap.margin_px)
    src = read_roi(stack, i, sx0, sy0, sx1, sy1)[..., list(fmap.channels)].astype(np.float32)
    return warp_from(src, sx0, sy0, fmap.matrix, x0, y0, x1, y1, interpolation, fmap.residual)


def warp_frame_by_profile(stack, i: int, profile, width: int, height: int) -> np.ndarray:
    """Frame ``i`` of ``stack`` whole, every channel, in the z_ref geometry of ``profile``: (height, width, C)
    float32 (:func:`frame_maps` and :func:`warp_region`; a stack as registration by the profile leaves it)."""
    out = np.zeros((height, width, len(stack.channels)), np.float32)
    for fm in frame_maps(profile, float(stack.z_um[i]), stack.channels):
        out[..., list(fm.channels)] = warp_region(stack, i, fm, 0, 0, width, height)
    return out


def warp_from(src: np.ndarray, sx0: int, sy0: int, matrix: np.ndarray, x0: int, y0: int, x1: int, y1: int,
              interpolation: str = "cv2", residual: ResidualGrid | None = None) -> np.ndarray:
    """Warp output box ``[y0:y1, x0:x1]`` from ``src``, a region of the frame whose top-left pixel is
    ``(sx0, sy0)`` and which covers :func:`source_box` of the box, ``h x w x C``: float32, or the input's
    dtype for uint8/uint16 with cv2 (rounded to whole DN, clipped to the dtype's range). ``residual``: the
    non-affine part of a dense map (bicubic ``cv2.remap``, like the affine path's kernel)."""
    m = matrix
    nch = src.shape[2]
    ow, oh = x1 - x0, y1 - y0
    if residual is not None:
        if src.dtype not in (np.uint8, np.uint16, np.float32):
            src = src.astype(np.float32)
        px, py = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
        rx, ry = residual.at(px, py)
        mapx = (m[0, 0] * px + m[0, 1] * py + m[0, 2] + rx - sx0).astype(np.float32)
        mapy = (m[1, 0] * px + m[1, 1] * py + m[1, 2] + ry - sy0).astype(np.float32)
        out = np.empty((oh, ow, nch), dtype=src.dtype)
        for k in range(0, nch, 4):
            part = np.ascontiguousarray(src[..., k:k + 4])
            res = cv2.remap(part, mapx, mapy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            out[..., k:k + 4] = res.reshape(oh, ow, -1)
        return out
    keys = interpolation == "keys" and m[0, 1] == 0.0 and m[1, 0] == 0.0
    if keys or src.dtype not in (np.uint8, np.uint16, np.float32):
        src = src.astype(np.float32)
    out = np.empty((oh, ow, nch), dtype=src.dtype)
    if keys:
        mx = axis_matrix(ow, m[0, 0] * np.arange(x0, x1) + m[0, 2] - sx0, src.shape[1])
        my = axis_matrix(oh, m[1, 1] * np.arange(y0, y1) + m[1, 2] - sy0, src.shape[0])
        for j in range(nch):
            tmp = my @ src[..., j]                  # oh x sw
            out[..., j] = (mx @ tmp.T).T            # oh x ow
        return out
    mm = m.copy()
    # Output-local p' = p - (x0, y0), source-local q' = q - (sx0, sy0).
    mm[:, 2] = m[:, 2] + m[:, :2] @ np.array([x0, y0], dtype=np.float64) - np.array([sx0, sy0], dtype=np.float64)
    # cv2 handles at most 4 channels per call and drops a single channel's axis.
    for k in range(0, nch, 4):
        part = np.ascontiguousarray(src[..., k:k + 4])
        res = cv2.warpAffine(part, mm, (ow, oh), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        out[..., k:k + 4] = res.reshape(oh, ow, -1)
    return out
