"""`fieldcal profile export --format lensfun`: the conversion in closed form, and lensfunpy applying the entry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.cli import main
from fieldcal.profile import LensProfile
from fieldcal.profile.lensfun import (brown_to_poly5, calibrated_focus_um, lensfun_model, lensfun_norm_radius_px,
                                      lensfun_xml)


def test_brown_to_poly5_is_exact():
    """The distorted radius of a point is the same in fieldcal's normalisation and in Lensfun's."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        k1, k2 = rng.normal(0, 0.05, 2)
        r_model, r_lf = rng.uniform(100, 2000, 2)
        k1l, k2l = brown_to_poly5(k1, k2, r_model, r_lf)
        rho = rng.uniform(0, 1.5 * r_model, 50)   # pixels from the centre
        u = rho / r_model
        want = r_model * u * (1 + k1 * u ** 2 + k2 * u ** 4)
        v = rho / r_lf
        got = r_lf * v * (1 + k1l * v ** 2 + k2l * v ** 4)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_norm_radius_is_lensfuns_3_2_half_short_side():
    # a 3:2 image: half its shorter side (of the pixel-centre span)
    assert lensfun_norm_radius_px(601, 401) == pytest.approx(200.0)
    # another aspect: half the shorter side of the 3:2 frame with the same diagonal
    assert lensfun_norm_radius_px(641, 361) == pytest.approx(0.5 * math.hypot(640, 360) / math.hypot(1, 1.5))


@pytest.fixture(scope="module")
def profile_path(hostile_world):
    return hostile_world / "lens.json"


def _lensfun(xml_path, prof, flags):
    import lensfunpy
    db = lensfunpy.Database(paths=[str(xml_path)], load_common=False, load_bundled=False)
    cams = db.find_cameras("fieldcal")
    assert cams, "lensfunpy found no camera in the exported file"
    lenses = db.find_lenses(cams[0])
    assert len(lenses) == 1
    w, h = prof.image_size_px
    mod = lensfunpy.Modifier(lenses[0], cams[0].crop_factor, w, h)
    mod.initialize(prof.focal_length_mm, prof.f_number, 1.0, scale=1.0, flags=flags)
    return mod


def _absolute(prof, terms, coef):
    """An absolute distortion of the profile's z_ref geometry (radial and tangential about the image centre)."""
    from fieldcal.fit.distortion import AbsoluteDistortion
    w, h = prof.image_size_px
    return AbsoluteDistortion(prof.z_ref_um, prof.reference_channel, (0.5 * (w - 1), 0.5 * (h - 1)),
                              0.5 * math.hypot(w - 1, h - 1), tuple(terms), np.asarray(coef, float),
                              np.zeros((len(terms),) * 2), 0.01, 100)


@pytest.mark.parametrize("terms, coef", [(("k1", "k2"), (-0.04, 0.012)), (("k1", "k2", "p1", "p2"),
                                                                          (0.03, -0.005, 4e-4, -3e-4))])
def test_lensfunpy_applies_the_distortion_and_tca_of_a_profile(profile_path, tmp_path, terms, coef):
    """Exported from a profile's absolute distortion (barrel; pincushion with tangential terms, which the
    entry's centre carries), lensfunpy's undistortion and TCA agree with ``distortion_px`` within 0.1 px."""
    lf = pytest.importorskip("lensfunpy")
    prof = LensProfile.load(profile_path)
    prof.absolute_distortion = _absolute(prof, terms, coef)
    model = lensfun_model(prof)
    assert "absolute distortion" in model.source
    out = tmp_path / "lens.xml"
    out.write_text(lensfun_xml(prof, model))
    w, h = prof.image_size_px
    ys, xs = np.mgrid[0:h:6, 0:w:6]
    z = model.z_um
    g = _lensfun(out, prof, lf.ModifyFlags.DISTORTION).apply_geometry_distortion()[ys, xs]
    fx, fy = prof.distortion_px(xs, ys, z, prof.reference_channel)
    err = np.hypot(g[..., 0] - fx, g[..., 1] - fy)
    assert err.max() < 0.1, err.max()
    assert np.hypot(g[..., 0] - xs, g[..., 1] - ys).max() > 1.0
    s = _lensfun(out, prof, lf.ModifyFlags.DISTORTION | lf.ModifyFlags.TCA).apply_subpixel_geometry_distortion()
    for i, ch in enumerate("RGB"):
        fx, fy = prof.distortion_px(xs, ys, z, ch)
        err = np.hypot(s[ys, xs, i, 0] - fx, s[ys, xs, i, 1] - fy)
        assert err.max() < 0.1, (ch, err.max())


