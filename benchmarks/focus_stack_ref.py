"""A reference re-implementation of focus-stack's merge (Petteri Aimonen, MIT), for benchmarks only.

focus-stack (github.com/PetteriAimonen/focus-stack) needs OpenCV's C++ development files to build, which this
machine lacks; its results on public stacks are the bar issue #15 sets. This module re-implements its default
merge path in NumPy, from its sources (``task_grayscale``, ``task_wavelet``, ``task_merge``, ``task_denoise``,
``task_reassign``), so that it runs on *the same registered frames* as fieldcal and is scored by the same
metrics:

1. grey: OpenCV ``BGR2GRAY`` of each 8-bit frame;
2. a complex Daubechies wavelet transform (Lina 1997; 6-tap complex low/high-pass filters, periodic borders),
   ``levels`` = the smallest number (5-10) that brings the longer side to <= 8 px;
3. merge: every coefficient (all sub-bands and the coarsest approximation) from the frame with the largest
   squared modulus, across *all* frames; the chosen frame per coefficient is the "depth map";
4. consistency 2 (the default): a two-out-of-three vote of the three detail sub-bands at each place (the odd
   one takes the other two's frame), then a 4-neighbour outlier filter of the index map (an index above or below
   all four neighbours becomes their rounded mean) -- here evaluated on the voted map at once (Jacobi) where
   focus-stack updates in raster order (Gauss-Seidel): a difference on isolated pixels only;
5. denoise 1.0 (the default): soft threshold of the real and imaginary parts of every detail coefficient by 1
   grey level;
6. inverse transform, rounded to 8 bits;
7. colour reassignment: each output pixel takes the colour of the frame whose grey value at that pixel is the
   closest to the merged grey (the first such frame), so every output pixel's colour is one a frame recorded.

Defaults as its ``main.cc`` (``--consistency=2``, ``--denoise=1.0``). Not reproduced: its own alignment (with
contrast and white-balance matching between frames; here the frames come registered by fieldcal, so the
comparison is of the merge alone), its merging in batches of 8 frames (all frames in one batch here), and its
JPEG output (quality 95 by default: its block artefacts would add high-frequency energy of their own). Not in
the package: a benchmark's yardstick.
"""

from __future__ import annotations

import cv2
import numpy as np

# Complex Daubechies filters, as in focus-stack's task_wavelet.cc (real and imaginary parts).
_HR = np.array([-0.0662912607, 0.1104854346, 0.6629126074, 0.6629126074, 0.1104854346, -0.0662912607])
_GR = np.array([-0.0662912607, -0.1104854346, 0.6629126074, -0.6629126074, 0.1104854346, 0.0662912607])
_HI = np.array([-0.0855816496, -0.0855816496, 0.1711632992, 0.1711632992, -0.0855816496, -0.0855816496])
_GI = np.array([0.0855816496, -0.0855816496, -0.1711632992, 0.1711632992, 0.0855816496, -0.0855816496])
LOW = (_HR + 1j * _HI).astype(np.complex64)
HIGH = (_GR + 1j * _GI).astype(np.complex64)
LOW_C, HIGH_C = np.conj(LOW), np.conj(HIGH)  # synthesis: the conjugate filters (an orthonormal pair)


def levels_for_size(h: int, w: int) -> int:
    """focus-stack's decomposition depth: the coarsest level about 8 px on the longer side (5-10 levels)."""
    n, levels = max(h, w), 5
    while (n >> levels) > 8 and levels < 10:
        levels += 1
    return levels


def _wrap(n: int, idx: np.ndarray) -> np.ndarray:
    """focus-stack's border rule (its current task_wavelet_templates.hh): periodic."""
    return np.mod(idx, n)


