"""Captured-sweep deconvolution: the moving-sweep OTF against closed forms, the image velocity against the thin-lens
geometry, and on a physically integrated sweep with strong breathing the breathing-aware kernel restoring better
than the blind one."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fieldcal.composite import deconvolve_sweep
from fieldcal.composite.sweep_zones import image_velocity_px_per_um, register_to_reference
from fieldcal.optics.sweep import disc_sweep_otf, integrated_otf, moving_sweep_otf
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep
from fieldcal.simulate import Renderer
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.sweep_exposure import render_windowed_sweep
from fieldcal.simulate.truth import TruthProfile

MODELS = Path(__file__).resolve().parents[1] / "models"


def _grid(n=33, fmax=30.0):
    a = np.linspace(-fmax, fmax, n)
    return np.meshgrid(a, a)


def test_without_motion_the_kernel_is_the_blind_sweep_otf_closed_form():
    prof = SyntheticProfile(pixel_pitch_um=10.0, f_number=2.0)  # its OTF is the blur disc alone
    fx, fy = _grid()
    h = moving_sweep_otf(prof, fx, fy, 40.0, "G", velocity_px_per_um=(0.0, 0.0), pitch_um=10.0)
    np.testing.assert_allclose(h.real, disc_sweep_otf(np.hypot(fx, fy), 40.0, 2.0), atol=2e-5)
    np.testing.assert_allclose(h.imag, 0.0, atol=1e-12)
    np.testing.assert_allclose(h.real, integrated_otf(prof, np.hypot(fx, fy), 40.0, "G"), atol=2e-5)


class _NoBlur(SyntheticProfile):
    def defocus_otf(self, f_cyc_per_mm, defocus_um, channel):
        return np.ones(np.broadcast(f_cyc_per_mm, defocus_um).shape)


def test_motion_alone_is_the_uniform_streak_sinc():
    prof = _NoBlur(pixel_pitch_um=5.0)
    fx, fy = _grid(41, 80.0)
    alpha, v, p = 30.0, (0.05, -0.02), 5.0
    h = moving_sweep_otf(prof, fx, fy, alpha, "G", velocity_px_per_um=v, pitch_um=p)
    # streak of 2 α v px = 2 α v p / 1000 mm: H = sinc(f . streak)
    streak_mm = 2 * alpha * np.asarray(v) * p / 1000.0
    np.testing.assert_allclose(h, np.sinc(fx * streak_mm[0] + fy * streak_mm[1]), atol=1e-9)


def test_image_velocity_is_the_radius_over_the_exit_pupil_plus_the_shift_slope(models_dir):
    spec = LensSpec.load(models_dir / "triplet-uncorrected.json").with_sensor_size(320, 180)
    prof = TruthProfile(spec)
    cx, cy = prof.optical_centre_px()
    x, y, z = np.array([0.0, 319.0, 160.0]), np.array([0.0, 179.0, 20.0]), np.array([-250.0, -200.0, -50.0])
    vx, vy = image_velocity_px_per_um(prof, x, y, z, 20.0, "G")
    e_um = spec.exit_pupil_mm * 1000.0
    m = 1 + (z - spec.z_ref_um) / e_um
    sx, sy = spec.shift_px(z)
    tx, ty = (math.tan(a * 1e-3) / spec.sensor.pixel_pitch_um for a in spec.stage_axis_tilt_mrad)
    np.testing.assert_allclose(vx, (x - cx - sx) / m / e_um + tx, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(vy, (y - cy - sy) / m / e_um + ty, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def breathing_sweep():
    """A physically integrated sweep of the triplet at 160x90 with breathing 8x the real lens's."""
    from fieldcal.simulate.scene import load_scene
    base = LensSpec.load(MODELS / "triplet-uncorrected.json").with_sensor_size(160, 90)
    spec = dataclasses.replace(base, exit_pupil_mm=base.exit_pupil_mm / 8,
                               sensor=dataclasses.replace(base.sensor, exposure_ms=16.0))
    scene = np.asarray(load_scene("chart", 160, 90, seed=3)[0], dtype=np.float32)
    rend = Renderer(spec, scene, seed=1)
    prof = TruthProfile(spec)
    alpha = 100.0
    plan = plan_sweep(prof, SweepRequest(alpha_um=alpha, pixel_exposure_ms=16.0, trade_alphas_um=()))
    sw = render_windowed_sweep(rend, plan.start_um, plan.velocity_um_per_ms, plan.total_time_ms,
                               plan.window_start_ms, plan.window_stop_ms, step_um=8.0)
    return spec, prof, alpha, sw.image.astype(np.float32), rend.truth().astype(np.float32)


def _psnr(img, truth, white, b=8):
    d = (np.clip(img, 0, white) - truth)[b:-b, b:-b]
    return 10 * np.log10(white ** 2 / np.mean(d * d))


