"""fusion.masked_copy: OpenCV's masked copy standing in for NumPy's, the same values."""
import numpy as np


def test_masked_copy_is_numpys_masked_copy():
    """masked_copy writes what np.copyto(where=) writes, in place, for OpenCV's cases and the fallbacks alike."""
    from fieldcal.composite.fusion import masked_copy

    rng = np.random.default_rng(5)
    mask = rng.random((37, 53)) < 0.4
    for dtype in (np.float32, np.float64, np.int16, np.uint8, np.uint16, np.bool_, np.int64):
        for shape in ((37, 53), (37, 53, 3), (37, 53, 6)):
            dst = (rng.random(shape) * 100).astype(dtype)
            src = (rng.random(shape) * 100).astype(dtype)
            m = mask if len(shape) == 2 else mask[..., None]
            want = dst.copy()
            np.copyto(want, src, where=m)
            got = dst
            assert masked_copy(dst, src, mask) is got
            assert np.array_equal(got, want) and np.array_equal(got[~mask], want[~mask])
    # a scalar (cast as casting="unsafe"), a strided destination (NumPy's path), a mask of another shape
    idx = np.zeros((37, 53), np.int16)
    masked_copy(idx, 7, mask)
    assert np.array_equal(idx, np.where(mask, 7, 0))
    small = np.zeros((37, 53), np.uint8)
    want = small.copy()
    np.copyto(want, np.int64(300), where=mask, casting="unsafe")  # a NumPy scalar wraps, as an unsafe cast does
    assert np.array_equal(masked_copy(small, np.int64(300), mask), want)
    big = np.zeros((37, 106), np.float32)
    view = big[:, ::2]
    masked_copy(view, np.ones((37, 53), np.float32), mask)
    assert np.array_equal(big[:, ::2], mask.astype(np.float32)) and not big[:, 1::2].any()
    flat = np.zeros(10, np.float32)
    masked_copy(flat, np.arange(10, dtype=np.float32), np.arange(10) % 2 == 0)
    assert np.array_equal(flat, np.where(np.arange(10) % 2 == 0, np.arange(10), 0))
