"""Honest bands (issue 14): stage errors, the leave-tiles-out self-check, and coverage end to end.

The asymmetric-curve tests (sharpest position of skewed through-focus curves) are in test_measure_curves.py.
"""

import math

import numpy as np
import pytest

from fieldcal.fit import fit_surfaces
from fieldcal.fit.result import SurfaceFit
from fieldcal.fit.selfcheck import WARN_RANGE, predictive_check
from fieldcal.fit.synthetic import band_coverage, random_lens, synthetic_tiles
from fieldcal.simulate.stackgen import simulate_stack, stage_positions_um


# ------------------------------------------------------------------------------------------ stage errors
def test_stage_positions_backlash_scale_and_noise():
    z = np.array([0.0, 10.0, 20.0, 15.0, 5.0, 5.0, 30.0])
    true = stage_positions_um(z, backlash_um=2.0)
    # moving up the carriage lags 1 µm below the command, moving down 1 µm above; no move keeps the play
    np.testing.assert_allclose(true - z, [-1, -1, -1, 1, 1, 1, -1])
    np.testing.assert_allclose(stage_positions_um(z, scale_error=1e-3), z * 1.001)
    zz = np.arange(4000.0)
    noise = stage_positions_um(zz, noise_um=0.3, seed=3) - zz
    assert np.std(noise) == pytest.approx(0.3, rel=0.05) and abs(np.mean(noise)) < 0.03
    np.testing.assert_array_equal(stage_positions_um(zz, noise_um=0.3, seed=3), stage_positions_um(zz, 0.3, seed=3))


# ------------------------------------------------------------------------------ leave-tiles-out check
def _fit(spec, rng, ripple_um=0.0):
    tiles, geom, truth = synthetic_tiles(spec, rng, nx=9, ny=7, sigma_um=(0.5, 1.0), directional=False)
    if ripple_um:
        # structure between tiles no polynomial surface represents (and the truth does not have: a stand-in for
        # what a real lens adds that the surface model cannot express)
        xh = (tiles.x_px - geom.width_px / 2) / geom.width_px
        yh = (tiles.y_px - geom.height_px / 2) / geom.height_px
        from dataclasses import replace
        tiles = replace(tiles, z_best_um=tiles.z_best_um + ripple_um * np.sin(9.0 * xh) * np.cos(7.0 * yh))
    fit = fit_surfaces(tiles, geom, effort="quick", seed=0, quiet=True)
    return fit, truth


def test_self_check_is_near_nominal_when_the_model_is_right():
    # Tiles from the model itself with honest sigmas: held-out tiles fall in their 90 % band at ~0.9 and the
    # band is not widened.
    covs, scales = [], []
    for k in range(3):
        rng = np.random.default_rng(300 + k)
        fit, _ = _fit(random_lens(rng, channels=("R", "G", "B")), rng)
        sc = fit.diagnostics["self_check"]
        assert sc["status"] == "ok" and sc["n_blocks"] >= 6
        covs.append(sc["coverage"])
        scales.append(fit.band_scale)
    assert 0.82 <= np.mean(covs) <= 0.97, covs
    assert max(scales) < 1.3, scales


def test_band_scale_recovers_a_known_scale_and_only_widens():
    from fieldcal.fit.selfcheck import _fit_scale
    rng = np.random.default_rng(7)
    v = rng.uniform(0.5, 2.0, 400)      # surface variance at the held-out tiles
    nv = rng.uniform(0.2, 1.0, 400)     # their own noise
    for c in (2.0, 3.0):
        r = rng.standard_normal(400) * np.sqrt(c * c * v + nv)
        assert _fit_scale(r, v, nv) == pytest.approx(c, rel=0.15)
    r = rng.standard_normal(400) * np.sqrt(0.25 * v + nv)   # bands too wide: the check does not narrow them
    assert _fit_scale(r, v, nv) == pytest.approx(1.0, abs=1e-3)


