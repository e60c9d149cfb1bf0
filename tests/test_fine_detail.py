"""Fine detail (composite/detail.py): per-coefficient selection near the depth map, and registered frames'
recorded support (composite/register.py FrameSupport)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldcal.composite.detail import fine_detail
from fieldcal.composite.register import EstimatedGeometry, FrameSupport
from fieldcal.composite.source import ArrayStack
from fieldcal.errors import FieldcalError

H, W = 96, 128


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (100.0 + 60.0 * cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), 0.8))


def _stack(frames: list[np.ndarray]) -> ArrayStack:
    return ArrayStack([f[..., None].astype(np.float32) for f in frames], [10.0 * k for k in range(len(frames))],
                      ["Y"])


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img.copy()


def test_a_blend_between_frames_gets_the_sharper_frames_fine_detail():
    # a step scene: the left half in focus at frame 2, the right half at frame 3; the depth map (sub-frame, at
    # 2.4 and 2.6) blends neighbours, diluting the finest octave, which the per-coefficient choice restores
    truth = _texture()
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    frames = [np.where(left, _blur(truth, 1.2 * abs(k - 2)), _blur(truth, 1.2 * abs(k - 3))) for k in range(5)]
    kd = np.where(left, 2.4, 2.6).astype(np.float32)
    blend = np.where(left, 0.6 * frames[2] + 0.4 * frames[3], 0.4 * frames[2] + 0.6 * frames[3])
    out, info = fine_detail(_stack(frames), blend[..., None], kd, quiet=True)
    inner = (slice(8, -8), np.r_[8:W // 2 - 6, W // 2 + 6:W - 8])
    err_blend = np.sqrt(np.mean((blend - truth)[inner] ** 2))
    err_out = np.sqrt(np.mean((out[..., 0] - truth)[inner] ** 2))
    assert err_out < 0.6 * err_blend
    assert info["fine_levels"] == 2


def test_a_far_frames_noise_is_not_chosen_but_its_real_detail_is():
    # the depth map says frame 0 everywhere; frame 4 is pure (louder) noise except one patch of real detail the
    # depth map missed: the noise stays out, the patch comes in
    rng = np.random.default_rng(3)
    flat = np.full((H, W), 100.0, np.float32)
    f0 = flat + rng.normal(0, 0.5, (H, W)).astype(np.float32)
    f4 = flat + rng.normal(0, 1.0, (H, W)).astype(np.float32)
    patch = (slice(32, 64), slice(48, 80))
    detail = _texture(5)[patch] - 100.0
    f4[patch] += detail
    mids = [flat + rng.normal(0, 0.5, (H, W)).astype(np.float32) for _ in range(3)]
    kd = np.zeros((H, W), np.float32)
    out, _ = fine_detail(_stack([f0, *mids, f4]), f0[..., None], kd, quiet=True)
    o = out[..., 0]
    away = np.ones((H, W), bool)
    away[24:72, 40:88] = False
    away[:8] = away[-8:] = False
    # away from the patch: frame 0's noise (0.5), not frame 4's (1.0)
    assert np.std(o[away]) < 0.6
    # in the patch: most of the missed detail's fine octaves are recovered
    fine = detail - cv2.GaussianBlur(detail, (0, 0), 2.0)
    got = (o[patch] - 100.0) - cv2.GaussianBlur(o[patch] - 100.0, (0, 0), 2.0)
    assert np.corrcoef(fine[4:-4, 4:-4].ravel(), got[4:-4, 4:-4].ravel())[0, 1] > 0.8


def test_without_significance_no_frame_beyond_the_reach_is_used():
    rng = np.random.default_rng(4)
    base = np.full((H, W), 50.0, np.float32)
    far = base + 20.0 * rng.standard_normal((H, W)).astype(np.float32)
    out, info = fine_detail(_stack([base, base, base, far]), base[..., None], np.zeros((H, W), np.float32),
                            significance=None, quiet=True)
    np.testing.assert_allclose(out[..., 0], base, atol=1e-3)
    assert info["coefficients_off_depth_map"] == [0.0, 0.0]


def test_a_frame_is_never_chosen_outside_its_recorded_support():
    truth = _texture(7)
    soft = _blur(truth, 2.5)
    mask = np.ones((H, W), bool)
    mask[:, : W // 2] = False  # the sharp frame's repeated edge on the left half

    def support(i):
        return mask if i == 1 else None

    out, _ = fine_detail(_stack([soft, truth]), soft[..., None], np.full((H, W), 0.5, np.float32),
                         support=support, quiet=True)
    np.testing.assert_allclose(out[8:-8, 8:W // 2 - 8, 0], soft[8:-8, 8:W // 2 - 8], atol=1e-3)
    assert np.abs(out[8:-8, W // 2 + 8:-8, 0] - truth[8:-8, W // 2 + 8:-8]).mean() < \
        0.5 * np.abs(soft - truth)[8:-8, W // 2 + 8:-8].mean()


def test_bad_arguments_are_refused_by_name():
    st = _stack([_texture(), _texture(1)])
    with pytest.raises(FieldcalError, match="depth map"):
        fine_detail(st, np.zeros((H, W, 1)), np.zeros((H, W + 1)), quiet=True)
    with pytest.raises(FieldcalError, match="odd"):
        fine_detail(st, np.zeros((H, W, 1)), np.zeros((H, W)), consistency_px=4, quiet=True)


def test_frame_support_follows_the_registration_shift():
    # a frame 10 px to the right of the reference (shift rate 1 px/um, 10 um away): output px x reads the frame
    # at x + 10, recorded for x <= W - 1 - 10 - margin
    geo = EstimatedGeometry(0.0, (W / 2, H / 2), 0.0, (1.0, 0.0), 1)
    sup = FrameSupport(geo, {0: 0.0, 1: 10.0}, W, H)
    assert sup(0) is None  # the reference covers everything
    m = sup(1)
    cols = np.flatnonzero(m.all(axis=0))
    assert cols.min() == 0 and cols.max() == W - 1 - 10 - sup.margin
    assert not m[:, W - 10:].any()
    assert sup(5) is None  # not a held frame: nothing known, nothing cut


def test_where_no_frame_is_sharp_the_frames_within_reach_are_averaged():
    # blank ground, every frame its own noise (sigma 1): the depth map at 1.5 reaches frames 1 and 2 (and 0.5
    # and 2.5 are beyond), whose average has 1/sqrt(2) of a frame's noise at the fine levels; choosing the
    # louder of the two would raise it instead
    rng = np.random.default_rng(11)
    frames = [np.full((H, W), 80.0, np.float32) + rng.standard_normal((H, W)).astype(np.float32) for _ in range(4)]
    base = np.full((H, W, 1), 80.0, np.float32)  # the coarse levels carry no noise: only the fine ones count
    out, info = fine_detail(_stack(frames), base, np.full((H, W), 1.5, np.float32), quiet=True)
    fine = out[8:-8, 8:-8, 0] - 80.0
    single = frames[1] - cv2.pyrUp(cv2.pyrUp(cv2.pyrDown(cv2.pyrDown(frames[1]))))  # its two finest levels
    assert info["coefficients_averaged"][0] > 0.9
    assert np.std(fine) < 0.8 * np.std(single[8:-8, 8:-8])


def test_composite_stack_adds_fine_detail_to_a_scene_with_depth_without_a_lens_model():
    from fieldcal.composite.api import composite_stack

    truth = _texture(2)
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    # in focus between frames (1.3 and 3.3): the depth map's blend mixes in the softer neighbour
    frames = [np.where(left, _blur(truth, 1.5 * abs(k - 1.3)), _blur(truth, 1.5 * abs(k - 3.3))) for k in range(5)]
    st = _stack(frames)
    with_detail = composite_stack(st, None, method="dff", depth="3d", register=False, quiet=True)
    without = composite_stack(st, None, method="dff", depth="3d", register=False, fine_detail=False, quiet=True)
    assert "fine_detail" in with_detail.info and "fine_detail" not in without.info
    inner = (slice(8, -8), np.r_[8:W // 2 - 6, W // 2 + 6:W - 8])
    err = [np.sqrt(np.mean((r.image[..., 0].astype(np.float64) - truth)[inner] ** 2)) for r in (with_detail, without)]
    # the blend's seams are narrow, so here it already holds the nearer frame; the step must not cost anything
    assert err[0] <= 1.02 * err[1]