def test_breathing_aware_kernel_restores_a_breathing_sweep_better_than_the_blind_one(breathing_sweep):
    spec, prof, alpha, img, truth = breathing_sweep
    white, black = float(spec.sensor.white_level_dn), float(spec.sensor.black_level_dn)
    out = {m: deconvolve_sweep(img, prof, alpha, spec.channel_names, black=black, white=white, breathing=m,
                               zone_px=32) for m in ("aware", "blind")}
    streak = out["aware"].info["channels"]["G"]["max_streak_px"]
    assert streak > 4.0  # strong breathing: the corners smear over several pixels during a window
    assert out["blind"].info["channels"]["G"]["max_streak_px"] == 0.0
    reg = np.stack([register_to_reference(img[..., c], prof, ch) for c, ch in enumerate(spec.channel_names)], -1)
    p_raw, p_aware, p_blind = (_psnr(x, truth, white) for x in (reg, out["aware"].image, out["blind"].image))
    assert p_aware > p_raw + 1.0, (p_raw, p_aware, p_blind)
    assert p_aware > p_blind + 0.5, (p_raw, p_aware, p_blind)


def test_registration_undoes_the_sensor_geometry_of_a_captured_sweep(breathing_sweep):
    spec, prof, alpha, img, truth = breathing_sweep
    white = float(spec.sensor.white_level_dn)
    reg = np.stack([register_to_reference(img[..., c], prof, ch) for c, ch in enumerate(spec.channel_names)], -1)
    # with 8x breathing the window centres (D ~ 330 µm apart) put the corners ~10 px off: registering must help
    assert _psnr(reg, truth, white) > _psnr(img, truth, white) + 1.0


def test_sweep_exposure_weights_by_open_time_and_counts_noise_once():
    from fieldcal.simulate.sweep_exposure import model_noise_sigma
    base = LensSpec.load(MODELS / "doublet-mono.json").with_sensor_size(64, 48)
    spec = dataclasses.replace(base, relative_illumination_edge=1.0,
                               sensor=dataclasses.replace(base.sensor, exposure_ms=10.0, signal_fraction=0.5))
    rend = Renderer(spec, np.full((48, 64), 0.5, np.float32), seed=4)  # flat: blur and breathing change nothing
    start = np.zeros((48, 64), np.float32)
    stop = np.where(np.arange(64)[None, :] < 32, 10.0, 5.0).astype(np.float32) + start  # left t_ref, right half
    stop[:4, :4] = np.nan  # never exposed
    sw = render_windowed_sweep(rend, -50.0, 2.0, 10.0, start, stop, step_um=1.0)
    img = sw.image.astype(np.float64)[..., 0] if sw.image.ndim == 3 else sw.image.astype(np.float64)
    s = spec.sensor
    g = (s.white_level_dn - s.black_level_dn) / s.full_well_e
    full = 0.5 * s.full_well_e * g  # DN above black of one metered exposure (mean scene 0.5 metered at 0.5 FW)
    left, right = img[8:, 4:28] - s.black_level_dn, img[8:, 36:60] - s.black_level_dn
    assert left.mean() == pytest.approx(full, rel=0.01) and right.mean() == pytest.approx(full / 2, rel=0.01)
    assert np.all(img[:4, :4] <= s.black_level_dn + 4 * g * s.read_noise_e + 1)
    # photon noise of one exposure of that many electrons (not averaged down over the 20 sub-exposures)
    for part, e in ((left, full / g), (right, full / 2 / g)):
        assert part.std() == pytest.approx(g * math.sqrt(e + s.read_noise_e ** 2), rel=0.1)
    sig = model_noise_sigma(img[8:, 4:28, None], rend)[0]
    assert sig == pytest.approx(left.std(), rel=0.1)


def test_without_breathing_or_shift_aware_and_blind_deconvolution_agree():
    prof = SyntheticProfile(72, 48, a_um=-100.0, pixel_pitch_um=10.0)  # m(z) = 1, s(z) = 0
    img = np.random.default_rng(5).uniform(100.0, 900.0, (48, 72, 1)).astype(np.float32)
    out = {m: deconvolve_sweep(img, prof, 30.0, ("G",), black=0.0, white=1000.0, breathing=m, noise_sigma=[5.0],
                               zone_px=32) for m in ("aware", "blind")}
    assert out["aware"].info["channels"]["G"]["max_streak_px"] == 0.0
    np.testing.assert_allclose(out["aware"].image, out["blind"].image, atol=1e-3)


def test_bad_breathing_arguments_are_parameter_errors():
    from fieldcal.errors import ParameterError
    prof = SyntheticProfile(40, 30, pixel_pitch_um=10.0)
    img = np.ones((30, 40, 1), np.float32)
    for kw, field in (({"breathing": "yes"}, "breathing"), ({"breathing": "aware", "method": "rl"}, "deconvolve"),
                      ({"breathing": "aware", "widen_um": np.ones((5, 5))}, "widen_um"),
                      ({"breathing": "aware", "widen_um": -np.ones((30, 40))}, "widen_um")):
        with pytest.raises(ParameterError) as e:
            deconvolve_sweep(img, prof, 20.0, ("G",), black=0.0, white=1.0, **kw)
        assert e.value.field == field
