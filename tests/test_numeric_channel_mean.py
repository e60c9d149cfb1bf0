import numpy as np
import pytest

from fieldcal._numeric import channel_mean


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8])
@pytest.mark.parametrize("n_channels", [1, 2, 3, 4, 7, 8, 9])
def test_channel_mean_is_numpys_mean_to_the_bit(dtype, n_channels):
    """The whole-plane sums give NumPy's own mean exactly (same sums in the same order, one division), for every
    channel count and dtype (the fallback for 1, 8 or more channels and integers), into ``out`` as well."""
    rng = np.random.default_rng(n_channels)
    a = (rng.standard_normal((37, 53, n_channels)) * 1e3 + 1e4).astype(dtype) if dtype != np.uint8 else \
        rng.integers(0, 256, (37, 53, n_channels), dtype=np.uint8)
    want = a.mean(axis=2)
    got = channel_mean(a)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got.view(np.uint8), want.view(np.uint8))
    out = np.empty_like(want)
    assert channel_mean(a[5:20], out=out[5:20]) is not None
    assert np.array_equal(out[5:20], want[5:20])
    # a strided view (a crop of the columns) as well
    assert np.array_equal(channel_mean(a[:, 3:40]), want[:, 3:40])
