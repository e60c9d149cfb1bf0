"""Channel planes of a frame: demosaiced channels as they are, raw Bayer mosaics as each colour's own sub-lattice.

A plane is a 2-D float32 view of one colour plus the affine map from its pixel grid to the full frame's
(``x_full = stride * x_plane + offset_x``), so measurements on a plane can be reported in frame pixels.
Nothing is interpolated: demosaicing would mix colours and blur exactly what focus measures look at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclass(frozen=True)
class PlaneLayout:
    """Where the pixels of one plane sit in the full frame."""

    name: str  # colour channel the plane belongs to ("G" appears twice for a Bayer mosaic)
    channel_index: int  # index into the stack's channel tuple
    stride: int  # 1 for demosaiced channels, 2 for a Bayer sub-lattice
    offset_x: int
    offset_y: int

    def to_full(self, x_plane, y_plane):
        """Plane pixel coordinates -> full-frame pixel coordinates."""
        return (self.stride * np.asarray(x_plane, dtype=np.float64) + self.offset_x,
                self.stride * np.asarray(y_plane, dtype=np.float64) + self.offset_y)

    def to_plane(self, x_full, y_full):
        """Full-frame pixel coordinates -> plane pixel coordinates (fractional)."""
        return ((np.asarray(x_full, dtype=np.float64) - self.offset_x) / self.stride,
                (np.asarray(y_full, dtype=np.float64) - self.offset_y) / self.stride)


def plane_layouts(channels: tuple[str, ...], cfa: str | None) -> list[PlaneLayout]:
    """The planes to measure for a stack's channels and CFA pattern (both G sites of a mosaic are kept)."""
    channels = tuple(channels)
    if cfa is None:
        return [PlaneLayout(c, i, 1, 0, 0) for i, c in enumerate(channels)]
    if cfa not in CFA_PATTERNS:
        raise ParameterError(f"unknown CFA pattern {cfa!r}", field="cfa", fix=f"use one of {', '.join(CFA_PATTERNS)}")
    out = []
    for k, colour in enumerate(cfa):
        if colour not in channels:
            raise ParameterError(f"CFA {cfa} has colour {colour} but the stack's channels are {channels}",
                                 field="channels", fix="list R, G and B as the channels of a Bayer stack")
        r, c = divmod(k, 2)
        out.append(PlaneLayout(colour, channels.index(colour), 2, c, r))
    return out


def extract_plane(frame: np.ndarray, layout: PlaneLayout) -> np.ndarray:
    """The float32 plane of ``layout`` from a normalised frame (H x W x C, or H x W for a mosaic)."""
    if layout.stride == 1:
        a = frame[:, :, layout.channel_index] if frame.ndim == 3 else frame
    else:
        a = frame[:, :, 0] if frame.ndim == 3 else frame
        a = a[layout.offset_y::2, layout.offset_x::2]
    return np.ascontiguousarray(a, dtype=np.float32)


def plane_shape(frame_shape: tuple[int, int], layout: PlaneLayout) -> tuple[int, int]:
    """(H, W) of a plane of a frame of size ``frame_shape`` (H, W)."""
    h, w = frame_shape
    if layout.stride == 1:
        return h, w
    return (h - layout.offset_y + 1) // 2, (w - layout.offset_x + 1) // 2
