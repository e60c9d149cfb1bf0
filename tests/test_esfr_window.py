"""The e-SFR's Hamming window in the through-focus law (esfr_focus.windowed_law and its uses): checked against a
windowed FFT of a closed-form line-spread function and the exact pupil OTF, and end to end on curves the window
widened."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure import esfr_focus as ef
from fieldcal.optics import pupil


def _hamming_mtf(lsf: np.ndarray, d_px: float, h_px: float, f_cy_per_px: float) -> float:
    """|FT(lsf * Hamming)| at f over its DC value: the e-SFR's step 5 on a finely sampled LSF centred at 0."""
    x = (np.arange(lsf.size) - (lsf.size - 1) / 2) * d_px
    w = (0.54 + 0.46 * np.cos(np.pi * x / h_px)) * (np.abs(x) <= h_px)
    lw = lsf * w
    return abs(np.sum(lw * np.exp(-2j * np.pi * f_cy_per_px * x))) / abs(np.sum(lw))


@pytest.mark.parametrize("b_px", [0.5, 2.0, 4.0, 6.0])
def test_windowed_law_is_the_windowed_fft_of_a_defocus_disc(b_px):
    # a uniform disc of diameter b projects to the LSF sqrt(1 - (2x/b)^2); the law's x = pi f b (geometric optics)
    fs, h = 0.24, 8.0
    d = 1e-3
    x = (np.arange(-int(h / d), int(h / d) + 1)) * d
    lsf = np.sqrt(np.clip(1.0 - (2.0 * x / b_px) ** 2, 0.0, None))
    want = _hamming_mtf(lsf, d, h, fs)
    got = float(np.abs(ef.windowed_law(np.array([math.pi * fs * b_px]), 0.0, math.nan, ef.window_r_of(h, fs))[0]))
    assert got == pytest.approx(want, abs=2e-4)
    # before the first zero the window reads a blurred edge high (the effect this corrects)
    plain = float(np.abs(ef.windowed_law(np.array([math.pi * fs * b_px]), 0.0, math.nan, 0.0)[0]))
    if b_px == 4.0:
        assert got > plain + 0.005


@pytest.mark.parametrize("nu", [0.2, 0.35])
def test_law_taps_are_the_exact_pupil_otf_at_the_shifted_frequency(nu):
    # each tap of the windowed law is the pupil OTF (with diffraction) at (1 + t) fs for the same wavefront
    w020, w040 = 0.3, -0.5  # waves
    x = -8.0 * math.pi * nu * w020
    s = 16.0 * math.pi * nu * w040
    for t in (1.0, 1.25, 0.75, 0.25):
        got = float(ef._law(np.array([x * t]), s * t, nu * t)[0])
        want = float(np.real(pupil.otf(nu * t, w020, w040)))
        assert got == pytest.approx(want, abs=2e-3)


FS, LAM = 0.08, 0.55  # cycles/µm, µm


def _tracks(s, nu, r, step_over_delta=0.5, n_tracks=6, noise=0.002, seed=0):
    """Tracks of the law as the window reads it, MTF 0.6 at best, about foci z0 (µm); the F-number is nu's."""
    n_f = nu / (FS * LAM)
    um_per_x = n_f / (math.pi * FS)  # x = pi fs dz / N
    _, xl, xr = ef.model_points(s, 0.05, nu)
    delta = 0.5 * (xr - xl) * um_per_x
    rng = np.random.default_rng(seed)
    out, z0s = [], []
    for k in range(n_tracks):
        z0 = (0.37 * k - 1.0) * delta
        z = np.arange(-6.0, 6.0 + 1e-9, step_over_delta) * delta
        v = 0.6 * np.abs(ef.windowed_law((z - z0) / um_per_x, s, nu, r)) + rng.normal(0, noise, z.size)
        out.append((z, v))
        z0s.append(z0)
    return out, np.array(z0s), um_per_x, delta


@pytest.mark.parametrize("window", [True, False])
def test_shaped_law_through_the_window_reads_the_lens_peak_and_tolerance(window):
    s, nu, r, q = -8.0, 0.3, 0.26, 0.05  # about the clean-room sa08's s, nu and its 8 px window at 0.24 cy/px
    tracks, z0, um_per_x, delta = _tracks(s, nu, r)
    xp, xl, xr = ef.model_points(s, q, nu)
    shape = ef.channel_shape(tracks, q, fs_cyc_per_um=FS, wavelength_um=LAM, window_r=r if window else 0.0)
    assert shape.selected and np.isfinite(shape.nu)
    tk, _ = ef.analyse_tracks(tracks, q, shape=shape)
    assert all(t.ok for t in tk)
    zb = np.array([t.z_best_um for t in tk])
    width = np.median([0.5 * t.depth_um for t in tk]) / delta
    bias = float(np.median(zb - (z0 + xp * um_per_x))) / delta
    if window:
        assert width == pytest.approx(1.0, abs=0.012)
        assert abs(bias) < 0.015
    else:  # the law alone, fitted to curves the window widened, reads wide and (with SA) off focus
        assert width > 1.03
        assert abs(bias) > 0.025


