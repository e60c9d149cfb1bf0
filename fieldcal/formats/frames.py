"""What every stage reads frames through: the :class:`FrameSource` protocol and its in-memory :class:`ArrayStack`.

:class:`fieldcal.formats.stack.Stack` (a ``fieldcal-stack/1`` folder, frames decoded lazily) is the on-disk
source; :class:`ArrayStack` gives the same reading interface to frames already in memory or rendered on demand
(tests, benchmarks, a capture preview, the Python API), so measurement and compositing never depend on files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Protocol, Sequence, runtime_checkable

import numpy as np

from ..errors import ParameterError
from .stack import _norm_roi


@runtime_checkable
class FrameSource(Protocol):
    """The read-only part of the ``fieldcal-stack/1`` reader that measurement and compositing use.

    Attributes
    ----------
    z_um : (n,) float64 array
        Stage position of each frame (µm), file order, distinct.
    shape : (H, W)
        Frame size in pixels.
    channels : tuple of str
        Channel names, in the order of the last axis (``H x W x C`` frames), or of the CFA's colours.
    cfa : str or None
        Bayer pattern of a raw mosaic (frames are then ``H x W``), None otherwise.
    dtype : numpy.dtype
        The frames' sample type.
    black_level, white_level : float
        Raw levels of black and of saturation (``read_normalized`` maps them to 0 and 1).
    pixel_pitch_um : float or None
        Sensor pixel pitch (µm); None when unknown (an in-memory stack made only for compositing).
    path : Path or None
        Where the frames come from (the stack folder), for messages; None for frames made in memory.
    """

    z_um: np.ndarray
    shape: tuple[int, int]
    channels: tuple[str, ...]
    cfa: str | None
    dtype: np.dtype
    black_level: float
    white_level: float
    pixel_pitch_um: float | None
    path: Path | None

    def __len__(self) -> int: ...

    @property
    def order_by_z(self) -> np.ndarray: ...

    def read(self, i: int, roi=None) -> np.ndarray: ...

    def read_normalized(self, i: int, roi=None) -> np.ndarray: ...

    def require_frames(self, n: int, operation: str) -> None: ...


def _default_white(dtype: np.dtype) -> float:
    return float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else 1.0


class ArrayStack:
    """A :class:`FrameSource` over frames in memory, or produced lazily by ``frames(i)``.

    Parameters
    ----------
    frames : sequence of ndarray, or callable ``i -> ndarray``
        ``H x W x C`` frames (``H x W`` is one channel, or a raw mosaic when ``cfa`` is given), one size and
        dtype. A callable renders frame ``i`` on demand (then ``len(z_um)`` frames; checked as they are read).
    z_um : sequence of float
        Stage position of each frame (µm), finite and distinct, any order.
    channels : sequence of str
        Channel names in the order of the last axis (the colours of the mosaic with ``cfa``).
    pixel_pitch_um : float, optional
        Sensor pixel pitch (µm); measurement needs it, compositing does not.
    cfa : str, optional
        Bayer pattern (``RGGB`` ...) of ``H x W`` mosaic frames.
    black_level : float, optional
        Raw black level (default 0).
    white_level : float, optional
        Raw saturation level (default from the dtype: uint8 255, uint16 65535, float 1.0).
    path : str or Path, optional
        Where the frames came from, for messages.

    Examples
    --------
    >>> import numpy as np
    >>> s = ArrayStack([np.zeros((4, 6), np.uint8)] * 2, [0.0, 10.0], ["Y"])
    >>> len(s), s.shape, s.read(1).shape, s.white_level
    (2, (4, 6), (4, 6, 1), 255.0)
    """

    def __init__(self, frames: Sequence[np.ndarray] | Callable[[int], np.ndarray], z_um: Sequence[float],
                 channels: Sequence[str], *, pixel_pitch_um: float | None = None, cfa: str | None = None,
                 black_level: float = 0.0, white_level: float | None = None, path: str | Path | None = None):
        self.channels = tuple(channels)
        self.cfa = cfa
        self.path = None if path is None else Path(path)
        z = np.asarray(z_um, dtype=np.float64)
        if z.ndim != 1 or z.size == 0:
            raise ParameterError("z positions must be a non-empty 1-D list", field="z_um",
                                 fix="give one stage position (µm) per frame")
        if np.unique(z).size != z.size or not np.all(np.isfinite(z)):
            raise ParameterError("z positions must be finite and distinct", field="z_um",
                                 fix="remove duplicate frames")
        self.z_um = z
        self._lazy = callable(frames)
        if self._lazy:
            self._frames = frames
            first = self._shape_frame(np.asarray(frames(0)))
            self._check_finite(first, 0)
        else:
            arrays = [self._shape_frame(np.asarray(a)) for a in frames]
            if not arrays:
                raise ParameterError("no frames given", field="frames", fix="pass at least one frame")
            if len(arrays) != z.size:
                raise ParameterError(f"{len(arrays)} frames but {z.size} z positions", field="z_um",
                                     fix="give one z_um per frame")
            shapes = {a.shape for a in arrays}
            dtypes = {a.dtype for a in arrays}
            if len(shapes) != 1 or len(dtypes) != 1:
                raise ParameterError(f"frames differ in shape {shapes} or dtype {dtypes}", field="frames",
                                     fix="give frames of one size and dtype")
            for k, a in enumerate(arrays):
                self._check_finite(a, k)
            self._frames = arrays
            first = arrays[0]
        if cfa is None and first.shape[2] != len(self.channels):
            raise ParameterError(f"frames have {first.shape[2]} channels but {len(self.channels)} names",
                                 field="channels", fix="name every channel")
        self.dtype = first.dtype
        self.shape = (int(first.shape[0]), int(first.shape[1]))
        self.pixel_pitch_um = None if pixel_pitch_um is None else float(pixel_pitch_um)
        self.black_level = float(black_level)
        self.white_level = _default_white(self.dtype) if white_level is None else float(white_level)
        if not self.white_level > self.black_level:
            raise ParameterError(f"white level {self.white_level:g} is not above black level {self.black_level:g}",
                                 field="white_level", fix="give the sensor's saturation and black levels")
        self.meta: dict = {}

    def _shape_frame(self, a: np.ndarray) -> np.ndarray:
        """``H x W x C`` (``H x W`` for a mosaic), as the on-disk reader returns it."""
        if self.cfa is None and a.ndim == 2:
            return a[:, :, None]
        if self.cfa is not None and a.ndim == 3 and a.shape[2] == 1:
            return a[:, :, 0]
        return a

    @staticmethod
    def _check_finite(a: np.ndarray, i: int) -> None:
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ParameterError(f"frame {i} has NaN or Inf pixels", field="frames",
                                 fix="repair or drop those frames (a file stack refuses them the same way)")

    def __len__(self) -> int:
        return int(self.z_um.size)

    def __repr__(self) -> str:
        return (f"ArrayStack({len(self)} frames, {self.shape[1]}x{self.shape[0]} px, {self.dtype}, "
                f"channels={list(self.channels)}{', cfa=' + self.cfa if self.cfa else ''})")

    @property
    def order_by_z(self) -> np.ndarray:
        """Frame indices sorted by increasing z."""
        return np.argsort(self.z_um, kind="stable")

    def read(self, i: int, roi=None) -> np.ndarray:
        """Frame ``i`` (file order), or a region ``(x, y, w, h)`` / ``(slice_y, slice_x)`` of it, as stored."""
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -len(self) <= i < len(self):
            raise ParameterError(f"frame index {i!r} is outside 0..{len(self) - 1}", field="index",
                                 fix=f"use an index from 0 to {len(self) - 1}")
        if self._lazy:
            a = self._shape_frame(np.asarray(self._frames(int(i))))
            if a.shape[:2] != self.shape or a.dtype != self.dtype:
                raise ParameterError(f"frame {i} is {a.shape} {a.dtype}, the first {self.shape} {self.dtype}",
                                     field="frames", fix="render every frame at one size and dtype")
            self._check_finite(a, int(i))
        else:
            a = self._frames[int(i)]
        box = _norm_roi(roi, *self.shape, self.cfa)
        if box is None:
            return a
        y0, y1, x0, x1 = box
        return a[y0:y1, x0:x1]

    def read_normalized(self, i: int, roi=None) -> np.ndarray:
        """Frame ``i`` as float32 ``(raw - black_level) / (white_level - black_level)`` (not clipped)."""
        a = self.read(i, roi).astype(np.float32)
        a -= np.float32(self.black_level)
        a *= np.float32(1.0 / (self.white_level - self.black_level))
        return a

    def require_frames(self, n: int, operation: str) -> None:
        """Raise ParameterError if there are fewer than ``n`` frames for ``operation``."""
        if len(self) < n:
            raise ParameterError(f"too few frames for {operation}: it needs at least {n}, got {len(self)}",
                                 field="frames", fix=f"give at least {n} frames")
