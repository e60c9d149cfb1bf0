"""Registration without a profile beyond scale and shift (fieldcal.composite.register), on frames made with a
known warp: a rolled and shifted camera (similarity), a tilted one (homography), and the lens model's own
breathing and shift, which must come back as scale-and-shift, unchanged."""

from pathlib import Path

import numpy as np
import pytest

from fieldcal.composite import register as R
from registration_util import similarity, warped
from fieldcal.formats.frames import ArrayStack

W, H = 240, 180
MARGIN = 40


def _texture(seed=0):
    rng = np.random.default_rng(seed)
    import cv2
    return cv2.GaussianBlur(rng.random((H + 2 * MARGIN, W + 2 * MARGIN)).astype(np.float32), (0, 0), 2.0)


def _frame(img, ref_to_frame):
    return warped(img, ref_to_frame, W, H, MARGIN)


def _similarity(scale, angle_deg, tx, ty):
    return similarity(scale, angle_deg, tx, ty, W, H)


def _corner_error_px(maps, truth):
    xs = np.array([0.0, W - 1, 0.0, W - 1])
    ys = np.array([0.0, 0.0, H - 1, H - 1])
    err = 0.0
    for m, t in zip(maps, truth):
        ax, ay = R._apply(m, xs, ys)
        bx, by = R._apply(t, xs, ys)
        err = max(err, float(np.max(np.hypot(ax - bx, ay - by))))
    return err


def test_handheld_roll_scale_and_shift_is_recovered_at_the_corners():
    tex = _texture()
    z = np.arange(0.0, 50.1, 10.0)
    # a hand that rolls (up to 0.6 deg), breathing of 0.4 % a frame and a drift of a few px
    angles = [0.0, 0.35, -0.2, 0.6, 0.1, -0.3]
    truth = [_similarity(1.0 + 0.004 * k, angles[k], 1.5 * k - 2.0, -0.8 * k + 1.0) for k in range(len(z))]
    ref = 2
    truth = [t @ np.linalg.inv(truth[ref]) for t in truth]  # reference frame: identity
    frames = [_frame(tex, t) for t in truth]
    geo = R.choose_model(ArrayStack(frames, z, ["Y"]), z_ref_um=z[ref], quiet=True)
    assert isinstance(geo, R.MatrixGeometry)
    assert geo.model == "similarity", geo.info()
    assert _corner_error_px(geo.maps, truth) < 0.1


def test_tilted_camera_takes_a_homography():
    tex = _texture(1)
    z = np.arange(0.0, 40.1, 10.0)
    truth = []
    for k in range(len(z)):
        m = _similarity(1.0 + 0.003 * k, 0.1 * k, 0.5 * k, 0.3 * k)
        m[2, :2] = np.array([4e-5, -3e-5]) * k  # perspective: corners move ~1-2 px per frame beyond affine
        truth.append(m / m[2, 2])
    frames = [_frame(tex, t) for t in truth]
    geo = R.choose_model(ArrayStack(frames, z, ["Y"]), z_ref_um=0.0, quiet=True)
    assert geo.model == "homography", geo.info()
    assert _corner_error_px(geo.maps, truth) < 0.1


def test_pure_breathing_and_shift_stays_scale_and_shift_unchanged():
    tex = _texture(2)
    z = np.arange(-40.0, 40.1, 10.0)
    truth = [_similarity(1.0 + 3e-4 * zz, 0.0, 0.02 * zz, -0.01 * zz) for zz in z]
    st = ArrayStack([_frame(tex, t) for t in truth], z, ["Y"])
    geo = R.choose_model(st, z_ref_um=0.0, quiet=True)
    plain = R.estimate_geometry(st, z_ref_um=0.0, quiet=True)
    assert type(geo) is type(plain) and not isinstance(geo, R.MatrixGeometry)
    assert geo.scale_rate_per_um == plain.scale_rate_per_um
    assert geo.shift_rate_px_per_um == plain.shift_rate_px_per_um
    assert geo.info()["model"].startswith("scale-shift")
    maps = [R.frame_map_matrix(geo, zz) for zz in z]
    assert _corner_error_px(maps, truth) < 0.1


