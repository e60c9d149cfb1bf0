"""Calibration charts: texture spectrum, ChArUco detection (ideal, degraded, rendered), slanted edges, files, CLI."""

from __future__ import annotations

import json
import math
import re

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from fieldcal.optics import through_focus_otf
from fieldcal.cli import main
from fieldcal.errors import FieldcalError, ParameterError
from fieldcal.charts.targets import (KINDS, CharucoSpec, chart_image, charuco_image, charuco_spec, detect_charuco,
                              parse_size_mm, print_requirements, random_texture, slanted_edge_image,
                              slanted_edge_spec, write_targets)


# ------------------------------------------------------------------------------------------------ texture
def _band_ratios(img: np.ndarray, bands) -> np.ndarray:
    """Measured radial power / closed-form dead-leaves power in each band, normalised to the first band.

    Expected power: ``1/f**2`` (scale invariance) times the pixel aperture ``sinc(fx)**2 sinc(fy)**2``
    (antialiased drawing integrates over each pixel). A texture with the right spectrum gives ratios ~1.
    """
    h, w = img.shape
    p = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    fr = np.hypot(fx, fy)
    expect = np.sinc(fx) ** 2 * np.sinc(fy) ** 2 / np.maximum(fr, 1e-9) ** 2
    out = []
    for lo, hi in bands:
        sel = (fr >= lo) & (fr < hi)
        out.append(p[sel].mean() / expect[sel].mean())
    out = np.asarray(out)
    return out / out[0]


BANDS = [(0.06, 0.12), (0.12, 0.25), (0.25, 0.35), (0.35, 0.45), (0.45, 0.5)]  # cycles/px; Nyquist = 0.5


@pytest.mark.parametrize("seed", [0, 7])
def test_texture_power_follows_inverse_f_squared_up_to_nyquist(seed):
    img = random_texture(192, 160, seed=seed)
    ratios = _band_ratios(img.astype(np.float64), BANDS)
    # Every band, including the one touching Nyquist, within a factor 2 of the 1/f^2 law.
    assert np.all(ratios > 0.5) and np.all(ratios < 2.0), ratios


def test_spectrum_check_rejects_textures_without_fine_detail():
    """The spectrum test above can fail: a slightly blurred texture or big-only discs lose the top band."""
    img = random_texture(192, 160, seed=0)
    blurred = cv2.GaussianBlur(img, (0, 0), 0.7)
    assert _band_ratios(blurred.astype(np.float64), BANDS)[-1] < 0.2
    coarse = random_texture(192, 160, seed=0, r_min_px=2.0)
    assert _band_ratios(coarse.astype(np.float64), BANDS)[-1] < 0.5


def test_texture_levels_mean_and_contrast():
    img = random_texture(200, 150, seed=3)
    assert img.dtype == np.float32 and img.shape == (150, 200)
    assert abs(float(img.mean()) - 0.5) < 0.05
    assert float(img.std()) > 0.15  # high contrast
    # never clipped: stays inside the grey range (antialiasing only mixes grey levels)
    assert img.min() >= 0.1 - 1 / 255 and img.max() <= 0.9 + 1 / 255
    # sharp edges: a large share of neighbouring-pixel steps exceed 0.1
    assert np.mean(np.abs(np.diff(img, axis=1)) > 0.1) > 0.2


def test_texture_is_deterministic_from_seed():
    a = random_texture(96, 64, seed=11)
    assert np.array_equal(a, random_texture(96, 64, seed=11))
    assert np.array_equal(a, chart_image("texture", 96, 64, seed=11))
    b = random_texture(96, 64, seed=12)
    assert np.mean(np.abs(a - b)) > 0.1  # a different seed is a different texture, not a shifted copy


@settings(max_examples=25, deadline=None)
@given(w=st.integers(8, 80), h=st.integers(8, 80), seed=st.integers(0, 2**31 - 1))
def test_texture_any_size_and_seed(w, h, seed):
    img = random_texture(w, h, seed=seed)
    assert img.shape == (h, w) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and img.min() >= 0.0 and img.max() <= 1.0
    assert img.std() > 0.01  # never a flat image, even at 8 px


@pytest.mark.parametrize("bad", [dict(width_px=4, height_px=64), dict(width_px=64.5, height_px=64),
                                 dict(width_px=64, height_px=64, grey_min=0.8, grey_max=0.2),
                                 dict(width_px=64, height_px=64, r_min_px=20.0, r_max_px=10.0),
                                 dict(width_px=64, height_px=64, coverage=0.0)])
