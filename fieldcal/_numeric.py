"""Small array helpers shared by the measurement and the compositor (NumPy only: cheap to import)."""

from __future__ import annotations

import numpy as np


def channel_mean(a: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``a.mean(axis=2)`` of an ``H x W x C`` float array, to the bit, at a fraction of its cost.

    NumPy reduces a short last axis pixel by pixel (its slow case: ~55 ms for a 2048 x 1536 x 3 plane) by summing
    the channels in order and dividing once by their number; for 2 to 7 float32 or float64 channels this does the
    same sums as whole-plane adds (8 or more: NumPy sums pairwise, so its own mean is used). ``out``: an
    ``H x W`` array of ``a``'s dtype to write into."""
    if a.ndim != 3 or a.dtype not in (np.float32, np.float64) or not 1 < a.shape[2] < 8:
        m = a.mean(axis=2)
        if out is None:
            return m
        out[...] = m
        return out
    s = np.add(a[:, :, 0], a[:, :, 1], out=out)
    for k in range(2, a.shape[2]):
        s += a[:, :, k]
    return np.true_divide(s, np.intp(a.shape[2]), out=s, casting="unsafe")
