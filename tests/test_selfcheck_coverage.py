"""The self-check as an estimator of the band's truth coverage (issue 14; fit/selfcheck.py ``coverage_estimate``).

Monte-Carlo truths: a fitted surface, errors drawn from its joint error model by an independent code path
(``profile.uncertainty.surface_estimate``: one multivariate normal over the grid), the band's coverage of each
draw; and the held-out kappa against residuals of known scale.
"""

import math

import numpy as np
import pytest

from fieldcal.fit import fit_surfaces
from fieldcal.fit.selfcheck import (GRID, LEVEL, SelfCheck, WARN_RANGE, coverage_draws, coverage_estimate,
                                    coverage_given_shared,
                                    kappa_posterior)
from fieldcal.fit.synthetic import random_lens, synthetic_tiles


class _Profile:
    """The parts of a LensProfile the self-check and the joint error model read (no field-wide systematics)."""

    def __init__(self, fit):
        self.surfaces, self.calibration = fit, {}

    def _channel(self, ch):
        return ch

    def best_focus_um(self, x, y, ch):
        return self.surfaces.predict(x, y, ch)

    def best_focus_interval_um(self, x, y, ch, level=0.9):
        return self.surfaces.interval(x, y, ch, level=level)


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(11)
    tiles, geom, _ = synthetic_tiles(random_lens(rng, channels=("G",)), rng, nx=9, ny=7, sigma_um=(0.5, 1.0),
                                     directional=False)
    return _Profile(fit_surfaces(tiles, geom, effort="quick", seed=0, quiet=True))


def _monte_carlo(prof, kappa: float, n: int = 3000, seed: int = 5) -> np.ndarray:
    """Coverage of the profile's band over the self-check's grid for ``n`` error fields drawn from the profile's
    joint covariance, its non-common part scaled by ``kappa``."""
    from fieldcal.profile.uncertainty import _common_var_um2, surface_estimate
    g = prof.surfaces.geometry
    gx, gy = np.meshgrid((np.arange(GRID[0]) + 0.5) * g.width_px / GRID[0] - 0.5,
                         (np.arange(GRID[1]) + 0.5) * g.height_px / GRID[1] - 0.5)
    x, y = gx.ravel(), gy.ravel()
    est = surface_estimate(prof, x, y, "G")
    common = _common_var_um2(prof, "G")
    cov = kappa ** 2 * (est.cov() - common) + common
    rng = np.random.default_rng(seed)
    e = rng.multivariate_normal(np.zeros(x.size), 0.5 * (cov + cov.T), size=n, method="eigh")
    lo, hi = prof.best_focus_interval_um(x, y, "G", level=LEVEL)
    # about the band's own centre: the posterior samples are a model average, whose mean is not the chosen
    # model's surface (best_focus_um) - up to 1.3 sd apart on this lens; the self-check judges the band as stated
    mid = 0.5 * (lo + hi)
    return np.mean((mid + e >= lo) & (mid + e <= hi), axis=1)


@pytest.mark.parametrize("kappa", [1.0, 0.6, 1.6])
def test_coverage_estimate_matches_monte_carlo_of_the_error_model(fitted, kappa):
    truth = _monte_carlo(fitted, kappa)
    rec = coverage_estimate(fitted, math.log(kappa), 0.0, n_draws=1500)
    assert rec["coverage"] == pytest.approx(truth.mean(), abs=0.02), (rec, truth.mean())
    assert rec["coverage_median"] == pytest.approx(np.median(truth), abs=0.03)
    assert rec["coverage_range"][0] == pytest.approx(np.quantile(truth, 0.05), abs=0.05)
    assert rec["coverage_range"][1] == pytest.approx(np.quantile(truth, 0.95), abs=0.03)
    assert rec["coverage_abs_dev"] == pytest.approx(np.mean(np.abs(truth - truth.mean())), rel=0.25, abs=0.01)
    if kappa == 1.0:  # an honest band holds the truth at its level on average
        assert abs(truth.mean() - LEVEL) < 0.04
    # a band too wide covers more, one too narrow less
    assert (rec["coverage"] > 0.93) == (kappa < 1.0) and (rec["coverage"] < 0.85) == (kappa > 1.0)


def test_coverage_draws_give_how_often_an_honest_band_lands_in_a_window(fitted):
    """coverage_draws (the per-lens coverage an exactly honest band gives under the profile's own error model)
    against the independent Monte Carlo: the same distribution, so the same chance of landing in 0.75-0.99
    (bench_band_local's count of lenses an honest band can put in the issue's window), and the same draws as
    coverage_estimate's expectation."""
    truth = _monte_carlo(fitted, 1.0)
    pooled, (at_one,), shares = coverage_draws(fitted, 1.0, n_draws=1500, extra_kappas=(1.0,))
    inside = lambda c: float(np.mean((c >= 0.75) & (c <= 0.99)))
    assert inside(pooled) == pytest.approx(inside(truth), abs=0.06), (inside(pooled), inside(truth))
    assert float(np.mean(pooled > 0.99)) == pytest.approx(float(np.mean(truth > 0.99)), abs=0.06)
    assert at_one == pytest.approx(float(pooled.mean()), abs=1e-12) and len(shares) == 1
    assert coverage_estimate(fitted, 0.0, 0.0, n_draws=1500, kappa_mode="one")["coverage"] == pytest.approx(
        float(pooled.mean()), abs=1e-12)


