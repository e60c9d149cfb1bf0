"""The machinery that makes compositing fast must not change what it computes.

Tight per-tile frame support, seam-only weights, the band thread pool, the direct frame reader and the coarser
focus grid at 4K are each checked against the plain definition: the weights of every frame at every z_b,
a single-threaded run, the Stack API, and the exact best-focus fixed point.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fieldcal.composite import ArrayStack
from fieldcal.composite.source import RowReader
from fieldcal.composite.stream import _block_extremes, _tile_edges, accumulate, tile_support
from fieldcal.composite.surface import grid_step_px, output_best_focus_um, profile_focus_map
from fieldcal.composite.weights import BlendKernel, SweepKernel
from fieldcal.composite.warp import FrameMap, affine_for, source_box
from fieldcal.errors import StackError
from fieldcal.simulate.lens import LensSpec
from fieldcal.formats.stack import Stack, StackWriter
from fieldcal.simulate.truth import TruthProfile

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

positions = st.lists(st.floats(-500, 500, allow_nan=False), min_size=1, max_size=10, unique=True).map(
    lambda v: np.array(sorted(v))).filter(lambda z: len(z) < 2 or np.min(np.diff(z)) > 1e-3)


# ------------------------------------------------------------------------------------- frame support
@settings(max_examples=60, deadline=None)
@given(positions, st.floats(0, 50), st.floats(0, 1), st.lists(st.floats(-700, 700), min_size=1, max_size=30))
@example(np.array([-1.0, 0.0, 1.0]), 0.0, 1.0, [0.0])  # full-width band, point on a frame (found by hypothesis)
def test_tight_support_holds_every_weighted_frame_and_at_most_two_per_point(z, tol, band, zb):
    k = BlendKernel(z, tol, min_band=band)
    zb = np.array(zb, dtype=np.float32)
    w = np.stack([k.weight(i, zb) for i in range(len(z))])
    lo, hi = k.supports(zb, zb)  # one point per "tile"
    for j in range(len(zb)):
        nz = np.flatnonzero(w[:, j])
        assert lo[j] <= nz.min() and nz.max() <= hi[j]  # never misses a weighted frame
        assert hi[j] - lo[j] <= 1  # a point blends at most the two frames of one seam
    # ranges: the union of the points' supports
    lo_r, hi_r = k.supports(np.array([zb.min()]), np.array([zb.max()]))
    assert lo_r[0] == lo.min() and hi_r[0] == hi.max()


@settings(max_examples=60, deadline=None)
@given(positions, st.floats(0, 50), st.floats(0, 1), st.lists(st.floats(-700, 700), min_size=1, max_size=30))
def test_seam_only_weights_equal_the_full_weights(z, tol, band, zb):
    k = BlendKernel(z, tol, min_band=band)
    zb = np.array(zb, dtype=np.float32)
    for i in range(len(z)):
        a, b = k.unit_range(i)
        full = k.weight(i, zb)
        inside = (zb >= a) & (zb <= b)
        assert np.all(full[inside] == 1.0)  # exactly one frame, no weights needed
        past_below = zb >= a
        np.testing.assert_array_equal(k.weight(i, zb[past_below], below=False), full[past_below])
        before_above = zb <= b
        np.testing.assert_array_equal(k.weight(i, zb[before_above], above=False), full[before_above])


@settings(max_examples=40, deadline=None)
@given(positions, st.floats(0.5, 100), st.lists(st.floats(-700, 700), min_size=1, max_size=20))
def test_sweep_supports_match_the_scalar_support(z, alpha, zb):
    k = SweepKernel(z, alpha)
    zb = np.array(zb)
    lo, hi = k.supports(zb, zb + 3.0)
    for j, v in enumerate(zb):
        assert (lo[j], hi[j]) == k.support(float(v), float(v) + 3.0)


def test_block_extremes_match_a_direct_reduction():
    rng = np.random.default_rng(2)
    zb = rng.normal(size=(133, 70, 2)).astype(np.float32)
    for tile in (1, 16, 64, 200):
        ye, xe = _tile_edges(133, tile), _tile_edges(70, tile)
        mn, mx = _block_extremes(zb, ye, xe, tile)
        for ty in range(len(ye) - 1):
            for tx in range(len(xe) - 1):
                blk = zb[ye[ty]:ye[ty + 1], xe[tx]:xe[tx + 1]]
                np.testing.assert_array_equal(mn[ty, tx], blk.min(axis=(0, 1)))
                np.testing.assert_array_equal(mx[ty, tx], blk.max(axis=(0, 1)))


def test_tile_support_falls_back_to_a_scalar_support_method():
    class Scalar:
        """A kernel with only the scalar API (third-party kernels keep working)."""

        def __init__(self, k):
            self.k = k

        def support(self, a, b):
            return self.k.support(a, b)

    k = BlendKernel(np.arange(0.0, 50.0, 5.0), 3.0)
    zb = np.random.default_rng(0).uniform(-5, 55, (40, 50, 3)).astype(np.float32)
    a = tile_support(zb, k, 16)
    b = tile_support(zb, Scalar(k), 16)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)


# ------------------------------------------------------------------------------------------ geometry
def test_near_identity_maps_read_exactly_the_box():
    almost = affine_for(1.0 + 1e-8, (50.0, 50.0), (1e-9, 0.0))
    assert FrameMap(almost, (0,)).is_identity
    assert source_box(almost, 3, 4, 20, 30, 100, 100) == (3, 4, 20, 30)  # consistent with is_identity
    assert not FrameMap(affine_for(1.0, (0.0, 0.0), (1e-3, 0.0)), (0,)).is_identity


def test_coarse_focus_grid_at_4k_is_within_hundredths_of_a_micron(triplet_path):
    assert grid_step_px(160, 120) == 8 and grid_step_px(3840, 2160) == 15
    spec = LensSpec.load(triplet_path)
    p = TruthProfile(spec, 3840, 2160)
    rng = np.random.default_rng(1)
    x = np.concatenate([[0, 3839, 0, 3839], rng.integers(0, 3840, 300)]).astype(float)
    y = np.concatenate([[0, 0, 2159, 2159], rng.integers(0, 2160, 300)]).astype(float)
    zb = profile_focus_map(p, 3840, 2160, p.channels)
    for ci, ch in enumerate(p.channels):
        exact = output_best_focus_um(p, x, y, ch)
        err = np.abs(zb[y.astype(int), x.astype(int), ci] - exact)
        assert err.max() < 0.02  # frames are ~8 µm apart, focus tolerance several µm


# ---------------------------------------------------------------------------- threads and the reader
def _stack(tmp_path, dtype=np.uint16, n=6, size=(96, 72)):
    rng = np.random.default_rng(5)
    w, h = size
    top = 4095 if dtype == np.uint16 else 1.0
    wr = StackWriter.create(tmp_path / "st", pixel_pitch_um=20.0, channels=["R", "G", "B"], overwrite=True,
                            **({"bit_depth": 12} if dtype == np.uint16 else {}))
    frames = []
    for k in range(n):
        f = (rng.random((h, w, 3)) * top).astype(dtype)
        frames.append(f)
        wr.add_frame(f, float(4 * k))
    return Stack.open(tmp_path / "st"), frames


def _lens(w, h):
    import dataclasses as dc

    from tests.conftest import MODELS
    spec = LensSpec.load(MODELS / "triplet-uncorrected.json").with_sensor_size(w, h)
    return dc.replace(spec, exit_pupil_mm=3.0)  # strong breathing: real warps everywhere


def test_result_does_not_depend_on_threads_or_reader(tmp_path):
    stack, frames = _stack(tmp_path)
    prof = TruthProfile(_lens(96, 72))
    zb = np.random.default_rng(3).uniform(-2, 22, (72, 96, 3)).astype(np.float32)
    k = BlendKernel(np.sort(stack.z_um), 1.0)
    one = accumulate(stack, zb, k, prof, tile=16, workers=1, quiet=True)
    two = accumulate(stack, zb, k, prof, tile=16, workers=3, quiet=True)
    mem = accumulate(ArrayStack(frames, stack.z_um, stack.channels), zb, k, prof, tile=16, workers=2, quiet=True)
    np.testing.assert_array_equal(one, two)
    np.testing.assert_array_equal(one, mem)  # files through the direct reader == frames in memory
    # finish() maps each band; the assembled result is the mapped whole
    fin = accumulate(stack, zb, k, prof, tile=16, quiet=True, finish=lambda b: np.rint(b).astype(np.int32))
    np.testing.assert_array_equal(fin, np.rint(one).astype(np.int32))
    # and it is the weighted sum of the warped frames by definition
    from fieldcal.composite.warp import frame_maps, warp_region
    ref = np.zeros_like(one)
    for j, i in enumerate(np.argsort(stack.z_um)):
        fm = frame_maps(prof, float(stack.z_um[i]), stack.channels)[0]
        ref += k.weight(j, zb) * warp_region(stack, int(i), fm, 0, 0, 96, 72)
    # cv2 quantises positions to 1/32 px from each box's origin: ~0.02 DN on white noise spanning 4095 DN
    np.testing.assert_allclose(one, ref, atol=0.1)


def test_reader_takes_the_stack_api_for_float_frames_and_reports_lost_files(tmp_path):
    stack, _ = _stack(tmp_path, dtype=np.float32)
    r = RowReader(stack)
    r.prepare(range(len(stack)))
    assert r._layouts[0] is None  # float frames need the NaN check of Stack.read
    stack16, frames = _stack(tmp_path / "b")
    r16 = RowReader(stack16)
    r16.prepare(range(len(stack16)))
    assert r16._layouts[0] is not None
    np.testing.assert_array_equal(r16.read(2, 5, 7, 60, 33), frames[2][7:33, 5:60])
    stack16.frames[3].path.unlink()  # the file vanishes after the stack was opened
    with pytest.raises(StackError, match="disappeared"):
        r16.read(3, 0, 0, 10, 10)
    zb = np.full((72, 96, 3), 12.0, np.float32)  # frame 3 (z = 12) is the one every pixel needs
    with pytest.raises(StackError):
        accumulate(stack16, zb, BlendKernel(np.sort(stack16.z_um), 1.0), None, tile=16, workers=2, quiet=True)
