"""Composite outputs a photographer can open: TIFF, PNG and JPEG by extension, metadata kept."""

from __future__ import annotations

import numpy as np
import pytest

from fieldcal.composite.io import read_composite_metadata, write_composite
from fieldcal.errors import FieldcalError
from fieldcal.formats.imageio import read_image


@pytest.fixture
def image12():
    return (np.random.default_rng(0).random((24, 32, 3)) * 4000 + 64).astype(np.uint16)


def test_tiff_keeps_dtype_and_values(tmp_path, image12):
    p = write_composite(tmp_path / "a.tiff", image12, ["R", "G", "B"], {"method": "dff"}, black_level=64,
                        white_level=4095)
    assert np.array_equal(read_image(p), image12)
    assert read_composite_metadata(p)["method"] == "dff"


def test_png_is_16_bit_scaled_from_the_stack_levels(tmp_path, image12):
    p = write_composite(tmp_path / "a.png", image12, ["R", "G", "B"], {"method": "profile"}, black_level=64,
                        white_level=4095)
    back = read_image(p)
    assert back.dtype == np.uint16
    expected = np.clip(np.rint((image12 - 64.0) * 65535 / (4095 - 64)), 0, 65535)
    assert np.array_equal(back, expected.astype(np.uint16))
    assert read_composite_metadata(p) == {"format": "fieldcal-composite/1", "channels": ["R", "G", "B"],
                                          "method": "profile"}


def test_uint8_png_stays_8_bit_and_exact(tmp_path):
    img = np.random.default_rng(1).integers(0, 256, size=(16, 20, 3), dtype=np.uint8)
    p = write_composite(tmp_path / "a.png", img, ["R", "G", "B"], {})
    back = read_image(p)
    assert back.dtype == np.uint8 and np.array_equal(back, img)


def test_jpeg_is_8_bit_close_and_copies_exif(tmp_path):
    from PIL import Image

    smooth = np.linspace(0, 1, 64 * 48 * 3).reshape(48, 64, 3)
    img = (smooth * 4095).astype(np.uint16)
    src = tmp_path / "frame.jpg"
    exif = Image.Exif()
    exif[0x0110] = "Cam Z"  # Model
    Image.fromarray((smooth * 255).astype(np.uint8)).save(src, exif=exif)
    p = write_composite(tmp_path / "out.jpg", img, ["R", "G", "B"], {"method": "dff"}, white_level=4095,
                        exif_from=src)
    back = read_image(p).astype(np.float64) / 255
    assert back.shape == img.shape and np.abs(back - smooth).mean() < 0.01
    with Image.open(p) as im:
        assert im.getexif().get(0x0110) == "Cam Z"
    assert read_composite_metadata(p)["method"] == "dff"


def test_unknown_extension_and_odd_channels_are_refused(tmp_path, image12):
    with pytest.raises(FieldcalError, match=r"\.tiff, \.png or \.jpg"):
        write_composite(tmp_path / "a.bmp", image12, ["R", "G", "B"], {})
    with pytest.raises(FieldcalError, match="write this composite as .tiff"):
        write_composite(tmp_path / "a.png", image12[..., :2], ["X", "Y2"], {})
    assert list(tmp_path.iterdir()) == []
