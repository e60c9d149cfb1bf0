"""Quick effort's sml@fs offset from a strip of tiles (fieldcal.measure.fs_strip), and the offset's error as a
field-wide band term (fit.tiles.measure_offset_sd_um)."""

import math

import numpy as np
import pytest

from fieldcal.measure import focus, fs_strip
from fieldcal.measure.throughfocus import CurveFit, offset_sd_um, shift_by_offset


def _texture(h, w, seed=0):
    import cv2
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 0.7)


@pytest.mark.parametrize("f0", [0.12, 0.25])
def test_strip_bandpass_equals_the_full_frame_bandpass_on_its_cells(f0):
    """The strip, band-passed with its margin and cropped, gives the full-frame band-pass's cell energies on
    its rows (the crop's border response stays in the margin), and 0 elsewhere."""
    plane = _texture(160, 200)
    cell = 4
    strip = fs_strip.centre_strip(plane.shape[0], 79.5, 40.0, cell, f0)
    assert strip.row0 % cell == 0 and strip.row1 - strip.row0 == 40 and strip.row0 <= 79.5 < strip.row1
    full = focus.cell_sums(np.square(focus.bandpass(plane, f0)), cell)
    out = np.full_like(full, -1.0)
    fs_strip.strip_bandpass_cells(plane, strip, f0, out)
    rows = slice(strip.row0 // cell, strip.row1 // cell)
    np.testing.assert_allclose(out[rows], full[rows], rtol=0.02, atol=1e-3 * float(full.max()))
    assert np.all(np.delete(out, np.r_[rows], axis=0) == 0.0)
    # without the margin the crop's borders leak into the strip's outer cells: the margin is what removes it
    crop = focus.cell_sums(np.square(focus.bandpass(plane[strip.row0:strip.row1], f0)), cell)
    assert np.max(np.abs(crop[0] - full[rows][0])) > 5 * np.max(np.abs(out[rows][0] - full[rows][0]))


def test_strip_coverage_marks_only_tiles_inside_in_every_frame():
    cell = 4
    strip = fs_strip.centre_strip(120, 59.5, 32.0, cell, 0.2)
    cover = fs_strip.coverage_cells((30, 40), strip, float(cell * cell))
    # per-pixel mean over a box of cells = fraction of the box on the strip
    c0, c1 = strip.row0 // cell, strip.row1 // cell
    assert np.mean(cover[c0:c1, 5:13]) / (cell * cell) == 1.0
    assert np.mean(cover[c0 - 1:c1 - 1, 5:13]) / (cell * cell) < 1.0
    curves = np.array([[1.0, 1.0, 1.0], [1.0, 0.97, 1.0], [1.0, np.nan, 1.0]])
    np.testing.assert_array_equal(fs_strip.inside(curves), [True, False, False])


def test_offset_moves_best_foci_and_its_error_is_one_field_wide_draw():
    """The offset moves every accepted tile by w x offset and leaves the tiles' sds alone (its error is shared
    by them all, not each tile's noise); that error is sqrt(w sd^2 + w (1 - w) mean^2)."""
    fits = [CurveFit(10.0, 0.3, math.nan, 1.0, 0.0, "ok", 9), CurveFit.rejected("low_texture")]
    rec = {"offset_um": -2.0, "offset_sd_um": 0.2, "offset_weight": 1.0, "n_tiles": 9}
    out = shift_by_offset(fits, rec)
    assert out[0].z_best_um == pytest.approx(8.0) and out[0].z_sigma_um == 0.3
    assert out[1].status == "low_texture"
    assert offset_sd_um(rec) == pytest.approx(0.2)
    half = {"offset_um": 1.0, "offset_sd_um": 0.0, "offset_weight": 0.5}
    assert shift_by_offset(fits, half)[0].z_best_um == pytest.approx(10.5)
    assert offset_sd_um(half) == pytest.approx(0.5)  # whether it applies at all: sqrt(0.5 * 0.5 * 1)
    assert offset_sd_um({}) == 0.0


def test_measure_offset_sd_joins_the_profile_band_per_channel():
    """fit.tiles.measure_offset_sd_um reads the table's skew records (a borrowed offset's error too: it is not in
    its tiles' sds), and the profile's band adds it in quadrature as a field-wide term."""
    from types import SimpleNamespace

    from fieldcal.fit.tiles import measure_offset_sd_um
    table = SimpleNamespace(skew={"R": {"offset_um": -3.0, "offset_sd_um": 0.4, "offset_weight": 1.0},
                                  "G": {"offset_um": -3.0, "offset_sd_um": 0.4, "offset_weight": 1.0,
                                        "offset_from": "R"},
                                  "B": {"shift_um": 0.1}})
    assert measure_offset_sd_um(table) == pytest.approx({"R": 0.4, "G": 0.4, "B": 0.0})


def test_profile_band_adds_the_offset_error_in_quadrature(tmp_path):
    from scipy.special import ndtri

    from pathlib import Path

    from fieldcal.profile.lens_profile import LensProfile
    prof = LensProfile.load(Path(__file__).parent / "data" / "legacy" / "lens.json")
    ch = prof.channels[0]
    x, y = np.array([10.0, 50.0]), np.array([5.0, 30.0])
    lo0, hi0 = prof.best_focus_interval_um(x, y, ch)
    prof.calibration["measure_offset_sd_um"] = {ch: 1.5}
    lo1, hi1 = prof.best_focus_interval_um(x, y, ch)
    base = float(prof.calibration.get("systematic_sd_um") or 0.0)
    br = float((prof.calibration.get("breathing_systematic_sd_um") or {}).get(ch) or 0.0)
    zq = float(ndtri(0.95))
    # the half-width without any systematic, then with the old ones, then with the offset's added
    core2 = (0.5 * (hi0 - lo0)) ** 2 - (zq * math.hypot(base, br)) ** 2
    np.testing.assert_allclose(0.5 * (hi1 - lo1), np.sqrt(core2 + (zq * math.hypot(base, br, 1.5)) ** 2),
                               rtol=1e-6)
    np.testing.assert_allclose(0.5 * (hi1 + lo1), 0.5 * (hi0 + lo0), atol=1e-9)


def test_strip_rows_follow_the_tile_count_and_the_pixel_budget():
    """One row on a 1080p frame (its 14 columns hold MIN_TILES; the budget pays for one 136 px row), more rows on
    narrow frames, every row on a small one, never more than the grid has."""
    assert fs_strip.tile_rows(14, 7, 1920, 136) == 1
    assert fs_strip.tile_rows(14, 7, 1920, 136) * 1920 * 136 <= fs_strip.BUDGET_PX
    assert fs_strip.tile_rows(3, 9, 4000, 400) == math.ceil(fs_strip.MIN_TILES / 3)   # narrow: the tile count
    assert fs_strip.tile_rows(9, 7, 320, 32) == 7                                     # small: every row
    ys = fs_strip.tile_centres_y(119.5, 3, 32.0)
    np.testing.assert_allclose(ys, [87.5, 119.5, 151.5])


def test_bandpass_many_equals_bandpass_at_each_frequency():
    plane = _texture(90, 128, seed=3)
    f0s = [0.1, 0.16, 0.25]
    for one, f0 in zip(focus.bandpass_many(plane, f0s), f0s):
        np.testing.assert_allclose(one, focus.bandpass(plane, f0), rtol=1e-5, atol=1e-6)


def _sa_stack(w040_um: float, n: int = 160, pitch_um: float = 5.0, f_number: float = 4.0, seed: int = 0):
    """A mono chart stack through focus whose every frame is the texture times the geometric OTF of defocus and
    primary spherical aberration (fieldcal.measure.spherical.sa_otf): a closed form of how the sharpest position
    moves with frequency."""
    import cv2

    from fieldcal.formats.frames import ArrayStack
    from fieldcal.measure import spherical

    z = np.arange(-300.0, 301.0, 25.0)
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((n, n)).astype(np.float32), (0, 0), 0.7).astype(np.float64)
    spec = np.fft.fft2(tex - tex.mean())
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n), indexing="ij")) / pitch_um  # cycles/µm
    frames = []
    for dz in z:
        o, _, _ = spherical.sa_otf(np.pi * f * dz / f_number, 16.0 * np.pi * f * f_number * w040_um)
        frames.append(np.clip(np.real(np.fft.ifft2(spec * o)) + tex.mean(), 0.0, 1.0)[:, :, None])
    return ArrayStack(frames, z, ["Y"], pixel_pitch_um=pitch_um)


