"""The band-pass that follows a breathing image samples a sensor frequency that changes through focus.

The band-pass ring is held at a fixed *scene* frequency (fs / s(z) at the sensor, s the frame's image scale), so
the through-focus curve is ``MTF(fs / s(z), z)^2``. Where the peak contrast itself falls with frequency
(diffraction, spherical aberration), that is a tilt ``-2 (d ln MTF_peak / d ln f) ln s(z)`` on ln E, which moves
the fitted peak towards the side where the image is larger by ~``2 |g0| b sigma^2`` (b = 1 / exit pupil,
sigma^2 the curve's variance). The y axis (:class:`fieldcal.measure.tiles._ScaleAxis`) removes the geometric
blur's scaling, not this; :func:`fieldcal.measure.breathing_mtf.band_energy_gain` divides the known
sensor-fixed factors (pixel aperture, diffraction) out. On the F/7.5, W040 0.27-wave lens 25 of the band benchmark
(exit pupil 14.9 mm, fs 13 cy/mm, 15 µm pixels), noiseless, exact pupil MTF x pixel aperture: +2.0 µm without
the gain, 0.00 without breathing.
"""
import math

import numpy as np

from fieldcal.measure.breathing_mtf import band_energy_gain
from fieldcal.measure.throughfocus import analyse_curves
from fieldcal.measure.tiles import _ScaleAxis
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.wave import ChannelOptics, terms_at

FS = 13.0
STEP_UM = 58.8


def _spec():
    return LensSpec.from_dict({
        "format": "fieldcal-lens/1", "name": "breathing F/7.5 with spherical aberration", "focal_length_mm": 16.0,
        "f_number": 7.5, "image_height_max_mm": 3.0,
        "channels": [{"name": "G", "wavelength_nm": 546.1, "focus_offset_um": 0.0, "curvature_um": [0.0]}],
        "sensor": {"width_px": 320, "height_px": 240, "pixel_pitch_um": 15.0},
        "exit_pupil_mm": 14.9,
        "aberrations": {"unit": "waves", "reference_wavelength_nm": 546.1, "spherical": [0.27]}})


def _fitted_minus_peak(b_per_um: float, corrected: bool) -> float:
    spec = _spec()
    opt = ChannelOptics(spec, "G")
    t = terms_at(spec, "G", 0.0, 0.0)
    z0 = opt.best_focus_shift_um(t, FS)
    z = (np.arange(12) - 6) * STEP_UM + 17.0 + z0
    z_ref = z0 + 150.0
    s = (1.0 + b_per_um * (z - z_ref)) / (1.0 + b_per_um * (z[0] - z_ref))  # frame 0's scale is the band's
    pitch = spec.sensor.pixel_pitch_um
    # what the band sees in frame k: the optics and the pixel aperture at the sensor frequency fs / s_k
    e = np.array([(opt.mtf(t, zz, FS / sk) * np.sinc(FS / sk * pitch * 1e-3)) ** 2 for zz, sk in zip(z, s)])
    if corrected:
        e = e * band_energy_gain(FS, s, pitch, spec.f_number, "G")
    axis = _ScaleAxis(z_ref, b_per_um)
    fit = analyse_curves(axis.y(z), e[None, :], "otf", FS, 0.05)[0]
    assert fit.status == "ok"
    return float(axis.z(fit.z_best_um)) - z0


def test_band_peak_exact_without_breathing():
    # telecentric: the curve is the sensor's contrast at fs itself, the gain is 1 and the fit finds the peak
    assert abs(_fitted_minus_peak(0.0, corrected=False)) < 0.05
    assert abs(_fitted_minus_peak(0.0, corrected=True)) < 0.05


def test_band_peak_with_breathing():
    b = 1.0 / 14900.0
    # the tilt the gain removes: 2 |g| b sigma^2 with g ~ -0.2 (pixel -0.13, diffraction -0.07)
    assert _fitted_minus_peak(b, corrected=False) > 1.0
    assert abs(_fitted_minus_peak(b, corrected=True)) < 0.25


def test_gain_closed_form():
    s = np.array([1.0, 0.98, 1.02])
    f, pitch, lam_g = 13.0, 15.0, 546.1
    got = band_energy_gain(f, s, pitch, None, "G")  # no F-number: the pixel aperture alone
    want = (np.sinc(f * pitch * 1e-3) / np.sinc(f / s * pitch * 1e-3)) ** 2
    assert np.allclose(got, want, rtol=1e-12)
    assert got[0] == 1.0 and got[1] > 1.0 > got[2]  # a smaller image saw a higher sensor frequency: less contrast
    # with the pupil: x the diffraction-limited MTF ratio (2/pi)(acos v - v sqrt(1 - v^2)), v = f lambda N
    n = 7.5

    def dmtf(fr):
        v = fr * lam_g * 1e-6 * n
        return 2 / math.pi * (math.acos(v) - v * math.sqrt(1 - v * v))
    got = band_energy_gain(f, s, pitch, n, "G")
    assert np.allclose(got, want * np.array([(dmtf(f) / dmtf(f / x)) ** 2 for x in s]), rtol=1e-12)
    assert np.array_equal(band_energy_gain(f, s, pitch, float("nan"), "G"), band_energy_gain(f, s, pitch, None, "G"))


def test_declared_factors():
    from fieldcal.measure.breathing_mtf import declared_factors
    assert declared_factors(None) is None
    assert declared_factors({"f_number": 4.0}) is None  # a stack that does not say gets no correction
    assert declared_factors({"f_number": 4.0, "sensor_mtf": {"pixel_aperture": True, "diffraction": True}}) == (True, 4.0)
    assert declared_factors({"f_number": 4.0, "sensor_mtf": {"pixel_aperture": True}}) == (True, None)
    assert declared_factors({"sensor_mtf": {"pixel_aperture": False, "diffraction": True}}) == (False, None)
    # no factor at all: the gain is 1 whatever the scale
    assert np.array_equal(band_energy_gain(13.0, np.array([0.97, 1.0, 1.03]), None, None, "G"), np.ones(3))