def test_coverage_draws_on_given_points_and_channels(fitted):
    """The self-check grid passed explicitly gives the default draws exactly; a band on points near the tiles
    (where the error model is tight) and on the corners gives coverages that still hold the truth at the level
    on average (an honest band on any point set); one channel named is that channel's coverage."""
    g = fitted.surfaces.geometry
    gx, gy = np.meshgrid((np.arange(GRID[0]) + 0.5) * g.width_px / GRID[0] - 0.5,
                         (np.arange(GRID[1]) + 0.5) * g.height_px / GRID[1] - 0.5)
    default, _, _ = coverage_draws(fitted, 1.0, n_draws=300)
    given, _, _ = coverage_draws(fitted, 1.0, n_draws=300, points_px=(gx, gy), channels=fitted.surfaces.channels)
    np.testing.assert_array_equal(default, given)
    ch = fitted.surfaces.channels[0]
    xs = np.array([0.0, g.width_px - 1.0, 0.5 * g.width_px, 0.0, g.width_px - 1.0])
    ys = np.array([0.0, g.height_px - 1.0, 0.5 * g.height_px, g.height_px - 1.0, 0.0])
    one, _, shares = coverage_draws(fitted, 1.0, n_draws=2000, points_px=(xs, ys), channels=(ch,))
    assert one.shape == (2000,) and len(shares) == 1
    np.testing.assert_allclose(one * xs.size, np.round(one * xs.size), atol=1e-9)  # counted on these 5 points
    assert abs(float(one.mean()) - LEVEL) < 0.04
    # kappa > 1: the truth is further from the surface than the band says, so the same points cover less
    less, _, _ = coverage_draws(fitted, 2.0, n_draws=2000, points_px=(xs, ys), channels=(ch,))
    assert float(less.mean()) < float(one.mean()) - 0.05


def test_kappa_enters_only_on_evidence(fitted):
    """Where the held-out tiles cannot tell kappa from 1 (its 90 % interval holds 1: a flat likelihood below 1
    leaves the prior's lower half), the estimate is the band as built, kappa = 1; where they can, kappa's
    posterior is integrated, against the same draws at the posterior's own kappa."""
    as_built = coverage_estimate(fitted, 0.0, 0.0, kappa_mode="one")
    no_evidence = coverage_estimate(fitted, math.log(0.5), 0.6)        # 90 % interval 0.19-1.34
    assert no_evidence["coverage"] == as_built["coverage"] and not no_evidence["kappa_evidence"]
    assert coverage_estimate(fitted, math.log(0.5), 0.6, kappa_mode="posterior")["coverage"] > as_built["coverage"]
    narrow = coverage_estimate(fitted, math.log(2.0), 0.2)             # 90 % interval 1.44-2.78: evidence
    assert narrow["kappa_evidence"]
    assert narrow["coverage"] == coverage_estimate(fitted, math.log(2.0), 0.2, kappa_mode="posterior")["coverage"]
    assert narrow["coverage"] < as_built["coverage"] - 0.1


def test_one_field_wide_draw_spreads_one_lens_coverage(fitted):
    """A field-wide term (one draw per lens) widens the range a lens's coverage falls in, not its mean: against
    the closed form for independent points plus one shared draw."""
    import copy
    prof = copy.copy(fitted)
    prof.calibration = {"breathing_systematic_sd_um": {"G": 3.0 * float(fitted.surfaces.sd(160, 120, "G"))}}
    prof.best_focus_interval_um = lambda x, y, ch, level=0.9: _interval_with_systematic(prof, fitted, x, y, ch, level)
    base, wide = coverage_estimate(fitted, 0.0, 0.0), coverage_estimate(prof, 0.0, 0.0)
    assert wide["field_wide_share"] > 0.8 > base["field_wide_share"]
    assert wide["coverage"] == pytest.approx(LEVEL, abs=0.03)
    assert wide["coverage_range"][0] < base["coverage_range"][0] - 0.2
    # nearly all of the variance one draw: the closed form with independent points agrees
    ref = coverage_given_shared(np.full(192, 1.0 - wide["field_wide_share"]), wide["field_wide_share"])
    assert wide["coverage_range"][0] == pytest.approx(ref["p05"], abs=0.12)


def _interval_with_systematic(prof, fitted, x, y, ch, level):
    from scipy.special import ndtri
    lo, hi = fitted.surfaces.interval(x, y, ch, level=level)
    sd = prof.calibration["breathing_systematic_sd_um"][ch]
    half = np.sqrt((0.5 * (hi - lo)) ** 2 + (float(ndtri(0.5 + 0.5 * level)) * sd) ** 2)
    return 0.5 * (lo + hi) - half, 0.5 * (lo + hi) + half


