"""The SML's sensor-fixed gain exponent on breathing stacks (fieldcal.measure.sml_gain) against closed forms, and the
breathing band term it sets (fieldcal.fit.tiles.breathing_systematic_sd_um)."""
import dataclasses
import math

import numpy as np
import pytest

from fieldcal.measure import ArrayStack, measure_stack
from fieldcal.measure import sml_gain as sg
from fieldcal.optics.defocus import default_wavelength_nm

N_PX = 128


def _stripes(cycles: int) -> np.ndarray:
    """Vertical stripes at exactly ``cycles`` per ``N_PX`` px (one FFT bin: the weight is at one frequency)."""
    x = np.arange(N_PX)
    return np.tile(1.0 + 0.5 * np.cos(2.0 * np.pi * cycles * x / N_PX), (N_PX, 1))


@pytest.mark.parametrize("cycles", [16, 32, 48])
def test_pixel_aperture_exponent_is_the_sinc_log_slope(cycles):
    # one frequency f (cycles/px) along x: k = -f d ln sinc(f)/df = 1 - pi f cot(pi f); the blurred frame flat
    f = cycles / N_PX
    k = sg.gain_exponent(_stripes(cycles), np.ones((N_PX, N_PX)), 5.0, 5.0, None, "G")
    assert k == pytest.approx(1.0 - math.pi * f / math.tan(math.pi * f), rel=0.02)


def test_diffraction_exponent_is_the_pupil_mtf_log_slope():
    # diffraction alone at f = 0.25 cycles/px of 10 µm pixels (25 cycles/mm), F/8 at the G wavelength:
    # M(rho) = 2/pi (acos rho - rho sqrt(1 - rho^2)), rho M'/M = -(4/pi) rho sqrt(1 - rho^2) / M
    f_mm = 0.25 / 10e-3
    rho = f_mm * default_wavelength_nm("G") * 1e-6 * 8.0
    m = 2.0 / math.pi * (math.acos(rho) - rho * math.sqrt(1.0 - rho * rho))
    expect = 4.0 / math.pi * rho * math.sqrt(1.0 - rho * rho) / m
    k = sg.gain_exponent(_stripes(32), np.ones((N_PX, N_PX)), 10.0, None, 8.0, "G")
    assert k == pytest.approx(expect, rel=0.02)


def test_noise_alike_in_both_frames_cancels_and_no_factor_is_no_gain():
    rng = np.random.default_rng(3)
    noise = 0.05 * rng.standard_normal((2, N_PX, N_PX))
    with_noise = sg.gain_exponent(_stripes(32) + noise[0], np.ones((N_PX, N_PX)) + noise[1], 5.0, 5.0, None, "G")
    # 0.215; clipping the noise's periodogram difference at 0 kept its positive half (weighted at Nyquist): +0.2
    assert with_noise == pytest.approx(1.0 - math.pi / 4.0, abs=0.03)
    assert sg.gain_exponent(_stripes(16), np.ones((N_PX, N_PX)), 5.0, None, None, "G") == 0.0
    assert sg.exponent_sd(0.0) == sg.SCALE_KERNEL_SD
    # a k anywhere in [0, k_max]: RMS about 0 is k_max / sqrt(3)
    assert sg.exponent_sd(0.6) == pytest.approx(math.hypot(sg.SCALE_KERNEL_SD, 0.6 / math.sqrt(3.0)))


@pytest.fixture(scope="module")
def breathing_stack():
    """A flat lens with a 6 mm exit pupil (the image scale changes by ~5 % over the scan), G only, 192x144."""
    from conftest import MODELS
    from fieldcal.charts.targets import chart_image
    from fieldcal.simulate import Renderer
    from fieldcal.simulate.lens import LensSpec

    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    chans = tuple(dataclasses.replace(c, focus_offset_um=0.0, curvature_um=(), astigmatism_um=0.0)
                  for c in base.channels[1:2])
    spec = dataclasses.replace(base, channels=chans, stage_axis_tilt_mrad=(0.0, 0.0),
                               exit_pupil_mm=6.0).with_sensor_size(192, 144)
    r = Renderer(spec, chart_image("texture", 192, 144, 1), seed=1)
    s = spec.sensor
    z = np.arange(-150.0, 150.0 + 1e-9, 20.0)
    return spec, ArrayStack([r.render(float(v), noise=False) for v in z], z, pixel_pitch_um=s.pixel_pitch_um,
                            channels=spec.channel_names, black_level=s.black_level_dn,
                            white_level=s.white_level_dn)


