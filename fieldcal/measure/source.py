"""What measurement reads: anything with the ``fieldcal.formats.stack.Stack`` reading interface.

:class:`ArrayStack` gives that interface to frames already in memory or rendered on demand (tests,
benchmarks, a capture preview), so measurement code never depends on files.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..errors import ParameterError


class ArrayStack:
    """A stack-like object over frames in memory or produced lazily by ``frame_fn(i)``.

    Parameters
    ----------
    z_um : sequence of float
        Stage position of each frame (µm), distinct.
    frames : sequence of arrays, or callable i -> array
        Raw frames (H x W x C, or H x W for a mosaic) in the dtype of the levels below.
    pixel_pitch_um, channels, cfa : as in ``fieldcal-stack/1``.
    black_level, white_level : raw levels for normalisation.
    """

    def __init__(self, z_um: Sequence[float], frames: Sequence[np.ndarray] | Callable[[int], np.ndarray], *,
                 pixel_pitch_um: float, channels: Sequence[str], cfa: str | None = None,
                 black_level: float = 0.0, white_level: float = 1.0, shape: tuple[int, int] | None = None):
        self.z_um = np.asarray(z_um, dtype=np.float64)
        if self.z_um.ndim != 1 or np.unique(self.z_um).size != self.z_um.size:
            raise ParameterError("z values must be a 1-D list of distinct positions", field="z_um",
                                 fix="give one distinct stage position per frame")
        self._frames = frames
        self.pixel_pitch_um = float(pixel_pitch_um)
        self.channels = tuple(channels)
        self.cfa = cfa
        self.black_level = float(black_level)
        self.white_level = float(white_level)
        if shape is None:
            shape = tuple(self.read(0).shape[:2])
        self.shape = (int(shape[0]), int(shape[1]))
        self.meta: dict = {}

    def __len__(self) -> int:
        return int(self.z_um.size)

    @property
    def order_by_z(self) -> np.ndarray:
        return np.argsort(self.z_um, kind="stable")

    def read(self, i: int, roi=None) -> np.ndarray:
        a = self._frames(i) if callable(self._frames) else self._frames[i]
        a = np.asarray(a)
        if self.cfa is None and a.ndim == 2:
            a = a[:, :, None]
        return a

    def read_normalized(self, i: int, roi=None) -> np.ndarray:
        a = self.read(i).astype(np.float32)
        a -= np.float32(self.black_level)
        a *= np.float32(1.0 / (self.white_level - self.black_level))
        return a

    def require_frames(self, n: int, operation: str) -> None:
        if len(self) < n:
            raise ParameterError(f"too few frames for {operation}: it needs at least {n}, got {len(self)}",
                                 field="frames", fix=f"give at least {n} frames")