def test_self_check_widens_a_band_whose_terms_miss_structure():
    # A corner bump (8 µm, tiles 0.5-1 µm): the fitted discrepancy covers it (scale 1, self-check ~0.9).
    # With the discrepancy's terms removed (as if the band had been tuned on another simulator), held-out blocks
    # fall outside their bands, and the check says so and widens.
    from dataclasses import replace
    rng = np.random.default_rng(401)
    spec = random_lens(rng, channels=("G",))
    tiles, geom, truth = synthetic_tiles(spec, np.random.default_rng(402), nx=9, ny=7, sigma_um=(0.5, 1.0),
                                         directional=False)
    xh, yh = tiles.x_px / geom.width_px, tiles.y_px / geom.height_px
    bump = 8.0 * np.exp(-((xh - 0.9) ** 2 + (yh - 0.85) ** 2) / (2 * 0.12 ** 2))
    fit = fit_surfaces(replace(tiles, z_best_um=tiles.z_best_um + bump), geom, effort="quick", seed=0, quiet=True)
    sc = fit.diagnostics["self_check"]
    assert WARN_RANGE[0] <= sc["coverage"] <= WARN_RANGE[1] and fit.band_scale < 1.2, sc
    d = fit.discrepancy
    # ... and the Student-t weights (which give the bump's tiles the variance of outliers) set to 1
    assert d.target.size == tiles.z_sigma_um.size
    nv = (tiles.z_sigma_um / fit.z_scale_um) ** 2
    bare = replace(d, tau=d.tau * 1e-3, jk_cov=None, misfit_scale=0.0, noise_var=nv, _cache={})
    chk = predictive_check(bare)
    assert chk.coverage_unscaled < 0.85 and chk.band_scale > 1.3, chk
    assert chk.coverage > chk.coverage_unscaled


def test_self_check_holds_out_every_tile_of_every_channel():
    rng = np.random.default_rng(5)
    fit, _ = _fit(random_lens(rng, channels=("R", "G", "B")), rng)
    sc = predictive_check(fit.discrepancy)
    assert sc.n_tiles == 3 * 63
    assert sc.time_s >= 0.0  # its cost is measured by benchmarks/bench_band_coverage.py, not here


def test_new_band_keys_are_optional_and_round_trip():
    rng = np.random.default_rng(8)
    fit, _ = _fit(random_lens(rng, channels=("G",)), rng, ripple_um=3.0)
    fit.stage_sd_um = {"G": 0.4}
    d = fit.to_dict()
    assert d["band_scale"] == fit.band_scale and d["stage_sd_um"] == {"G": 0.4}
    back = SurfaceFit.from_dict(d)
    x, y = np.array([10.0, 300.0]), np.array([10.0, 200.0])
    np.testing.assert_allclose(np.array(back.interval(x, y, "G")), np.array(fit.interval(x, y, "G")), atol=1e-9)
    # a profile written before: no band scale, no stage term, no self-check -> the band of scale 1
    for k in ("band_scale", "stage_sd_um"):
        d.pop(k)
    d["diagnostics"].pop("self_check")
    old = SurfaceFit.from_dict(d)
    assert old.band_scale == 1.0 and old.stage_sd_um == {}
    fit.band_scale, fit.stage_sd_um = 1.0, {}
    np.testing.assert_allclose(np.array(old.interval(x, y, "G")), np.array(fit.interval(x, y, "G")), atol=1e-9)


def test_report_shows_the_self_check_and_warns_outside_the_range():
    from fieldcal.report.calibration_report import self_check_summary

    class P:  # the parts of a LensProfile the summary reads
        def __init__(self, sc):
            self.surfaces = SurfaceFit.__new__(SurfaceFit)
            self.surfaces.band_scale = 1.0
            self.diagnostics = {"surface": {"self_check": sc} if sc else {}}

    base = {"status": "ok", "n_tiles": 60, "n_blocks": 12, "level": 0.9, "coverage_unscaled": 0.9, "band_scale": 1.0}
    line, warn = self_check_summary(P({**base, "coverage": 0.9}))
    assert "90 % of 60 left-out tiles" in line and warn is None
    for cov in (WARN_RANGE[0] - 0.05, WARN_RANGE[1] + 0.02):
        assert self_check_summary(P({**base, "coverage": cov}))[1]
    line, warn = self_check_summary(P(None))
    assert "no self-check" in line and warn is None


# ------------------------------------------------------------------------------------- end to end
W, H = 256, 192


def _stage_stack(tmp_path, k, noise_um=0.3, backlash_um=1.5, scale_error=1e-4):
    from fieldcal.validation.run import chart_positions_um, default_fs
    rng = np.random.default_rng(9100 + k)
    spec = random_lens(rng, channels=("R", "G", "B") if k % 4 else ("Y",), optics=True).with_sensor_size(W, H)
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    d = tmp_path / f"lens{k}"
    simulate_stack(spec, d, z, scene="chart", seed=k, progress=False, stage_noise_um=noise_um,
                   stage_backlash_um=backlash_um, stage_scale_error=scale_error)
    return spec, d, fs, float(z[1] - z[0])


