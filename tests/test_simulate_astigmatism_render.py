"""The geometric renderer's astigmatic PSF against closed forms: an ellipse of diameters |dz -+ A/2| / N oriented
radially (second moments and MTF along T and S), e-SFR peaks at the tangential and sagittal foci, and lenses
without astigmatism rendering exactly as the isotropic path."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from fieldcal.errors import FieldcalError
from fieldcal.simulate import astigmatism as astig
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.render import Renderer

MODELS = Path(__file__).resolve().parents[1] / "models"


def _spec(n_px: int, pitch_um: float, astig_um=0.0, flat: bool = False, mono: bool = False) -> LensSpec:
    d = LensSpec.load(MODELS / "triplet-astigmatic.json").to_dict()
    d["sensor"].update(width_px=n_px[0], height_px=n_px[1], pixel_pitch_um=pitch_um)
    d["image_height_max_mm"] = 0.5 * math.hypot(*n_px) * pitch_um * 1e-3
    for c in d["channels"]:
        c["astigmatism_um"] = astig_um
        if flat:
            c["curvature_um"], c["focus_offset_um"] = [], 0.0
    if flat:
        d["stage_axis_tilt_mrad"], d["exit_pupil_mm"] = [0.0, 0.0], None
    if mono:
        d["channels"] = [dict(d["channels"][1], name="Y")]
    return LensSpec.from_dict(d)


def _otf_along(img: np.ndarray, centre: tuple[int, int], angle_rad: float, f_cyc_per_px: np.ndarray) -> np.ndarray:
    """Real part of the DFT of a centred PSF at frequencies f along one direction (normalised at f = 0)."""
    h, w = img.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    s = (x - centre[0]) * math.cos(angle_rad) + (y - centre[1]) * math.sin(angle_rad)
    p = img.astype(np.float64)
    return np.array([np.sum(p * np.cos(2.0 * np.pi * f * s)) for f in np.atleast_1d(f_cyc_per_px)]) / p.sum()


@pytest.fixture(scope="module")
def point_renderer():
    n = 256
    spec = _spec((n, n), 4.9)
    scene = np.zeros((n, n), np.float32)
    scene[n // 2, n // 2] = 1.0
    r = Renderer(spec, scene, compact_levels=False)  # float32 levels: a point source's tails are ~1e-4
    return r, r.blur_map("G", np.zeros((n, n), np.float32)), (n // 2, n // 2)


# (b_T, b_S) blur diameters in px (tangential = radial direction, sagittal = azimuthal), field azimuth (rad)
CASES = [(3.0, 6.0, 0.3), (6.0, 3.0, 1.1), (0.0, 4.0, 2.6), (2.5, 2.5, 0.0), (9.0, 7.0, -0.8)]


@pytest.mark.parametrize("b_t, b_s, theta", CASES)
def test_second_moments_along_t_and_s_are_the_discs(point_renderer, b_t, b_s, theta):
    """Var along T = b_T^2 / 16 and along S = b_S^2 / 16 (a disc of radius R has R^2 / 4 per axis), from the
    rendered PSF's low-frequency OTF relative to the in-focus PSF (diffraction and the residual Gaussian
    multiply both, so their ratio is the defocus ellipse's OTF ~ 1 - 2 pi^2 var f^2)."""
    r, focus, c = point_renderer
    n_um = r.spec.f_number * r.pitch_um
    dz, half = 0.5 * (b_t + b_s) * n_um, 0.5 * (b_s - b_t) * n_um
    img = r.blur_astigmatic("G", dz, half, theta)
    for angle, b in ((theta, b_t), (theta + 0.5 * math.pi, b_s)):
        f = np.linspace(0.1, 0.6, 11) / max(b_t, b_s, 2.0)  # where the f^4 term is small and known
        ratio = _otf_along(img, c, angle, f) / _otf_along(focus, c, angle, f)
        design = np.stack([-2.0 * np.pi**2 * f**2, f**4], axis=1)
        var = np.linalg.lstsq(design, ratio - 1.0, rcond=None)[0][0]
        # the level ladder interpolates linearly in diameter: variance exact at a level, <= 1.3 % high between
        assert var == pytest.approx(b * b / 16.0, rel=0.03, abs=0.01), (angle, b)


