"""The streaming accumulator shared by every stack method.

Given a best-focus map ``z_b`` (H x W x C, µm, z_ref geometry) and a kernel that turns ``z_b`` into per-frame
weights (:mod:`.weights`), the output is ``sum_k w_k(z_b) * warp_k(frame_k)``. Frames are visited one at a
time in z order; the image is cut into tiles, each tile knows (from its z_b range) which frames can weigh in
it, and a frame reads and warps only the runs of tiles it contributes to. Peak memory: the accumulator, the
z_b map and one frame region — independent of the number of frames.
"""

from __future__ import annotations

import numpy as np

from ..progress import progress
from .source import image_size, z_positions
from .source import read_roi
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
    lo = np.zeros((len(ye) - 1, len(xe) - 1, c), dtype=np.int32)
    hi = np.zeros_like(lo)
    for ty in range(len(ye) - 1):
        band = zb[ye[ty]:ye[ty + 1]]
        for tx in range(len(xe) - 1):
            blk = band[:, xe[tx]:xe[tx + 1]].reshape(-1, c)
            for ci in range(c):
                lo[ty, tx, ci], hi[ty, tx, ci] = kernel.support(float(blk[:, ci].min()), float(blk[:, ci].max()))
    return ye, xe, lo, hi


def _runs(mask_row: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index runs of True in a 1-D boolean array."""
    d = np.diff(np.concatenate([[0], mask_row.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist()))


def accumulate(stack, zb: np.ndarray, kernel, profile=None, *, lateral_colour: bool = False,
               tile: int = DEFAULT_TILE_PX, frames=None, desc: str = "compositing",
               quiet: bool = False) -> np.ndarray:
    """Weighted sum of warped frames, float32 ``H x W x C`` in the stack's raw units.

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
    ye, xe, lo, hi = tile_support(zb, kernel, tile)
    acc = np.zeros((h, w, len(channels)), dtype=np.float32)
    for k, i in enumerate(progress(order, total=len(order), desc=desc, quiet=quiet, unit="frame")):
        active = (lo <= k) & (hi >= k)  # (ty, tx, C)
        if not active.any():
            continue
        for fmap in frame_maps(profile, float(z_all[i]), channels, lateral_colour):
            ch = list(fmap.channels)
            identity = fmap.is_identity
            act = active[..., ch].any(axis=-1)
            for ty in range(act.shape[0]):
                runs = _runs(act[ty])
                if not runs:
                    continue
                y0, y1 = int(ye[ty]), int(ye[ty + 1])
                todo = []
                for t0, t1 in runs:
                    x0, x1 = int(xe[t0]), int(xe[t1])
                    # only the channels this frame serves in this run are warped
                    run_ch = [c for c in ch if active[ty, t0:t1, c].any()]
                    if run_ch == list(range(run_ch[0], run_ch[-1] + 1)):
                        run_ch = slice(run_ch[0], run_ch[-1] + 1)  # basic slicing: views, no fancy copies
                        chans = range(run_ch.start, run_ch.stop)
                    else:
                        chans = run_ch
                    wts = np.stack([kernel.weight(k, zb[y0:y1, x0:x1, c]) for c in chans], axis=-1)
                    if wts.any():
                        todo.append((x0, x1, run_ch, wts))
                if not todo:
                    continue
                # Runs whose source boxes are close share one read (fewer calls); distant ones (the two sides
                # of a ring) are read apart (no pixels read for nothing).
                boxes = [source_box(fmap.matrix, x0, y0, x1, y1, w, h) for x0, x1, _, _ in todo]
                groups: list[list[int]] = [[0]]
                for j in range(1, len(todo)):
                    if boxes[j][0] - boxes[groups[-1][-1]][2] <= tile:
                        groups[-1].append(j)
                    else:
                        groups.append([j])
                for g in groups:
                    sx0, sy0 = min(boxes[j][0] for j in g), min(boxes[j][1] for j in g)
                    sx1, sy1 = max(boxes[j][2] for j in g), max(boxes[j][3] for j in g)
                    src = read_roi(stack, int(i), sx0, sy0, sx1, sy1)
                    for j in g:
                        x0, x1, run_ch, wts = todo[j]
                        bx0, by0, bx1, by1 = boxes[j]
                        part = src[by0 - sy0:by1 - sy0, bx0 - sx0:bx1 - sx0, run_ch].astype(np.float32)
                        if identity:
                            warped = part
                        else:
                            warped = warp_from(part, bx0, by0, fmap.matrix, x0, y0, x1, y1)
                        acc[y0:y1, x0:x1, run_ch] += wts * warped
    return acc
