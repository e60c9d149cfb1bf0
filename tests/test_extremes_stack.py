"""Extremes of the stack reader/writer: NaN/Inf frames, black and saturated frames, every sample type, one-frame
and tiny stacks. Each case gives exact numbers (normalisation has a closed form) or a StackError that names
the file and the field; no numpy warning escapes (warnings are errors in this module)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldcal.errors import FieldcalError, StackError
from fieldcal.formats.stack import Stack, StackWriter

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

TOP = {np.uint8: 255.0, np.uint16: 65535.0, np.float32: 1.0}


def _stack_with_raw_frame(root, frame: np.ndarray):
    """A stack whose one frame file is written directly (StackWriter itself refuses NaN/Inf)."""
    (root / "frames").mkdir(parents=True)
    tifffile.imwrite(root / "frames" / "0000.tiff", frame)
    meta = {"format": "fieldcal-stack/1", "pixel_pitch_um": 3.45, "channels": ["Y"],
            "frames": [{"file": "frames/0000.tiff", "z_um": 0.0}]}
    (root / "stack.json").write_text(json.dumps(meta))
    return Stack.open(root)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_inf_float_frame_is_a_stack_error_naming_file_and_count(tmp_path, bad):
    frame = np.full((16, 16), 0.5, np.float32)
    frame[3, 4] = bad
    frame[7, 1] = bad
    stack = _stack_with_raw_frame(tmp_path / "s", frame)  # opening reads headers only: fine
    with pytest.raises(StackError) as e:
        stack.read(0)
    msg = str(e.value)
    assert "0000.tiff" in msg and "2 NaN/Inf" in msg and "fix:" in msg
    with pytest.raises(StackError):
        stack.read_normalized(0)
    with pytest.raises(StackError):
        list(stack.iter_frames())
    # an ROI that avoids the bad pixels reads fine: the check is on the pixels actually read
    assert np.all(stack.read(0, roi=(8, 8, 8, 8)) == np.float32(0.5))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_writer_refuses_nan_inf_and_leaves_no_frame(tmp_path, bad):
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"])
    img = np.zeros((16, 16), np.float32)
    img[0, 0] = bad
    with pytest.raises(StackError, match="NaN/Inf"):
        w.add_frame(img, 0.0)
    assert len(w) == 0 and list((tmp_path / "s" / "frames").iterdir()) == []
    assert json.loads((tmp_path / "s" / "stack.json").read_text())["frames"] == []


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("level", ["black", "saturated"])
def test_black_and_saturated_frames_normalise_to_exactly_0_and_1(tmp_path, dtype, level):
    top = TOP[dtype]
    value = 0 if level == "black" else top
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["R", "G", "B"])
    w.add_frame(np.full((16, 16, 3), value, dtype), -5.0)
    w.add_frame(np.full((16, 16, 3), value, dtype), 5.0)
    stack = w.stack()
    assert stack.dtype == np.dtype(dtype) and stack.white_level == top and stack.black_level == 0.0
    for i in range(2):
        n = stack.read_normalized(i)
        assert n.dtype == np.float32 and n.shape == (16, 16, 3)
        assert np.all(n == (0.0 if level == "black" else 1.0))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dtype=st.sampled_from([np.uint8, np.uint16, np.float32]),
       h=st.integers(1, 20), w=st.integers(1, 20), c=st.sampled_from([1, 3]),
       seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["tiff", "png"]))
def test_every_dtype_round_trips_bit_exact_and_normalises_in_0_1(tmp_path_factory, dtype, h, w, c, seed, kind):
    if kind == "png" and dtype == np.float32:
        kind = "tiff"  # PNG holds no floats (the writer refuses it, tested elsewhere)
    rng = np.random.default_rng(seed)
    top = TOP[dtype]
    img = (rng.random((h, w, c)) * top).astype(dtype) if dtype != np.float32 else rng.random((h, w, c)).astype(dtype)
    img.flat[-1] = 0  # the extremes are always present (white wins on a 1-pixel frame)
    img.flat[0] = top
    root = tmp_path_factory.mktemp("rt")
    wr = StackWriter.create(root / "s", pixel_pitch_um=1.0, channels=["Y"] if c == 1 else ["R", "G", "B"])
    wr.add_frame(img if c == 3 else img[:, :, 0], 1.5, kind=kind)
    stack = wr.stack()
    back = stack.read(0)
    assert back.dtype == np.dtype(dtype) and back.shape == (h, w, c)
    assert np.array_equal(back, img)
    n = stack.read_normalized(0)
    assert n.dtype == np.float32 and np.all(np.isfinite(n))
    np.testing.assert_allclose(n, img.astype(np.float64) / top, rtol=0, atol=1e-6)
    assert n.max() == pytest.approx(1.0, abs=1e-7)  # flat[0] = white
    if img.size > 1:
        assert n.min() == 0.0  # flat[-1] = black


def test_twelve_bit_data_with_black_level_normalise_by_the_declared_levels(tmp_path):
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"], bit_depth=12, black_level=64)
    img = np.array([[0, 64, 4095, 65535]], np.uint16)  # below black, black, white, beyond the ADC (corrupt)
    w.add_frame(img, 0.0)
    n = w.stack().read_normalized(0)[0, :, 0]
    np.testing.assert_allclose(n, (img[0].astype(np.float64) - 64) / (4095 - 64), rtol=1e-6)
    assert np.all(np.isfinite(n))


def test_one_frame_stack_opens_and_refuses_operations_needing_more(tmp_path):
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"])
    w.add_frame(np.zeros((16, 16), np.uint16), 0.0)
    stack = w.stack()
    assert len(stack) == 1 and stack.shape == (16, 16) and list(stack.order_by_z) == [0]
    stack.require_frames(1, "anything")
    with pytest.raises(StackError) as e:
        stack.require_frames(2, "calibration")
    assert "too few frames for calibration" in str(e.value) and str(tmp_path / "s") in str(e.value)


def test_empty_stack_is_refused_with_a_fix(tmp_path):
    StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"])
    with pytest.raises(StackError) as e:
        Stack.open(tmp_path / "s")
    assert "fix:" in str(e.value)


@pytest.mark.parametrize("shape", [(1, 1), (1, 16), (16, 1), (16, 16)])
def test_tiny_frames_read_with_rois(tmp_path, shape):
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"])
    img = np.arange(np.prod(shape), dtype=np.uint16).reshape(shape)
    w.add_frame(img, 0.0)
    w.add_frame(img[::-1, ::-1].copy(), 1.0)
    stack = w.stack()
    assert stack.shape == shape
    assert np.array_equal(stack.read(0)[:, :, 0], img)
    assert np.array_equal(stack.read(0, roi=(0, 0, 1, 1))[:, :, 0], img[:1, :1])
    with pytest.raises(FieldcalError):  # an ROI outside a tiny frame is a clear ParameterError
        stack.read(0, roi=(shape[1], 0, 1, 1))


def test_no_warnings_reading_extreme_float_values(tmp_path):
    """Largest finite float32 and subnormals are finite: read, normalise, no overflow warning."""
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=["Y"])
    img = np.array([[np.finfo(np.float32).max, np.finfo(np.float32).tiny / 4, -np.finfo(np.float32).max, 0.0]],
                   np.float32)
    w.add_frame(img, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        n = w.stack().read_normalized(0)
    assert np.all(np.isfinite(n)) and n[0, 0, 0] == np.finfo(np.float32).max