def test_register_stack_holds_frames_warped_to_the_reference():
    tex = _texture(3)
    z = np.arange(0.0, 30.1, 10.0)
    truth = [_similarity(1.0, 0.5 * k, 2.0 * k, -1.0 * k) for k in range(len(z))]
    frames = [np.repeat(_frame(tex, t)[..., None], 3, axis=2) for t in truth]
    held, geo = R.register_stack(ArrayStack(frames, z, ["R", "G", "B"]), z_ref_um=0.0, quiet=True)
    assert geo.model == "similarity"
    ref = frames[0].astype(np.float64)
    inner = (slice(20, -20), slice(20, -20))
    for k in range(1, len(z)):
        got = np.asarray(held.read(k), dtype=np.float64)
        before = np.abs(frames[k].astype(np.float64) - ref)[inner].mean()
        after = np.abs(got - ref)[inner].mean()
        assert after < 0.05 * before
    with pytest.raises(ValueError):
        R.fit_pair(np.zeros((40, 40)), np.zeros((40, 40)), model="perspective")


@pytest.mark.parametrize("budget", [None, 0])  # in memory, and streamed from the temporary file
def test_held_frames_round_trip_in_memory_and_from_file(budget):
    from fieldcal.composite.source import HeldFrames

    rng = np.random.default_rng(4)
    frames = [rng.integers(0, 256, (30, 40, 3), dtype=np.uint8) for _ in range(3)]
    src = ArrayStack(frames, [0.0, 5.0, 10.0], ["R", "G", "B"])
    held = HeldFrames(src, [0, 2], np.uint16, scale=256.0, budget_bytes=budget)
    assert held.in_memory == (budget is None)
    for i in (0, 2):
        held.put(i, frames[i].astype(np.float32) + 0.25)
    got = held.read(2, roi=(5, 7, 20, 10))
    assert got.dtype == np.float32 and held.dtype == np.uint8 and len(held) == 3
    np.testing.assert_allclose(got, frames[2][7:17, 5:25] + 0.25, atol=1 / 512)
    np.testing.assert_array_equal(held.read(1), frames[1])  # not held: the source's
    strict = HeldFrames(src, [0], np.float32, strict=True, budget_bytes=budget)
    with pytest.raises(ValueError):
        strict.read(1)


