"""The focus-stack reference of the real-stack benchmark (benchmarks/focus_stack_ref.py): its wavelet inverts
exactly, its merge takes each region from the frame in focus there, and its colours are ones a frame recorded."""

from __future__ import annotations

import cv2
import numpy as np
import pytest


@pytest.fixture(scope="module")
def ref():
    from bench_util import import_bench
    return import_bench("focus_stack_ref")


def test_the_complex_wavelet_inverts_exactly(ref):
    rng = np.random.default_rng(0)
    img = (255 * rng.random((64, 96))).astype(np.float32)
    levels = ref.levels_for_size(64, 96)
    assert levels == 5  # the smallest depth focus-stack uses; 96 >> 5 = 3 px, already <= 8
    coef = ref.forward(img, levels)
    assert np.abs(coef.imag).max() > 1.0  # a complex transform, not a real one
    np.testing.assert_allclose(ref.inverse(coef, levels), img, atol=1e-3)
    # the filter pair is orthonormal: energy is kept (Parseval)
    assert np.sum(np.abs(coef) ** 2) == pytest.approx(float(np.sum(img.astype(np.float64) ** 2)), rel=1e-4)


def test_levels_follow_focus_stacks_rule(ref):
    assert ref.levels_for_size(1536, 2048) == 8  # 2048 >> 8 = 8 px
    assert ref.levels_for_size(8, 8) == 5  # at least 5
    assert ref.levels_for_size(1 << 20, 16) == 10  # at most 10


def test_each_half_comes_from_the_frame_in_focus_there_with_a_frames_own_colours(ref):
    rng = np.random.default_rng(1)
    h, w = 64, 64
    sharp = np.clip(128 + 60 * rng.standard_normal((h, w, 3)), 0, 255).astype(np.float32)
    soft = cv2.GaussianBlur(sharp, (0, 0), 3.0)
    left = np.zeros((h, w, 1), bool)
    left[:, : w // 2] = True
    a = np.where(left, sharp, soft).astype(np.uint8)  # in focus on the left
    b = np.where(left, soft, sharp).astype(np.uint8)  # in focus on the right
    out, info = ref.focus_stack([a, b])
    truth = sharp.astype(np.uint8)
    inner = (slice(6, -6), np.r_[6:w // 2 - 6, w // 2 + 6:w - 6])
    err = np.abs(out.astype(float) - truth)[inner].mean()
    err_frame = np.abs(a.astype(float) - truth)[inner].mean()
    assert err < 0.25 * err_frame
    # every output pixel's colour is the colour of one of the frames at that pixel
    same = (out == a).all(axis=2) | (out == b).all(axis=2)
    assert same.all()
    assert info["levels"] == 5 and 0.0 <= info["coefficients_changed_by_consistency"] < 1.0
