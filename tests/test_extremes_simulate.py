"""Extremes of the simulator: tiny frames, black/saturated/NaN scenes, every output dtype, defocus far beyond
the scanned range, extreme focus breathing (exit pupil of a few mm), one- and two-frame stacks.

Numbers are checked against closed forms (levels, the geometry ``c + m (p - c)``); impossible requests end in a
ParameterError naming the field. RuntimeWarnings are errors here."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import FieldcalError, ParameterError
from fieldcal.simulate.lens import ChannelSpec, LensSpec, SensorSpec
from fieldcal.simulate import Renderer, simulate_stack

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def tiny_lens(w=48, h=32, pitch_um=4.0, curvature_um=-40.0, focus_offset_um=0.0, exit_pupil_mm=math.inf,
              bit_depth=12, black=0.0, read_noise_e=2.0, channels=("Y",)) -> LensSpec:
    hmax = 0.5 * math.hypot(w, h) * pitch_um / 1000.0
    return LensSpec(name="tiny", focal_length_mm=10.0, f_number=4.0, image_height_max_mm=hmax,
                    channels=tuple(ChannelSpec(c, 546.1, focus_offset_um, (curvature_um,)) for c in channels),
                    sensor=SensorSpec(w, h, pitch_um, bit_depth=bit_depth, black_level_dn=black,
                                      full_well_e=20000.0, read_noise_e=read_noise_e),
                    exit_pupil_mm=exit_pupil_mm)


def texture(h, w, seed=0):
    return np.random.default_rng(seed).random((h, w)).astype(np.float32)


def test_tiny_16x16_frames_render_in_range():
    spec = tiny_lens(16, 16)
    r = Renderer(spec, texture(16, 16))
    for z in (-60.0, -20.0, 0.0, 30.0):
        f = r.render(z)
        assert f.shape == (16, 16, 1) and f.dtype == np.uint16
        assert 0 <= f.min() and f.max() <= spec.sensor.white_level_dn
    # in focus keeps more contrast than 60 µm out (closed form: the OTF falls with defocus)
    assert r.render_float(0.0).std() > 1.5 * r.render_float(-60.0).std()


def test_black_scene_gives_the_black_level_plus_read_noise_only():
    spec = tiny_lens(black=64.0, read_noise_e=3.0)
    f = Renderer(spec, np.zeros((32, 48), np.float32)).render(0.0).astype(np.float64)
    gain = (spec.sensor.white_level_dn - 64.0) / spec.sensor.full_well_e
    assert abs(f.mean() - 64.0) < 0.5  # zero signal: mean is the black level
    assert f.std() == pytest.approx(3.0 * gain, abs=0.5)  # ~0.6 DN of read noise, rounded


def test_saturated_scene_is_metered_below_white_and_clips_exactly_at_white():
    spec = tiny_lens(bit_depth=8)
    r = Renderer(spec, np.ones((32, 48), np.float32))
    f = r.render(0.0)
    assert f.dtype == np.uint8 and f.max() <= 255
    assert np.mean(f == 255) < 0.01  # the metered exposure keeps a white scene below full well
    r.exposure = 4.0  # 4x over-exposed: every pixel clips at white, no wrap-around to 0
    f = r.render(0.0)
    assert np.all(f == 255)


@pytest.mark.parametrize("bit_depth,dtype,white", [(8, np.uint8, 255), (10, np.uint16, 1023),
                                                    (16, np.uint16, 65535), (32, np.float32, 1.0)])
def test_every_output_dtype_and_white_level(bit_depth, dtype, white):
    spec = tiny_lens(bit_depth=bit_depth)
    r = Renderer(spec, texture(32, 48))
    f = r.render(0.0)
    assert f.dtype == dtype and 0 <= f.min() and f.max() <= white
    # the noise-free frame is the linear signal scaled to white (quantised for integers)
    exact = r.render_float(0.0) * white
    tol = 0.5 + white * 2e-7 if dtype != np.float32 else 1e-6  # rounding + float32 resolution
    assert np.max(np.abs(r.render(0.0, noise=False).astype(np.float64) - exact)) <= tol


@pytest.mark.parametrize("scene", [np.nan, np.inf, -0.5, 1.5])
def test_invalid_scene_values_are_a_parameter_error(scene):
    img = texture(32, 48)
    img[3, 3] = scene
    with pytest.raises(ParameterError) as e:
        Renderer(tiny_lens(), img)
    assert e.value.field == "scene" and e.value.fix


def test_defocus_far_beyond_the_scan_is_flat_grey_then_a_clear_error():
    spec = tiny_lens(16, 16)
    r = Renderer(spec, texture(16, 16))
    # 2 mm defocus: a 125 px blur disc on a 16 px frame, within the renderer's limit -> nearly uniform
    far = r.render_float(2000.0)
    assert np.all(np.isfinite(far))
    assert far.std() < 0.02 * far.mean()
    with pytest.raises(ParameterError) as e:  # 1 m: the blur disc would be 62500 px (was a 43 GiB MemoryError)
        r.render(1e6)
    assert e.value.field == "z_um" and "µm" in e.value.fix


def _centroid_near(img, x, y, r=6):
    """Centroid of the image in a window around (x, y): m < 1 also shows mirrored copies of the scene
    (the renderer extends the scene by mirroring), so the window isolates the blob the geometry predicts."""
    y0, x0 = max(int(round(y)) - r, 0), max(int(round(x)) - r, 0)
    win = img[y0:int(round(y)) + r + 1, x0:int(round(x)) + r + 1]
    ys, xs = np.mgrid[y0:y0 + win.shape[0], x0:x0 + win.shape[1]]
    w = win - win.min()
    return float((w * xs).sum() / w.sum()), float((w * ys).sum() / w.sum()), float(win.max())


@pytest.mark.parametrize("exit_pupil_mm,z_um", [(2.0, -1000.0), (2.0, 1000.0), (-3.0, 1500.0)])
def test_extreme_focus_breathing_puts_a_blob_where_m_z_says(exit_pupil_mm, z_um):
    """Exit pupil of a few mm: m(z) = 1 + dz / exit pupil from 0.5 to 1.5; geometry p' = c + m (p - c)."""
    w, h = 64, 48
    spec = tiny_lens(w, h, curvature_um=0.0, focus_offset_um=z_um, exit_pupil_mm=exit_pupil_mm)
    ys, xs = np.mgrid[0:h, 0:w]
    px, py = 40.0, 30.0
    scene = (0.8 * np.exp(-((xs - px) ** 2 + (ys - py) ** 2) / (2 * 2.0 ** 2))).astype(np.float32)
    r = Renderer(spec, scene)
    img = r.render_float(z_um)[:, :, 0]
    m = 1.0 + z_um / (exit_pupil_mm * 1000.0)
    cx, cy = spec.optical_centre_px()
    ex, ey = cx + m * (px - cx), cy + m * (py - cy)
    gx, gy, peak = _centroid_near(img, ex, ey)
    assert peak > 0.9 * img.max()  # the blob is there ...
    assert math.hypot(gx - ex, gy - ey) < 0.3  # ... centred where m(z) puts it
    assert np.all(np.isfinite(img))