def test_entry_is_fitted_over_the_whole_frame_beyond_the_board(profile_path, tmp_path):
    """A board that covered the central half of the frame: the entry still follows the profile (barrel, k2 and
    tangential terms: the benchmark lens's coefficients) over the whole frame within 0.1 px, what it reports
    of its own fit is what lensfunpy does, and the note says the field beyond the board is extrapolated."""
    lf = pytest.importorskip("lensfunpy")
    prof = LensProfile.load(profile_path)
    w, h = prof.image_size_px
    prof.absolute_distortion = _absolute(prof, ("k1", "k2", "p1", "p2"), (-0.04, 0.008, 1e-3, -6e-4))
    a, b = 0.5 * (1 - math.sqrt(0.5)), 0.5 * (1 + math.sqrt(0.5))   # a centred box of half the frame's area
    prof.absolute_distortion.hull_px = np.array([[a * w, a * h], [b * w, a * h], [b * w, b * h], [a * w, b * h]])
    model = lensfun_model(prof)
    assert any("extrapolation" in n for n in model.notes)
    out = tmp_path / "lens.xml"
    out.write_text(lensfun_xml(prof, model))
    ys, xs = np.mgrid[0:h, 0:w]
    g = _lensfun(out, prof, lf.ModifyFlags.DISTORTION).apply_geometry_distortion()
    fx, fy = prof.distortion_px(xs, ys, model.z_um, prof.reference_channel)
    err = np.hypot(g[..., 0] - fx, g[..., 1] - fy)
    ref = prof.reference_channel
    assert err.max() < 0.1, err.max()
    assert err.max() == pytest.approx(max(model.max_err_px[ref], model.max_err_outside_px[ref]), abs=0.01)


def test_cli_export_of_a_calibrated_profile(profile_path, tmp_path, capsys):
    """The texture profile has no absolute distortion: refused, or with --allow-no-distortion an entry without a
    distortion element (Lensfun's geometry map is the identity), its TCA the lateral colour."""
    lf = pytest.importorskip("lensfunpy")
    out = tmp_path / "lens.xml"
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out)]) == 2
    assert "no absolute distortion" in capsys.readouterr().err and not out.exists()
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out),
                 "--allow-no-distortion"]) == 0
    assert "Lensfun database version 1" in capsys.readouterr().out
    assert "<distortion" not in out.read_text()
    prof = LensProfile.load(profile_path)
    mod = _lensfun(out, prof, lf.ModifyFlags.DISTORTION)
    assert mod.apply_geometry_distortion() is None  # no distortion element: Lensfun leaves the geometry alone
    w, h = prof.image_size_px
    mod = _lensfun(out, prof, lf.ModifyFlags.TCA)
    s = mod.apply_subpixel_distortion()
    cx = 0.5 * (w - 1)
    for i, ch in enumerate(prof.channels):
        sc = prof.lateral_colour_scale(ch)
        assert s[0, 0, i, 0] == pytest.approx(cx + sc * (0 - cx), abs=0.01)
    # refuses to overwrite without --overwrite, and then replaces
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out),
                 "--allow-no-distortion"]) == 2
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out),
                 "--allow-no-distortion", "--overwrite", "--z", str(calibrated_focus_um(prof) + 50)]) == 0
