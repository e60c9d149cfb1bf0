"""Posterior: emcee convergence bookkeeping and agreement with the Laplace approximation."""

from dataclasses import replace

import numpy as np

from fieldcal.fit import fit_surfaces
from fieldcal.fit.map import fit_map
from fieldcal.fit.posterior import Effort, laplace, run_emcee
from fieldcal.fit.select import build_rows
from fieldcal.fit.surface import SurfaceModel
from fieldcal.fit.synthetic import band_coverage, base_lens, random_lens, synthetic_tiles


def _mono_problem(seed=0):
    spec = base_lens(("G",))
    spec = replace(spec, channels=(replace(spec.channels[0], curvature_um=(-120.0,)),))
    tiles, geom, truth = synthetic_tiles(spec, np.random.default_rng(seed), nx=7, ny=5, directional=False)
    rows, zc, zs = build_rows(tiles, geom, ("G",))
    model = SurfaceModel(("G",), 1, False, False, False, False)
    return model, rows, fit_map(model, rows)


def test_emcee_converges_and_agrees_with_laplace():
    model, rows, res = _mono_problem()
    lap = laplace(model, rows, res.theta)
    post = run_emcee(model, rows, res.theta, Effort("t", "emcee", 1, 1000, 6000), ball_cov=np.cov(lap.samples.T),
                     quiet=True)
    d = post.diagnostics
    assert d["converged"] and d["n_steps"] > 50 * d["tau_max"]
    assert 0.05 < d["acceptance_fraction"] < 0.9 and d["effective_sample_size"] > 500
    assert post.samples.shape[0] <= 2000
    # the coefficients' posterior sds agree with the Laplace approximation (a near-Gaussian problem)
    sd_mc = post.samples[:, :2].std(0)
    sd_lap = lap.samples[:, :2].std(0)
    np.testing.assert_allclose(sd_mc, sd_lap, rtol=0.25)
    np.testing.assert_allclose(post.samples[:, :2].mean(0), res.theta[:2], atol=0.5 * sd_lap.max())


def test_non_convergence_is_reported_not_hidden():
    model, rows, res = _mono_problem(1)
    post = run_emcee(model, rows, res.theta, Effort("t", "emcee", 1, 60, 120), quiet=True)
    assert post.diagnostics["converged"] is False and post.diagnostics["n_steps"] == 120


def test_standard_effort_reports_chain_diagnostics():
    spec = random_lens(np.random.default_rng(11), channels=("G",))
    tiles, geom, truth = synthetic_tiles(spec, np.random.default_rng(12), nx=6, ny=5, underestimate=1.5)
    f = fit_surfaces(tiles, geom, effort="standard", quiet=True)
    d = f.diagnostics["posterior"]
    assert d["method"] == "emcee" and {"tau_max", "acceptance_fraction", "effective_sample_size"} <= set(d)
    assert band_coverage(f, truth, n=9) > 0.5