def _coverage(prof, spec, backlash_um, scale_error):
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import _grid
    truth = TruthProfile(spec, W, H, z_ref_um=prof.z_ref_um)
    X, Y = _grid(W, H, 8)
    cov, sq = [], []
    for c in prof.channels:
        zt = (truth.best_focus_um(X, Y, c) + 0.5 * backlash_um) / (1.0 + scale_error)  # commanded coordinates
        lo, hi = prof.best_focus_interval_um(X, Y, c)
        cov.append(np.mean((zt >= lo) & (zt <= hi)))
        sq.append(np.mean((prof.best_focus_um(X, Y, c) - zt) ** 2))
    return float(np.mean(cov)), float(np.sqrt(np.mean(sq)))


def Stack_z(d):
    from fieldcal.formats.stack import Stack
    return Stack.open(d).z_um


def test_stage_repeatability_comes_from_the_stack_and_joins_the_band(tmp_path):
    from fieldcal.calibration.pipeline import calibrate
    spec, d, fs, step = _stage_stack(tmp_path, 1, noise_um=0.8)
    prof = calibrate(d, fs_cyc_per_mm=fs, effort="quick", z_ref_um=0.0, quiet=True)
    assert prof.calibration["stage_repeatability_um"] == pytest.approx(0.8)
    assert "stack.json" in prof.calibration["stage_repeatability_source"]
    sd = prof.surfaces.stage_sd_um
    assert set(sd) == {"R", "G", "B"} and all(0.05 < v < 0.8 for v in sd.values()), sd
    x, y = np.array([W / 2]), np.array([H / 2])
    lo, hi = prof.best_focus_interval_um(x, y, "G")
    # the frames' errors are fitted with the surface (fieldcal.fit.stage): without them the band narrows
    disc = prof.surfaces.discrepancy
    assert disc.has_stage and prof.calibration["stage_errors"]["n_frames"] == len(Stack_z(d))
    sc = prof.diagnostics["surface"]["self_check"]
    lo_c, hi_c = sc["coverage_range"]
    assert 0.0 <= lo_c <= sc["coverage_median"] <= hi_c <= 1.0 and 0.0 <= sc["field_wide_share"] <= 1.0
    disc.stage_c = None
    disc._cache.clear()
    lo0, hi0 = prof.best_focus_interval_um(x, y, "G")
    assert (hi - lo)[0] > (hi0 - lo0)[0]
    from fieldcal.calibration.pipeline import stage_repeatability, stage_sd_um
    from fieldcal.errors import ParameterError
    from fieldcal.formats.stack import Stack
    assert stage_repeatability(Stack.open(d), 0.0) == (0.0, "given")   # --stage-repeatability-um wins
    with pytest.raises(ParameterError):
        stage_repeatability(Stack.open(d), -1.0)
    table = type("T", (), {"channel": np.array(["G", "G"]), "ok": np.array([True, True]),
                           "stage_gain": np.array([0.3, 0.4])})()
    assert stage_sd_um(table, 2.0) == {"G": pytest.approx(2.0 * math.sqrt((0.09 + 0.16) / 2))}
    assert stage_sd_um(table, 0.0) == {"G": 0.0}


