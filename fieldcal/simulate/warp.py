"""Exact sub-pixel scale + shift resampling (the renderer's geometry).

The frame geometry is ``p' = a p + t`` with the same scale ``a`` in x and y and no rotation, so the warp is
separable: one banded 1-D resampling matrix per axis, applied as two sparse matrix products. Unlike
``cv2.warpAffine`` (positions quantised to 1/32 px; its bicubic kernel with a = -0.75 moves centroids by ~6%
of a sub-pixel shift), positions here are exact and the kernel is Keys' cubic convolution with a = -0.5 (Catmull-Rom), which
reproduces linear and quadratic signals exactly, so image centroids land where the geometry puts them
(Lanczos windows do not: ~6% bias of a 0.3 px shift). Its cost is a slight low-pass at sub-pixel phases:
at a half-pixel phase the response is 0.996 at 0.1 cycles/px and 0.88 at 0.25 cycles/px.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

_TAPS = 2  # Keys cubic: 4 taps per output sample


def _keys(x: np.ndarray, a: float = -0.5) -> np.ndarray:
    """Keys (1981) cubic convolution kernel."""
    x = np.abs(x)
    near = ((a + 2) * x - (a + 3)) * x * x + 1
    far = ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
    return np.where(x <= 1, near, np.where(x < 2, far, 0.0))


def _reflect(i: np.ndarray, n: int) -> np.ndarray:
    """Mirror indices about the edge pixels (OpenCV's BORDER_REFLECT_101)."""
    if n == 1:
        return np.zeros_like(i)
    period = 2 * (n - 1)
    i = np.mod(i, period)
    return np.where(i >= n, period - i, i)


def resample_matrix(n_out: int, n_in: int, scale: float, offset: float) -> sparse.csr_matrix:
    """Sparse (n_out x n_in) matrix sampling a signal at ``u = (o - offset) / scale`` for output pixel o."""
    u = (np.arange(n_out, dtype=np.float64) - offset) / scale
    base = np.floor(u).astype(np.int64)
    k = np.arange(-_TAPS + 1, _TAPS + 1)
    idx = base[:, None] + k[None, :]
    w = _keys(u[:, None] - idx)
    w /= w.sum(axis=1, keepdims=True)  # already 1 analytically; guards rounding
    rows = np.repeat(np.arange(n_out), k.size)
    m = sparse.coo_matrix((w.ravel().astype(np.float32), (rows, _reflect(idx, n_in).ravel())),
                          shape=(n_out, n_in))
    return m.tocsr()  # duplicate (reflected) entries are summed


def scale_shift(img: np.ndarray, scale: float, tx: float, ty: float) -> np.ndarray:
    """Resample a 2-D float32 image so that input pixel p lands at ``scale * p + (tx, ty)``."""
    h, w = img.shape
    mx = resample_matrix(w, w, scale, tx)
    my = resample_matrix(h, h, scale, ty)
    tmp = np.asarray(mx @ img.T)  # W x H: rows resampled
    return np.ascontiguousarray(np.asarray(my @ tmp.T), dtype=np.float32)
