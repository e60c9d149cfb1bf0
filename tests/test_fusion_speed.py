"""The speed-ups of the depth-from-focus path compute what the plain formulations compute."""

import cv2
import numpy as np

from fieldcal.composite.dff import _weighted_lstsq, frame_planes, map_in_order
from fieldcal.composite.fusion import _GuidedFilter, _PeakTracker
from fieldcal.formats.frames import ArrayStack


def test_guided_filter_matches_opencv():
    rng = np.random.default_rng(0)
    guide = cv2.GaussianBlur(rng.random((90, 120)).astype(np.float32), (0, 0), 3)
    guide = (guide - guide.min()) / np.ptp(guide)
    gf = _GuidedFilter(guide, 5, 1e-3)
    for _ in range(2):  # the guide's statistics are reused
        src = rng.random((90, 120)).astype(np.float32) ** 3
        ref = cv2.ximgproc.guidedFilter(guide, src, 5, 1e-3)
        np.testing.assert_allclose(gf(src), ref, atol=5e-5 * float(np.abs(ref).max()))  # float32 rounding


def test_peak_tracker_matches_argmax_and_neighbours():
    rng = np.random.default_rng(1)
    vol = rng.integers(0, 6, size=(7, 20, 30)).astype(np.float32)  # many ties: the first frame must win
    t = _PeakTracker(vol[0])
    for f in vol[1:]:
        t.add(f)
    n = len(vol)
    k = np.argmax(vol, axis=0)
    take = lambda j: np.take_along_axis(vol, j[None], 0)[0]  # noqa: E731
    np.testing.assert_array_equal(t.index, k)
    np.testing.assert_array_equal(t.peak, take(k))
    np.testing.assert_array_equal(t.before, take(np.clip(k - 1, 0, n - 1)))
    np.testing.assert_array_equal(t.after, take(np.clip(k + 1, 0, n - 1)))
    np.testing.assert_allclose(t.total, vol.sum(axis=0))


def test_map_in_order_keeps_order_and_raises():
    assert list(map_in_order(lambda v: v * v, range(9), workers=2)) == [v * v for v in range(9)]

    def bad(v):
        if v == 3:
            raise ValueError("frame 3")
        return v

    try:
        list(map_in_order(bad, range(6), workers=2))
    except ValueError as exc:
        assert "frame 3" in str(exc)
    else:
        raise AssertionError("the worker's error was lost")


def test_frame_planes_are_the_frame(monkeypatch):
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 255, size=(70, 50, 3)).astype(np.uint8) for _ in range(2)]
    st = ArrayStack(frames, [0.0, 5.0], ["R", "G", "B"])
    monkeypatch.setattr("fieldcal.composite.dff.BAND_BYTES", 50 * 3 * 4 * 16)  # 16-row bands: 5 bands
    planes = frame_planes(st, None, 5.0, 1, st.channels, 50, 70)
    for c in range(3):
        np.testing.assert_array_equal(planes[c], frames[1][..., c].astype(np.float32))


def test_weighted_lstsq_matches_lapack():
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-1, 1, (2, 400))
    a = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v, (u * u + v * v) ** 2, (u * u + v * v) ** 3], axis=1)
    z = a @ rng.normal(size=8) + 0.01 * rng.normal(size=400)
    sw = np.sqrt(rng.uniform(0, 1, 400))
    ref = np.linalg.lstsq(a * sw[:, None], z * sw, rcond=None)[0]
    np.testing.assert_allclose(_weighted_lstsq(a, z, sw), ref, rtol=1e-8, atol=1e-10)