def _sharpest_um(f_cyc_per_um: float, w040_um: float, f_number: float = 4.0) -> float:
    from fieldcal.measure import spherical
    dz = np.linspace(-300.0, 300.0, 6001)
    o, _, _ = spherical.sa_otf(np.pi * f_cyc_per_um * dz / f_number, 16.0 * np.pi * f_cyc_per_um * f_number * w040_um)
    return float(dz[np.argmax(o * o)])


@pytest.mark.parametrize("w040_um", [0.0, 1.0])
def test_band_pass_peak_error_from_the_measured_frequency_slope(w040_um):
    """The band-pass weights a band of frequencies about fs; with spherical aberration the sharpest position moves
    with frequency, so its peak is that of the band's effective frequency. The slope dz/dln f measured either side
    of fs matches the closed form (peaks of the SA OTF at those frequencies), the effective frequency lies inside
    the band, and the measure's band term (fit.tiles.measure_offset_sd_um) is the sd of the correction that moves
    the band's peak to fs (fit.tiles.band_correction_um; tests/test_band_frequency.py); without spherical
    aberration the slope is 0 within its sd and the term is ~0. Before, the band had no such term: a band-pass
    profile stated 0 for it."""
    from fieldcal.fit.tiles import band_correction_um, measure_offset_sd_um
    from fieldcal.measure.tiles import measure_stack

    fs = 30.0  # cycles/mm: 0.15 cycles/px
    table, _ = measure_stack(_sa_stack(w040_um), fs_cyc_per_mm=fs, measure="bandpass", quiet=True)
    rec = table.skew["Y"]
    slope, sd, shift = rec["freq_slope_um"], rec["freq_slope_sd_um"], rec["freq_shift_ln"]
    assert rec["freq_n_tiles"] >= 6 and sd > 0
    # the effective frequency: inside the ring's own sd in ln f, and off fs (the band's energy and the curves'
    # sharpness change with f)
    assert 1e-3 < abs(shift) < math.sqrt(fs_strip.BAND_LOG_VAR)
    lo, hi = (_sharpest_um(fs * 1e-3 * r, w040_um) for r in fs_strip.SLOPE_FACTORS)
    expect = (hi - lo) / math.log(fs_strip.SLOPE_FACTORS[1] / fs_strip.SLOPE_FACTORS[0])
    band = measure_offset_sd_um(table)["Y"]
    # the band term is the sd of the correction that moves the band's peak to fs (slope and curvature of z(ln f))
    assert "freq_curv_um" in rec and rec["freq_curv_sd_um"] > 0
    assert band == pytest.approx(band_correction_um(rec)[1], rel=1e-9)
    if w040_um == 0.0:
        assert expect == 0.0 and abs(slope) < 3.0 * sd and band < 0.02
    else:
        assert abs(expect) > 1.0                                   # the closed form: the peak moves with f
        assert abs(slope) > 2.0 * sd and np.sign(slope) == np.sign(expect)
        assert abs(slope - expect) < 3.0 * sd + 0.25 * abs(expect)
        assert band > 0.01