@pytest.mark.parametrize("fit", [0, 1, 2, 3])
def test_held_frames_beyond_the_budget_go_to_the_file_the_others_stay_in_memory(fit):
    """As many whole frames as the budget holds stay in memory, the others (only they) go to the temporary file;
    every frame reads back as put, whole or by region, in any order of puts."""
    import os

    from fieldcal.composite.source import HeldFrames

    rng = np.random.default_rng(7)
    frames = [rng.integers(0, 256, (30, 40, 3), dtype=np.uint8) for _ in range(3)]
    src = ArrayStack(frames, [0.0, 5.0, 10.0], ["R", "G", "B"])
    frame_bytes = 30 * 40 * 3 * 2
    held = HeldFrames(src, [2, 0, 1], np.uint16, scale=256.0, budget_bytes=fit * frame_bytes + frame_bytes // 2)
    assert held.n_in_memory == fit and held.in_memory == (fit == 3)
    for i in (1, 2, 0):
        held.put(i, frames[i])
    assert (held._file is None) == (fit == 3)
    if held._file is not None:
        assert os.fstat(held._file.fileno()).st_size == (3 - fit) * frame_bytes  # only the frames beyond
    for i in range(3):
        np.testing.assert_array_equal(held.read(i), frames[i].astype(np.float32))
        np.testing.assert_array_equal(held.read(i, roi=(3, 4, 20, 10)), frames[i][4:14, 3:23].astype(np.float32))


def test_a_jpeg_stack_is_decoded_once_per_frame(tmp_path, monkeypatch):
    """JPEG frames decode whole for any region: compositing (registration, focus volume, blending) decodes each
    frame once, and the registered composite matches the same frames composited from memory."""
    import cv2

    from fieldcal.composite import composite_stack
    from fieldcal.formats import imageio
    from fieldcal.formats.importer import import_stack
    from fieldcal.formats.stack import Stack

    tex = _texture(5)
    files = []
    for k in range(4):
        g = _frame(tex, _similarity(1.0 + 0.002 * k, 0.0, 0.7 * k, -0.4 * k))
        img = np.clip(g * 255, 0, 255).astype(np.uint8)
        files.append(tmp_path / f"f{k}.jpg")
        cv2.imwrite(str(files[-1]), np.repeat(img[..., None], 3, axis=2), [cv2.IMWRITE_JPEG_QUALITY, 95])
    import_stack(files, tmp_path / "st", z_start_um=0.0, z_step_um=10.0, pixel_pitch_um=2.0)
    st = Stack.open(tmp_path / "st")
    calls = []
    real = imageio._read_jpeg
    monkeypatch.setattr(imageio, "_read_jpeg", lambda *a: calls.append(a[0]) or real(*a))
    res = composite_stack(st, None, quiet=True, depth="flat")
    assert sorted(calls) == sorted(set(calls)) and len(calls) == 4
    assert res.info["registration"]["model"].startswith("scale-shift")
    mem = ArrayStack([st.read(i) for i in range(4)], st.z_um, st.channels)
    ref = composite_stack(mem, None, quiet=True, depth="flat")
    assert np.abs(res.image.astype(int) - ref.image.astype(int)).max() <= 1


def test_model_check_on_a_coarser_level_of_larger_frames(monkeypatch):
    """640x480 frames: the model check runs on a half-size level (CHECK_SIDE_PX), the refit on the full planes."""
    monkeypatch.setitem(globals(), "W", 640)
    monkeypatch.setitem(globals(), "H", 480)
    test_handheld_roll_scale_and_shift_is_recovered_at_the_corners()


def test_large_frames_register_on_third_size_planes_within_a_tenth_of_a_px(monkeypatch):
    """1920 x 1440 frames register on planes a third of their size (REGISTRATION_MIN_SIDE_PX: 640 px long) and the
    hand's roll, breathing and drift still come back within 0.1 px at the corners (full-size px)."""
    assert R._factor(1920, 1440) == 3 and R._factor(1279, 900) == 1
    monkeypatch.setitem(globals(), "W", 1920)
    monkeypatch.setitem(globals(), "H", 1440)
    test_handheld_roll_scale_and_shift_is_recovered_at_the_corners()


REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-stacks" / "pcb-depthmap"


def _real_board_quarter(roll_scale: float, seed: int = 14):
    """The real board's 10 frames (grey, 1/4 size, 512 x 384) moved as a hand would: frame 0 kept, frames 1..
    rolled by up to 0.2 deg x ``roll_scale`` and shifted by up to 0.75 px x ``roll_scale`` (Lanczos). Returns
    the frames and each frame's roll (deg)."""
    import cv2
    files = sorted(REAL.glob("*.JPG"))
    grey = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0 for p in files]
    grey = [cv2.resize(g, (g.shape[1] // 4, g.shape[0] // 4), interpolation=cv2.INTER_AREA) for g in grey]
    h, w = grey[0].shape
    rng = np.random.default_rng(seed)
    out, rolls = [grey[0]], [0.0]
    for g in grey[1:]:
        a = rng.uniform(-0.2, 0.2) * roll_scale
        m = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), a, 1.0)
        m[:, 2] += rng.uniform(-0.75, 0.75, 2) * roll_scale
        out.append(cv2.warpAffine(g, m, (w, h), flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT_101))
        rolls.append(a)
    return out, np.array(rolls)


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/real-stacks not beside the checkout")
def test_a_hand_held_roll_on_a_real_3d_scene_is_found_despite_its_parallax():
    # The board's relief gives the two halves a small systematic difference in every pair, which the chains to
    # the reference add up (~1.6 px here); the hand's roll (~1.2 px at the outline) must still be taken, and the
    # rolls recovered: the maps take reference px to frame px, so their angles are minus the frames' rolls.
    frames, rolls = _real_board_quarter(1.0)
    geo = R.choose_model(ArrayStack(frames, np.arange(10) * 50.0, ["Y"]), z_ref_um=0.0, quiet=True)
    assert isinstance(geo, R.MatrixGeometry) and geo.model == "similarity", geo.info()
    est = np.array([np.degrees(np.arctan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1])) for m in geo.maps])
    assert np.max(np.abs(est + rolls)) < 0.02  # 0.02 deg: 0.1 px at the outline of 512 x 384


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/real-stacks not beside the checkout")
def test_the_real_3d_scene_on_its_rail_stays_scale_and_shift():
    # the same frames without the hand: the halves' parallax alone must not read as a roll
    frames, _ = _real_board_quarter(0.0)
    geo = R.choose_model(ArrayStack(frames, np.arange(10) * 50.0, ["Y"]), z_ref_um=0.0, quiet=True)
    assert not isinstance(geo, R.MatrixGeometry), geo.info()


