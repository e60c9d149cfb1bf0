"""The fast renderer against a slow reference spelled out from exact parts, and its building blocks.

The reference is the renderer's former per-frame algorithm: levels by the exact OTF (``blur_uniform``) every
frame, level weights from the full-resolution defocus formula, the exact chirp-z warp (``warp.scale_shift``).
"""

import math

import numpy as np
import pytest

from fieldcal.charts.targets import chart_image
from fieldcal.simulate import Renderer
from fieldcal.simulate.bandwarp import scale_shift_fast
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.levels import LevelStack, fractional_level, fractional_level_lut
from fieldcal.simulate.noise import POISSON_EXACT_BELOW_E, add_noise_e
from fieldcal.simulate.warp import scale_shift


def reference_linear(r: Renderer, z_um):
    """Renderer.render_float by the former per-frame path (slow, exact parts)."""
    planes = []
    for ch in r.channels:
        aff = r._affine(r.spec.z_ref_um if z_um is None else z_um, ch, z_um is not None)
        kf = fractional_level(r.diameter_px(r._defocus_exact(z_um, ch, aff)).astype(np.float32), r.level_ratio,
                              r.level_floor_px)
        lo = np.floor(kf)
        t = kf - lo
        img = np.zeros(kf.shape, dtype=np.float64)
        for k in range(int(lo.min()), int(lo.max()) + 2):
            w = np.where(lo == k, 1.0 - t, 0.0) + np.where(lo == k - 1, t, 0.0)
            if w.any():
                d_um = r._level_diameter_px(k) * r.spec.f_number * r.pitch_um
                img += w * r.blur_uniform(ch, d_um)
        img = img.astype(np.float32)
        if not np.allclose(aff, [[1, 0, 0], [0, 1, 0]], rtol=0, atol=1e-12):
            img = scale_shift(img, aff[0, 0], aff[0, 2], aff[1, 2])
        planes.append(np.maximum(img * r._illum * np.float32(r.exposure), 0.0))
    return np.stack(planes, axis=2)


def psnr(a, b, peak=1.0):
    return 10 * math.log10(peak * peak / float(np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2)))


def small_triplet(w=240, h=136):
    """The paper's triplet on a small sensor of the same area (pitch ~26 µm: blur up to a few px)."""
    from pathlib import Path
    return LensSpec.load(Path(__file__).parents[1] / "models" / "triplet-uncorrected.json").with_sensor_size(w, h)


def busy_lens(w=200, h=120):
    """Everything the geometry and the level map handle: curvature, astigmatism, tilt, decentre, lateral
    colour, strong focus breathing and a tilted stage axis, at 5 µm pixels (blur up to ~30 px)."""
    ch = [{"name": "R", "wavelength_nm": 640.0, "curvature_um": [-60.0, 8.0], "astigmatism_um": 12.0,
           "lateral_colour": 0.004},
          {"name": "G", "wavelength_nm": 540.0, "curvature_um": [-55.0], "focus_offset_um": 5.0},
          {"name": "B", "wavelength_nm": 470.0, "curvature_um": [-50.0], "astigmatism_um": -6.0,
           "lateral_colour": -0.003}]
    return LensSpec.from_dict({
        "format": "fieldcal-lens/1", "name": "busy", "focal_length_mm": 10.0, "f_number": 2.8,
        "image_height_max_mm": math.hypot(w, h) * 5.0 / 2000.0, "channels": ch,
        "sensor": {"width_px": w, "height_px": h, "pixel_pitch_um": 5.0, "bit_depth": 32, "black_level_dn": 0,
                   "read_noise_e": 0.0, "full_well_e": 10000},
        "residual_blur_um": 0.8, "exit_pupil_mm": 12.0, "decentre_mm": [0.03, -0.02],
        "tilt_um_per_mm": [4.0, -3.0], "stage_axis_tilt_mrad": [2.0, -1.0], "relative_illumination_edge": 0.8})


@pytest.mark.parametrize("coarse", [False, True])
@pytest.mark.parametrize("lens,zs", [(small_triplet, [-300.0, -150.0, 0.0, 200.0, None]),
                                     (busy_lens, [-120.0, -40.0, 0.0, 90.0, None])])