@pytest.mark.parametrize("window", [True, False])
def test_symmetric_law_width_freed_of_the_window(window):
    nu, r, q = 0.3, 0.26, 0.05
    tracks, _, _, delta = _tracks(0.0, nu, r, step_over_delta=0.7)
    shape = ef.channel_shape(tracks, q, fs_cyc_per_um=FS, wavelength_um=LAM, window_r=r if window else 0.0)
    assert not shape.selected
    tk, _ = ef.analyse_tracks(tracks, q, shape=shape)
    width = np.median([0.5 * t.depth_um for t in tk if t.ok]) / delta
    if window:
        assert width == pytest.approx(1.0, abs=0.015)
    else:
        assert width > 1.025


def test_window_ratio_is_one_without_a_window_or_a_width():
    assert ef.window_width_ratio(10.0, 20.0, 0.05, 0.0, 0.3) == 1.0
    assert ef.window_width_ratio(10.0, math.nan, 0.05, 0.26, 0.3) == 1.0
    assert ef.window_r_of(math.nan, 0.24) == 0.0
    assert ef.window_r_of(8.0, 0.25) == pytest.approx(0.25)


def _cleanroom_windowed_tracks(w040_waves, nu, r, step_over_delta=0.5, n_tracks=8):
    """Tracks of MTF(fs) through focus from the clean room's own pupil quadrature (benchmarks/cleanroom/otf.py, an
    implementation independent of fieldcal's), read through the e-SFR's Hamming window (taps at fs, (1 +- r) fs
    over the DC term at r fs: a cosine times the LSF is the OTF shifted in frequency), and each track's true
    sharpest position (the unwindowed curve's maximum, on a 0.002-step grid). z in units of the tolerance."""
    from benchmarks.cleanroom.otf import otf_quadrature

    n_f = nu / (FS * LAM)  # the F-number of this nu

    def otf(dz_um, f_rel):  # signed OTF at f_rel fs for defocus dz (W020 = dz / 8 N^2)
        w020 = np.asarray(dz_um) / (8.0 * n_f ** 2 * LAM)
        return otf_quadrature(w020, w020, w040_waves, (1.0, 0.0), 2.0 * nu * f_rel, (1.0, 0.0), n=48)

    fine = np.linspace(-40.0, 40.0, 4001) * n_f  # µm: well past a few tolerances at any nu here
    m = np.abs(otf(fine, 1.0))
    j = int(np.argmax(m))
    peak = float(fine[j])
    above = fine[m >= 0.95 * m[j]]
    delta = 0.5 * float(above[-1] - above[0])
    a0, a1 = 0.54, 0.23
    out, z0s = [], []
    for k in range(n_tracks):
        z0 = (0.29 * k - 1.0) * delta  # the lens's paraxial focus of this track
        z = np.arange(-6.0, 6.0 + 1e-9, step_over_delta) * delta
        dz = z - z0
        v = np.abs((a0 * otf(dz, 1.0) + a1 * (otf(dz, 1.0 + r) + otf(dz, 1.0 - r))) / (a0 + 2.0 * a1 * otf(dz, r)))
        out.append((z, 0.8 * v))
        z0s.append(z0 + peak)
    return out, np.array(z0s), delta


@pytest.mark.parametrize("w040_waves, nu", [(0.5, 0.12), (0.5, 0.105), (0.3, 0.088)])
def test_windowed_skewed_curves_below_the_wave_threshold_read_the_sharpest_position(w040_waves, nu):
    # the clean room's sa05-f2.8 G / B and breath-sa03-f2 G at 80 cy/mm: nu below spherical.WAVE_MIN_NU, where the
    # ray law alone reads the peak within 0.002 step, but through the window the ray law's s (which absorbs
    # diffraction at fs only) gives the wrong taps at (1 +- r) fs and r fs: main read these +0.05 step high
    # (docs/benchmarks.md bench_edge_bias_s18); the exact law reads them within 0.01 step
    r, q, step_over_delta = 0.26, 0.05, 0.5
    tracks, truth, delta = _cleanroom_windowed_tracks(w040_waves, nu, r, step_over_delta)
    shape = ef.channel_shape(tracks, q, fs_cyc_per_um=FS, wavelength_um=LAM, window_r=r)
    assert shape.selected
    tk, _ = ef.analyse_tracks(tracks, q, shape=shape)
    assert all(t.ok for t in tk)
    err_steps = (np.array([t.z_best_um for t in tk]) - truth) / (step_over_delta * delta)
    assert abs(float(np.mean(err_steps))) < 0.012
    assert float(np.max(np.abs(err_steps))) < 0.025
    assert np.isfinite(shape.nu)  # the exact law, at the lens's own s (not one that absorbed diffraction)
    assert shape.s == pytest.approx(-16.0 * math.pi * nu * w040_waves, rel=0.06)
