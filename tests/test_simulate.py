"""The renderer against closed forms: OTF/MTF vs defocus, blur-disc size, geometry, noise, Bayer, levels."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.optimize import minimize_scalar
from skimage.registration import phase_cross_correlation

from fieldcal.errors import ParameterError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate import Renderer
from fieldcal.simulate.noise import gain_dn_per_e
from fieldcal.simulate.render import fractional_level, level_diameters_px


def make_spec(w=128, h=128, pitch_um=5.0, f_number=2.0, channels=None, sensor=None, **kw) -> LensSpec:
    """A small lens: flat field (no curvature), telecentric, no vignetting, float output, unless overridden."""
    d = {"format": "fieldcal-lens/1", "name": "test", "focal_length_mm": 10.0, "f_number": f_number,
         "image_height_max_mm": math.hypot(w, h) * pitch_um / 2000.0,
         "channels": channels or [{"name": "Y", "wavelength_nm": 550.0}],
         "sensor": {"width_px": w, "height_px": h, "pixel_pitch_um": pitch_um, "bit_depth": 32,
                    "black_level_dn": 0, "read_noise_e": 0.0, "full_well_e": 10000, **(sensor or {})},
         "residual_blur_um": 0.5}
    d.update(kw)
    return LensSpec.from_dict(d)


def stripes(w, h, cycles, lo=0.2, hi=0.8):
    """Vertical sine stripes with an integer number of periods across the width."""
    x = np.arange(w)
    row = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(2 * np.pi * cycles * x / w)
    return np.tile(row, (h, 1)).astype(np.float32)


def amplitude(img, cycles, x0=0, x1=None):
    """Signed amplitude of cos(2 pi cycles x / w) in columns x0:x1 (least squares on the row mean)."""
    w = img.shape[1]
    x1 = w if x1 is None else x1
    x = np.arange(x0, x1)
    row = img[:, x0:x1].mean(axis=0)
    a = np.stack([np.ones_like(x, dtype=float), np.cos(2 * np.pi * cycles * x / w),
                  np.sin(2 * np.pi * cycles * x / w)], axis=1)
    coef, *_ = np.linalg.lstsq(a, row, rcond=None)
    return coef[1]


def random_scene(w, h, seed=0, smooth=1.5):
    import cv2
    a = np.random.default_rng(seed).random((h, w)).astype(np.float32)
    a = cv2.GaussianBlur(a, (0, 0), smooth)
    return (a - a.min()) / (a.max() - a.min())


# ------------------------------------------------------------------------------------ optics
@pytest.mark.parametrize("f_number", [2.0, 4.0])
def test_contrast_vs_defocus_follows_lens_otf(f_number):
    spec = make_spec(f_number=f_number)
    cycles = 16  # 0.125 cycles/px = 25 cycles/mm at 5 µm pitch
    fs = cycles / 128 / 5e-3
    r = Renderer(spec, stripes(128, 128, cycles))
    a0 = 0.3
    for dz in [0.0, 10.0, 33.0, 60.0, 95.0, 140.0]:
        got = amplitude(r.render_float(dz)[:, :, 0], cycles) / r.exposure / a0
        want = float(spec.otf(fs, dz, "Y"))  # signed: contrast reversal past the first zero
        assert got == pytest.approx(want, abs=0.02), (dz, got, want)


def test_in_focus_is_sharp_on_a_curved_field():
    # Curved field: at stage position z the ring rho0 with best focus z is sharp, the centre is blurred.
    spec = make_spec(w=256, h=64, channels=[{"name": "Y", "wavelength_nm": 550.0, "curvature_um": [-120.0]}])
    cycles = 32
    fs = cycles / 256 / 5e-3
    r = Renderer(spec, stripes(256, 64, cycles))
    xs = np.arange(256)
    xm, ym = spec.pixel_to_mm(xs, np.full(256, 31.5))
    z = float(spec.best_focus_um(xm[216], ym[216], "Y"))  # in focus ~88 px right of centre
    img = r.render_float(z)[:, :, 0] / r.exposure
    for x0 in range(8, 248, 16):
        got = amplitude(img, cycles, x0, x0 + 16) / 0.3
        dz = spec.effective_defocus_um(z, xm[x0:x0 + 16], ym[x0:x0 + 16], "Y")
        want = float(np.mean(spec.otf(fs, dz, "Y")))
        assert got == pytest.approx(want, abs=0.04), (x0, got, want)
    amps = {x0: amplitude(img, cycles, x0, x0 + 16) for x0 in range(8, 248, 16)}
    peak = max(amps, key=lambda x0: abs(amps[x0]))
    assert abs(abs(peak + 7.5 - 127.5) - 88.5) <= 16  # the in-focus ring (either side of the centre)
    assert amps[peak] > abs(amps[120]) + 0.1  # the centre is visibly blurred


def disc_esf(x, radius):
    """Fraction of a uniform disc of this radius left of a line at signed offset x (closed form)."""
    u = np.clip(x / radius, -1.0, 1.0)
    return 0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / np.pi


@pytest.mark.parametrize("f_number", [2.0, 4.0])
def test_blur_diameter_grows_as_defocus_over_f_number(f_number):
    # Negligible diffraction and residual: the edge spread is the geometric disc's.
    spec = make_spec(f_number=f_number, channels=[{"name": "Y", "wavelength_nm": 1.0}], residual_blur_um=0.0)
    scene = np.full((128, 128), 0.2, dtype=np.float32)
    scene[:, 64:] = 0.8
    r = Renderer(spec, scene)
    x = np.arange(28, 100) - 63.5
    for dz in [80.0, 160.0, 240.0, 320.0]:  # 4..32 px discs
        row = r.render_float(dz)[:, :, 0].mean(axis=0)[28:100] / r.exposure
        b_true = dz / f_number / 5.0
        cost = lambda b: np.sum((0.2 + 0.6 * (1 - disc_esf(-x, b / 2)) - row) ** 2)
        b_fit = minimize_scalar(cost, bounds=(0.5, 60), method="bounded").x
        assert b_fit == pytest.approx(b_true, rel=0.05), (dz, b_fit, b_true)


def test_blur_disc_on_the_sensor_does_not_breathe():
    # A defocus cone's disc on the sensor is |dz| / N however much the image has grown (exit pupil 2 mm: the image
    # is 10 % larger at +200 µm than at -200 µm); the renderer blurs before it magnifies, so it must blur less
    # where it then magnifies more. Before, the disc breathed with the image: 11 px at +200, 9 px at -200.
    spec = make_spec(f_number=4.0, channels=[{"name": "Y", "wavelength_nm": 1.0}], residual_blur_um=0.0,
                     exit_pupil_mm=2.0)
    scene = np.full((128, 128), 0.2, dtype=np.float32)
    scene[:, 64:] = 0.8  # the edge through the optical centre: magnification leaves it in place
    r = Renderer(spec, scene)
    x = np.arange(40, 88) - 63.5
    for dz in (-200.0, 200.0):
        assert float(spec.magnification(dz)) == pytest.approx(1.0 + dz / 2000.0)
        row = r.render_float(dz)[:, :, 0].mean(axis=0)[40:88] / r.exposure
        b_true = abs(dz) / 4.0 / 5.0  # 10 px on both sides of focus
        cost = lambda b: np.sum((0.2 + 0.6 * (1 - disc_esf(-x, b / 2)) - row) ** 2)
        b_fit = minimize_scalar(cost, bounds=(0.5, 30), method="bounded").x
        assert b_fit == pytest.approx(b_true, rel=0.02), (dz, b_fit, b_true)


def ecc_affine(ref, mov, motion=cv2.MOTION_AFFINE, border_px=8):
    """The 2x3 warp taking ref pixel coordinates to mov's (OpenCV's ECC, sub-pixel).

    The frame border is left out: what lies beyond the frame is unknown to any resampler (the renderer mirrors
    it), so the outermost pixels carry a few-percent artefact that would bias a sub-pixel registration.
    """
    warp = np.eye(2, 3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 300, 1e-9)
    mask = np.zeros(ref.shape, dtype=np.uint8)
    mask[border_px:-border_px, border_px:-border_px] = 255
    _, warp = cv2.findTransformECC(ref, mov, warp, motion, crit, mask, 1)
    return warp.astype(np.float64)


def test_geometry_shift_and_magnification_match_spec():
    # stage axis tilted: shift = dz tan(tilt) / pitch; both frames equally defocused (best focus at 50 µm)
    spec = make_spec(f_number=16.0, stage_axis_tilt_mrad=[40.0, -25.0],
                     channels=[{"name": "Y", "wavelength_nm": 550.0, "focus_offset_um": 50.0}])
    r = Renderer(spec, random_scene(128, 128))
    a, b = r.render_float(0.0)[:, :, 0], r.render_float(100.0)[:, :, 0]
    warp = ecc_affine(a, b, cv2.MOTION_TRANSLATION)
    np.testing.assert_allclose(warp[:, 2], np.array(spec.shift_px(100.0)), atol=0.01)
    # phase correlation agrees to its own (edge-biased) accuracy
    shift, *_ = phase_cross_correlation(b, a, upsample_factor=100, normalization=None)
    np.testing.assert_allclose(shift[::-1], np.array(spec.shift_px(100.0)), atol=0.15)
    # focus breathing: exit pupil 5 mm gives m(100 µm) = 1.02 about the (decentred) optical centre
    spec = make_spec(w=160, h=128, f_number=16.0, exit_pupil_mm=5.0, decentre_mm=[0.05, -0.03],
                     stage_axis_tilt_mrad=[10.0, 0.0],
                     channels=[{"name": "Y", "wavelength_nm": 550.0, "focus_offset_um": 50.0}])
    r = Renderer(spec, random_scene(160, 128, seed=3))
    a, b = r.render_float(0.0)[:, :, 0], r.render_float(100.0)[:, :, 0]
    warp = ecc_affine(a, b)
    m = float(spec.magnification(100.0))
    cx, cy = spec.optical_centre_px()
    sx, sy = spec.shift_px(100.0)
    want = np.array([[m, 0, cx * (1 - m) + sx], [0, m, cy * (1 - m) + sy]])
    np.testing.assert_allclose(warp[:, :2], want[:, :2], atol=5e-4)
    np.testing.assert_allclose(warp[:, 2], want[:, 2], atol=0.05)


def test_lateral_colour_scales_channels_about_centre():
    ch = [{"name": "R", "wavelength_nm": 656.3, "lateral_colour": 0.02},
          {"name": "G", "wavelength_nm": 546.1}, {"name": "B", "wavelength_nm": 486.1, "lateral_colour": -0.02}]
    spec = make_spec(w=160, h=128, channels=ch)
    r = Renderer(spec, random_scene(160, 128, seed=4))
    img = r.truth()
    for ci, lc in ((0, 0.02), (2, -0.02)):
        warp = ecc_affine(img[:, :, 1], img[:, :, ci])
        assert warp[0, 0] == pytest.approx(1 + lc, abs=5e-4) and warp[1, 1] == pytest.approx(1 + lc, abs=5e-4)
        assert warp[0, 2] == pytest.approx(-lc * 79.5, abs=0.05)


# -------------------------------------------------------------------------------- levels
def test_level_grid_and_fractional_index():
    d = level_diameters_px(10.0, 1.25, 0.5)
    assert d[0] == 0 and d[1] == 0.5 and d[-2] >= 10.0 and d[-3] < 10.0
    np.testing.assert_allclose(d[2:] / d[1:-1], 1.25)
    k = fractional_level(d.astype(np.float32), 1.25, 0.5)
    np.testing.assert_allclose(k, np.arange(len(d)), atol=1e-4)
    # between two levels the weight gives the blend the disc's second moment: (1 - t) b3^2 + t b4^2 = b^2
    b = np.float32([(d[3] + d[4]) / 2, 0.25])
    mid = fractional_level(b, 1.25, 0.5)
    t = np.array([(b[0] ** 2 - d[3] ** 2) / (d[4] ** 2 - d[3] ** 2), (b[1] / 0.5) ** 2])
    np.testing.assert_allclose(mid, [3 + t[0], t[1]], atol=1e-4)


def test_level_blend_follows_the_disc_law_near_focus():
    # The blend of the two bracketing levels' OTFs against the disc's own OTF at 1/3 cycle/px for discs up to
    # 2 px: second-order agreement, the fourth-order rest x^4 / 192 of a level step (no cusp at focus:
    # linear-in-diameter weights were 0.008 off at 0.25 px)
    from fieldcal.optics.defocus import disc_otf
    levels = level_diameters_px(4.0, 1.25, 0.5)
    f = 1.0 / 3.0
    for b in np.linspace(0.0, 2.0, 81):
        kf = float(fractional_level(np.float32([b]), 1.25, 0.5)[0])
        k = int(np.floor(kf))
        t = kf - k
        blend = (1 - t) * disc_otf(np.pi * f * levels[k]) + t * disc_otf(np.pi * f * levels[k + 1])
        assert abs(blend - disc_otf(np.pi * f * b)) < (2e-4 if b < 0.5 else 3.5e-3), b


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 150.0))
def test_level_interpolation_error_is_bounded(dz):
    # White noise (worst case: energy up to Nyquist) in [0, 1]: level-interpolated vs exact-OTF render.
    r = _noise_renderer()
    interp = r.blur_map("Y", np.full((128, 128), dz, dtype=np.float32))
    exact = r.blur_uniform("Y", dz)
    err = np.abs(interp - exact)
    assert err.max() <= 0.03  # ratio 1.25: measured worst 0.022 of the scene range (docs/simulator.md)
    assert np.sqrt(np.mean(err ** 2)) <= 0.006


def test_exact_levels_equal_direct_render():
    r = _noise_renderer()
    for d_px in level_diameters_px(20.0, 1.25, 0.5):
        dz = d_px * 2.0 * 5.0
        interp = r.blur_map("Y", np.full((128, 128), dz, dtype=np.float32))
        np.testing.assert_allclose(interp, r.blur_uniform("Y", dz), atol=3e-4)  # pads differ


_CACHE = {}


def _noise_renderer():
    if "r" not in _CACHE:
        scene = np.random.default_rng(1).random((128, 128)).astype(np.float32)
        _CACHE["r"] = Renderer(make_spec(), scene)
    return _CACHE["r"]


# --------------------------------------------------------------------------------- sensor
def test_noise_statistics_match_photon_and_read_noise():
    sensor = {"bit_depth": 12, "black_level_dn": 64, "full_well_e": 2000, "read_noise_e": 6.0,
              "signal_fraction": 0.5}
    spec = make_spec(sensor=sensor)
    r = Renderer(spec, np.full((128, 128), 0.4, dtype=np.float32), seed=7)
    frame = r.render(0.0).astype(np.float64)
    e = 0.5 * 2000  # metered: the mean scene value reaches signal_fraction of the full well
    g = gain_dn_per_e(spec.sensor)
    mean, var = 64 + g * e, g * g * (e + 36.0) + 1 / 12  # + quantisation
    n = frame.size
    assert frame.mean() == pytest.approx(mean, abs=5 * math.sqrt(var / n))
    assert frame.var() == pytest.approx(var, rel=5 * math.sqrt(2 / n))
    clean = r.render(0.0, noise=False)
    assert np.all(clean == round(mean))


def test_vignetting_follows_relative_illumination():
    spec = make_spec(relative_illumination_edge=0.6)
    r = Renderer(spec, np.full((128, 128), 0.5, dtype=np.float32))
    img = r.render_float(0.0)[:, :, 0]
    xm, ym = spec.pixel_to_mm(np.arange(128)[None, :], np.arange(128)[:, None])
    want = spec.relative_illumination(xm, ym) * 0.5 * r.exposure
    np.testing.assert_allclose(img[8:-8, 8:-8], want[8:-8, 8:-8], rtol=1e-3)
    assert img[0, 0] < 0.65 * img[64, 64]


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_bayer_mosaic_pattern(cfa):
    ch = [{"name": n, "wavelength_nm": w} for n, w in (("R", 656.3), ("G", 546.1), ("B", 486.1))]
    spec = make_spec(w=64, h=48, channels=ch, sensor={"bit_depth": 12, "cfa": cfa})
    scene = np.empty((48, 64, 3), dtype=np.float32)
    scene[...] = [0.9, 0.5, 0.1]
    frame = Renderer(spec, scene).render(0.0, noise=False)
    assert frame.shape == (48, 64) and frame.dtype == np.uint16
    level = {c: frame[i // 2::2, i % 2::2] for i, c in enumerate(cfa)}
    assert np.all(level["R"] > level["G"]) and np.all(level["G"] > level["B"])
    full = Renderer(spec, scene).truth()
    assert full.shape == (48, 64, 3)  # the truth is demosaiced


@pytest.mark.parametrize("bits,dtype", [(8, np.uint8), (10, np.uint16), (12, np.uint16), (16, np.uint16),
                                        (32, np.float32)])
def test_bit_depths_keep_scale(bits, dtype):
    spec = make_spec(w=64, h=64, sensor={"bit_depth": bits, "black_level_dn": 0, "signal_fraction": 0.5,
                                         "read_noise_e": 2.0})
    r = Renderer(spec, np.full((64, 64), 0.3, dtype=np.float32))
    frame = r.render(10.0)
    assert frame.dtype == dtype
    white = (1 << bits) - 1 if bits < 32 else 1.0
    assert frame.max() <= white
    # half the full well -> half the white level, in the sensor's own units (no rescaling to 16 bits)
    assert float(frame.mean()) == pytest.approx(0.5 * white, rel=0.02)


def test_clipping_at_white():
    spec = make_spec(w=32, h=32, sensor={"bit_depth": 8, "signal_fraction": 3.0})
    # the metered exposure leaves 10% headroom: a flat scene does not clip
    r = Renderer(spec, np.full((32, 32), 0.5, dtype=np.float32))
    assert r.exposure == pytest.approx(0.9 / 0.5)
    assert np.mean(r.render(0.0) == 255) < 0.01
    # over-exposed so the scene sits exactly at full well: noise pushes about half past white
    r.exposure = 1.0 / 0.5
    frame = r.render(0.0)
    assert frame.dtype == np.uint8 and frame.max() == 255
    assert 0.3 < np.mean(frame == 255) < 0.7


def test_determinism_and_order_independence():
    spec = make_spec(w=64, h=64, sensor={"bit_depth": 12, "read_noise_e": 3.0})
    scene = random_scene(64, 64)
    r1 = Renderer(spec, scene, seed=5)
    a, b = r1.render(-20.0), r1.render(35.0)
    r2 = Renderer(spec, scene, seed=5)
    assert np.array_equal(r2.render(35.0), b) and np.array_equal(r2.render(-20.0), a)
    assert not np.array_equal(Renderer(spec, scene, seed=6).render(-20.0), a)


def test_truth_is_in_focus_render_without_noise():
    spec = make_spec(w=64, h=64, channels=[{"name": "Y", "wavelength_nm": 550.0, "focus_offset_um": 0.0}],
                     exit_pupil_mm=8.0, stage_axis_tilt_mrad=[3.0, 1.0])
    r = Renderer(spec, random_scene(64, 64))
    np.testing.assert_allclose(r.truth()[..., 0], r.render_float(0.0)[..., 0], atol=1e-6)
    assert r.truth().dtype == np.float32


def test_truth_keeps_astigmatic_residual():
    ch = [{"name": "Y", "wavelength_nm": 550.0, "astigmatism_um": 80.0}]
    spec = make_spec(w=256, h=32, channels=ch)
    cycles = 32
    r = Renderer(spec, stripes(256, 32, cycles))
    t = r.truth()[:, :, 0] / r.exposure
    centre, edge = amplitude(t, cycles, 112, 144) / 0.3, amplitude(t, cycles, 0, 16) / 0.3
    xm, ym = spec.pixel_to_mm(np.arange(0, 16), np.full(16, 15.5))
    want = float(np.mean(spec.otf(cycles / 256 / 5e-3, 40.0 * spec.rho(xm, ym) ** 2, "Y")))
    assert centre == pytest.approx(float(spec.otf(cycles / 256 / 5e-3, 0.0, "Y")), abs=0.02)
    assert edge == pytest.approx(want, abs=0.03) and edge < centre - 0.05


# --------------------------------------------------------------------------------- errors
def test_bad_scene_and_arguments_raise_clear_errors():
    spec = make_spec(w=32, h=32)
    with pytest.raises(ParameterError, match="sensor is 32x32"):
        Renderer(spec, np.zeros((16, 16), dtype=np.float32))
    with pytest.raises(ParameterError, match=r"\[0, 1\]"):
        Renderer(spec, np.full((32, 32), 2.0, dtype=np.float32))
    with pytest.raises(ParameterError, match="channels"):
        Renderer(spec, np.zeros((32, 32, 2), dtype=np.float32))
    with pytest.raises(ParameterError, match="level_ratio"):
        Renderer(spec, np.zeros((32, 32), dtype=np.float32), level_ratio=1.0)
    r = Renderer(spec, np.zeros((32, 32), dtype=np.float32))
    with pytest.raises(ParameterError, match="finite"):
        r.render(float("nan"))
    bad = make_spec(w=32, h=32, sensor={"bit_depth": 8, "black_level_dn": 300})
    with pytest.raises(ParameterError, match="black_level_dn"):
        Renderer(bad, np.zeros((32, 32), dtype=np.float32))


def test_rgb_scene_on_mono_lens_uses_luma():
    spec = make_spec(w=32, h=32)
    scene = np.zeros((32, 32, 3), dtype=np.float32)
    scene[..., 1] = 1.0
    r = Renderer(spec, scene)
    np.testing.assert_allclose(r.scene[..., 0], 0.7152, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.sampled_from([8, 10, 12, 14, 16, 32]), st.floats(0.0, 3.0), st.floats(0.0, 50.0),
       st.integers(0, 2**31 - 1))
def test_sensor_output_always_in_range(bits, level, read_e, seed):
    from fieldcal.simulate.noise import frame_rng, to_dn
    spec = make_spec(w=16, h=16, sensor={"bit_depth": bits, "read_noise_e": read_e, "full_well_e": 500,
                                         "black_level_dn": 0 if bits == 32 else 10})
    sig = np.full((16, 16, 1), level, dtype=np.float32)
    out = to_dn(sig, spec.sensor, frame_rng(seed, -3.5))
    white = spec.sensor.white_level_dn
    assert out.dtype == {8: np.uint8, 32: np.float32}.get(bits, np.uint16)
    assert np.all(np.isfinite(out)) and out.min() >= 0 and out.max() <= white
    if level >= 1.5 and read_e < 10:  # far above full well: saturated
        assert np.all(out == white)


@pytest.mark.parametrize("phase", [0.0, 0.25, 0.5])
def test_warp_has_no_phase_dependent_blur(phase):
    """A camera magnifies without resampling: the renderer's warp must not soften detail by an amount that
    depends on the sub-pixel phase (a cubic kernel passes 0.88 at 0.25 cycles/px at half a pixel and 1.0 at
    zero, which pulled every measured best focus towards z_ref by ~0.1 scan step on the triplet)."""
    from fieldcal.simulate.warp import scale_shift
    h, w = 96, 160
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    for f in (0.1, 0.25, 0.4):
        img = np.cos(2 * np.pi * f * x).astype(np.float32)
        out = scale_shift(img, 1.0 + 1e-3, phase, 0.0)
        ref = np.cos(2 * np.pi * f * (x - phase) / (1.0 + 1e-3))
        assert np.abs(out - ref)[16:-16, 16:-16].max() < 0.01, f


def test_breathing_magnifies_the_scene_not_the_sensor_psf():
    """The sensor image is the magnified scene convolved with the PSF at the sensor: stripes of scene frequency
    f, magnified by a = m(z), reach the sensor at f / a, and their contrast there is the lens's OTF at f / a
    (closed form, with and without defocus). Blurring first and magnifying after gave OTF(f) with the whole
    PSF widened by a: here (a = 1.05, F/8, residual blur 3 µm) 0.03 off, 10 % of the contrast."""
    w, h, pitch, cycles = 128, 64, 5.0, 40  # 0.31 cycles/px of the scene
    spec = make_spec(w=w, h=h, pitch_um=pitch, f_number=8.0, residual_blur_um=3.0, exit_pupil_mm=2.0,
                     channels=[{"name": "Y", "wavelength_nm": 550.0, "focus_offset_um": 100.0}])
    r = Renderer(spec, stripes(w, h, cycles, lo=0.3, hi=0.7))
    c = (w - 1) / 2.0
    p = np.arange(24, w - 24)
    for dz in (0.0, -20.0, 25.0):
        z = 100.0 + dz
        a = float(spec.magnification(z))
        assert abs(a - (1.0 + z / 2000.0)) < 1e-12
        row = r.render_float(z)[:, :, 0].mean(axis=0)[24:w - 24] / r.exposure
        arg = 2 * np.pi * cycles * (c + (p - c) / a) / w  # where each sensor column's scene point was
        basis = np.stack([np.ones_like(arg), np.cos(arg), np.sin(arg)], axis=1)
        got = float(np.hypot(*np.linalg.lstsq(basis, row, rcond=None)[0][1:])) / 0.2
        f_sensor = cycles / w / a / (pitch * 1e-3)
        want = abs(float(spec.otf(f_sensor, dz, "Y")))
        old = abs(float(spec.otf(f_sensor * a, dz * a, "Y")))  # the PSF magnified with the scene
        assert got == pytest.approx(want, abs=0.004), (dz, got, want, old)
        assert abs(old - want) > 0.015
