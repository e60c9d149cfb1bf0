"""Fast near-band-limited scale + shift resampling: the renderer's per-frame warp.

:func:`fieldcal.simulate.warp.scale_shift` evaluates the exact band-limited interpolant of the mirrored image
with the chirp-z transform (three FFTs of >= 3n per row and per column: ~0.4 s a channel at 1920 x 1080).
This module evaluates the same interpolant with a finite kernel: a Kaiser-windowed sinc of ``TAPS`` = 32 taps
(beta 5), normalised to sum 1 at every phase, on the same half-sample mirrored extension. Its error against
the ideal response, over all phases, is 1.2e-3 at 0.1, 2.4e-4 at 0.25, 2.3e-3 at 0.4 and 3.6e-3 at 0.45
cycles/px (tests/test_simulate_fast.py checks it and the agreement with the exact resampler), so it keeps the
property the renderer needs: no sub-pixel-phase-dependent blur, which would pull measured best focus towards
z_ref (warp.py). Only content within ~0.05 cycles/px of Nyquist is reproduced less exactly.

The warp ``p' = a p + t`` is separable, so each axis is a banded (n_out x n_in) matrix. Applied as blocks of
``_BLOCK`` output samples (each block's inputs are a contiguous run of ~_BLOCK / a + TAPS samples), each
block is one small dense single-precision matrix product: ~2 (_BLOCK + TAPS) flops per pixel and axis.
Call it with BLAS limited to one thread (:func:`single_threaded_blas`) when channels run in parallel:
OpenBLAS's threads on these small products cost far more than they save on a shared machine.
"""

from __future__ import annotations

import contextlib
from functools import lru_cache

import numpy as np

TAPS = 32  # kernel length (even): taps at floor(u) - 15 .. floor(u) + 16
BETA = 5.0  # Kaiser window shape
_BLOCK = 32  # output samples per matrix product


def _fold(i: np.ndarray, n: int) -> np.ndarray:
    """Mirror indices about the half-sample edges (the period-2n extension warp.scale_shift uses)."""
    p = 2 * n
    i = np.mod(i, p)
    return np.where(i >= n, p - 1 - i, i)


@lru_cache(maxsize=64)
def _blocks(n_out: int, n_in: int, scale: float, offset: float) -> tuple:
    """Block matrices sampling a length-n_in signal at ``u = (o - offset) / scale``, o = 0 .. n_out - 1.

    Returns a tuple of ``(o0, o1, i0, i1, M)`` with ``out[o0:o1] = M.T @ x[i0:i1]`` (M is (i1 - i0) x (o1 - o0)).
    """
    u = (np.arange(n_out, dtype=np.float64) - offset) / scale
    n0 = np.floor(u)
    phase = u - n0
    t = np.arange(-TAPS // 2 + 1, TAPS // 2 + 1, dtype=np.float64)
    d = t[None, :] - phase[:, None]
    half = TAPS / 2.0
    w = np.sinc(d) * np.i0(BETA * np.sqrt(np.clip(1.0 - (d / half) ** 2, 0.0, 1.0)))
    w /= w.sum(axis=1, keepdims=True)  # flat field stays flat at every phase
    idx = _fold(n0.astype(np.int64)[:, None] + t.astype(np.int64)[None, :], n_in)
    out = []
    for o0 in range(0, n_out, _BLOCK):
        o1 = min(o0 + _BLOCK, n_out)
        ib = idx[o0:o1]
        i0, i1 = int(ib.min()), int(ib.max()) + 1
        m = np.zeros((i1 - i0, o1 - o0), dtype=np.float64)
        cols = np.broadcast_to(np.arange(o1 - o0)[:, None], ib.shape)
        np.add.at(m, (ib - i0, cols), w[o0:o1])  # mirrored taps that land on one sample add up
        out.append((o0, o1, i0, i1, np.ascontiguousarray(m.astype(np.float32))))
    return tuple(out)


def scale_shift_fast(img: np.ndarray, scale: float, tx: float, ty: float) -> np.ndarray:
    """Resample a 2-D float32 image so that input pixel p lands at ``scale * p + (tx, ty)`` (32-tap
    windowed sinc, mirrored edges); the fast counterpart of :func:`fieldcal.simulate.warp.scale_shift`."""
    src = np.ascontiguousarray(img, dtype=np.float32)
    if scale == 1.0 and tx == 0.0 and ty == 0.0:
        return src.copy()
    if scale == 1.0:  # a pure shift (telecentric image space): exact, by a phase ramp
        return _shift_axis(_shift_axis(src, float(tx)).T, float(ty)).T.copy()
    h, w = src.shape
    rows = np.empty((h, w), dtype=np.float32)
    for o0, o1, i0, i1, m in _blocks(w, w, float(scale), float(tx)):
        rows[:, o0:o1] = src[:, i0:i1] @ m
    out = np.empty((h, w), dtype=np.float32)
    for o0, o1, i0, i1, m in _blocks(h, h, float(scale), float(ty)):
        np.matmul(m.T, rows[i0:i1], out=out[o0:o1])
    return out


_CONTROLLER = []  # threadpoolctl's controller, made once (finding the loaded BLAS libraries takes a while)


def _shift_axis(img: np.ndarray, shift: float) -> np.ndarray:
    """Along the last axis: the band-limited interpolant of the half-sample mirrored signal (period 2n) at
    ``o - shift``, by multiplying its real FFT with a phase ramp (exact below Nyquist at every phase; a finite
    kernel is not, and a shift's phase is the same everywhere, so its loss would change with z)."""
    from scipy import fft as sfft
    n = img.shape[-1]
    if shift == 0.0 or n == 1:
        return np.ascontiguousarray(img, dtype=np.float32)
    ext = np.concatenate([img, img[..., ::-1]], axis=-1).astype(np.float32, copy=False)
    spec = sfft.rfft(ext, axis=-1, workers=-1)
    k = np.arange(spec.shape[-1], dtype=np.float64)
    spec *= np.exp(-2j * np.pi * k * shift / (2 * n)).astype(np.complex64)
    return np.ascontiguousarray(sfft.irfft(spec, n=2 * n, axis=-1, workers=-1)[..., :n], dtype=np.float32)


@contextlib.contextmanager
def single_threaded_blas():
    """Limit BLAS to one thread inside the block (threadpoolctl), e.g. while channels render in parallel."""
    if not _CONTROLLER:
        from threadpoolctl import ThreadpoolController
        _CONTROLLER.append(ThreadpoolController())
    with _CONTROLLER[0].limit(limits=1, user_api="blas"):
        yield