def _decompose_1d(x: np.ndarray, axis: int) -> np.ndarray:
    """One analysis step along ``axis``: low-pass half then high-pass half, both decimated by 2."""
    x = np.moveaxis(x, axis, 0)
    n = x.shape[0]
    base = np.arange(0, n, 2)
    lo = np.zeros((n // 2, *x.shape[1:]), np.complex64)
    hi = np.zeros_like(lo)
    for j in range(6):
        s = x[_wrap(n, base + j - 3)]
        lo += s * LOW[j]
        hi += s * HIGH[j]
    return np.moveaxis(np.concatenate([lo, hi], axis=0), 0, axis)


def _compose_1d(x: np.ndarray, axis: int) -> np.ndarray:
    """The synthesis step inverting :func:`_decompose_1d` (focus-stack's compose_1d)."""
    x = np.moveaxis(x, axis, 0)
    half = x.shape[0] // 2
    lo, hi = x[:half], x[half:]
    out = np.zeros((2 * half, *x.shape[1:]), np.complex64)
    m = np.arange(half)
    for parity in (0, 1):
        y = 2 * m + parity
        acc = np.zeros((half, *x.shape[1:]), np.complex64)
        for j in range((parity + 3) % 2, 6, 2):
            pos = _wrap(half, (y - j + 3) // 2)
            acc += lo[pos] * LOW_C[j] + hi[pos] * HIGH_C[j]
        out[parity::2] = acc
    return np.moveaxis(out, 0, axis)


def forward(img: np.ndarray, levels: int) -> np.ndarray:
    """The complex wavelet image (focus-stack's layout: sub-bands in quadrants, the approximation top-left)."""
    out = img.astype(np.complex64)
    h, w = out.shape
    for lev in range(levels):
        hh, ww = h >> lev, w >> lev
        out[:hh, :ww] = _decompose_1d(_decompose_1d(out[:hh, :ww], 0), 1)
    return out


def inverse(coef: np.ndarray, levels: int) -> np.ndarray:
    """The real image of a wavelet image (real part, as focus-stack keeps)."""
    out = coef.copy()
    h, w = out.shape
    for lev in range(levels - 1, -1, -1):
        hh, ww = h >> lev, w >> lev
        out[:hh, :ww] = _compose_1d(_compose_1d(out[:hh, :ww], 0), 1)
    return out.real


def focus_stack(frames: list[np.ndarray], consistency: int = 2, denoise: float = 1.0) -> tuple[np.ndarray, dict]:
    """focus-stack's merge of registered 8-bit RGB frames (``H x W x 3``, any order): the composite (8-bit RGB)
    and the share of coefficients each consistency step changed."""
    rgb = [np.asarray(f)[..., :3] for f in frames]
    if any(f.dtype != np.uint8 for f in rgb):
        rgb = [np.clip(np.rint(f.astype(np.float32) / (257.0 if f.dtype == np.uint16 else 1.0)), 0, 255)
               .astype(np.uint8) for f in rgb]
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in rgb]  # BGR2GRAY of focus-stack's BGR frames
    h0, w0 = grey[0].shape
    levels = levels_for_size(h0, w0)
    div = 1 << levels
    ph, pw = -h0 % div, -w0 % div  # focus-stack pads to a multiple of 2**levels (edge replicated here)
    coefs = [forward(np.pad(g, ((0, ph), (0, pw)), mode="edge").astype(np.float32), levels) for g in grey]
    h, w = coefs[0].shape
    best = np.full((h, w), -1.0, np.float32)
    index = np.zeros((h, w), np.int32)
    for i, c in enumerate(coefs):
        a = c.real * c.real + c.imag * c.imag
        take = a > best
        best[take], index[take] = a[take], i
    stack = np.stack(coefs)  # frames x h x w
    info = {"levels": levels}
    changed = 0
    if consistency >= 1:  # two-out-of-three vote of the detail sub-bands, level by level
        for lev in range(levels):
            hh, ww = h >> lev, w >> lev
            h2, w2 = hh // 2, ww // 2
            s1 = (slice(0, h2), slice(w2, ww))
            s2 = (slice(h2, hh), slice(w2, ww))
            s3 = (slice(h2, hh), slice(0, w2))
            v1, v2, v3 = index[s1].copy(), index[s2].copy(), index[s3].copy()
            all_same = (v1 == v2) & (v2 == v3)
            fix1 = ~all_same & (v2 == v3)
            fix2 = ~all_same & ~fix1 & (v1 == v3)
            fix3 = ~all_same & ~fix1 & ~fix2 & (v1 == v2)
            for sl, fix, v in ((s1, fix1, v2), (s2, fix2, v1), (s3, fix3, v1)):
                sub = index[sl]
                sub[fix] = v[fix]
                changed += int(fix.sum())
    if consistency >= 2:  # a pixel above or below all four neighbours takes their rounded mean
        c = index[1:-1, 1:-1]
        nb = (index[:-2, 1:-1], index[2:, 1:-1], index[1:-1, :-2], index[1:-1, 2:])
        hi = (c > nb[0]) & (c > nb[1]) & (c > nb[2]) & (c > nb[3])
        lo = (c < nb[0]) & (c < nb[1]) & (c < nb[2]) & (c < nb[3])
        out = hi | lo
        avg = (nb[0] + nb[1] + nb[2] + nb[3] + 2) // 4
        c[out] = avg[out]
        changed += int(out.sum())
    info["coefficients_changed_by_consistency"] = round(changed / index.size, 4)
    merged = np.take_along_axis(stack, index[None], axis=0)[0]
    del stack, coefs
    if denoise > 0:
        detail = np.ones((h, w), bool)
        detail[: h >> levels, : w >> levels] = False  # the approximation is not thresholded
        for part in (merged.real, merged.imag):
            shrunk = np.sign(part) * np.maximum(np.abs(part) - np.float32(denoise), 0.0)
            part[detail] = shrunk[detail]
    g = np.clip(np.rint(inverse(merged, levels)), 0, 255).astype(np.uint8)[:h0, :w0]
    # colour reassignment: the colour of the frame whose grey is nearest the merged grey (the first such frame)
    dist = np.stack([np.abs(gi.astype(np.int16) - g.astype(np.int16)) for gi in grey])
    pick = np.argmin(dist, axis=0)
    out = np.take_along_axis(np.stack(rgb), pick[None, ..., None], axis=0)[0]
    info["depth"], info["grey"] = pick, g
    return out, info