def test_texture_bad_arguments_raise_clear_errors(bad):
    with pytest.raises(ParameterError) as e:
        random_texture(**bad)
    assert "fix:" in str(e.value)


def test_chart_image_kinds_and_unknown_kind():
    for kind in KINDS:
        img = chart_image(kind, 160, 120)
        assert img.shape == (120, 160) and img.dtype == np.float32
        assert 0.0 <= img.min() < img.max() <= 1.0
    with pytest.raises(ParameterError, match="unknown chart kind"):
        chart_image("checkerboard", 64, 64)


@settings(max_examples=15, deadline=None)
@given(kind=st.sampled_from(KINDS), w=st.integers(80, 300), h=st.integers(80, 300))
def test_every_chart_at_any_usable_size(kind, w, h):
    img = chart_image(kind, w, h)
    assert img.shape == (h, w) and img.dtype == np.float32 and np.all(np.isfinite(img))
    assert 0.0 <= img.min() and img.max() <= 1.0 and img.max() - img.min() > 0.5


# ------------------------------------------------------------------------------------------------ ChArUco
def test_charuco_detected_exactly_on_ideal_board():
    spec = charuco_spec(256, 192)
    img = charuco_image(spec)
    corners, ids = detect_charuco(img)  # default spec = the one for this size
    assert len(ids) == spec.n_corners
    assert np.array_equal(ids, np.arange(spec.n_corners))
    assert np.abs(corners - spec.corner_px(ids)).max() < 0.1
    # ids are row-major over interior corners, one square apart
    nx = spec.squares_x - 1
    p = spec.corner_px(ids)
    assert np.allclose(p[1] - p[0], [spec.square_px, 0]) and np.allclose(p[nx] - p[0], [0, spec.square_px])


def _scale_about_centre(img, scale):
    h, w = img.shape
    cx, cy = (w - 1) / 2, (h - 1) / 2
    a = np.array([[scale, 0, cx - scale * cx], [0, scale, cy - scale * cy]])
    return cv2.warpAffine(img, a, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE), (cx, cy)


def test_charuco_detected_on_blurred_noisy_scaled_board():
    """Blur with the lens model's through-focus OTF (FFT), shrink 3 %, add noise: corners still sub-pixel."""
    spec = charuco_spec(320, 240)
    img = charuco_image(spec).astype(np.float64)
    pitch_um, f_number, defocus_um = 5.0, 2.0, 30.0  # blur disc 15 µm = 3 px
    fy = np.fft.fftfreq(img.shape[0], d=pitch_um / 1000.0)[:, None]
    fx = np.fft.rfftfreq(img.shape[1], d=pitch_um / 1000.0)[None, :]
    otf = through_focus_otf(np.hypot(fx, fy), defocus_um, f_number, 546.1, 0.5)
    blurred = np.fft.irfft2(np.fft.rfft2(img) * otf, s=img.shape)
    assert blurred.std() < 0.95 * img.std()  # the OTF really blurred it
    scaled, (cx, cy) = _scale_about_centre(blurred.astype(np.float32), 0.97)
    noisy = scaled + np.random.default_rng(0).normal(0.0, 0.03, scaled.shape).astype(np.float32)
    corners, ids = detect_charuco(noisy, spec, min_corners=int(0.8 * spec.n_corners))
    truth = spec.corner_px(ids)
    truth = np.column_stack([cx + 0.97 * (truth[:, 0] - cx), cy + 0.97 * (truth[:, 1] - cy)])
    err = np.hypot(*(corners - truth).T)
    assert err.max() < 0.5 and np.median(err) < 0.15


def test_charuco_detected_on_rendered_frame_with_focus_breathing():
    """DESIGN: the ChArUco chart is detected by OpenCV on a frame rendered by the simulator."""
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate import Renderer
    from tests.conftest import MODELS

    spec = LensSpec.load(MODELS / "triplet-uncorrected.json").with_sensor_size(320, 180)
    board = charuco_spec(320, 180)
    r = Renderer(spec, chart_image("charuco", 320, 180), seed=1)
    z_um = -120.0  # mid-field in focus; 0.6 % focus breathing moves the edge corners ~1 px
    frame = r.render(z_um)  # uint16 with noise, black level, vignetting
    corners, ids = detect_charuco(frame[:, :, 1], min_corners=int(0.9 * board.n_corners))
    p = board.corner_px(ids)
    cx, cy = spec.optical_centre_px()
    m = float(spec.magnification(z_um, "G")) * spec.lateral_colour_scale("G")
    sx, sy = (float(v) for v in spec.shift_px(z_um))
    expected = np.column_stack([cx + m * (p[:, 0] - cx) + sx, cy + m * (p[:, 1] - cy) + sy])
    err_model = np.hypot(*(corners - expected).T).max()
    err_static = np.hypot(*(corners - p).T).max()
    assert err_model < 0.3
    assert err_model < 0.5 * err_static  # detections resolve the magnification change