def test_coverage_with_stage_errors_and_self_check_agreement(tmp_path):
    """Three random lenses with stage noise, backlash and a scale error at quick effort: the band holds the
    truth (in commanded stage coordinates) at 0.75-0.98 on average (too narrow and too wide both fail), the
    surface is within 0.1 step, and the profile's self-check (its estimate of this truth coverage, with the range
    one lens's coverage falls in) holds the measured coverage in its stated range."""
    from fieldcal.calibration.pipeline import calibrate
    covs, checks, ranges, too_far = [], [], [], []
    for k in range(3):
        spec, d, fs, step = _stage_stack(tmp_path, k)
        prof = calibrate(d, fs_cyc_per_mm=fs, effort="quick", z_ref_um=0.0, quiet=True)
        cov, rms = _coverage(prof, spec, 1.5, 1e-4)
        if rms >= 0.1 * step:
            too_far.append((k, rms, step))
        covs.append(cov)
        sc = prof.diagnostics["surface"]["self_check"]
        checks.append(sc["coverage"])
        ranges.append(sc["coverage_range"])
    # session 11: measured 0.98 / 0.62 / 0.76; self-check expectation 0.95 / 0.96 / 0.95, stated 5-95 % ranges
    # 0.53-1.00 / 0.78-1.00 / 0.75-1.00. One lens's coverage is a random variable (field-wide draws, correlated
    # coefficient errors): the check states its range. Lens 1 falls below it: an error shared by its tiles that
    # no held-out check sees (known, not fixed; issue 14's 0.05 per lens is not met: docs/fitting.md
    # "Self-checked coverage"). Before session 11 the check was the held-out tiles' coverage, mean gap 0.15.
    assert 0.75 <= np.mean(covs) <= 0.98, covs
    assert sum(lo - 0.005 <= c <= hi + 0.005 for c, (lo, hi) in zip(covs, ranges)) >= 2, (covs, ranges)
    assert abs(np.mean(checks) - np.mean(covs)) <= 0.2, (checks, covs)
    assert all(0.0 <= lo <= e <= hi <= 1.0 for e, (lo, hi) in zip(checks, ranges)), (checks, ranges)
    # Lens 0 (256x192, quick) was a known defect until session 8: its ring of edge tiles read low because the SML's
    # absolute values change as the breathing image crosses the pixel grid (measure/focus.sml), and the surface
    # carried that to the corners beyond the tiles: 3.2 µm RMS = 0.12 step. With the phase-invariant RMS second
    # difference 1.5 µm = 0.054 step.
    assert not too_far, too_far


# --------------------------------------------------------------------------- wave-optics truth is kept
def test_wave_truth_survives_load_and_z_ref_rebuild(tmp_path):
    """A wave-optics stack's truth is its sharpest position (spherical aberration moves it ~20 µm off the
    spec's surface here); loading truth.json and rebuilding for a profile's z_ref must not fall back to the
    geometric surface (validation compared wave profiles with the wrong truth)."""
    from pathlib import Path

    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import load_truth
    from fieldcal.validation.run import surface_metrics

    spec = LensSpec.load(Path(__file__).resolve().parents[1] / "models" / "triplet-wave-sa.json")
    simulate_stack(spec, tmp_path / "st", [-20.0, 0.0, 20.0], size=(96, 54), optics="wave", fs_cyc_per_mm=10.0,
                   progress=False)
    truth = load_truth(tmp_path / "st")
    assert truth.optics == "wave" and truth.fs_cyc_per_mm == 10.0
    x, y = np.array([5.0, 48.0, 90.0]), np.array([3.0, 27.0, 50.0])
    shift = truth.best_focus_um(x, y, "G") - truth.reference_focus_um(x, y, "G")
    assert np.all(np.abs(shift) > 5.0)  # the case where the two truths differ
    moved = truth.with_z_ref(7.0)
    assert moved.optics == "wave" and moved.image_size_px == truth.image_size_px and moved.z_ref_um == 7.0
    # a "profile" that is the exact wave truth in another reference geometry: zero error only if the rebuilt
    # truth is the wave one too
    metrics, _, _ = surface_metrics(moved, truth)
    assert max(m["rms_um"] for m in metrics.values()) < 1e-6


def test_sub_spacing_discrepancy_is_tile_noise_in_the_check():
    """A discrepancy GP shorter than a tile spacing cannot be told from tile noise, and the band leaves it out
    (Discrepancy.gp_identified() = 0). Held-out tiles that scatter by exactly that nugget must not make the
    check widen the surface band (it did: c = 2.3 on a random lens whose surface error was 1/7 of the band)."""
    from dataclasses import replace

    rng = np.random.default_rng(11)
    fit, _ = _fit(random_lens(rng, channels=("R", "G", "B")), rng)
    d = fit.discrepancy
    spacing = d.diagnostics["tile_spacing"]
    tau = 2.0 * np.sqrt(np.median(d.noise_var)) * np.ones(d.tau.size)
    nug = replace(d, length_scale=0.5 * spacing, tau=tau, _cache={},
                  target=d.target + tau[d.ch_index] * np.random.default_rng(2).standard_normal(d.target.size))
    assert nug.gp_identified() == 0.0 and replace(d, length_scale=spacing).gp_identified() == 1.0
    chk = predictive_check(nug)
    assert chk.band_scale < 1.3 and 0.82 <= chk.coverage <= 0.97, chk
    # the same scatter with the GP's identified (>= one spacing) is surface: then the check is free to widen
    assert predictive_check(replace(nug, length_scale=0.5 * spacing, tau=0.0 * tau, _cache={})).band_scale > 1.3