@pytest.mark.parametrize("w, h", [(2600, 48), (8000, 100), (20000, 64), (4000, 300), (300, 4000), (2048, 1536),
                                  (1920, 1080), (6000, 4000), (1279, 900), (96, 64)])
def test_registration_planes_keep_both_sides_resolved(w, h):
    """Review finding: the factor looked at the long side only, so a 2600 x 48 strip registered on 12-row planes
    (1.55 px RMS against 0.39 px before) and 20000 x 64 on 2-row ones. A plane keeps at least
    REGISTRATION_MIN_SIDE_PX on the long side and REGISTRATION_MIN_SHORT_SIDE_PX on the short one (or the
    frame's own), and the factor is the coarsest that does."""
    f = R._factor(w, h)
    long_px, short_px = max(w, h) // f, min(w, h) // f
    assert long_px >= min(R.REGISTRATION_MIN_SIDE_PX, max(w, h))
    assert short_px >= min(R.REGISTRATION_MIN_SHORT_SIDE_PX, min(w, h))
    g = f + 1  # the next coarser factor breaks one of the two bounds
    assert (max(w, h) // g < R.REGISTRATION_MIN_SIDE_PX or min(w, h) // g < R.REGISTRATION_MIN_SHORT_SIDE_PX)


@pytest.mark.parametrize("n_ch", [1, 3, 4, 5])
def test_warp_frame_and_photometric_correction_treat_every_channel_alike(n_ch):
    """Frames of up to 4 channels warp and correct in one OpenCV call, more in several: each channel comes out as
    that channel warped alone (a 1-channel frame), and corrected as g v + o + b (1 - g) about the black level in
    fixed point, rounded."""
    import cv2

    from fieldcal.composite import photometric as P

    rng = np.random.default_rng(n_ch)
    img = (rng.random((H, W, n_ch)) * 65535).astype(np.uint16)
    m = np.array([[1.01, 0.02, -3.2], [-0.015, 0.995, 2.7], [0.0, 0.0, 1.0]])
    tilt = m.copy()
    tilt[2, :2] = (2e-5, -1e-5)
    for mat in (m, tilt):
        out = R.warp_frame(img, mat)
        assert out.shape == img.shape and out.dtype == img.dtype
        for c in range(n_ch):
            np.testing.assert_array_equal(out[..., c], R.warp_frame(img[..., c:c + 1], mat)[..., 0])
        if n_ch == 1:  # the 1-channel frame against OpenCV's own warp of the plane
            flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
            ref = (cv2.warpAffine(img[..., 0], mat[:2], (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
                   if mat is m else cv2.warpPerspective(img[..., 0], mat, (W, H), flags=flags,
                                                         borderMode=cv2.BORDER_REPLICATE))
            np.testing.assert_array_equal(out[..., 0], ref)
    gain, off = 1.0 + 0.03 * np.arange(n_ch), 5.0 - 2.0 * np.arange(n_ch)
    scale, black = 256.0, 16.0
    fixed = P.apply_correction(img, P.Correction(gain, off, 100), scale, black)
    want = np.clip(np.rint(img * gain + (off + black * (1 - gain)) * scale), 0, 65535)
    assert fixed.shape == img.shape and fixed.dtype == img.dtype
    assert np.max(np.abs(fixed.astype(np.float64) - want)) <= 1.0  # OpenCV's float32 arithmetic