def test_measure_offset_sd_adds_the_band_frequency_term_in_quadrature():
    from types import SimpleNamespace

    from fieldcal.fit.tiles import measure_offset_sd_um
    table = SimpleNamespace(skew={"R": {"offset_um": -3.0, "offset_sd_um": 0.4, "offset_weight": 1.0,
                                        "freq_slope_um": 2.0, "freq_slope_sd_um": 0.5, "freq_shift_ln": -0.03},
                                  "G": {"shift_um": 0.1, "freq_slope_um": -10.0, "freq_slope_sd_um": 0.0,
                                        "freq_shift_ln": 0.02}})
    out = measure_offset_sd_um(table)
    assert out["R"] == pytest.approx(math.hypot(0.4, 0.03 * math.hypot(2.0, 0.5)))
    assert out["G"] == pytest.approx(0.2)
    # the ring's ln-f variance is the log-Gabor energy response's: ln(sigma_ratio)^2 / 2; a band energy x
    # sharpness going as f^t moves the measure's effective frequency by that variance x t
    assert fs_strip.BAND_LOG_VAR == pytest.approx(math.log(focus.LOG_GABOR_SIGMA_RATIO) ** 2 / 2.0)
    assert fs_strip.effective_shift_ln(-1.0, -1.0) == pytest.approx(fs_strip.BAND_LOG_VAR * 1.0)
    assert fs_strip.effective_shift_ln(math.nan, 0.0) == 0.0


