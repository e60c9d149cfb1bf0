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


def _brown_warp(prof, k1, k2, colour):
    """A map with radial distortion about the image centre (normalised by the half-diagonal) and a
    lateral-colour scale per channel: what the geometry maps of a distorting lens give at one z."""
    w, h = prof.image_size_px
    cx, cy, r = 0.5 * (w - 1), 0.5 * (h - 1), 0.5 * math.hypot(w, h)

    def warp(x, y, z_um, channel):
        ux, uy = (np.asarray(x, float) - cx) / r, (np.asarray(y, float) - cy) / r
        r2 = ux * ux + uy * uy
        f = (1 + k1 * r2 + k2 * r2 * r2) * colour.get(channel, 1.0)
        return cx + r * ux * f, cy + r * uy * f
    return warp


def test_lensfunpy_applies_the_distortion_and_tca_of_a_map(profile_path, tmp_path):
    """Exported from a distorting map, lensfunpy's undistortion and TCA agree with the map within 0.1 px."""
    lf = pytest.importorskip("lensfunpy")
    prof = LensProfile.load(profile_path)
    colour = {"R": 1.0015, "B": 0.9990}
    warp = _brown_warp(prof, -0.04, 0.012, colour)
    prof.warp_px = warp  # as a profile with geometry maps offers it
    model = lensfun_model(prof)
    assert model.source == "warp_px maps"
    out = tmp_path / "lens.xml"
    out.write_text(lensfun_xml(prof, model))
    w, h = prof.image_size_px
    mod = _lensfun(out, prof, lf.ModifyFlags.DISTORTION)
    g = mod.apply_geometry_distortion()          # undistorted pixel -> where it lies in the distorted image
    ys, xs = np.mgrid[0:h:6, 0:w:6]
    # the map's undistorted image is the one with Lensfun's scale: warp(p) for p on Lensfun's grid
    wx, wy = warp(xs, ys, model.z_um, "G")
    err = np.hypot(g[ys, xs, 0] - wx, g[ys, xs, 1] - wy)
    assert err.max() < 0.1, err.max()
    mod = _lensfun(out, prof, lf.ModifyFlags.TCA)
    s = mod.apply_subpixel_distortion()          # (h, w, 3, 2): per channel R, G, B
    for i, ch in enumerate("RGB"):
        # TCA is about the green channel: the R (B) image is green's scaled by its lateral colour
        cx, cy = 0.5 * (w - 1), 0.5 * (h - 1)
        ex = cx + colour.get(ch, 1.0) * (xs - cx)
        ey = cy + colour.get(ch, 1.0) * (ys - cy)
        err = np.hypot(s[ys, xs, i, 0] - ex, s[ys, xs, i, 1] - ey)
        assert err.max() < 0.1, (ch, err.max())


def test_cli_export_of_a_calibrated_profile(profile_path, tmp_path, capsys):
    """The scalar profile has no distortion: Lensfun's geometry map is the identity, its TCA the lateral colour."""
    lf = pytest.importorskip("lensfunpy")
    out = tmp_path / "lens.xml"
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out)]) == 0
    assert "Lensfun database version 1" in capsys.readouterr().out
    prof = LensProfile.load(profile_path)
    mod = _lensfun(out, prof, lf.ModifyFlags.DISTORTION)
    g = mod.apply_geometry_distortion()
    w, h = prof.image_size_px
    ys, xs = np.mgrid[0:h, 0:w]
    assert np.hypot(g[..., 0] - xs, g[..., 1] - ys).max() < 0.1
    mod = _lensfun(out, prof, lf.ModifyFlags.TCA)
    s = mod.apply_subpixel_distortion()
    cx = 0.5 * (w - 1)
    for i, ch in enumerate(prof.channels):
        sc = prof.lateral_colour_scale(ch)
        assert s[0, 0, i, 0] == pytest.approx(cx + sc * (0 - cx), abs=0.01)
    # refuses to overwrite without --overwrite, and then replaces
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out)]) == 2
    assert main(["profile", "export", str(profile_path), "--format", "lensfun", "--out", str(out),
                 "--overwrite", "--z", str(calibrated_focus_um(prof) + 50)]) == 0