# ------------------------------------------------------------------------- --confidence stack plans
def test_confidence_plan_states_the_expected_fraction_in_tolerance():
    """The plan's expected_fraction is the fraction of pixels in tolerance it promises on average: with true
    surfaces drawn from the profile's own band (a field-wide shift ~ N(0, sigma), sigma = band / z_0.95), the
    measured fraction averaged over the draws (Gauss-Hermite) matches it within 2 points (issue 14); the worst-
    pixel probability is a lower bound of it."""
    from scipy.special import ndtri

    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.plan.cover import nearest_index
    from fieldcal.plan.scene import full_grid
    from fieldcal.plan.synthetic import SyntheticProfile

    band, tol = 1.0, 4.0
    prof = SyntheticProfile(97, 65, a_um=-120.0, tolerance_um=tol, band_um=band)
    for conf in (0.5, 0.9):
        plan = plan_stack(prof, StackRequest(confidence=conf, grid_step_px=4))
        sigma = band / float(ndtri(0.5 + 0.5 * conf))
        x, y = full_grid(plan.field.roi)
        frames = np.sort(plan.frames_um)
        z = prof.best_focus_um(x, y, "G")
        nodes, w = np.polynomial.hermite_e.hermegauss(40)
        zf = frames[nearest_index(frames, z)]  # the frame the profile assigns each pixel
        measured = sum(wi * np.mean(np.abs(zf - (z + sigma * c)) <= tol) for c, wi in zip(nodes, w)) / w.sum()
        st = plan.stats
        assert st["probability"] <= st["expected_fraction"] <= 1.0
        assert abs(st["expected_fraction"] - measured) <= 0.02, (conf, st["expected_fraction"], measured)


def test_wave_truth_tolerance_is_the_pupils_own():
    """Wave optics: the truth's tolerance comes from the pupil's through-focus MTF at fs (spherical aberration
    skews it), the nearer of the two sides where MTF has fallen by q: there MTF = (1 - q) peak, on the far side
    at the same distance it is still above."""
    from pathlib import Path

    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.simulate.wave import ChannelOptics, terms_at

    spec = LensSpec.load(Path(__file__).resolve().parents[1] / "models" / "triplet-wave-sa.json")
    spec = spec.with_sensor_size(96, 54)
    fs, q = 40.0, 0.05
    t = TruthProfile(spec, optics="wave", fs_cyc_per_mm=fs)
    tol = float(t.focus_tolerance_um(10.0, 10.0, "G", fs, q))
    opt = ChannelOptics(spec, "G")
    terms = terms_at(spec, "G", 0.0, 0.0)
    z0 = opt.best_focus_shift_um(terms, fs)
    peak = opt.mtf(terms, z0, fs)
    m = sorted(opt.mtf(terms, z0 + s * tol, fs) / peak for s in (-1.0, 1.0))
    assert m[0] == pytest.approx(1.0 - q, abs=2e-4) and m[1] > m[0] + 1e-4, m  # skewed: the sides differ
    assert tol != pytest.approx(TruthProfile(spec).focus_tolerance_um(10.0, 10.0, "G", fs, q), rel=1e-3)


def test_decomposition_summary_recovers_which_field_wide_term_is_real():
    """The benchmark's per-term check (bench_band_coverage.decomposition_summary) on pistons drawn with known
    variances: a term stated 4x too large in variance gets a multiplier near 1/4, an honest one near 1, a term no
    profile states none; the RMS piston / stated sd is the closed form sqrt(sum a v / sum v)."""
    from bench_util import import_bench
    bench = import_bench("bench_band_coverage")
    rng = np.random.default_rng(3)
    rows = []
    for _ in range(400):
        v = rng.uniform(0.01, 0.1, 2)          # stated frames and breathing variances (µm²) of one lens
        true_var = v[0] * 1.0 + v[1] * 0.25    # frames honest, breathing stated 4x its real variance
        rows.append({"dec_piston_um": [float(rng.normal(0.0, math.sqrt(true_var)))],
                     "dec_tilt_um": [[0.0, 0.0]], "dec_rest_um": [0.1], "dec_coef_piston_var": [0.0],
                     "dec_coef_tilt_var": [0.01], "dec_local_var": [0.01],
                     "dec_frames_var": [float(v[0])], "dec_common_var": [0.0], "dec_breathing_var": [float(v[1])],
                     "dec_offset_var": [0.0]})
    d = bench.decomposition_summary(rows)
    assert d["n"] == 400
    assert 0.75 < d["ml_frames"] < 1.3 and 0.05 < d["ml_breathing"] < 0.5, d
    assert math.isnan(d["ml_common"]) and math.isnan(d["ml_offset"])
    assert d["rest_local_med"] == pytest.approx(1.0)
    assert 0.7 < d["piston_z_rms"] < 0.9, d    # sqrt((1 + 0.25) / 2) = 0.79 on average


