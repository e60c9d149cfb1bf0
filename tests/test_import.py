"""`fieldcal import`: camera files (PNG, JPEG, TIFF, DNG) into a stack, checked against the files themselves."""

from __future__ import annotations

import dataclasses
import json
import hashlib
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from fieldcal.cli import main
from fieldcal.errors import FieldcalError
from fieldcal.formats.importer import import_stack, natural_key, read_z_csv
from fieldcal.formats.stack import Stack

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-stacks" / "pcb-depthmap"


def _frames(n=4, h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, size=(h, w, 3), dtype=np.uint8) for _ in range(n)]


def _write_png(folder: Path, names, images):
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, im in zip(names, images):
        p = folder / name
        assert cv2.imwrite(str(p), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
        paths.append(p)
    return paths


def _write_jpeg_with_exif(path: Path, image: np.ndarray, *, f_number=2.8, focal_mm=50.0, plane_res_per_mm=None,
                          model="Cam A"):
    from PIL import Image

    im = Image.fromarray(image)
    exif = Image.Exif()
    exif[0x010F] = "Maker"      # Make
    exif[0x0110] = model        # Model
    ifd = exif.get_ifd(0x8769)  # the EXIF sub-IFD
    ifd[0x829D] = f_number      # FNumber
    ifd[0x920A] = focal_mm      # FocalLength
    ifd[0x829A] = 0.02          # ExposureTime (s)
    if plane_res_per_mm:
        ifd[0xA20E] = plane_res_per_mm  # FocalPlaneXResolution
        ifd[0xA210] = 4                 # FocalPlaneResolutionUnit: mm
    im.save(path, quality=95, exif=exif)


def test_natural_key_orders_numbers_by_value():
    names = ["f10.png", "f2.png", "F1.png", "f1b.png"]
    assert sorted(names, key=natural_key) == ["F1.png", "f1b.png", "f2.png", "f10.png"]


def test_png_frames_in_natural_order_with_z_grid_and_checksums(tmp_path):
    images = _frames(3)
    src = _write_png(tmp_path / "shots", ["img10.png", "img2.png", "img1.png"], images)
    stack = import_stack(src, tmp_path / "stack", z_start_um=-20, z_step_um=10, pixel_pitch_um=3.45)
    # natural order: img1, img2, img10 -> the 3rd, 2nd and 1st images written
    expected = [images[2], images[1], images[0]]
    assert list(stack.z_um) == [-20.0, -10.0, 0.0]
    for k in range(3):
        assert np.array_equal(stack.read(k), expected[k])
        info = stack.frames[k]
        assert info.sha256 == hashlib.sha256(info.path.read_bytes()).hexdigest()
    assert stack.channels == ("R", "G", "B") and stack.pixel_pitch_um == 3.45
    assert stack.verify_checksums() == []


def test_z_csv_gives_order_and_positions(tmp_path):
    images = _frames(3, seed=1)
    src = _write_png(tmp_path / "shots", ["a.png", "b.png", "c.png"], images)
    csv = tmp_path / "z.csv"
    csv.write_text("file,z_um\nc.png,5.5\na.png,-3\nb.png,12\n")
    stack = import_stack(src, tmp_path / "stack", z_csv=csv, pixel_pitch_um=2.0)
    assert list(stack.z_um) == [5.5, -3.0, 12.0]
    assert np.array_equal(stack.read(0), images[2]) and np.array_equal(stack.read(1), images[0])
    assert [int(i) for i in stack.order_by_z] == [1, 0, 2]


@pytest.mark.parametrize("text, needle", [
    ("file,z_um\na.png,0\nb.png,10\n", "no row for"),
    ("a.png,0\nb.png,10\nc.png,20\nzz.png,30\n", "not among the images"),
    ("a.png,0\nb.png,x\nc.png,20\n", "not a number"),
    ("a.png,0\nb.png,nan\nc.png,20\n", "not a finite"),
    ("a.png,0\na.png,5\nc.png,20\n", "twice"),
])
def test_bad_csv_is_refused_naming_the_csv(tmp_path, text, needle):
    src = _write_png(tmp_path / "shots", ["a.png", "b.png", "c.png"], _frames(3))
    csv = tmp_path / "z.csv"
    csv.write_text(text)
    with pytest.raises(FieldcalError, match=needle) as exc:
        import_stack(src, tmp_path / "stack", z_csv=csv, pixel_pitch_um=2.0)
    assert str(csv) in str(exc.value)
    assert not (tmp_path / "stack").exists()


def test_jpeg_exif_gives_f_number_focal_length_and_pitch(tmp_path):
    folder = tmp_path / "jpg"
    folder.mkdir()
    for k, im in enumerate(_frames(3, seed=2)):
        _write_jpeg_with_exif(folder / f"DSC_{k:04d}.JPG", im, plane_res_per_mm=250.0)  # 4 µm pixels
    stack = import_stack([folder], tmp_path / "stack", z_start_um=0, z_step_um=25)
    assert stack.meta["f_number"] == pytest.approx(2.8)
    assert stack.meta["focal_length_mm"] == pytest.approx(50.0)
    assert stack.pixel_pitch_um == pytest.approx(4.0)
    assert stack.meta["imported"]["pixel_pitch_source"].startswith("EXIF")
    assert stack.frames[0].meta["exposure_ms"] == pytest.approx(20.0)
    assert stack.meta["camera"] == {"make": "Maker", "model": "Cam A"}
    # the stored JPEG is the file itself, byte for byte
    assert stack.frames[1].path.read_bytes() == (folder / "DSC_0001.JPG").read_bytes()
    frame = stack.read(0)
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8


def test_mixed_cameras_sizes_and_missing_pitch_are_refused(tmp_path):
    folder = tmp_path / "jpg"
    folder.mkdir()
    ims = _frames(3, seed=3)
    _write_jpeg_with_exif(folder / "a1.jpg", ims[0], model="Cam A")
    _write_jpeg_with_exif(folder / "a2.jpg", ims[1], model="Cam B")
    with pytest.raises(FieldcalError, match="camera model"):
        import_stack([folder / "a1.jpg", folder / "a2.jpg"], tmp_path / "s1", z_start_um=0, z_step_um=1,
                     pixel_pitch_um=2)
    _write_jpeg_with_exif(folder / "b1.jpg", ims[0])
    _write_jpeg_with_exif(folder / "b2.jpg", ims[1][:40])
    with pytest.raises(FieldcalError, match="height"):
        import_stack([folder / "b1.jpg", folder / "b2.jpg"], tmp_path / "s2", z_start_um=0, z_step_um=1,
                     pixel_pitch_um=2)
    with pytest.raises(FieldcalError, match="pixel pitch") as exc:
        import_stack([folder / "a1.jpg", folder / "b1.jpg"], tmp_path / "s3", z_start_um=0, z_step_um=1)
    assert exc.value.field == "pixel_pitch_um"
    assert not any(p.name.startswith(("s1", "s2", "s3", ".s")) for p in tmp_path.iterdir())


def test_cli_refusals_exit_2_without_traceback_and_leave_no_output(tmp_path, capsys):
    src = _write_png(tmp_path / "shots", ["a.png", "b.png"], _frames(2))
    out = tmp_path / "stack"
    rc = main(["import", *map(str, src), "--out", str(out), "--z", "0", "10"])
    err = capsys.readouterr().err
    assert rc == 2 and "field '--pixel-pitch-um'" in err and "Traceback" not in err
    assert not out.exists()
    # an existing folder that is not a stack is never replaced, even with --overwrite
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    rc = main(["import", *map(str, src), "--out", str(out), "--z", "0", "10", "--pixel-pitch-um", "2",
               "--overwrite"])
    assert rc == 2 and (out / "notes.txt").read_text() == "mine"
    # an output folder that holds an input is refused
    rc = main(["import", *map(str, src), "--out", str(tmp_path / "shots"), "--z", "0", "10",
               "--pixel-pitch-um", "2", "--overwrite"])
    assert rc == 2 and all(p.exists() for p in src)


def test_overwrite_replaces_a_stack_and_only_a_stack(tmp_path):
    src = _write_png(tmp_path / "shots", ["a.png", "b.png"], _frames(2))
    out = tmp_path / "stack"
    import_stack(src, out, z_start_um=0, z_step_um=10, pixel_pitch_um=2)
    with pytest.raises(FieldcalError, match="not empty"):
        import_stack(src, out, z_start_um=0, z_step_um=5, pixel_pitch_um=2)
    stack = import_stack(src, out, z_start_um=0, z_step_um=5, pixel_pitch_um=2, overwrite=True)
    assert list(stack.z_um) == [0.0, 5.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shots", "stack"]  # nothing left beside it


@pytest.mark.parametrize("mode", ["hard", "symlink"])
def test_link_modes_share_the_files(tmp_path, mode):
    src = _write_png(tmp_path / "shots", ["a.png", "b.png"], _frames(2, seed=4))
    stack = import_stack(src, tmp_path / "stack", z_start_um=0, z_step_um=10, pixel_pitch_um=2, link=mode)
    for info, s in zip(stack.frames, src):
        if mode == "hard":
            assert os.stat(info.path).st_ino == os.stat(s).st_ino
        else:
            assert info.path.is_symlink() and info.path.resolve() == s.resolve()
    assert np.array_equal(Stack.open(tmp_path / "stack").read(1), cv2.imread(str(src[1]))[:, :, ::-1])


def test_symlinked_frames_are_refused_unless_the_stack_says_it_links(tmp_path):
    """A hand-made stack.json cannot reach outside its folder through a symlink unless it declares links."""
    import json

    src = _write_png(tmp_path / "shots", ["a.png", "b.png"], _frames(2))
    import_stack(src, tmp_path / "stack", z_start_um=0, z_step_um=10, pixel_pitch_um=2, link="symlink")
    meta = json.loads((tmp_path / "stack" / "stack.json").read_text())
    del meta["links"]
    (tmp_path / "stack" / "stack.json").write_text(json.dumps(meta))
    with pytest.raises(FieldcalError, match="outside"):
        Stack.open(tmp_path / "stack")


def test_read_z_csv_accepts_headerless_rows(tmp_path):
    p = tmp_path / "z.csv"
    p.write_text("\ufeffa.png, 1.5\n\nb.png,-2\n")
    assert read_z_csv(p) == [("a.png", 1.5), ("b.png", -2.0)]


# ----------------------------------------------------------------------------------------- DNG / raw


def _write_dng(path: Path, mosaic: np.ndarray, *, black: int, white: int, cfa: str = "RGGB", f_number=(28, 10)):
    from pidng.core import RAW2DNG, DNGTags, Tag
    from pidng.defs import (CalibrationIlluminant, CFAPattern, DNGVersion, Orientation, PhotometricInterpretation,
                            PreviewColorSpace)

    h, w = mosaic.shape
    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)
    t.set(Tag.TileLength, h)
    t.set(Tag.Orientation, Orientation.Horizontal)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, getattr(CFAPattern, cfa))
    t.set(Tag.BlackLevel, black)
    t.set(Tag.WhiteLevel, white)
    t.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    t.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    t.set(Tag.Make, "SimCam")
    t.set(Tag.Model, "Bayer 1")
    t.set(Tag.FNumber, [list(f_number)])
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    t.set(Tag.PreviewColorSpace, PreviewColorSpace.sRGB)
    r = RAW2DNG()
    r.options(t, path="", compress=False)
    r.convert(np.ascontiguousarray(mosaic, dtype=np.uint16), filename=str(path.with_suffix("")))
    assert path.is_file()