@pytest.mark.parametrize("kappa", [0.5, 1.0, 2.0])
def test_kappa_posterior_recovers_a_known_scale(kappa):
    rng = np.random.default_rng(int(kappa * 10))
    n = 600
    v = rng.uniform(0.5, 2.0, n)
    nv = rng.uniform(0.1, 0.3, n)      # the surface's share dominates: kappa is identified
    lab = np.repeat(np.arange(12), n // 12)
    r = rng.standard_normal(n) * np.sqrt(kappa ** 2 * v + nv)
    mean, sd = kappa_posterior(r, v, nv, lab)
    assert abs(mean - math.log(kappa)) < max(3.0 * sd, 0.05) and sd < 0.2


def test_kappa_posterior_says_so_when_tile_noise_hides_the_surface():
    rng = np.random.default_rng(3)
    v, nv = np.full(300, 0.01), np.full(300, 1.0)   # held-out tiles: 99 % their own noise
    r = rng.standard_normal(300) * np.sqrt(nv + 0.25 * v)
    _, sd = kappa_posterior(r, v, nv, np.repeat(np.arange(12), 25))
    assert sd > 0.5    # no evidence either way: the prior's spread (sd 1) remains


def test_warning_only_on_evidence():
    base = dict(band_scale=1.0, coverage=0.9, coverage_unscaled=0.9, n_tiles=100, n_blocks=12, z_rms=1.0,
                time_s=0.0)
    assert SelfCheck(**base, log_kappa=math.log(0.5), log_kappa_sd=1.0).warning is None   # weak evidence
    assert "narrow" in SelfCheck(**base, log_kappa=math.log(2.0), log_kappa_sd=0.1).warning
    assert "wide" in SelfCheck(**base, log_kappa=math.log(0.4), log_kappa_sd=0.1).warning
    assert SelfCheck(**base, log_kappa=math.log(1.1), log_kappa_sd=0.1).warning is None
    assert WARN_RANGE == (0.8, 0.97)


def test_report_states_the_estimate_its_range_and_warns_on_evidence_only():
    from fieldcal.fit.result import SurfaceFit
    from fieldcal.fit.selfcheck import ESTIMATES
    from fieldcal.report.calibration_report import self_check_summary

    class P:
        def __init__(self, sc):
            self.surfaces = SurfaceFit.__new__(SurfaceFit)
            self.surfaces.band_scale = 1.0
            self.diagnostics = {"surface": {"self_check": sc}}

    sc = {"status": "ok", "n_tiles": 60, "n_blocks": 12, "level": 0.9, "coverage_unscaled": 0.9, "band_scale": 1.0,
          "tile_coverage": 0.9, "coverage": 0.62, "coverage_range": [0.2, 1.0], "field_wide_share": 0.8,
          "kappa_90": [0.3, 1.4], "estimates": ESTIMATES, "warning": None}
    line, warn = self_check_summary(P(sc))
    # a low expected coverage with a wide range is no evidence against the band: no warning
    assert "62 %" in line and "20-100 %" in line and warn is None
    line, warn = self_check_summary(P({**sc, "warning": "too narrow"}))
    assert warn == "too narrow"
    # how far one lens's coverage falls from the expectation, and whether the held-out kappa was used
    line, _ = self_check_summary(P({**sc, "coverage_abs_dev": 0.087, "kappa_evidence": False}))
    assert "on average 9 points from the expectation" in line and "taken as built" in line
    line, _ = self_check_summary(P({**sc, "kappa_evidence": True}))
    assert "evidence, used" in line


def test_benchmark_summary_counts_against_known_rows():
    """benchmarks/bench_selfcheck.py's per-group figures on rows whose answers are known by hand."""
    from bench_util import import_bench
    bench = import_bench("bench_selfcheck")

    def row(measured, sc, lo, hi, group="own: wave"):
        return {"group": group, "effort": "quick", "lens": "x", "measured": measured, "self_check": sc, "lo": lo,
                "hi": hi, "sd": 0.1, "abs_dev": 0.08, "evidence": False, "warning": False}

    rows = [row(0.80, 0.90, 0.70, 1.0), row(1.00, 0.92, 0.60, 0.99), row(0.60, 0.88, 0.65, 1.0),
            row(0.95, 0.90, 0.50, 1.0, group="own: geometric")]
    s = {r["group"]: r for r in bench.summary(rows, compare=False)}
    wave = s["own: wave"]
    assert wave["n"] == 3 and wave["sc"] == pytest.approx(0.9) and wave["meas"] == pytest.approx(0.8)
    assert wave["abs"] == pytest.approx((0.10 + 0.08 + 0.28) / 3)
    assert wave["inside"] == "1/3" and wave["within"] == "0/3"      # 1.00 > 0.99 + tolerance; 0.60 < 0.65
    # the mean difference in its standard errors: sqrt(3 x 0.01) / 3
    assert wave["diff"] == f"{0.1:+.3f} ({0.1 / (math.sqrt(0.03) / 3):+.1f})"
    assert s["own: all"]["n"] == 4 and s["own: geometric"]["within"] == "1/1"