def test_detect_charuco_on_blank_and_bad_input():
    corners, ids = detect_charuco(np.full((128, 128), 0.5, np.float32))
    assert corners.shape == (0, 2) and ids.shape == (0,)
    with pytest.raises(ParameterError, match="found 0 ChArUco corners"):
        detect_charuco(np.zeros((128, 128), np.uint8), min_corners=4)
    bad = np.full((128, 128), np.nan, np.float32)
    with pytest.raises(ParameterError, match="NaN"):
        detect_charuco(bad)


def test_charuco_spec_roundtrip_and_physical_corners():
    spec = charuco_spec(600, 400, dpi=150)
    again = CharucoSpec.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert again == spec
    ids = np.array([0, 1, spec.squares_x - 1])
    mm = spec.corner_mm(ids)
    assert np.allclose(mm[1] - mm[0], [spec.square_mm, 0])
    assert np.allclose(mm[2] - mm[0], [0, spec.square_mm])
    assert math.isclose(spec.square_mm, spec.square_px * 25.4 / 150)
    with pytest.raises(ParameterError):
        charuco_spec(600, 400).corner_mm(ids)  # no physical size
    with pytest.raises(ParameterError):
        spec.corner_px([spec.n_corners])  # id out of range
    with pytest.raises(ParameterError):
        CharucoSpec.from_dict({"squares_x": 5})


@settings(max_examples=12, deadline=None)
@given(w=st.integers(80, 700), h=st.integers(80, 400))
def test_charuco_layout_fits_and_is_detectable_at_any_size(w, h):
    spec = charuco_spec(w, h)
    assert spec.origin_x_px >= spec.square_px // 2 - 1 and spec.origin_y_px >= spec.square_px // 2 - 1
    assert spec.origin_x_px + spec.squares_x * spec.square_px <= w
    assert spec.origin_y_px + spec.squares_y * spec.square_px <= h
    assert (spec.square_px - spec.marker_px) % 2 == 0  # centred markers: no half-pixel corner bias
    corners, ids = detect_charuco(charuco_image(spec), spec)
    assert len(ids) == spec.n_corners
    assert np.abs(corners - spec.corner_px(ids)).max() < 0.05


def test_charuco_small_markers_in_a_large_frame_are_found():
    """OpenCV's default minimum marker size (3 % of the frame) would drop these 14 px markers."""
    spec = charuco_spec(2400, 100)
    corners, ids = detect_charuco(charuco_image(spec), spec)
    assert spec.marker_px == 14 and len(ids) == spec.n_corners


def test_charuco_too_small_chart_is_a_clear_error():
    with pytest.raises(ParameterError, match="fix:"):
        charuco_spec(60, 60)


# ------------------------------------------------------------------------------------------ slanted edge
def test_slanted_edges_have_the_stated_angle_and_levels():
    spec = slanted_edge_spec(256, 192, angle_deg=5.0)
    img = slanted_edge_image(spec)
    assert abs(img.min() - spec.dark) < 1e-6 and abs(img.max() - spec.light) < 1e-6  # not clipped
    edges = spec.edges()
    assert len(edges) == 4 * spec.nx * spec.ny
    angles = []
    for e in edges:
        x0, y0, x1, y1 = e["roi"]
        roi = img[y0:y1, x0:x1].astype(np.float64)
        assert roi.max() - roi.min() > 0.5 * (spec.light - spec.dark)  # the ROI holds the transition
        if e["orientation"] == "near-vertical":
            g = np.abs(np.diff(roi, axis=1))  # edge position per row: centroid of the gradient
            pos = (g * (np.arange(g.shape[1]) + 0.5)).sum(1) / g.sum(1)
            slope = np.polyfit(np.arange(len(pos)), pos, 1)[0]  # dx/dy
            angles.append(math.degrees(math.atan(abs(slope))))
        else:
            g = np.abs(np.diff(roi, axis=0))
            pos = (g * (np.arange(g.shape[0]) + 0.5)[:, None]).sum(0) / g.sum(0)
            slope = np.polyfit(np.arange(len(pos)), pos, 1)[0]  # dy/dx
            angles.append(math.degrees(math.atan(abs(slope))))
    assert np.allclose(angles, 5.0, atol=0.15), angles
    # edges cover the field: centre and all four quadrants
    mids = np.array([e["mid_px"] for e in edges])
    assert mids[:, 0].min() < 64 and mids[:, 0].max() > 192 and mids[:, 1].min() < 48 and mids[:, 1].max() > 144


