"""Undo focus breathing and stage-axis shift: map each frame (and channel) into the geometry of ``z_ref``.

DESIGN.md: a point at pixel ``p`` of the frame at ``z_ref`` appears at ``c + m(z) (p - c) + s(z)`` in the frame
at ``z`` (``c`` the optical centre). With lateral-colour correction the channel's constant scale ``L_c`` about
``c`` is undone too, so every channel lands in the reference channel's geometry. The map from output pixel to
source pixel is affine, so a frame region is warped with one ``cv2.warpAffine`` call.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .source import read_roi

# Extra source pixels around a mapped region: the bicubic kernel reaches 2 px, plus rounding.
_MARGIN_PX = 3


@dataclass(frozen=True)
class FrameMap:
    """Affine map output pixel (z_ref geometry) -> source pixel (frame at z) for a group of channels.

    ``matrix`` is the 2x3 ``[A | b]`` with ``q = A p + b``; ``channels`` are indices into the last image axis.
    """

    matrix: np.ndarray
    channels: tuple[int, ...]

    @property
    def is_identity(self) -> bool:
        return bool(np.allclose(self.matrix, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], rtol=0.0, atol=1e-6))


def affine_for(scale: float, centre_px: tuple[float, float], shift_px: tuple[float, float]) -> np.ndarray:
    """2x3 matrix of ``q = c + scale (p - c) + shift``."""
    cx, cy = centre_px
    dx, dy = shift_px
    return np.array([[scale, 0.0, cx * (1.0 - scale) + dx],
                     [0.0, scale, cy * (1.0 - scale) + dy]], dtype=np.float64)


def frame_maps(profile, z_um: float, channels, lateral_colour: bool = False) -> list[FrameMap]:
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


def source_box(matrix: np.ndarray, x0: int, y0: int, x1: int, y1: int, width: int, height: int,
               margin: int = _MARGIN_PX) -> tuple[int, int, int, int]:
    """Bounding box (half-open, clipped to the frame) of the source pixels an output box needs."""
    xs = np.array([x0, x1 - 1, x0, x1 - 1], dtype=np.float64)
    ys = np.array([y0, y0, y1 - 1, y1 - 1], dtype=np.float64)
    qx = matrix[0, 0] * xs + matrix[0, 1] * ys + matrix[0, 2]
    qy = matrix[1, 0] * xs + matrix[1, 1] * ys + matrix[1, 2]
    sx0 = int(np.clip(np.floor(qx.min()) - margin, 0, width - 1))
    sy0 = int(np.clip(np.floor(qy.min()) - margin, 0, height - 1))
    sx1 = int(np.clip(np.ceil(qx.max()) + margin + 1, sx0 + 1, width))
    sy1 = int(np.clip(np.ceil(qy.max()) + margin + 1, sy0 + 1, height))
    return sx0, sy0, sx1, sy1


def warp_region(stack, i: int, fmap: FrameMap, x0: int, y0: int, x1: int, y1: int,
                interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
    """Output pixels ``[y0:y1, x0:x1]`` (z_ref geometry) of frame ``i``, channels ``fmap.channels``, float32.

    Only the source region the output box maps to is read (``stack.read(i, roi=...)``) and warped.
    Outside the frame the nearest edge pixel is repeated.
    """
    h, w = stack.shape[:2]
    ch = list(fmap.channels)
    if fmap.is_identity:
        return read_roi(stack, i, x0, y0, x1, y1)[..., ch].astype(np.float32)
    sx0, sy0, sx1, sy1 = source_box(fmap.matrix, x0, y0, x1, y1, w, h)
    src = read_roi(stack, i, sx0, sy0, sx1, sy1)[..., ch].astype(np.float32)
    m = fmap.matrix.copy()
    # Output-local p' = p - (x0, y0), source-local q' = q - (sx0, sy0).
    m[:, 2] = m[:, 2] + m[:, :2] @ np.array([x0, y0], dtype=np.float64) - np.array([sx0, sy0], dtype=np.float64)
    out = np.empty((y1 - y0, x1 - x0, len(ch)), dtype=np.float32)
    # cv2 handles at most 4 channels per call and drops a single channel's axis.
    for k in range(0, len(ch), 4):
        part = np.ascontiguousarray(src[..., k:k + 4])
        res = cv2.warpAffine(part, m, (x1 - x0, y1 - y0), flags=interpolation | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        out[..., k:k + 4] = res.reshape(y1 - y0, x1 - x0, -1)
    return out
