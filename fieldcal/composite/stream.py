"""The streaming accumulator shared by every stack method.

Given a best-focus map ``z_b`` (H x W x C, µm, z_ref geometry) and a kernel that turns ``z_b`` into per-frame
weights (:mod:`.weights`), the output is ``sum_k w_k(z_b) * warp_k(frame_k)``. The image is cut into 64-px
tiles; each tile knows (from its z_b range) which frames can weigh in it. The output is built one band of tile
rows at a time: for each frame that weighs in the band (in z order), only the runs of tiles it contributes to are
read (``Stack.read`` with an ROI: a memory map of an uncompressed TIFF) and warped, and only the channels it
serves there. Bands are independent, so a small thread pool works on several at once (OpenCV and NumPy release
the GIL), and a finished band can be converted to the output dtype at once: no full-size float accumulator is
needed. Peak memory: the output, the z_b map and one band plus its source rows per worker — independent of the
number of frames.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Callable

import numpy as np

from ..optics import FrameGeometry
from ..progress import progress
from .source import RowReader, default_workers, image_size, z_positions
from .warp import frame_maps, source_box, warp_from

DEFAULT_TILE_PX = 64


def _tile_edges(n: int, tile: int) -> np.ndarray:
    return np.append(np.arange(0, n, tile), n)


def tile_support(zb: np.ndarray, kernel, tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per tile and channel, the inclusive range of sorted frame indices with non-zero weight.

    Returns ``(ye, xe, lo, hi)``: tile edges along y and x and ``lo, hi`` of shape (ty, tx, C).
    """
    h, w, c = zb.shape
    ye, xe = _tile_edges(h, tile), _tile_edges(w, tile)
    lo, hi = _supports(kernel, *_block_extremes(zb, ye, xe, tile))
    return ye, xe, lo, hi