@pytest.mark.parametrize("w,h", [(32, 32), (47, 200), (96, 96), (400, 90)])
def test_slanted_edge_small_charts_keep_usable_edges(w, h):
    spec = slanted_edge_spec(w, h)
    img = slanted_edge_image(spec)
    assert spec.side_px >= 12 and len(spec.edges()) >= 4
    for e in spec.edges():
        x0, y0, x1, y1 = e["roi"]
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h
        roi = img[y0:y1, x0:x1]
        assert roi.max() - roi.min() > 0.5 * (spec.light - spec.dark)


def test_slanted_edge_bad_arguments():
    with pytest.raises(ParameterError, match="angle"):
        slanted_edge_spec(256, 192, angle_deg=0.0)
    with pytest.raises(ParameterError, match="dark"):
        slanted_edge_spec(256, 192, dark=0.9, light=0.1)


# ------------------------------------------------------------------------------------------ files / CLI
def _pdf_page_pt(data: bytes) -> tuple[float, float]:
    m = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", data)
    assert m, "no MediaBox in the PDF"
    return float(m.group(1)), float(m.group(2))


def test_write_targets_files_sizes_and_manifest(tmp_path):
    from PIL import Image

    man = write_targets(tmp_path, 80.0, 60.0, 100.0, seed=3)
    w_px, h_px = round(80 / 25.4 * 100), round(60 / 25.4 * 100)
    assert [c["kind"] for c in man["charts"]] == list(KINDS)
    assert json.loads((tmp_path / "targets.json").read_text()) == json.loads(json.dumps(man))
    for c in man["charts"]:
        assert (c["width_mm"], c["height_mm"], c["dpi"]) == (80.0, 60.0, 100.0)
        assert (c["width_px"], c["height_px"]) == (w_px, h_px)
        png = tmp_path / next(f for f in c["files"] if f.endswith(".png"))
        with Image.open(png) as im:
            assert im.size == (w_px, h_px) and im.mode == "L"
            assert all(abs(d - 100.0) < 0.05 for d in im.info["dpi"])
            pixels = np.asarray(im, dtype=np.float32) / 255.0
        pdf = (tmp_path / next(f for f in c["files"] if f.endswith(".pdf"))).read_bytes()
        assert pdf.startswith(b"%PDF")
        pw, ph = _pdf_page_pt(pdf)
        assert abs(pw - 80 / 25.4 * 72) < 0.01 and abs(ph - 60 / 25.4 * 72) < 0.01  # exact physical size
        assert f"/Width {w_px}".encode() in pdf and f"/Height {h_px}".encode() in pdf  # pixels not resampled
        if c["kind"] == "texture":
            assert c["seed"] == 3
            assert np.abs(pixels - random_texture(w_px, h_px, seed=3)).max() <= 0.5 / 255 + 1e-6
        if c["kind"] == "charuco":
            board = CharucoSpec.from_dict(c["params"])
            corners, ids = detect_charuco(pixels, board, min_corners=board.n_corners)
            mm = board.corner_mm(ids)
            # physical scale: corner spacing in pixels / dpi equals the stated mm spacing
            px_per_mm = np.linalg.norm(corners[1] - corners[0]) / np.linalg.norm(mm[1] - mm[0])
            assert abs(px_per_mm - 100 / 25.4) < 0.01
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_write_targets_merges_manifest_and_rejects_bad_input(tmp_path):
    write_targets(tmp_path, 60, 60, 80, kinds=["charuco"], formats=("png",))
    man = write_targets(tmp_path, 60, 60, 80, kinds=["slanted-edge"], formats=("png",))
    assert sorted(c["kind"] for c in man["charts"]) == ["charuco", "slanted-edge"]
    before = sorted(p.name for p in tmp_path.iterdir())
    for kw in (dict(width_mm=5.0), dict(dpi=10.0), dict(dpi=float("nan")), dict(kinds=["grid"]),
               dict(formats=("jpg",)), dict(width_mm=2000.0, height_mm=2000.0, dpi=1200.0)):
        args = dict(width_mm=60.0, height_mm=60.0, dpi=80.0)
        args.update(kw)
        with pytest.raises(ParameterError) as e:
            write_targets(tmp_path, **args)
        assert "fix:" in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing half-written


@settings(max_examples=40, deadline=None)
@given(w=st.floats(10, 2000), h=st.floats(10, 2000))
def test_parse_size_roundtrip(w, h):
    pw, ph = parse_size_mm(f"{w!r}x{h!r}")
    assert pw == w and ph == h