@pytest.fixture(scope="module")
def bayer_tiff_stack(tmp_path_factory):
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack, z_grid

    base = LensSpec.load(Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json")
    spec = dataclasses.replace(base, sensor=dataclasses.replace(base.sensor, cfa="RGGB"))
    out = tmp_path_factory.mktemp("bayer") / "tiff"
    simulate_stack(spec, out, z_grid(-360.0, 50.0, 10.0), scene="chart", seed=5, size=(384, 216), progress=False)
    return out, spec


def test_dng_stack_imports_to_the_same_mosaics_and_calibrates_the_same(bayer_tiff_stack, tmp_path):
    pytest.importorskip("pidng")
    import fieldcal
    from fieldcal.simulate.truth import TruthProfile

    tiff_dir, spec = bayer_tiff_stack
    tiff = Stack.open(tiff_dir)
    assert tiff.cfa == "RGGB"
    folder = tmp_path / "dng"
    folder.mkdir()
    rows = []
    for k, info in enumerate(tiff.frames):
        name = f"IMG_{k + 1}.dng"
        _write_dng(folder / name, tiff.read(k), black=int(tiff.black_level), white=int(tiff.white_level))
        rows.append(f"{name},{info.z_um!r}")
    (tmp_path / "z.csv").write_text("\n".join(rows) + "\n")
    dng = import_stack([folder], tmp_path / "stack", z_csv=tmp_path / "z.csv", pixel_pitch_um=tiff.pixel_pitch_um)
    assert dng.cfa == "RGGB" and dng.channels == ("R", "G", "B")
    assert dng.black_level == tiff.black_level and dng.white_level == tiff.white_level
    assert dng.meta["f_number"] == pytest.approx(2.8)
    assert np.array_equal(dng.z_um, tiff.z_um)
    for k in range(len(tiff)):
        assert np.array_equal(dng.read(k), tiff.read(k))
    assert len(dng.frames[0].meta["source"]["sha256"]) == 64

    # a camera's files declare the sensor-fixed MTFs (pixel aperture, diffraction at f_number) that the band-pass
    # of a breathing stack is corrected for; the simulator's stack says nothing: give it the same record, so the
    # two calibrations see the same stack description
    assert dng.meta["sensor_mtf"] == {"pixel_aperture": True, "diffraction": True}
    import shutil
    same = tmp_path / "tiff-declared"
    shutil.copytree(tiff_dir, same)
    doc = json.loads((same / "stack.json").read_text())
    doc["sensor_mtf"] = dng.meta["sensor_mtf"]
    doc["f_number"] = dng.meta["f_number"]  # the DNGs' EXIF (the diffraction factor's F-number)
    (same / "stack.json").write_text(json.dumps(doc))
    kw = dict(fs_cyc_per_mm=8.0, effort="quick", z_ref_um=0.0, seed=0, quiet=True)
    p_tiff = fieldcal.calibrate(Stack.open(same), **kw)
    p_dng = fieldcal.calibrate(dng, **kw)
    truth = TruthProfile(spec, 384, 216, z_ref_um=p_dng.z_ref_um)
    # inside the tile grid: at 384x216 each Bayer plane is 192x108 px (at 256x144 the planes are too small to
    # calibrate R and B: 10 µm off, a known limit of tiny images)
    xs, ys = np.meshgrid(np.linspace(58, 326, 8), np.linspace(43, 173, 5))
    for ch in ("R", "G", "B"):
        a = p_tiff.best_focus_um(xs, ys, ch)
        b = p_dng.best_focus_um(xs, ys, ch)
        assert np.max(np.abs(a - b)) < 1e-6, ch  # same pixels, same calibration
        err = np.sqrt(np.mean((b - truth.best_focus_um(xs, ys, ch)) ** 2))
        assert err < 0.1 * 10.0, (ch, err)  # surface RMS <= 0.1 scan step (10 µm steps)


def test_raw_files_cannot_be_linked(tmp_path):
    pytest.importorskip("pidng")
    folder = tmp_path / "dng"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        _write_dng(folder / f"r{k}.dng", rng.integers(64, 4000, size=(32, 48)).astype(np.uint16), black=64,
                   white=4095)
    with pytest.raises(FieldcalError, match="cannot be linked"):
        import_stack([folder], tmp_path / "stack", z_start_um=0, z_step_um=10, pixel_pitch_um=2, link="hard")


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/real-stacks not beside the checkout")
def test_real_jpeg_stack_imports_with_its_exif(tmp_path):
    stack = import_stack([REAL], tmp_path / "pcb", z_start_um=0, z_step_um=50, pixel_pitch_um=1.12)
    assert len(stack) == 10 and stack.shape == (1536, 2048) and stack.channels == ("R", "G", "B")
    assert stack.meta["f_number"] == pytest.approx(1.8)
    assert [Path(f.meta["source"]["file"]).stem for f in stack.frames] == [f"pcb_{k:03d}" for k in range(10)]


def test_quiet_import_of_frames_without_exif_prints_nothing(tmp_path):
    # PNG frames carry no EXIF; exifread's warning about that reached stderr once per frame under --quiet (through
    # Python's last-resort log handler: a process of its own, as a user runs it, since pytest installs handlers)
    import subprocess
    import sys

    _write_png(tmp_path / "shots", ["a.png", "b.png", "c.png"], _frames(3, seed=4))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    r = subprocess.run([sys.executable, "-m", "fieldcal", "import", str(tmp_path / "shots"), "--out",
                        str(tmp_path / "stack"), "--z", "0", "10", "--pixel-pitch-um", "2", "--quiet"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == ""
    assert len(Stack.open(tmp_path / "stack").frames) == 3


def test_read_z_csv_keeps_declared_columns_and_quoted_names(tmp_path):
    """A header may declare more columns than file,z_um (the rest are ignored), and a quoted file name may hold a
    comma; the row count check follows the header, so neither is mistaken for a decimal comma."""
    p = tmp_path / "z.csv"
    p.write_text('file,z_um,note\n"shot, 1.png",1.5,first\nb.png,-2,\n')
    assert read_z_csv(p) == [("shot, 1.png", 1.5), ("b.png", -2.0)]
    p.write_text("file,z_um,note\nb.png,-2,5,x\n")
    with pytest.raises(FieldcalError, match="line 2"):
        read_z_csv(p)


def test_read_z_csv_says_when_a_row_ends_in_an_empty_column(tmp_path):
    """A trailing comma is not a decimal comma: the message says which it is (and the row is still refused: its
    column count is not the file's)."""
    p = tmp_path / "z.csv"
    p.write_text("a.png,1.5\nb.png,-2,\n")
    with pytest.raises(FieldcalError, match="line 2.*empty column") as exc:
        read_z_csv(p)
    assert "decimal" not in str(exc.value)
