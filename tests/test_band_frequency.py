"""The band-pass measure weights a band of frequencies, not fs alone: its peak moved to the sharpest position at fs.

Synthetic tiles from the exact (diffraction-included) pupil OTF of :mod:`fieldcal.optics.pupil`: each tile's
band-pass energy through focus is the log-Gabor ring's weight x a dead-leaves-like texture spectrum x the pixel
aperture x |OTF(f, z)|^2 summed over the ring, at fs and at the two side bands the slope strip measures. The tiles
go through the same code as a calibration's (curve fits, pooled skew shift, ``measure.tiles._frequency_slope``,
``fit.tiles.band_correction_um``) and the corrected best focus is compared with the exact peak of MTF(fs).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure import focus, fs_strip
from fieldcal.optics import pupil

FS_CYC_PER_UM = 0.08        # 80 cy/mm
PITCH_UM = 3.0
LAMBDA_UM = 0.54
SIGMA_LN = abs(math.log(focus.LOG_GABOR_SIGMA_RATIO))
N_TILES = 6


def _mtf(f_cyc_per_um, z_um, f_number, w040_waves):
    """|OTF| at frequency f for stage position z (W020 = -z / (8 N^2) in µm: the sign only mirrors the curve)."""
    w020 = -np.asarray(z_um, dtype=np.float64) / (8.0 * f_number ** 2) / LAMBDA_UM
    return np.abs(pupil.otf(f_cyc_per_um * LAMBDA_UM * f_number, w020, w040_waves))


def _band_energy(f0, z_um, f_number, w040_waves, spectrum_exp=3.0):
    """Band-pass energy of the ring at f0: G(f)^2 x texture power f^-a x pixel sinc^2 x |OTF|^2, over ln f."""
    ln_f = np.linspace(math.log(f0) - 4 * SIGMA_LN, math.log(f0) + 4 * SIGMA_LN, 33)
    f = np.exp(ln_f)
    g2 = np.exp(-(ln_f - math.log(f0)) ** 2 / SIGMA_LN ** 2)   # the ring's weight on the energy
    w = g2 * f ** -spectrum_exp * np.sinc(f * PITCH_UM) ** 2 * f * f  # d^2f = 2 pi f^2 dln f
    return sum(wi * _mtf(fi, z_um, f_number, w040_waves) ** 2 for wi, fi in zip(w, f))


def _mtf_peak_um(f_number, w040_waves):
    centre = 8.0 * f_number ** 2 * LAMBDA_UM * w040_waves      # the focus that balances W040
    g = np.linspace(centre - 80.0, centre + 80.0, 3201)
    z0 = g[np.argmax(_mtf(FS_CYC_PER_UM, g, f_number, w040_waves))]
    g = np.linspace(z0 - 0.06, z0 + 0.06, 241)
    m = _mtf(FS_CYC_PER_UM, g, f_number, w040_waves)
    zz = np.linspace(z0 - 80.0, z0 + 80.0, 6401)
    above = zz[_mtf(FS_CYC_PER_UM, zz, f_number, w040_waves) >= 0.95 * m.max()]
    return float(g[np.argmax(m)]), 0.5 * float(above.max() - above.min())


def _tiles(f_number, w040_waves):
    """Band curves (lo, fs, hi) of N_TILES tiles on one scan: the lens focus is the same, the scan's sampling phase
    differs per tile (as across a curved field), steps of half the q = 0.05 half-width."""
    z_peak, delta = _mtf_peak_um(f_number, w040_waves)
    step = 0.5 * delta
    z = z_peak + (np.arange(31) - 15) * step
    phase = (np.arange(N_TILES) / N_TILES - 0.5) * step        # tile t's focus: z_peak + phase[t]
    zt = z[None, :] - phase[:, None]
    lo, hi = fs_strip.SLOPE_FACTORS
    curves = {key: _band_energy(FS_CYC_PER_UM * r, zt, f_number, w040_waves)
              for key, r in (("bp_lo", lo), ("bandpass", 1.0), ("bp_hi", hi))}
    scale = curves["bandpass"].max()
    cc = {k: v / scale + 1e-3 for k, v in curves.items()}     # + a small noise floor
    cc["sum"] = np.ones_like(zt)
    cc["slope_cover"] = np.ones_like(zt)
    return z, cc, phase, z_peak, step


def _texture_best_focus(f_number, w040_waves):
    """(error of the band-pass peak, error after the band correction, the correction's sd), per tile, in steps."""
    from fieldcal.fit.tiles import band_correction_um
    from fieldcal.measure.throughfocus import analyse_curves, apply_pooled_skew
    from fieldcal.measure.tiles import TileRules, _frequency_slope

    z, cc, phase, z_peak, step = _tiles(f_number, w040_waves)
    fits = analyse_curves(z, cc["bandpass"], "otf", FS_CYC_PER_UM * 1e3, 0.05, wavelength_nm=LAMBDA_UM * 1e3)
    fits = apply_pooled_skew(fits, apply=True)[0]
    bp = np.array([f.z_best_um for f in fits])
    rec = _frequency_slope(cc, z, FS_CYC_PER_UM * 1e3, 0.05, TileRules())
    corr, sd = band_correction_um(rec)
    truth = z_peak + phase
    return (bp - truth) / step, (bp + corr - truth) / step, sd / step, rec


@pytest.mark.parametrize("f_number", [5.6, 8.0])
def test_texture_best_focus_is_the_mtf_peak_at_fs_with_spherical_aberration(f_number):
    """W040 = 0.8 waves: the band-pass's own peak is 0.1 (F/5.6) and 0.23 (F/8) scan step off the exact MTF(fs)
    peak (what the texture path reported before: the clean-room's uniform -0.8 / -1.1 µm); moved by the band
    correction it is within 0.05 step, and that residual lies inside the correction's stated sd."""
    raw, fixed, sd, rec = _texture_best_focus(f_number, 0.8)
    assert np.all(np.abs(raw) > 0.05)                      # the band's peak is not fs's (fails as before)
    assert np.all(np.abs(fixed) < 0.05), (raw, fixed, rec)
    assert np.all(np.abs(fixed) < 2.0 * sd)               # the band term covers what is left
    assert rec["freq_n_tiles"] == N_TILES and math.isfinite(rec["freq_curv_um"])


def test_no_spherical_aberration_no_band_correction():
    """W040 = 0: every frequency peaks at the same focus; the slope and curvature are 0 and so is the correction
    (the band-pass peak is the MTF(fs) peak already)."""
    raw, fixed, sd, rec = _texture_best_focus(4.0, 0.0)
    assert np.all(np.abs(raw) < 0.005) and np.all(np.abs(fixed) < 0.005)
    assert sd < 0.01


def test_band_peak_correction_closed_form():
    """The correction is -b s - c (V - s^2) / 2 for a parabola z(ln f) (slope b measured between the side bands,
    curvature c, effective shift s): checked against the Gaussian-weighted mean of a parabola; a record without
    the curvature is not corrected and keeps the first-order term as its sd."""
    from fieldcal.measure.throughfocus import band_peak_correction_um
    V = fs_strip.BAND_LOG_VAR
    b0, c, s = 7.0, -40.0, -0.04          # the parabola's slope and curvature at fs; the band's weight centre
    # the band measure at fs: E_w[z] for Gaussian weights of mean s, variance V, and at the side bands the same
    band = lambda l0: b0 * (l0 + s) + 0.5 * c * ((l0 + s) ** 2 + V)  # noqa: E731  (z(fs) = 0)
    h = SIGMA_LN
    rec = {"freq_slope_um": (band(h) - band(-h)) / (2 * h), "freq_slope_sd_um": 1e-9,
           "freq_curv_um": (band(h) - 2 * band(0.0) + band(-h)) / h ** 2, "freq_curv_sd_um": 1e-9,
           "freq_shift_ln": s, "freq_n_tiles": 9.0}
    corr, sd = band_peak_correction_um(rec, V)
    assert band(0.0) + corr == pytest.approx(0.0, abs=1e-9)
    assert sd == pytest.approx(math.hypot(0.5 * b0 * s * 0 + 0.5 * rec["freq_slope_um"] * s,
                                          0.5 * 0.5 * c * (V - s * s)), rel=1e-6)
    old = {k: v for k, v in rec.items() if not k.startswith("freq_curv")}
    assert band_peak_correction_um(old, V) == pytest.approx((0.0, abs(s) * math.hypot(rec["freq_slope_um"], 1e-9)))