def test_a_stack_sets_its_own_breathing_term(breathing_stack):
    """Undeclared: a camera's k bounds the exponent (k > 0, sd above the operator's own); declared without
    sensor-fixed MTFs: k 0 and the sd is the operator's. The breathing term scales with that sd, tile by tile."""
    from fieldcal.fit.tiles import breathing_systematic_sd_um

    spec, stack = breathing_stack
    fs = 0.2 / (spec.sensor.pixel_pitch_um * 1e-3)
    stack.meta = {"f_number": spec.f_number}
    said_nothing, _ = measure_stack(stack, fs_cyc_per_mm=fs, measure="sml", quiet=True)
    stack.meta = {"f_number": spec.f_number, "sensor_mtf": {"pixel_aperture": False, "diffraction": False}}
    said_none, _ = measure_stack(stack, fs_cyc_per_mm=fs, measure="sml", quiet=True)
    stack.meta = {}
    assert said_none.ok.sum() >= 10
    g0, g1 = said_nothing.sml_gain["G"], said_none.sml_gain["G"]
    assert not g0["declared"] and 0.05 < g0["k_max"] < 2.0
    assert g1["declared"] and g1["k_max"] == 0.0 and g1["k_sd"] == sg.SCALE_KERNEL_SD
    assert g0["k_sd"] == pytest.approx(sg.exponent_sd(g0["k_max"]))
    b0, b1 = breathing_systematic_sd_um(said_nothing)["G"], breathing_systematic_sd_um(said_none)["G"]
    assert b1 > 0.0
    assert b0 / b1 == pytest.approx(g0["k_sd"] / g1["k_sd"], rel=1e-6)
    # the tiles' best foci are the same: the term is carried, not corrected
    np.testing.assert_array_equal(said_nothing.z_best_um, said_none.z_best_um)


def test_telecentric_stack_has_no_gain_record(breathing_stack):
    spec, _ = breathing_stack
    from fieldcal.charts.targets import chart_image
    from fieldcal.simulate import Renderer

    flat = dataclasses.replace(spec, exit_pupil_mm=math.inf)
    r = Renderer(flat, chart_image("texture", 192, 144, 1), seed=1)
    z = np.arange(-150.0, 150.0 + 1e-9, 20.0)
    s = flat.sensor
    stack = ArrayStack([r.render(float(v), noise=False) for v in z], z, pixel_pitch_um=s.pixel_pitch_um,
                       channels=flat.channel_names, black_level=s.black_level_dn, white_level=s.white_level_dn)
    table, _ = measure_stack(stack, fs_cyc_per_mm=0.2 / (s.pixel_pitch_um * 1e-3), measure="sml", quiet=True)
    # the measured scale of a telecentric stack is 1 to ~1e-5, not exactly 1: a record, and a term ~0
    from fieldcal.fit.tiles import breathing_systematic_sd_um
    assert breathing_systematic_sd_um(table)["G"] < 0.01


def test_simulated_stacks_say_which_sensor_fixed_mtfs_they_carry(tmp_path):
    """The geometric path does not declare (no band-pass correction; its SML's k bounded as a camera's: see
    simulate/stackgen.py for why it does not say "none"), the wave path declares both."""
    import json

    from conftest import MODELS
    from fieldcal.measure.breathing_mtf import declared_factors
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack

    spec = LensSpec.load(MODELS / "triplet-uncorrected.json")
    simulate_stack(spec, tmp_path / "g", np.array([-10.0, 0.0, 10.0]), seed=1, size=(64, 48), progress=False)
    meta = json.loads((tmp_path / "g" / "stack.json").read_text())
    assert "sensor_mtf" not in meta
    assert declared_factors(meta) is None  # undeclared: no band-pass breathing correction