@pytest.mark.parametrize("exit_pupil_mm,z_um", [(1.0, -1000.0), (1.0, -1500.0), (-1.0, 1000.0)])
def test_sensor_at_or_beyond_the_exit_pupil_is_a_clear_error(exit_pupil_mm, z_um):
    r = Renderer(tiny_lens(exit_pupil_mm=exit_pupil_mm), texture(32, 48))
    with pytest.raises(ParameterError) as e:  # m(z) <= 0: was a division by zero / a mirrored frame
        r.render(z_um)
    assert e.value.field == "z_um" and "exit pupil" in str(e.value)


@settings(max_examples=20, deadline=None)
@given(z_um=st.floats(-3000, 3000, allow_nan=False),
       exit_pupil_mm=st.sampled_from([math.inf, 2.0, -2.0, 5.0, -40.0, 0.5]),
       bit_depth=st.sampled_from([8, 12, 16, 32]))
def test_any_stage_position_renders_in_range_or_fails_cleanly(z_um, exit_pupil_mm, bit_depth):
    spec = tiny_lens(24, 16, exit_pupil_mm=exit_pupil_mm, bit_depth=bit_depth)
    r = Renderer(spec, texture(16, 24, seed=3))
    m = float(spec.magnification(z_um))
    try:
        f = r.render(z_um)
    except ParameterError as e:  # only the two documented limits (the blur includes the field curvature at
        assert e.field == "z_um"  # the magnified positions, so a large m can reach the blur limit too)
        assert ("exit pupil" in str(e) and m <= 0) or ("blurs a point" in str(e) and m > 0)
        return
    assert m > 0
    white = spec.sensor.white_level_dn
    assert f.shape == (16, 24, 1) and np.all(np.isfinite(f)) and f.min() >= 0 and f.max() <= white


@pytest.mark.parametrize("z", [[0.0], [-10.0, 10.0]])
def test_one_and_two_frame_stacks_are_written_with_truth(tmp_path, z):
    stack = simulate_stack(tiny_lens(16, 16), tmp_path / "s", z, seed=1, progress=False)
    assert len(stack) == len(z) and sorted(stack.z_um) == sorted(z)
    for i in range(len(z)):
        assert np.all(np.isfinite(stack.read_normalized(i)))
    assert (tmp_path / "s" / "truth.tiff").is_file()


def test_impossible_stack_requests_leave_nothing_behind(tmp_path):
    for bad in ([], [0.0, 0.0], [np.nan]):
        with pytest.raises(FieldcalError):
            simulate_stack(tiny_lens(16, 16), tmp_path / "s", bad, progress=False)
    with pytest.raises(FieldcalError):  # fails on the frame at 1 m, after writing the first
        simulate_stack(tiny_lens(16, 16), tmp_path / "s", [0.0, 1e6], progress=False)
    assert not (tmp_path / "s").exists()
    assert [p.name for p in tmp_path.iterdir()] == []