def test_misfit_term_adds_only_what_a_model_average_does_not_already_state():
    """The misfit term (F test of the chosen surface against the richest) and a model average's other members
    both widen the band for "the chosen surface may be too simple": ``Discrepancy.predict(covered=v)`` adds the
    misfit variance only beyond v, closed form ``extra(v) = extra(None) - min(misfit, v)`` pointwise."""
    from fieldcal.fit.discrepancy import Discrepancy, misfit_term
    from fieldcal.fit.surface import SurfaceModel
    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.linspace(-0.8, 0.8, 9), np.linspace(-0.6, 0.6, 7))
    xh, yh = gx.ravel(), gy.ravel()
    ci = np.zeros(xh.size, np.int64)
    flat = SurfaceModel(("G",), 0, False, False, False, False, 0)
    X = flat.design(xh, yh, ci, np.zeros(xh.size, np.int64), np.zeros(2))
    cov = np.linalg.inv(X.T @ X)
    y = 4.0 * (xh ** 2 + yh ** 2) ** 2 + rng.standard_normal(xh.size)
    rich, rcov, scale, diag = misfit_term(flat, np.zeros(2), xh, yh, ci, y, np.ones(xh.size), cov)
    assert scale > 1.0
    d = Discrepancy(flat, np.zeros(2), xh, yh, ci, y, np.ones(xh.size), np.array([0.0]), 1.0, 1.0, cov,
                    rich_model=rich, rich_cov=rcov, misfit_scale=scale)
    px, py = np.linspace(-1.0, 1.0, 9), np.linspace(-0.7, 0.7, 9)
    _, base = d.predict(px, py, 0)
    _, no_misfit = _with_misfit_scale(d, 0.0).predict(px, py, 0)
    misfit = base - no_misfit
    assert np.all(misfit > 0)
    for v in (np.zeros(px.size), 0.5 * misfit, 10.0 * misfit, np.linspace(0.0, 2.0, px.size) * misfit):
        _, extra = d.predict(px, py, 0, covered=v)
        np.testing.assert_allclose(extra, base - np.minimum(misfit, v), rtol=1e-9, atol=1e-12)


def _with_misfit_scale(d, scale):
    from dataclasses import replace
    return replace(d, misfit_scale=scale, _cache={})


def test_profiles_written_before_keep_the_summed_misfit():
    """A new fit marks its discrepancy (misfit beyond the model average); a profile written before has no mark and
    keeps the band it had (the misfit added in full), through a round trip."""
    from fieldcal.fit.discrepancy import Discrepancy
    rng = np.random.default_rng(4)
    fit = fit_surfaces(*synthetic_tiles(random_lens(rng, channels=("G",)), rng, nx=9, ny=7, sigma_um=(0.5, 1.0),
                                        directional=False)[:2], effort="quick", seed=0, quiet=True)
    d = fit.discrepancy
    assert d.misfit_beyond_average
    assert Discrepancy.from_dict(d.to_dict(), d.model).misfit_beyond_average
    old = d.to_dict()
    old.pop("misfit_beyond_average")
    assert not Discrepancy.from_dict(old, d.model).misfit_beyond_average
    z = np.random.default_rng(0).normal(size=(50, 3))
    xh, yh = np.zeros(3), np.zeros(3)
    fit.diagnostics["model_average"] = {"members": [{"name": "a"}, {"name": "b"}]}
    assert fit.model_average_covered(z, xh, yh, 0) is not None
    fit.discrepancy = Discrepancy.from_dict(old, d.model)
    assert fit.model_average_covered(z, xh, yh, 0) is None