@pytest.mark.parametrize("b_t, b_s, theta", CASES[:3])
def test_mtf_along_t_and_s_is_the_disc_of_each_axis(point_renderer, b_t, b_s, theta):
    """Across the band, the MTF along T (S) is the disc OTF of diameter b_T (b_S): 2 J1(pi b f) / (pi b f)."""
    r, focus, c = point_renderer
    n_um = r.spec.f_number * r.pitch_um
    img = r.blur_astigmatic("G", 0.5 * (b_t + b_s) * n_um, 0.5 * (b_s - b_t) * n_um, theta)
    f = np.linspace(0.05, 0.45, 9)
    for angle, b in ((theta, b_t), (theta + 0.5 * math.pi, b_s)):
        got = _otf_along(img, c, angle, f) / _otf_along(focus, c, angle, f)
        np.testing.assert_allclose(got, astig._disc_otf(f * b), atol=0.03)


def test_wedge_count_meets_its_tolerance():
    f = np.linspace(0.0, np.pi, 50)
    np.testing.assert_allclose(astig.wedge_weights(f, 7).sum(axis=-1), 1.0, atol=1e-12)
    for a_px in (0.2, 0.9, 2.1, 3.5):
        k = astig.wedge_count(a_px)
        assert k % 2 == 1 and astig.interpolation_error(k, a_px) <= astig.WEDGE_TOLERANCE
        assert k == 3 or astig.interpolation_error(k - 2, a_px) > astig.WEDGE_TOLERANCE  # the smallest
    assert astig.wedge_count(0.0) == 3


def test_lens_without_astigmatism_renders_as_the_isotropic_path():
    spec = _spec((160, 120), 9.0)
    scene = np.random.default_rng(0).random((120, 160)).astype(np.float32)
    a = Renderer(spec, scene, seed=2)
    b = Renderer(spec, scene, seed=2, astigmatism="isotropic")
    assert not a._wedges
    for z in (-60.0, 0.0, 25.0):
        assert np.array_equal(a.render(z), b.render(z))
        # the isotropic pipeline spelled out: the sensor's disc |dz| shrunk by the warp's scale s (blurred in scene
        # pixels by level interpolation), the in-focus factors at the sensor's scale, warp, illumination
        for ci, ch in enumerate(a.channels):
            aff = a._affine(z, ch)
            s = float(aff[0, 0])
            blurred = a._at_sensor_scale(a.blur_map(ch, a._defocus_at(z, ch, aff) * np.float32(1.0 / s)), ch, s)
            want = a._warp(blurred, aff, z, ch) * a._exposed_illum()
            assert np.array_equal(a.render_float(z)[:, :, ci], np.maximum(want, 0.0))
    assert np.array_equal(a.truth(), b.truth())


def test_astigmatic_lens_differs_only_by_orientation():
    """Same lens: the anisotropic and the isotropic (RMS-defocus disc) renders agree in mean and in total blur
    energy but not pixel by pixel, and the truth (each pixel at its least-confusion focus: a disc) agrees."""
    spec = _spec((160, 120), 9.0, astig_um=[60.0])
    scene = np.random.default_rng(1).random((120, 160)).astype(np.float32)
    a = Renderer(spec, scene)
    b = Renderer(spec, scene, astigmatism="isotropic")
    fa, fb = a.render_float(10.0), b.render_float(10.0)
    assert abs(float(fa.mean() - fb.mean())) < 1e-3
    assert np.max(np.abs(fa - fb)) > 0.02
    np.testing.assert_allclose(a._linear(None), b._linear(None), atol=2e-4)
    assert a.settings()["orientation_wedges"] and b.settings()["astigmatism"] == "isotropic"


def test_compact_wedge_levels_round_only():
    spec = _spec((160, 120), 9.0, astig_um=[60.0])
    scene = np.random.default_rng(3).random((120, 160)).astype(np.float32)
    a = Renderer(spec, scene).render_float(-15.0)
    b = Renderer(spec, scene, compact_levels=False).render_float(-15.0)
    assert 0.0 < np.max(np.abs(a - b)) < 3e-4 and float(np.sqrt(np.mean((a - b) ** 2))) < 1e-4


def test_unknown_astigmatism_model_is_a_parameter_error():
    spec = _spec((64, 48), 9.0)
    with pytest.raises(FieldcalError, match="astigmatism"):
        Renderer(spec, np.zeros((48, 64), np.float32), astigmatism="round")


