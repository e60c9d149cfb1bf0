"""fieldcal-stack/1 reader and writer: round trips, foreign stacks, every malformed case, laziness, atomicity."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fieldcal
import fieldcal.formats.stack as stack_mod
from fieldcal.errors import FieldcalError, ParameterError, StackError
from fieldcal.formats.stack import FORMAT, Stack, StackWriter

H, W = 24, 32


def random_image(rng, dtype, channels, shape=(H, W)):
    shp = shape if channels == 1 else (*shape, channels)
    if dtype == np.float32:
        return rng.random(shp, dtype=np.float32)
    return rng.integers(0, np.iinfo(dtype).max + 1, shp, endpoint=False).astype(dtype)


def write_foreign(root: Path, frames: list[tuple[str, np.ndarray, float]], **meta) -> Path:
    """A stack written 'by another program': tifffile / cv2 and json directly, no fieldcal code."""
    root.mkdir(parents=True, exist_ok=True)
    entries = []
    for name, image, z in frames:
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if name.endswith(".png"):
            bgr = image[..., ::-1] if image.ndim == 3 else image  # OpenCV writes BGR
            assert cv2.imwrite(str(p), np.ascontiguousarray(bgr))
        else:
            tifffile.imwrite(p, image, photometric="rgb" if image.ndim == 3 and image.shape[2] == 3 else None)
        entries.append({"file": name, "z_um": z})
    doc = {"format": FORMAT, "pixel_pitch_um": 3.45, "channels": ["R", "G", "B"], "frames": entries}
    doc.update(meta)
    (root / "stack.json").write_text(json.dumps(doc))
    return root


def rgb_stack(tmp_path, n=3, dtype=np.uint16, **meta):
    rng = np.random.default_rng(1)
    frames = [(f"frames/{k:04d}.tiff", random_image(rng, dtype, 3), float(10 * k)) for k in range(n)]
    return write_foreign(tmp_path / "s", frames, **meta), frames


def edit_json(root: Path, fn) -> Path:
    doc = json.loads((root / "stack.json").read_text())
    fn(doc)
    (root / "stack.json").write_text(json.dumps(doc))
    return root


def expect_error(root, *needles, call=None):
    """Stack.open (or ``call``) raises StackError whose message holds every needle (file, field, ...)."""
    with pytest.raises(StackError) as ei:
        (call or (lambda: Stack.open(root)))()
    msg = str(ei.value)
    for needle in needles:
        assert str(needle) in msg, f"{needle!r} not in message:\n{msg}"
    assert "fix:" in msg
    return ei.value


# --------------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("kind", ["tiff", "png"])
@pytest.mark.parametrize("channels", [["Y"], ["R", "G", "B"]])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_round_trip(tmp_path, kind, channels, dtype):
    if kind == "png" and dtype == np.float32:
        w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.0, channels=channels)
        expect_error(None, "PNG", "float32", "frames[0].file",
                     call=lambda: w.add_frame(random_image(np.random.default_rng(0), dtype, len(channels)), 0.0,
                                              kind="png"))
        assert not list((tmp_path / "s" / "frames").iterdir())  # nothing half-written
        return
    rng = np.random.default_rng(7)
    zs = [30.0, -12.5, 4.0]
    images = [random_image(rng, dtype, len(channels)) for _ in zs]
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=2.2, channels=channels, f_number=4.0)
    for img, z in zip(images, zs):
        w.add_frame(img, z, kind=kind, exposure_ms=12.5)
    s = Stack.open(tmp_path / "s")
    assert len(s) == 3 and s.shape == (H, W) and s.dtype == np.dtype(dtype)
    assert s.channels == tuple(channels) and s.pixel_pitch_um == 2.2 and s.cfa is None
    np.testing.assert_array_equal(s.z_um, zs)
    np.testing.assert_array_equal(s.order_by_z, [1, 2, 0])
    for k, img in enumerate(images):
        got = s.read(k)
        assert got.dtype == np.dtype(dtype) and got.shape == (H, W, len(channels))  # always 3-D
        np.testing.assert_array_equal(got, img.reshape(H, W, len(channels)))
        roi = s.read(k, roi=(3, 5, 8, 6))
        np.testing.assert_array_equal(roi, got[5:11, 3:11])
        assert s.frames[k].exposure_ms == 12.5 and s.frames[k].file.endswith("." + kind)
    assert s.verify_checksums() == []
    if kind == "png" and len(channels) == 3:  # other programs (OpenCV) see the colours the right way round
        bgr = cv2.imread(str(s.frames[0].path), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(bgr[..., ::-1], images[0])
    if kind == "tiff":
        np.testing.assert_array_equal(tifffile.imread(s.frames[0].path).reshape(images[0].shape), images[0])


def test_foreign_stack_reads_with_rgb_order_and_any_layout(tmp_path):
    rng = np.random.default_rng(3)
    img = np.zeros((H, W, 3), np.uint16)
    img[..., 0] = 1000  # R
    img[..., 1] = 2000  # G
    img[..., 2] = 3000  # B
    planar = random_image(rng, np.uint16, 3)
    compressed = random_image(rng, np.uint16, 3)
    root = write_foreign(tmp_path / "s", [("a/x.png", img, 5.0), ("frames/b.tif", img, -5.0)])
    tifffile.imwrite(root / "planar.tif", np.moveaxis(planar, -1, 0), photometric="rgb", planarconfig="separate")
    tifffile.imwrite(root / "zip.tiff", compressed, compression="zlib")
    tifffile.imwrite(root / "big.tiff", compressed, byteorder=">")
    edit_json(root, lambda d: d["frames"].extend([{"file": "planar.tif", "z_um": 1},
                                                   {"file": "zip.tiff", "z_um": 2, "extra": [1, 2]},
                                                   {"file": "big.tiff", "z_um": 3}]))
    s = Stack.open(root)
    for k in (0, 1):
        got = s.read(k)
        assert tuple(got[0, 0]) == (1000, 2000, 3000), "channel order must be R, G, B"
    np.testing.assert_array_equal(s.read(2), planar)
    np.testing.assert_array_equal(s.read(3), compressed)
    np.testing.assert_array_equal(s.read(3, roi=(slice(2, 9), slice(4, 20))), compressed[2:9, 4:20])
    big = s.read(4)
    assert big.dtype == np.dtype("=u2") and big.dtype.isnative
    np.testing.assert_array_equal(big, compressed)
    np.testing.assert_array_equal(s.read(4, roi=(1, 2, 3, 4)), compressed[2:6, 1:4])
    assert s.frames[3].meta["extra"] == [1, 2]
    assert [s.frames[k].z_um for k in s.order_by_z] == [-5.0, 1.0, 2.0, 3.0, 5.0]


def test_stack_json_path_and_public_api(tmp_path):
    root, _ = rgb_stack(tmp_path)
    assert fieldcal.Stack is Stack and fieldcal.StackWriter is StackWriter
    assert len(Stack.open(root / "stack.json")) == 3


def test_unknown_and_optional_keys_round_trip_through_writer(tmp_path):
    root, frames = rgb_stack(tmp_path, n=2, bit_depth=12, lens={"name": "triplet"}, chart="texture",
                             object_distance_mm=None, vendor_x={"gain": 2})
    edit_json(root, lambda d: d["frames"][0].update(time="2024-05-01T10:00:00", z_measured_um=0.3, note="a"))
    w = StackWriter.open_existing(root)
    img = frames[0][1]
    info = w.add_frame(img, 99.0, time=12.5, vendor_y="b")
    assert info.index == 2 and info.file == "frames/0002.tiff"
    s = Stack.open(root)
    assert s.meta["vendor_x"] == {"gain": 2} and s.meta["lens"] == {"name": "triplet"} and s.bit_depth == 12
    assert s.frames[0].meta["note"] == "a" and s.frames[0].z_measured_um == 0.3
    assert s.frames[2].meta["vendor_y"] == "b" and s.frames[2].meta["time"] == 12.5
    np.testing.assert_array_equal(s.read(2), img)


# --------------------------------------------------------------------------------------------- levels


@pytest.mark.parametrize("dtype,meta,black,white", [
    (np.uint8, {}, 0, 255),
    (np.uint16, {}, 0, 65535),
    (np.uint16, {"bit_depth": 12}, 0, 4095),
    (np.uint16, {"bit_depth": 12, "white_level": 4000, "black_level": 64}, 64, 4000),
    (np.float32, {}, 0, 1.0),
    (np.float32, {"black_level": 0.1}, 0.1, 1.0),
])
def test_levels_and_read_normalized(tmp_path, dtype, meta, black, white):
    root, frames = rgb_stack(tmp_path, n=1, dtype=dtype, **meta)
    s = Stack.open(root)
    assert (s.black_level, s.white_level) == (black, white)
    norm = s.read_normalized(0)
    assert norm.dtype == np.float32
    expected = (frames[0][1].astype(np.float64) - black) / (white - black)
    np.testing.assert_allclose(norm, expected, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("meta,field", [
    ({"bit_depth": 10}, "bit_depth"),          # 10 bits in uint8 frames
    ({"white_level": 300}, "white_level"),     # above uint8 max
    ({"black_level": 200, "white_level": 100}, "white_level"),
    ({"black_level": 255}, "black_level"),     # black == white
    ({"bit_depth": 0}, "bit_depth"),
    ({"white_level": "max"}, "white_level"),
])
def test_bad_levels(tmp_path, meta, field):
    root, _ = rgb_stack(tmp_path, n=1, dtype=np.uint8, **meta)
    expect_error(root, "stack.json", f"'{field}'")


# --------------------------------------------------------------------------------------------- CFA


def test_cfa_stack_reads_mosaic(tmp_path):
    rng = np.random.default_rng(5)
    mosaic = random_image(rng, np.uint16, 1)
    root = tmp_path / "s"
    w = StackWriter.create(root, pixel_pitch_um=1.5, channels=["R", "G", "B"], cfa="RGGB", bit_depth=12)
    w.add_frame(mosaic, 0.0)
    s = Stack.open(root)
    assert s.cfa == "RGGB" and s.read(0).shape == (H, W)
    np.testing.assert_array_equal(s.read(0, roi=(2, 4, 6, 8)), mosaic[4:12, 2:8])
    with pytest.raises(ParameterError, match="even"):
        s.read(0, roi=(1, 0, 4, 4))
    with pytest.raises(StackError, match="mosaic"):
        w.add_frame(random_image(rng, np.uint16, 3), 1.0)


@pytest.mark.parametrize("cfa,channels,needle", [("RGBG", ["R", "G", "B"], "'cfa'"), ("RGGB", ["Y"], "'channels'")])
def test_bad_cfa_key(tmp_path, cfa, channels, needle):
    root = write_foreign(tmp_path / "s", [("f.tiff", np.zeros((H, W), np.uint16), 0.0)], cfa=cfa, channels=channels)
    expect_error(root, "stack.json", needle)


def test_cfa_with_three_channel_image(tmp_path):
    root, _ = rgb_stack(tmp_path, n=1, cfa="BGGR")
    expect_error(root, "0000.tiff", "'frames[0].file'", "Bayer")


# --------------------------------------------------------------------------------------------- malformed stacks


def test_missing_folder_and_stack_json(tmp_path):
    expect_error(tmp_path / "nope", "nope", "does not exist")
    (tmp_path / "empty").mkdir()
    expect_error(tmp_path / "empty", "stack.json", "not found")


@pytest.mark.parametrize("text,needle", [("{not json", "not valid JSON"), ("[1, 2]", "JSON object"),
                                         (b"\xff\xfe{}", "UTF-8")])
def test_stack_json_not_json_or_not_object(tmp_path, text, needle):
    root = tmp_path / "s"
    root.mkdir()
    (root / "stack.json").write_bytes(text if isinstance(text, bytes) else text.encode())
    expect_error(root, "stack.json", needle)


@pytest.mark.parametrize("value,needle", [(None, "is missing"), ("fieldcal-stack/2", "fieldcal-stack/2"),
                                          ("fieldcal-profile/1", "reads only")])
def test_format_version(tmp_path, value, needle):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d.pop("format") if value is None else d.update(format=value))
    expect_error(root, "stack.json", "'format'", needle)


@pytest.mark.parametrize("key", ["pixel_pitch_um", "channels", "frames"])
def test_missing_required_key(tmp_path, key):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d.pop(key))
    expect_error(root, "stack.json", f"'{key}'", "missing")


@pytest.mark.parametrize("pitch", [0, -3.45, float("nan"), float("inf"), "3.45", True, None])
def test_bad_pixel_pitch(tmp_path, pitch):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d.update(pixel_pitch_um=pitch))
    expect_error(root, "stack.json", "'pixel_pitch_um'")


@pytest.mark.parametrize("channels", ["RGB", [], ["R", "G", "G"], ["R", 1, "B"], ["R", "", "B"], None])
def test_bad_channels(tmp_path, channels):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d.update(channels=channels))
    # the field is named down to the bad item (channels[1]) when one item is wrong
    expect_error(root, "stack.json", "'channels" if isinstance(channels, list) else "'channels'")


def test_empty_frames_list_and_frames_not_list(tmp_path):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d.update(frames=[]))
    expect_error(root, "stack.json", "'frames'", "no frames")
    edit_json(root, lambda d: d.update(frames={"a": 1}))
    expect_error(root, "stack.json", "'frames'", "list")


@pytest.mark.parametrize("entry,field", [({"z_um": 1.0}, "frames[1].file"), ({"file": "x.tiff"}, "frames[1].z_um"),
                                         ("frames/0001.tiff", "frames[1]"),
                                         ({"file": "", "z_um": 1.0}, "frames[1].file"),
                                         ({"file": "frames/0001.tiff", "z_um": 1, "sha256": "abc"},
                                          "frames[1].sha256"),
                                         ({"file": "frames/0001.tiff", "z_um": 1, "exposure_ms": -1},
                                          "frames[1].exposure_ms")])
def test_bad_frame_entry(tmp_path, entry, field):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d["frames"].__setitem__(1, entry))
    expect_error(root, "stack.json", f"'{field}'")


@pytest.mark.parametrize("z", [float("nan"), float("inf"), float("-inf"), "1.0", None])
def test_non_finite_z(tmp_path, z):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d["frames"][2].update(z_um=z))
    expect_error(root, "stack.json", "'frames[2].z_um'", "finite")


def test_duplicate_z_names_both_frames(tmp_path):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d["frames"][2].update(z_um=0.0))
    expect_error(root, "stack.json", "'frames[2].z_um'", "frames[0] (frames/0000.tiff)", "frames[2] (frames/0002.tiff)")


def test_two_entries_one_file(tmp_path):
    root, _ = rgb_stack(tmp_path)
    edit_json(root, lambda d: d["frames"][2].update(file="./frames/0000.tiff"))
    expect_error(root, "stack.json", "'frames[2].file'", "frames[0]")


@pytest.mark.parametrize("file", ["../outside.tiff", "frames/../../outside.tiff", "/etc/passwd"])
def test_frame_path_escaping_folder(tmp_path, file):
    root, frames = rgb_stack(tmp_path)
    tifffile.imwrite(tmp_path / "outside.tiff", frames[0][1])
    edit_json(root, lambda d: d["frames"][1].update(file=file))
    expect_error(root, "stack.json", "'frames[1].file'", "outside the stack folder")


def test_symlink_escaping_folder(tmp_path):
    root, frames = rgb_stack(tmp_path)
    tifffile.imwrite(tmp_path / "outside.tiff", frames[0][1])
    (root / "frames" / "link.tiff").symlink_to(tmp_path / "outside.tiff")
    edit_json(root, lambda d: d["frames"][1].update(file="frames/link.tiff"))
    expect_error(root, "'frames[1].file'", "outside the stack folder")


def test_missing_frame_file(tmp_path):
    root, _ = rgb_stack(tmp_path)
    (root / "frames" / "0001.tiff").unlink()
    expect_error(root, "stack.json", "'frames[1].file'", "0001.tiff", "does not exist")


@pytest.mark.parametrize("content,needle", [(b"hello, not an image", "not a TIFF, PNG or JPEG"),
                                            (b"II*\x00\xff\xff\xff\x7f", "TIFF header"),
                                            (b"\x89PNG\r\n\x1a\n\x00\x00", "PNG header")])
def test_corrupt_frame_header(tmp_path, content, needle):
    root, _ = rgb_stack(tmp_path)
    (root / "frames" / "0001.tiff").write_bytes(content)
    expect_error(root, "0001.tiff", "'frames[1].file'", needle)


@pytest.mark.parametrize("kind", ["tiff", "png"])
def test_truncated_pixels_fail_at_read_not_open(tmp_path, kind):
    rng = np.random.default_rng(2)
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["R", "G", "B"])
    images = [random_image(rng, np.uint8, 3) for _ in range(3)]
    infos = [w.add_frame(img, float(k), kind=kind) for k, img in enumerate(images)]
    data = infos[1].path.read_bytes()
    infos[1].path.write_bytes(data[: len(data) // 2])  # header intact, pixels cut
    if kind == "tiff":  # the header check of an uncompressed TIFF sees the data end early, at open
        expect_error(None, infos[1].file, "'frames[1].file'", "truncated",
                     call=lambda: Stack.open(tmp_path / "s", verify=False))
        return
    with pytest.raises(StackError, match="sha256 differs"):  # the recorded checksum sees it at open ...
        Stack.open(tmp_path / "s")
    s = Stack.open(tmp_path / "s", verify=False)  # header-only validation cannot see a cut PNG ...
    np.testing.assert_array_equal(s.read(2), images[2])  # ... other frames still read ...
    expect_error(None, infos[1].file, "'frames[1].file'", call=lambda: s.read(1))  # ... and this one names itself
    assert [f.index for f in s.verify_checksums()] == [1]


@pytest.mark.parametrize("dtype", [np.int16, np.float64, np.uint32])
def test_unsupported_dtype(tmp_path, dtype):
    root, frames = rgb_stack(tmp_path)
    tifffile.imwrite(root / "frames" / "0001.tiff", frames[1][1].astype(dtype), photometric="rgb")
    expect_error(root, "0001.tiff", "'frames[1].file'", "unsupported sample type")


def test_mixed_sizes_and_dtypes(tmp_path):
    root, frames = rgb_stack(tmp_path)
    tifffile.imwrite(root / "frames" / "0002.tiff", frames[2][1][:-2])
    expect_error(root, "0002.tiff", "'frames[2].file'", f"{W}x{H - 2}", "frames[0]")
    tifffile.imwrite(root / "frames" / "0002.tiff", (frames[2][1] >> 8).astype(np.uint8))
    expect_error(root, "0002.tiff", "'frames[2].file'", "uint8", "uint16")


@pytest.mark.parametrize("channels,image_channels", [(["R", "G", "B"], 1), (["Y"], 3), (["R", "G", "B"], 4)])
def test_channel_count_mismatch(tmp_path, channels, image_channels):
    rng = np.random.default_rng(0)
    img = random_image(rng, np.uint8, image_channels)
    root = write_foreign(tmp_path / "s", [("f.tiff", img, 0.0)], channels=channels)
    expect_error(root, "f.tiff", "'frames[0].file'", "channel")


def test_multi_image_tiff_refused(tmp_path):
    root, frames = rgb_stack(tmp_path)
    tifffile.imwrite(root / "frames" / "0001.tiff", np.stack([frames[1][1]] * 2))
    expect_error(root, "0001.tiff", "'frames[1].file'", "one 2-D image")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_pixels_detected_at_read(tmp_path, bad):
    rng = np.random.default_rng(0)
    good = random_image(rng, np.float32, 3)
    poisoned = good.copy()
    poisoned[3, 4, 1] = bad
    root = write_foreign(tmp_path / "s", [("a.tiff", good, 0.0), ("b.tiff", poisoned, 1.0)])
    s = Stack.open(root)
    s.read(0)
    expect_error(None, "b.tiff", "'frames[1].file'", "NaN/Inf", "z_um=1", call=lambda: s.read(1))
    expect_error(None, "b.tiff", call=lambda: list(s.iter_frames()))


def test_require_frames(tmp_path):
    root, _ = rgb_stack(tmp_path, n=2)
    s = Stack.open(root)
    s.require_frames(2, "calibration")
    expect_error(None, "stack.json", "'frames'", "too few frames for calibration", "at least 5", "has 2",
                 call=lambda: s.require_frames(5, "calibration"))


def test_bad_index_and_roi(tmp_path):
    root, _ = rgb_stack(tmp_path)
    s = Stack.open(root)
    for bad in (3, -4, 1.0, True):
        with pytest.raises(ParameterError, match="index"):
            s.read(bad)
    for roi in ((0, 0, W + 1, 4), (-1, 0, 4, 4), (0, 0, 0, 4), (1, 2, 3), (slice(5, 2), slice(0, 4)),
                (slice(0, 8, 2), slice(0, 4))):
        with pytest.raises(ParameterError) as ei:
            s.read(0, roi=roi)
        assert "'roi'" in str(ei.value)
    assert s.read(-1).shape == (H, W, 3)


# --------------------------------------------------------------------------------------------- laziness


def test_open_decodes_nothing_and_read_decodes_only_its_frame(tmp_path, monkeypatch):
    root, frames = rgb_stack(tmp_path, n=4)
    calls = []
    real = stack_mod.read_image

    def counting(path, roi=None, header=None):
        calls.append(Path(path).name)
        return real(path, roi, header)

    monkeypatch.setattr(stack_mod, "read_image", counting)
    s = Stack.open(root)
    assert calls == []
    for f in ("0000.tiff", "0001.tiff", "0003.tiff"):
        (root / "frames" / f).unlink()  # reading frame 2 must not need any other frame
    np.testing.assert_array_equal(s.read(2, roi=(0, 0, 8, 8)), frames[2][1][:8, :8])
    np.testing.assert_array_equal(s.read(2), frames[2][1])
    assert calls == ["0002.tiff", "0002.tiff"]
    expect_error(None, "0001.tiff", "disappeared", call=lambda: s.read(1))


def test_iter_frames_streams_in_z_order(tmp_path, monkeypatch):
    rng = np.random.default_rng(4)
    zs = [3.0, -1.0, 2.0, 0.5]
    root = write_foreign(tmp_path / "s", [(f"{k}.tiff", random_image(rng, np.uint8, 3), z) for k, z in enumerate(zs)])
    s = Stack.open(root)
    calls = []
    real = stack_mod.read_image
    monkeypatch.setattr(stack_mod, "read_image", lambda p, r=None, h=None: calls.append(Path(p).name) or real(p, r, h))
    it = s.iter_frames(order="z", normalized=True)
    info, arr = next(it)
    assert info.z_um == -1.0 and arr.dtype == np.float32 and calls == ["1.tiff"]  # one frame at a time
    assert [i.z_um for i, _ in it] == [0.5, 2.0, 3.0]
    assert [i.index for i, _ in s.iter_frames(order="file")] == [0, 1, 2, 3]
    with pytest.raises(ParameterError):
        s.iter_frames(order="random")  # checked when called, not at the first frame
    with pytest.raises(ParameterError):
        s.iter_frames(roi=(0, 0, 999, 4))


# --------------------------------------------------------------------------------------------- writer


def test_writer_refuses_non_empty_folder_unless_overwrite(tmp_path):
    root, _ = rgb_stack(tmp_path)
    expect_error(None, str(root), "not empty", "overwrite=True",
                 call=lambda: StackWriter.create(root, pixel_pitch_um=1.0, channels=["Y"]))
    assert len(Stack.open(root)) == 3  # untouched
    w = StackWriter.create(root, pixel_pitch_um=1.0, channels=["Y"], overwrite=True)
    w.add_frame(np.zeros((4, 5), np.uint8), 0.0)
    s = Stack.open(root)
    assert len(s) == 1 and s.channels == ("Y",) and not (root / "frames" / "0002.tiff").exists()
    other = tmp_path / "docs"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    expect_error(None, "docs", "not a stack",
                 call=lambda: StackWriter.create(other, pixel_pitch_um=1.0, channels=["Y"], overwrite=True))
    assert (other / "thesis.tex").read_text() == "precious"


def test_writer_validates_header_before_touching_disk(tmp_path):
    root = tmp_path / "s"
    for kwargs, field in [(dict(pixel_pitch_um=-1, channels=["Y"]), "pixel_pitch_um"),
                          (dict(pixel_pitch_um=1, channels=["Y", "Y"]), "channels"),
                          (dict(pixel_pitch_um=1, channels=["Y"], bit_depth=99), "bit_depth"),
                          (dict(pixel_pitch_um=1, channels=["Y"], lens=object()), None)]:
        with pytest.raises(StackError) as ei:
            StackWriter.create(root, **kwargs)
        assert "stack.json" in str(ei.value) and (field is None or f"'{field}'" in str(ei.value))
        assert not root.exists()


def test_add_frame_validation(tmp_path):
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["R", "G", "B"])
    rng = np.random.default_rng(0)
    w.add_frame(random_image(rng, np.uint16, 3), 0.0)
    cases = [(random_image(rng, np.uint16, 3, shape=(H, W + 2)), 1.0, "same size"),
             (random_image(rng, np.uint8, 3), 1.0, "same size and dtype"),
             (random_image(rng, np.uint16, 1), 1.0, "channel"),
             (random_image(rng, np.uint16, 3), 0.0, "already used by frames[0]"),
             (random_image(rng, np.uint16, 3), float("nan"), "finite"),
             (rng.random((H, W, 3)), 1.0, "float64"),
             (random_image(rng, np.uint16, 3)[None], 1.0, "H x W")]
    for image, z, needle in cases:
        expect_error(None, "stack.json", "'frames[1]", needle, call=lambda: w.add_frame(image, z))
    expect_error(None, "frames[1]", call=lambda: w.add_frame(random_image(rng, np.uint16, 3), 2.0, file="../x.tiff"))
    expect_error(None, "frames[1].file", ".jpg", call=lambda: w.add_frame(random_image(rng, np.uint16, 3), 2.0,
                                                                           file="f.jpg"))
    expect_error(None, "JSON", call=lambda: w.add_frame(random_image(rng, np.uint16, 3), 2.0, note=object()))
    assert len(Stack.open(tmp_path / "s")) == 1 and sorted(p.name for p in (tmp_path / "s" / "frames").iterdir()) \
        == ["0000.tiff"]
    fw = StackWriter.create(tmp_path / "f", pixel_pitch_um=1.0, channels=["Y"])
    fw.add_frame(random_image(rng, np.float32, 1), 0.0)
    bad = random_image(rng, np.float32, 1)
    bad[0, 0] = np.inf
    expect_error(None, "NaN/Inf", call=lambda: fw.add_frame(bad, 1.0))


def test_stack_json_never_lists_an_incomplete_frame(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["R", "G", "B"], bit_depth=12)
    first = random_image(rng, np.uint16, 3)
    w.add_frame(first, 0.0)

    def crash(*a, **k):
        raise KeyboardInterrupt("power cut")

    # crash while the frame file is being written: stack.json unchanged
    monkeypatch.setattr(stack_mod, "atomic_write_bytes", crash)
    with pytest.raises(KeyboardInterrupt):
        w.add_frame(random_image(rng, np.uint16, 3), 1.0)
    monkeypatch.undo()
    assert len(Stack.open(tmp_path / "s")) == 1
    # crash after the frame file landed but before stack.json: the frame is simply not listed
    monkeypatch.setattr(stack_mod, "atomic_write_text", crash)
    with pytest.raises(KeyboardInterrupt):
        w.add_frame(random_image(rng, np.uint16, 3), 1.0)
    monkeypatch.undo()
    s = Stack.open(tmp_path / "s")
    assert len(s) == 1 and s.verify_checksums() == []
    # resume: the writer re-uses the orphan name and the stack is whole again
    w2 = StackWriter.open_existing(tmp_path / "s")
    second = random_image(rng, np.uint16, 3)
    w2.add_frame(second, 1.0)
    s = Stack.open(tmp_path / "s")
    assert len(s) == 2 and s.bit_depth == 12 and s.verify_checksums() == []
    np.testing.assert_array_equal(s.read(1), second)
    np.testing.assert_array_equal(s.read(0), first)
    assert not [p for p in (tmp_path / "s").rglob(".*.tmp")]


def test_empty_stack_can_be_resumed_but_not_opened(tmp_path):
    StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["Y"], vendor="x")
    expect_error(tmp_path / "s", "stack.json", "no frames")
    w = StackWriter.open_existing(tmp_path / "s")
    w.add_frame(np.ones((4, 6), np.uint8), -2.0)
    s = w.stack()
    assert len(s) == 1 and s.meta["vendor"] == "x" and s.read(0).shape == (4, 6, 1)


def test_verify_checksums_finds_modified_and_missing_frames(tmp_path):
    rng = np.random.default_rng(0)
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["Y"])
    infos = [w.add_frame(random_image(rng, np.uint8, 1), float(k)) for k in range(4)]
    s = Stack.open(tmp_path / "s")
    assert s.verify_checksums() == []
    data = bytearray(infos[1].path.read_bytes())
    data[-1] ^= 0xFF  # one pixel bit flipped: header still fine
    infos[1].path.write_bytes(bytes(data))
    infos[3].path.unlink()
    assert [f.index for f in s.verify_checksums()] == [1, 3]


# --------------------------------------------------------------------------------------------- properties


z_sets = st.lists(st.floats(min_value=-5000, max_value=5000, allow_nan=False, allow_infinity=False),
                  min_size=1, max_size=7, unique=True)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(zs=z_sets, kind=st.sampled_from(["tiff", "png"]), data=st.data())
def test_property_any_z_order_round_trips_and_sorts(zs, kind, data):
    order = data.draw(st.permutations(range(len(zs))))
    zs = [zs[k] for k in order]
    with tempfile.TemporaryDirectory() as tmp:
        w = StackWriter.create(Path(tmp) / "s", pixel_pitch_um=1.0, channels=["Y"])
        for k, z in enumerate(zs):
            w.add_frame(np.full((3, 5), k, np.uint8), z, kind=kind)  # pixel value = file index
        s = Stack.open(Path(tmp) / "s")
        np.testing.assert_array_equal(s.z_um, zs)  # exact: floats survive JSON
        by_z = s.order_by_z
        assert np.all(np.diff(s.z_um[by_z]) > 0)
        assert sorted(by_z.tolist()) == list(range(len(zs)))
        got = [(info.z_um, int(arr[0, 0, 0])) for info, arr in s.iter_frames(order="z")]
        assert got == sorted((z, k) for k, z in enumerate(zs))


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 12), w=st.integers(1, 12), c=st.sampled_from([1, 3]),
       layout=st.sampled_from(["raw", "zlib", "planar", "png"]), data=st.data())
def test_property_roi_equals_slice_of_full_frame(h, w, c, layout, data):
    if layout == "planar":
        c = 3  # channel-planar storage needs several channels
    image = np.arange(h * w * c, dtype=np.uint16).reshape((h, w, c)) * 7
    x0 = data.draw(st.integers(0, w - 1))
    y0 = data.draw(st.integers(0, h - 1))
    rw = data.draw(st.integers(1, w - x0))
    rh = data.draw(st.integers(1, h - y0))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        name = "f.png" if layout == "png" else "f.tiff"
        if layout == "png":
            cv2.imwrite(str(root / name), image[..., ::-1] if c == 3 else image[..., 0])
        elif layout == "planar":
            tifffile.imwrite(root / name, np.moveaxis(image, -1, 0), planarconfig="separate", photometric="rgb")
        else:
            tifffile.imwrite(root / name, image if c == 3 else image[..., 0], compression=None if layout == "raw"
                             else "zlib", photometric="rgb" if c == 3 else "minisblack")
        doc = {"format": FORMAT, "pixel_pitch_um": 2.0, "channels": ["R", "G", "B"] if c == 3 else ["Y"],
               "frames": [{"file": name, "z_um": 0.0}]}
        (root / "stack.json").write_text(json.dumps(doc))
        s = Stack.open(root)
        full = s.read(0)
        np.testing.assert_array_equal(full, image)
        np.testing.assert_array_equal(s.read(0, roi=(x0, y0, rw, rh)), image[y0:y0 + rh, x0:x0 + rw])


@settings(max_examples=30, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True).filter(lambda v: not math.isfinite(v) or v <= 0),
                 st.text(max_size=3), st.none(), st.booleans()))
def test_property_bad_pitch_always_named(pitch):
    with tempfile.TemporaryDirectory() as tmp:
        root = write_foreign(Path(tmp) / "s", [("a.tiff", np.zeros((4, 4, 3), np.uint8), 0.0)])
        edit_json(root, lambda d: d.update(pixel_pitch_um=pitch))
        with pytest.raises(StackError, match="pixel_pitch_um"):
            Stack.open(root)


def test_errors_are_fieldcal_errors():
    assert issubclass(StackError, FieldcalError)


def test_background_verification_refuses_what_verify_refuses(tmp_path):
    rng = np.random.default_rng(1)
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=1.0, channels=["Y"])
    infos = [w.add_frame(random_image(rng, np.uint8, 1), float(k)) for k in range(5)]
    s = Stack.open(tmp_path / "s", verify=False)
    s.start_verify()
    s.start_verify()  # a second start while one runs does nothing
    s.finish_verify()
    s.finish_verify()  # nothing pending: nothing to do
    assert all(s.frame_sha256(i) == str(infos[i].sha256).lower() for i in range(5))  # the hashes are kept
    data = bytearray(infos[2].path.read_bytes())
    data[-1] ^= 0x01
    infos[2].path.write_bytes(bytes(data))
    s = Stack.open(tmp_path / "s", verify=False)
    s.start_verify()
    assert s.read(0).shape[:2] == s.shape  # reading goes on while the frames hash
    for _ in range(2):  # the refusal is kept until the caller sees it, and after
        with pytest.raises(StackError, match=r"sha256 differs.*frames\[2\]"):
            s.finish_verify()
    with pytest.raises(StackError, match="sha256 differs"):  # the same verdict as verifying at open
        Stack.open(tmp_path / "s")