def test_fast_frames_match_the_reference_path(lens, zs, coarse, monkeypatch):
    """The fast warp always; with ``coarse`` the large-frame level map (coarse grid + table) as well."""
    import fieldcal.simulate.render as render
    if coarse:
        monkeypatch.setattr(render, "_EXACT_MAP_MAX_PX", 0)
    spec = lens()
    s = spec.sensor
    scene = chart_image("texture", s.width_px, s.height_px, 3)
    r = Renderer(spec, np.dstack([scene, scene[::-1], scene[:, ::-1]]), warp="fast")
    for z in zs:
        fast = r._linear(None) if z is None else r.render_float(z)  # the truth's signal, before quantisation
        ref = reference_linear(r, z)
        assert psnr(fast, ref) >= 45.0, z
        # away from the mirrored border (what lies beyond the frame is unknown to any resampler)
        assert np.abs(fast - ref)[8:-8, 8:-8].max() <= 0.05, z


def test_auto_warp_is_fast_only_where_the_optics_are_soft_near_nyquist():
    from pathlib import Path
    spec = LensSpec.load(Path(__file__).parents[1] / "models" / "triplet-uncorrected.json")
    blank = np.zeros((8, 8), np.float32)
    small = Renderer(spec.with_sensor_size(8, 8), blank)  # 0.4 mm pixels: sharp to Nyquist
    assert small.warp == "exact" and "chirp-z" in small.settings()["warp"]
    big = spec.with_sensor_size(1920, 1080)  # in-focus |OTF| ~0.5 at 0.47 cycles/px, 2 Mpx
    assert Renderer(big, np.zeros((1080, 1920), np.float32)).warp == "fast"
    pitch = spec.with_sensor_size(1920, 1080).sensor.pixel_pitch_um  # the same pixels, a 0.5 Mpx frame
    crop = LensSpec.from_dict({**big.to_dict(), "sensor": {**big.to_dict()["sensor"], "width_px": 960,
                                                           "height_px": 540, "pixel_pitch_um": pitch}})
    assert Renderer(crop, np.zeros((540, 960), np.float32)).warp == "exact"
    with pytest.raises(Exception, match="warp"):
        Renderer(spec.with_sensor_size(8, 8), blank, warp="cubic")


def test_prepare_gives_the_same_frames_as_lazy_levels():
    spec = busy_lens(96, 64)
    scene = chart_image("texture", 96, 64, 1)
    lazy = Renderer(spec, scene, seed=4)
    eager = Renderer(spec, scene, seed=4)
    eager.prepare([-100.0, 80.0])
    for z in (80.0, -100.0, 10.0):
        assert np.array_equal(lazy.render(z), eager.render(z))


@pytest.mark.parametrize("phase", [0.0, 0.25, 0.5])
def test_fast_warp_has_no_phase_dependent_blur(phase):
    h, w = 96, 160
    x = np.mgrid[0:h, 0:w][1].astype(np.float64)
    for f in (0.1, 0.25, 0.4):
        img = np.cos(2 * np.pi * f * x).astype(np.float32)
        out = scale_shift_fast(img, 1.0 + 1e-3, phase, 0.0)
        ref = np.cos(2 * np.pi * f * (x - phase) / (1.0 + 1e-3))
        assert np.abs(out - ref)[16:-16, 16:-16].max() < 3e-3, f


def test_fast_warp_matches_the_exact_resampler_on_band_limited_content():
    # a random image band-limited to 0.4 cycles/px: the two resamplers agree to the kernel's stated accuracy
    rng = np.random.default_rng(2)
    spec = np.fft.rfft2(rng.standard_normal((90, 150)))
    fy = np.fft.fftfreq(90)[:, None]
    fx = np.fft.rfftfreq(150)[None, :]
    spec[np.maximum(np.abs(fy), np.abs(fx)) > 0.4] = 0
    img = np.fft.irfft2(spec, s=(90, 150)).astype(np.float32)
    img /= np.abs(img).max()
    for a, tx, ty in ((1.01, -0.7, 0.3), (0.985, 2.4, -1.6), (1.0, 0.5, 0.0)):
        err = np.abs(scale_shift_fast(img, a, tx, ty) - scale_shift(img, a, tx, ty))[12:-12, 12:-12]
        assert err.max() < 5e-3, (a, tx, ty)
    flat = scale_shift_fast(np.full((16, 16), 0.7, np.float32), 1.3, 5.2, -7.1)  # tiny image, far shift
    np.testing.assert_allclose(flat, 0.7, atol=1e-6)


def test_level_table_matches_the_closed_form():
    import cv2
    lut, step = fractional_level_lut(40.0, 1.25, 0.5)
    b = np.random.default_rng(0).uniform(0, 40, (64, 64)).astype(np.float32)
    got = cv2.remap(lut, b / np.float32(step), np.zeros_like(b), cv2.INTER_LINEAR)
    np.testing.assert_allclose(got, fractional_level(b, 1.25, 0.5), atol=0.01)