def test_offset_zone_jackknife_sees_an_offset_that_varies_over_the_field():
    """Delete-a-zone jackknife of the pooled offset: with equal sds and zones of equal count it is the sd of the
    zone means over sqrt(K) (closed form); an offset that changes with field radius gets that, where the pooled
    mean's own sd (scatter / sqrt(n)) is smaller; independent tile noise gives about the pooled sd."""
    from fieldcal.measure.throughfocus import OFFSET_ZONES, pooled_mean, zone_jackknife_sd

    k, per = OFFSET_ZONES, 12
    radius = np.repeat(np.arange(k, dtype=float), per) + np.tile(np.linspace(0.0, 0.5, per), k)
    zone_means = np.array([-3.0, -2.6, -2.5, -2.2, -1.7])[:k]
    d = np.repeat(zone_means, per)
    sd = np.full(d.size, 0.3)
    jk = zone_jackknife_sd(d, sd, radius)
    assert jk == pytest.approx(np.std(zone_means, ddof=1) / math.sqrt(k), rel=1e-9)
    assert jk > 1.5 * pooled_mean(d, sd)[1]
    rng = np.random.default_rng(5)
    ratios = []
    for _ in range(200):
        e = rng.normal(0.0, 0.3, 60)
        ratios.append(zone_jackknife_sd(e, np.full(60, 0.3), rng.random(60)) / pooled_mean(e, np.full(60, 0.3))[1])
    assert 0.8 < float(np.sqrt(np.mean(np.square(ratios)))) < 1.2
    assert zone_jackknife_sd(d[:5], sd[:5], radius[:5]) == 0.0   # too few tiles for the zones


def test_strip_frames_keep_the_strip_rows_and_read_as_full_maps():
    """The side bands are stored as the strip's rows only; a frame reads back as the full cell map that
    strip_bands_cells wrote (zeros off the strip)."""
    plane = _texture(120, 96, seed=7)
    strip = fs_strip.centre_strip(plane.shape[0], 59.5, 24.0, 4, 0.2)
    full = [np.empty((30, 24), np.float32) for _ in range(2)]
    fs_strip.strip_bands_cells(plane, strip, [0.16, 0.25], full)
    frames = [fs_strip.StripFrames(3, (30, 24), strip) for _ in range(2)]
    for f, m in zip(frames, full):
        f.write(1, m)
        np.testing.assert_array_equal(f[1], m)
        assert not f[0].any() and f.rows.shape[1] == (strip.row1 - strip.row0) // 4
