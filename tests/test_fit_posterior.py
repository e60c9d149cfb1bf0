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


def test_independence_proposal_samples_a_known_gaussian():
    """The t independence move (with its Hastings ratio) leaves an exactly known posterior invariant: its
    samples of a correlated 6-d Gaussian have the true mean and sds, from a proposal that is off-centre, too
    wide in some directions and too narrow in others."""
    import emcee
    from fieldcal.fit.posterior import _TProposal

    rng = np.random.default_rng(3)
    d = 6
    a = rng.standard_normal((d, d))
    cov = a @ a.T / d + 0.1 * np.eye(d)
    prec = np.linalg.inv(cov)

    def log_prob(x):
        x = np.atleast_2d(x)
        return -0.5 * np.einsum("bi,ij,bj->b", x, prec, x)

    wrong = cov * np.linspace(0.6, 1.6, d)[:, None] * np.linspace(0.6, 1.6, d)[None, :]
    prop = _TProposal(0.3 * np.sqrt(np.diag(cov)), wrong, 10.0, 1.1)
    s = emcee.EnsembleSampler(32, d, log_prob, vectorize=True, moves=[(emcee.moves.MHMove(prop), 1.0)])
    s.random_state = np.random.RandomState(0).get_state()
    s.run_mcmc(rng.multivariate_normal(np.zeros(d), cov, 32), 3000, progress=False)
    x = s.get_chain(discard=200, flat=True)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(x.std(0) / sd, 1.0, atol=0.04)
    np.testing.assert_allclose(x.mean(0) / sd, 0.0, atol=0.05)


def test_pilot_chain_matches_a_long_chain_in_far_fewer_steps():
    """Standard effort's pilot + independence chain gives the posterior a long differential-evolution chain
    gives (sds and means of every parameter), meets the 50-tau rule at its first length, with a short tau."""
    from fieldcal.fit.posterior import EFFORTS

    model, rows, res = _mono_problem(2)
    cov = np.cov(laplace(model, rows, res.theta).samples.T)
    ref = run_emcee(model, rows, res.theta, Effort("ref", "emcee", 1, 6000, 6000), ball_cov=cov, seed=4,
                    quiet=True)
    post = run_emcee(model, rows, res.theta, EFFORTS["standard"], ball_cov=cov, seed=5, quiet=True)
    d = post.diagnostics
    assert d["converged"] and d["n_steps"] <= 400 and d["tau_max"] < 10 < ref.diagnostics["tau_max"]
    assert d["pilot"]["steps"] == EFFORTS["standard"].pilot_steps
    sd_ref = ref.samples.std(0)
    np.testing.assert_allclose(post.samples.std(0) / sd_ref, 1.0, atol=0.12)
    np.testing.assert_allclose((post.samples.mean(0) - ref.samples.mean(0)) / sd_ref, 0.0, atol=0.15)

from fieldcal.fit.posterior import _tau as posterior_tau  # noqa: E402


# The chain-length rule must survive a parameter whose walkers never move (its autocorrelation is 0/0).


class _Chain:
    def __init__(self, chain):
        self._chain = chain

    def get_chain(self):
        return self._chain


def test_tau_is_finite_when_a_parameter_is_stuck():
    rng = np.random.default_rng(0)
    n_steps, n_walkers = 400, 16
    moving = rng.normal(size=(n_steps, n_walkers))
    stuck = np.full((n_steps, n_walkers), 3.0)  # zero variance: emcee's estimate is NaN
    tau = posterior_tau(_Chain(np.stack([moving, stuck], axis=-1)))
    assert np.all(np.isfinite(tau))
    assert tau[0] < 5.0  # white noise: tau ~ 1
    assert tau[1] == n_steps  # counted as not mixing within the chain: the caller extends and flags it