def test_level_pages_blend_like_a_direct_gather():
    # 5 levels per page forces several pages (consecutive pages share a level); the remap path, the numpy
    # path and a direct formula agree
    rng = np.random.default_rng(3)
    levels = rng.random((12, 20, 30)).astype(np.float32)
    st = LevelStack(20, 30)
    st.per_page = 5
    kf = rng.uniform(0, 10.99, (20, 30)).astype(np.float32)
    lo = np.floor(kf).astype(int)
    t = kf - lo
    yy, xx = np.mgrid[0:20, 0:30]
    want = (1 - t) * levels[lo, yy, xx] + t * levels[lo + 1, yy, xx]
    np.testing.assert_allclose(st.blend(kf, levels.__getitem__), want, atol=1e-6)
    st._remap_ok = False
    np.testing.assert_allclose(st.blend(kf, levels.__getitem__), want, atol=1e-6)


@pytest.mark.parametrize("e_mean,read", [(150.0, 0.0), (1000.0, 3.0), (20.0, 2.0)])
def test_photon_noise_has_poisson_moments(e_mean, read):
    n = 400_000
    rng = np.random.default_rng(5)
    x = add_noise_e(np.full(n, e_mean, np.float32), read, rng).astype(np.float64)
    var = e_mean + read * read
    assert x.mean() == pytest.approx(e_mean, abs=5 * math.sqrt(var / n))
    assert x.var() == pytest.approx(var, rel=5 * math.sqrt(2 / n))
    skew = np.mean((x - x.mean()) ** 3) / x.var() ** 1.5
    want = e_mean / var ** 1.5  # Poisson(e) + N(0, r^2)
    assert skew == pytest.approx(want, abs=5 * math.sqrt(6 / n) + 0.01)
    if e_mean < POISSON_EXACT_BELOW_E and read == 0:
        assert np.all(x == np.round(x))


def test_large_frame_noise_path_keeps_the_sensor_statistics(monkeypatch):
    """Frames above _EXACT_NOISE_MAX_PX draw per-channel streams with the normal approximation: same mean and
    variance on a flat scene (as tests/test_simulate.py checks for the exact draw), still a function of (seed, z)."""
    import fieldcal.simulate.render as render
    from fieldcal.simulate.noise import gain_dn_per_e
    monkeypatch.setattr(render, "_EXACT_NOISE_MAX_PX", 0)
    spec = busy_lens(128, 128)
    spec = LensSpec.from_dict({**spec.to_dict(), "sensor": {**spec.to_dict()["sensor"], "bit_depth": 12,
                                                            "black_level_dn": 64, "full_well_e": 2000,
                                                            "read_noise_e": 6.0, "signal_fraction": 0.5},
                               "relative_illumination_edge": 1.0})
    r = Renderer(spec, np.full((128, 128), 0.4, dtype=np.float32), seed=7)
    frame = r.render(0.0).astype(np.float64)
    e, g = 0.5 * 2000, gain_dn_per_e(spec.sensor)
    mean, var = 64 + g * e, g * g * (e + 36.0) + 1 / 12
    n = frame.size
    assert frame.mean() == pytest.approx(mean, abs=5 * math.sqrt(var / n))
    assert frame.var() == pytest.approx(var, rel=5 * math.sqrt(2 / n))
    assert np.array_equal(Renderer(spec, np.full((128, 128), 0.4, dtype=np.float32), seed=7).render(0.0),
                          r.render(0.0))


def test_a_renderer_and_its_levels_are_freed_without_the_cycle_collector():
    import gc
    import weakref
    spec = busy_lens(64, 48)
    r = Renderer(spec, chart_image("texture", 64, 48, 0))
    r.render(30.0)
    ref = weakref.ref(r._stacks[0])
    gc.disable()
    try:
        del r
        assert ref() is None  # no renderer <-> level-stack cycle keeps the levels alive
    finally:
        gc.enable()


def test_a_pure_shift_is_exact():
    # telecentric image space: scale 1, the stage-axis shift only; the phase ramp equals the chirp-z resampler
    a = np.random.default_rng(4).random((40, 70)).astype(np.float32)
    for tx, ty in ((0.3, -0.7), (2.5, 1.25), (0.0, 0.4)):
        np.testing.assert_allclose(scale_shift_fast(a, 1.0, tx, ty), scale_shift(a, 1.0, tx, ty), atol=1e-5)