@pytest.mark.parametrize("text", ["", "297", "297x", "x210", "297x210x3", "abcxdef", "nanx210", "infx210", "0x210",
                                  "-297x210", "A9"])
def test_parse_size_rejects_garbage(text):
    with pytest.raises(ParameterError, match="size|width|height"):
        parse_size_mm(text)


def test_parse_size_paper_names():
    assert parse_size_mm("A4") == (297.0, 210.0) and parse_size_mm("a3") == (420.0, 297.0)


def test_print_requirements_for_the_paper_triplet(triplet_path):
    """Closed form for models/triplet-uncorrected.json: f = 17.6 mm at 1 m gives m = 17.6 / 982.4."""
    from fieldcal.simulate.lens import LensSpec

    spec = LensSpec.load(triplet_path)
    assert (spec.focal_length_mm, spec.object_distance_mm, spec.sensor.pixel_pitch_um) == (17.6, 1000.0, 1.6342)
    req = print_requirements(spec.sensor.pixel_pitch_um, spec.sensor.size_mm, spec.focal_length_mm,
                             spec.object_distance_mm)
    m = 17.6 / (1000.0 - 17.6)
    assert math.isclose(req["magnification"], m, rel_tol=1e-12)
    # at min_dpi one printed pixel (25.4/dpi mm) images onto exactly one 1.6342 µm sensor pixel
    assert math.isclose(25.4 / req["min_dpi"] * m * 1000.0, 1.6342, rel_tol=1e-12)
    assert 275 < req["min_dpi"] < 282  # so 300 dpi prints suit this camera at 1 m
    assert math.isclose(req["field_width_mm"], 3840 * 1.6342e-3 / m, rel_tol=1e-12)
    with pytest.raises(ParameterError, match="focal length"):
        print_requirements(1.6, (6.0, 4.0), 20.0, 15.0)


def test_cli_writes_targets(tmp_path, capsys):
    out = tmp_path / "charts"
    rc = main(["targets", "--out", str(out), "--kind", "charuco", "--size-mm", "100x70", "--dpi", "90"])
    assert rc == 0
    man = json.loads((out / "targets.json").read_text())
    assert [c["kind"] for c in man["charts"]] == ["charuco"]
    assert all((out / f).exists() for f in man["charts"][0]["files"])


def test_cli_lens_check_warns_when_dpi_too_low(tmp_path, capsys, monkeypatch, triplet_path):
    from fieldcal.simulate.lens import LensSpec

    monkeypatch.setenv("FIELDCAL_PROGRESS", "1")  # the status lines are the output under test
    rc = main(["targets", "--out", str(tmp_path), "--kind", "slanted-edge", "--size-mm", "100x70",
               "--dpi", "100", "--format", "png", "--lens", str(triplet_path)])
    err = capsys.readouterr().err
    assert rc == 0 and "needs >= 278 dpi" in err and "below 278 dpi" in err and "does not fill" in err
    # the same lens sampled by 320 x 180 pixels needs 278 * 180 / 2160 = 23 dpi over the same 350 x 197 mm field
    small = tmp_path / "small.json"
    LensSpec.load(triplet_path).with_sensor_size(320, 180).save(small)
    rc = main(["targets", "--out", str(tmp_path), "--kind", "slanted-edge", "--size-mm", "360x200",
               "--dpi", "50", "--format", "png", "--lens", str(small)])
    err = capsys.readouterr().err
    assert rc == 0 and "needs >= 23 dpi" in err and "warning" not in err
    rc = main(["targets", "--out", str(tmp_path / "x"), "--lens", str(tmp_path / "missing.json")])
    assert rc != 0 and "lens spec not found" in capsys.readouterr().err


@pytest.mark.parametrize("args,field", [(["--size-mm", "297by210"], "--size-mm"), (["--dpi", "5"], "--dpi"),
                                        (["--dpi", "many"], "--dpi"), (["--seed", "-2"], "--seed"),
                                        (["--size-mm", "3x3"], "--size-mm")])
def test_cli_bad_input_clear_error_no_output(tmp_path, capsys, args, field):
    out = tmp_path / "charts"
    rc = main(["targets", "--out", str(out)] + args)
    err = capsys.readouterr().err
    assert rc == FieldcalError.exit_code and rc != 0
    assert f"field '{field}'" in err and "fix:" in err and "Traceback" not in err
    assert not out.exists()


def test_cli_help_has_example(capsys):
    with pytest.raises(SystemExit):
        main(["targets", "--help"])
    assert "example:\n  fieldcal targets" in capsys.readouterr().out