def test_esfr_through_focus_peaks_at_the_tangential_and_sagittal_foci():
    """fieldcal's own e-SFR on a slanted-edge chart through focus: each edge's MTF(0.25 cy/px) peaks where the
    blur across it vanishes, z_c + (A/2) cos 2 phi for an edge normal at phi from the radius (phi = 0: the
    tangential focus z_c + A/2; 90 deg: the sagittal z_c - A/2)."""
    from fieldcal.charts.targets import slanted_edge_image, slanted_edge_spec
    from fieldcal.measure.esfr_focus import through_focus_peak
    from fieldcal.measure.mtf import default_grid, measure_frame

    w, h = 256, 192
    spec = _spec((w, h), 5.0, astig_um=[30.0], flat=True, mono=True)
    r = Renderer(spec, slanted_edge_image(slanted_edge_spec(w, h)))
    zs = np.arange(-17.5, 17.51, 2.5)
    tracks = defaultdict(list)
    for z in zs:
        for e in measure_frame(r.render_float(z), channels=("Y",), z_um=z)[0]:
            tracks[(round(e["x_px"] / 4), round(e["y_px"] / 4), round(e["angle_deg"] / 30))].append(e)
    grid = default_grid()
    errs, seen = [], set()
    for es in tracks.values():
        q = es[len(es) // 2]["quality"]
        if len(es) != zs.size or not q["orientation_clear"]:
            continue
        peak = through_focus_peak(zs, [np.interp(0.25, grid, e["mtf"]) for e in es], sigma=0.0)
        a_um = float(spec.channel("Y").astigmatism_at(spec.rho(*spec.pixel_to_mm(es[0]["x_px"], es[0]["y_px"]))))
        want = 0.5 * a_um * math.cos(2.0 * math.radians(q["radial_angle_deg"]))
        errs.append(peak.z_um - want)
        seen.add(es[0]["orientation"])
    assert seen == {"tangential", "sagittal"} and len(errs) >= 20
    errs = np.array(errs)

    # T - S reaches 30 µm at the corners; the scan step is 2.5 µm
    assert np.sqrt(np.mean(errs**2)) < 0.4 and np.max(np.abs(errs)) < 1.0


def test_calibrate_recovers_tangential_and_sagittal_surfaces(tmp_path):
    """`fieldcal calibrate` on a geometric slanted-edge stack of a strongly astigmatic lens (T - S = 30 µm rho^2,
    flat mean surface): its tangential and sagittal surfaces within 1 µm RMS of the truth (an isotropic blur
    puts both on the mean: up to 15 µm off)."""
    import fieldcal
    from fieldcal.simulate.stackgen import simulate_stack, z_grid
    from fieldcal.simulate.truth import TruthProfile

    spec = _spec((256, 192), 5.0, astig_um=[30.0], flat=True, mono=True)
    simulate_stack(spec, tmp_path / "s", z_grid(-21.0, 21.0, 3.0), scene="slanted-edge", seed=0, progress=False)
    prof = fieldcal.calibrate(tmp_path / "s", effort="quick", fs_cyc_per_mm=50.0, quiet=True)  # 0.25 cy/px
    assert prof.calibration["measurement"] == "esfr"
    w, h = prof.image["width_px"], prof.image["height_px"]
    truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um)
    gx, gy = np.meshgrid(np.linspace(0.05, 0.95, 15) * (w - 1), np.linspace(0.05, 0.95, 9) * (h - 1))
    for o in ("tangential", "sagittal"):
        e = prof.best_focus_um(gx, gy, "Y", orientation=o) - truth.best_focus_um(gx, gy, "Y", orientation=o)
        assert float(np.sqrt(np.mean(e * e))) <= 1.0, o


def test_coarse_grid_parts_above_one_megapixel_match_the_formulas():
    """Above 1 Mpx the signed defocus, h cos 2 theta and h sin 2 theta come from the coarse grid: within 0.002 px
    of blur diameter of the formulas at every pixel (the level ladder's floor is 0.5 px)."""
    spec = LensSpec.load(MODELS / "triplet-astigmatic.json").with_sensor_size(1280, 800)
    r = Renderer(spec, np.zeros((800, 1280), np.float32))
    for z in (-200.0, -5.0, 40.0):
        aff = r._affine(z, "G", True)
        coarse = r._astig_parts_at(z, "G", aff)
        exact = r._astig_parts(z, "G", *r._landing(z, "G", aff))
        for c, e in zip(coarse, exact):
            assert np.max(np.abs(c - e)) < 2e-3