def test_subsampled_guided_filter_keeps_the_filter_and_the_guides_edges():
    """He and Sun's fast guided filter (coefficients on planes subsampled by s, applied to the full guide): on a
    smooth input it is the exact filter to a small fraction of the input's range, and across a step of the guide
    it keeps the step as sharp as the exact filter does (the edge comes from the full-resolution guide), where a
    plain box of the same width would spread it over its whole width."""
    rng = np.random.default_rng(4)
    h, w = 240, 320
    guide = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 6)
    guide = (guide - guide.min()) / np.ptp(guide)
    guide[:, w // 2:] += 1.0  # a step edge of the guide
    guide /= guide.max()
    src = (2.0 * guide + 0.3 * cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 8)).astype(np.float32)
    r = 12
    s = 3
    exact = _GuidedFilter(guide, r, 1e-3)(src)
    fast = _GuidedFilter(guide, r, 1e-3, subsample=s)(src)
    inner = (slice(2 * r, -2 * r), slice(2 * r, -2 * r))
    assert np.abs(fast - exact)[inner].max() < 0.02 * float(np.ptp(src))
    # the step: the exact and the fast filters' rise over 2 px equals the source's; a box of 2r + 1 px does not
    rows = slice(2 * r, -2 * r)
    rise = lambda img: float(np.median(img[rows, w // 2 + 1] - img[rows, w // 2 - 2]))  # noqa: E731
    box = cv2.blur(src, (2 * r + 1, 2 * r + 1))
    assert abs(rise(fast) - rise(src)) < 0.1 * rise(src) and abs(rise(exact) - rise(src)) < 0.1 * rise(src)
    assert rise(box) < 0.3 * rise(src)


def test_fusion_row_bands_are_the_whole_planes_selection(monkeypatch):
    """The selection split in row bands over threads (each band's salience window filtered with a halo) gives
    the single-band selection bit for bit: coefficients, saliences, frame index, with and without a support
    mask; a halo short of the Gaussian's support would change the rows beside the bands' edges."""
    from concurrent.futures import ThreadPoolExecutor

    import fieldcal.composite.fusion as fusion

    monkeypatch.setattr(fusion, "_BAND_MIN_ROWS", 8)  # several bands at every level of a small image
    rng = np.random.default_rng(5)
    h, w, n = 150, 97, 4
    scene = rng.random((h, w, 3)).astype(np.float32) * 100
    region = (np.arange(w)[None, :] * n // w + np.arange(h)[:, None] * 2 // h) % n  # where frame k is sharp
    blurred = cv2.GaussianBlur(scene, (0, 0), 2.0)
    frames = [np.where((region == k)[..., None], scene, blurred) + rng.normal(0, 1, (h, w, 3)).astype(np.float32)
              for k in range(n)]
    supports = [None if k % 2 else (rng.random((h, w)) > 0.2) for k in range(n)]

    def run(workers: int):
        with ThreadPoolExecutor(max_workers=max(1, workers - 1)) as pool:
            sel = fusion._Selection(h, w, 3, 4, 2.5, 1, pool=pool, workers=workers)
            for k, f in enumerate(frames):
                sel.add([np.ascontiguousarray(f[..., c]) for c in range(3)], k, supports[k])
        return sel

    one, banded = run(1), run(3)
    assert len(banded._bands(h)) == 3
    for lev in range(4):
        np.testing.assert_array_equal(banded.best_sal[lev], one.best_sal[lev])
        for c in range(3):
            np.testing.assert_array_equal(banded.best[c][lev], one.best[c][lev])
    np.testing.assert_array_equal(banded.best_idx, one.best_idx)
    assert len(np.unique(one.best_idx)) == n  # every frame chosen somewhere: the test compares real choices

    st = ArrayStack(frames, [0.0, 1.0, 2.0, 3.0], ["R", "G", "B"])
    for min_rows in (8, 64):  # (64: split at the finest level only, the coarser levels whole on one thread)
        monkeypatch.setattr(fusion, "_BAND_MIN_ROWS", min_rows)
        monkeypatch.setattr(fusion, "default_workers", lambda: 1)
        ref = fusion.fuse_pyramid(st, quiet=True)
        monkeypatch.setattr(fusion, "default_workers", lambda: 3)
        got = fusion.fuse_pyramid(st, quiet=True)
        np.testing.assert_array_equal(got.image, ref.image)
        np.testing.assert_array_equal(got.depth_index, ref.depth_index)
