"""How compositing reads frames: any :class:`fieldcal.formats.frames.FrameSource`.

The on-disk ``fieldcal.formats.stack.Stack`` and the in-memory :class:`ArrayStack` (both in
:mod:`fieldcal.formats`) are the sources; compositing uses ``z_um``, ``shape``, ``channels``, ``dtype``,
``black_level``, ``white_level``, ``len()`` and ``read(i, roi)``. :func:`read_roi` is the one place that knows
how a region of a frame is asked for; :class:`RowReader` is the fast path for uncompressed TIFF frames.
"""

from __future__ import annotations

import mmap

import numpy as np

from ..formats.frames import ArrayStack, FrameSource

__all__ = ["ArrayStack", "FrameSource", "RowReader", "image_size", "read_roi", "z_positions"]


def read_roi(stack, i: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels ``[y0:y1, x0:x1]`` of frame ``i`` (file order) as ``h x w x C`` in the file's dtype.

    The region is given to ``stack.read`` as ``roi=(x, y, w, h)`` (the Stack API) so only that part is
    decoded where the file allows it (uncompressed or tiled TIFF).
    """
    a = stack.read(i, roi=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)))
    return a if a.ndim == 3 else a[..., None]


def z_positions(stack) -> np.ndarray:
    """Stage positions (µm) of the frames in file order."""
    return np.asarray(stack.z_um, dtype=np.float64)


def image_size(stack) -> tuple[int, int]:
    """``(W, H)`` of the stack's frames."""
    h, w = stack.shape[:2]
    return int(w), int(h)


class RowReader:
    """Regions of a stack's frames for the streaming accumulator, fast on uncompressed TIFF frames.

    A region is read with ``Stack.read(i, roi)`` (the Stack API) unless the frame is an uncompressed,
    contiguous, native-order integer TIFF (what the simulator and ``StackWriter`` write): then the rows holding
    it are memory-mapped with :mod:`mmap` and only the region is copied out (only its pages are touched), and
    the map is closed at once so the process's resident memory stays small. That skips ``numpy.memmap``'s and
    the Stack API's per-call overhead (~0.6 ms per region; a 4K run reads ~2000 regions). Anything unusual (float frames, which need the NaN check, compressed or planar files, a
    file that changed or vanished) takes the Stack API, which also gives the clear error.
    """

    def __init__(self, stack):
        self.stack = stack
        self._layouts: dict[int, tuple | None] = {}

    def prepare(self, indices) -> None:
        """Probe the frame files once, before threads share the reader."""
        for i in indices:
            self._layouts[int(i)] = self._layout(int(i))

    def _layout(self, i: int):
        frames = getattr(self.stack, "frames", None)  # FrameInfo of an on-disk Stack; an ArrayStack has none
        if frames is None or self.stack.cfa:
            return None
        try:
            from fieldcal.formats.imageio import probe
            hdr = probe(frames[i].path)
        except Exception:  # the Stack API will report it properly
            return None
        h, w = self.stack.shape[:2]
        dt = np.dtype(hdr.file_dtype) if hdr.file_dtype else None
        if (hdr.kind != "tiff" or hdr.mmap_offset is None or hdr.planar or dt is None or dt.kind not in "ui"
                or dt.byteorder not in ("=", "|", "<" if np.little_endian else ">")
                or (hdr.height, hdr.width) != (h, w) or hdr.dtype != np.dtype(self.stack.dtype)):
            return None
        return frames[i].path, int(hdr.mmap_offset), w, int(hdr.n_channels), np.dtype(hdr.dtype)

    def read(self, i: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """Pixels ``[y0:y1, x0:x1]`` of frame ``i`` as ``h x w x C`` in the file's dtype (a new array)."""
        lay = self._layouts.get(int(i))
        if lay is None:
            return read_roi(self.stack, i, x0, y0, x1, y1)
        path, base, width, nch, dtype = lay
        row_bytes = width * nch * dtype.itemsize
        start = base + y0 * row_bytes
        aligned = start - start % mmap.ALLOCATIONGRANULARITY
        length = start - aligned + (y1 - y0) * row_bytes
        try:
            with open(path, "rb") as f:
                mm = mmap.mmap(f.fileno(), length, offset=aligned, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # vanished or truncated: the Stack API raises the clear error
            return read_roi(self.stack, i, x0, y0, x1, y1)
        try:
            rows = np.frombuffer(mm, dtype=dtype, count=(y1 - y0) * width * nch, offset=start - aligned)
            box = rows.reshape(y1 - y0, width, nch)[:, x0:x1].copy()  # touches only the box's pages
            del rows
        finally:
            mm.close()
        return box