def _supports(kernel, zmin: np.ndarray, zmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``kernel.supports`` (vectorised) or, for kernels with only the scalar ``support``, a loop."""
    if hasattr(kernel, "supports"):
        lo, hi = kernel.supports(zmin, zmax)
        return np.asarray(lo, dtype=np.int32), np.asarray(hi, dtype=np.int32)
    lo = np.zeros(zmin.shape, dtype=np.int32)
    hi = np.zeros_like(lo)
    for idx in np.ndindex(*zmin.shape):
        lo[idx], hi[idx] = kernel.support(float(zmin[idx]), float(zmax[idx]))
    return lo, hi


def _block_extremes(zb: np.ndarray, ye: np.ndarray, xe: np.ndarray, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum of ``zb`` over every tile, ``(ty, tx, C)`` each.

    Rows are reduced first as whole image rows (contiguous, vectorised: one pass over the map), then the
    small ``(ty, W, C)`` result along x; ``ufunc.reduceat`` along axis 0 is ~10x slower on a 4K map.
    """
    h = zb.shape[0]
    full = (h // tile) * tile
    mins, maxs = [], []
    if full:
        blocks = zb[:full].reshape(full // tile, tile, *zb.shape[1:])
        mins.append(blocks.min(axis=1))
        maxs.append(blocks.max(axis=1))
    if full < h:
        mins.append(zb[full:].min(axis=0, keepdims=True))
        maxs.append(zb[full:].max(axis=0, keepdims=True))
    rmin, rmax = np.concatenate(mins), np.concatenate(maxs)
    return np.minimum.reduceat(rmin, xe[:-1], axis=1), np.maximum.reduceat(rmax, xe[:-1], axis=1)


def _runs(mask_row: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index runs of True in a 1-D boolean array."""
    d = np.diff(np.concatenate([[0], mask_row.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist()))


class _Job:
    """Everything the band workers share (read-only), so a band is a pure function of its index."""

    def __init__(self, stack, zb, kernel, order, maps, tile):
        self.reader = RowReader(stack)
        self.reader.prepare(order)
        self.stack, self.zb, self.kernel, self.order, self.maps, self.tile = stack, zb, kernel, order, maps, tile
        h, w, _ = zb.shape
        self.ye, self.xe = _tile_edges(h, tile), _tile_edges(w, tile)
        self.zmin, self.zmax = _block_extremes(zb, self.ye, self.xe, tile)  # (ty, tx, C)
        self.lo, self.hi = _supports(kernel, self.zmin, self.zmax)
        self.w, self.h = image_size(stack)

    def band(self, ty: int) -> np.ndarray:
        """Float32 ``sum_k w_k warp_k`` over output rows ``ye[ty]:ye[ty+1]``, full width."""
        y0, y1 = int(self.ye[ty]), int(self.ye[ty + 1])
        lo, hi = self.lo[ty], self.hi[ty]  # (tx, C)
        acc = np.zeros((y1 - y0, self.w, self.zb.shape[2]), dtype=np.float32)
        for k in range(int(lo.min()), int(hi.max()) + 1):
            active = (lo <= k) & (hi >= k)  # (tx, C)
            if not active.any():
                continue
            for fmap in self.maps[k]:
                self._add_frame(acc, k, fmap, active, ty, y0, y1)
        return acc

    def _weights(self, k: int, ty: int, t0: int, t1: int, chans, run_ch, y0: int, y1: int):
        """Weights of frame ``k`` on tiles ``t0:t1`` of band ``ty`` (float32 ``h x w x len(chans)``), or None where
        they are all exactly 1. With a :class:`BlendKernel` they are computed only on the tiles that hold a seam,
        and only for the seam(s) there."""
        kernel = self.kernel
        if not hasattr(kernel, "unit_range"):
            return kernel.weight(k, self.zb[y0:y1, self.xe[t0]:self.xe[t1], run_ch])
        a, b = kernel.unit_range(k)
        below = (self.zmin[ty, t0:t1][:, chans] < a).any(axis=1)  # (tiles,): seam k-1 reaches into the tile
        above = (self.zmax[ty, t0:t1][:, chans] > b).any(axis=1)  # seam k reaches into the tile
        need = below.astype(np.int8) + 2 * above.astype(np.int8)
        if not need.any():
            return None
        x0 = int(self.xe[t0])
        wts = np.ones((y1 - y0, int(self.xe[t1]) - x0, len(chans)), dtype=np.float32)
        edges = np.flatnonzero(np.diff(need)) + 1
        for s0, s1 in zip([0, *edges.tolist()], [*edges.tolist(), len(need)]):
            if need[s0]:
                xa, xb = int(self.xe[t0 + s0]), int(self.xe[t0 + s1])
                wts[:, xa - x0:xb - x0] = kernel.weight(k, self.zb[y0:y1, xa:xb, run_ch],
                                                        below=bool(need[s0] & 1), above=bool(need[s0] & 2))
        return wts

    def _add_frame(self, acc, k, fmap, active, ty, y0, y1) -> None:
        # Runs of active tiles per channel; channels with the same run (G and B usually) are warped together.
        by_run: dict[tuple[int, int], list[int]] = {}
        for c in fmap.channels:
            for run in _runs(active[:, c]):
                by_run.setdefault(run, []).append(c)
        todo = []
        for (t0, t1), chans in sorted(by_run.items()):
            x0, x1 = int(self.xe[t0]), int(self.xe[t1])
            run_ch = slice(chans[0], chans[-1] + 1) if chans == list(range(chans[0], chans[-1] + 1)) else chans
            # weights depend on z_b only (not the channel): one call for all channels of the run
            wts = self._weights(k, ty, t0, t1, chans, run_ch, y0, y1)
            if wts is not None and not wts.any():
                continue
            todo.append((x0, x1, run_ch, wts))
        if not todo:
            return
        # Runs whose source boxes are close share one read (fewer calls); distant ones (the two sides of a ring)
        # are read apart (no pixels read for nothing).
        w, h = self.w, self.h
        boxes = [source_box(fmap.matrix, x0, y0, x1, y1, w, h, fmap.margin_px) for x0, x1, _, _ in todo]
        gap = self.tile
        groups: list[list[int]] = [[0]]
        for j in range(1, len(todo)):
            if boxes[j][0] - max(boxes[i][2] for i in groups[-1]) <= gap:
                groups[-1].append(j)
            else:
                groups.append([j])
        identity = fmap.is_identity
        i = int(self.order[k])
        for g in groups:
            sx0, sy0 = min(boxes[j][0] for j in g), min(boxes[j][1] for j in g)
            sx1, sy1 = max(boxes[j][2] for j in g), max(boxes[j][3] for j in g)
            src = self.reader.read(i, sx0, sy0, sx1, sy1)
            for j in g:
                x0, x1, run_ch, wts = todo[j]
                bx0, by0, bx1, by1 = boxes[j]
                part = src[by0 - sy0:by1 - sy0, bx0 - sx0:bx1 - sx0, run_ch].astype(np.float32)
                warped = part if identity else warp_from(part, bx0, by0, fmap.matrix, x0, y0, x1, y1,
                                                         residual=fmap.residual)
                if wts is None:  # between the seams: the frame is taken as it is
                    acc[:, x0:x1, run_ch] += warped
                else:
                    wts *= warped
                    acc[:, x0:x1, run_ch] += wts


def accumulate(stack, zb: np.ndarray, kernel, profile: FrameGeometry | None = None, *, lateral_colour: bool = False,
               tile: int = DEFAULT_TILE_PX, frames=None, desc: str = "compositing", quiet: bool = False,
               finish: Callable[[np.ndarray], np.ndarray] | None = None, workers: int | None = None) -> np.ndarray:
    """Weighted sum of warped frames, ``H x W x C`` in the stack's raw units.

    Parameters
    ----------
    stack : Stack or ArrayStack
        Frames (file order); only ``frames`` (file indices) are used if given.
    zb : ndarray
        Best-focus map (µm) per pixel and channel in the geometry of ``z_ref``.
    kernel : BlendKernel or SweepKernel
        Built on the z positions of the used frames, sorted.
    profile : lens profile or None
        Geometry source (None: frames are already registered).
    finish : callable, optional
        Applied to each finished float32 band (e.g. rounding to the input's dtype); the result is assembled from
        the finished bands, so no full-size float32 image is ever held. Default: float32 output.
    workers : int, optional
        Threads working on bands at once (default :func:`default_workers`). The result does not depend on it.
    """
    w, h = image_size(stack)
    if zb.shape[:2] != (h, w):
        raise ValueError(f"best-focus map {zb.shape[:2]} does not match frames {(h, w)}")
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    if len(order) != len(kernel):
        raise ValueError("kernel and frame selection disagree")
    channels = tuple(stack.channels)
    # Frame maps up front, in this thread: profiles need not be thread-safe.
    maps = [frame_maps(profile, float(z_all[i]), channels, lateral_colour) for i in order]
    job = _Job(stack, zb, kernel, order, maps, tile)
    ye = job.ye
    n_bands = len(ye) - 1
    workers = default_workers() if workers is None else max(1, int(workers))

    def band(ty: int) -> np.ndarray:
        b = job.band(ty)
        return finish(b) if finish is not None else b

    def fill(ty: int) -> int:
        out[int(ye[ty]):int(ye[ty + 1])] = band(ty)  # bands are disjoint rows: no locking needed
        return ty

    first = band(0)  # its dtype is the output's
    out = np.empty((h, w, len(channels)), dtype=first.dtype)
    out[:int(ye[1])] = first
    del first
    rest = range(1, n_bands)
    if workers == 1 or n_bands < 3:
        for ty in progress(rest, total=len(rest), desc=desc, quiet=quiet, unit="band"):
            fill(ty)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(fill, ty) for ty in rest]
            try:
                for f in progress(as_completed(futures), total=len(rest), desc=desc, quiet=quiet, unit="band"):
                    f.result()  # re-raises a worker's error here
            except BaseException:
                for f in futures:  # a bad frame or Ctrl-C: stop at once, not after every band
                    f.cancel()
                raise
    return out
