"""Posterior of the chosen surface model: Laplace approximation ("quick") or emcee ("standard"/"thorough").

Both return parameter samples (a few thousand at most) plus diagnostics; the surface bands are quantiles of
the surface evaluated at those samples (:class:`fieldcal.fit.result.SurfaceFit`).

emcee convergence rule (docs/fitting.md): walkers start in a small ball around the MAP; the chain is
converged when its length exceeds 50 integrated autocorrelation times of every parameter
(``emcee.autocorr.integrated_time``). Otherwise the chain is extended, up to a cap; if the cap is reached
the result says ``converged: False`` and keeps the samples (no silent pretence).

With a pilot (standard and thorough effort) a short differential-evolution run from Laplace draws gives the
posterior's mean and covariance, and the chain proper uses an independence Metropolis-Hastings move whose
proposal is a multivariate t fitted to the pilot (plus some differential-evolution moves): on these nearly
Gaussian posteriors its autocorrelation time is ~1-2 steps instead of ~30, so the same 50-tau rule is met
(and a larger effective sample size reached) in a tenth of the steps. The chain is still exact MCMC (the
Hastings ratio carries the proposal density); a posterior the t does not describe shows up as low
acceptance and a long tau, and the rule then extends the chain as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..progress import status
from .surface import COEF_PRIOR_SD, Rows, SurfaceModel

MAX_SAMPLES = 2000
AUTOCORR_FACTOR = 50
# Independence proposal: multivariate t with this many degrees of freedom (heavier tails than the posterior, so
# the importance ratio posterior / proposal stays bounded: uniformly ergodic), its scale the pilot's
# covariance times PROPOSAL_SCALE^2, chosen with probability INDEPENDENCE_WEIGHT per step (the rest are
# differential-evolution moves, which need no Gaussian shape).
PROPOSAL_DOF = 10.0
PROPOSAL_SCALE = 1.1
INDEPENDENCE_WEIGHT = 0.85
# Refits of the proposal when the chain proper misses the rule at its first length: at least MIN_ADAPT_ROUNDS, then
# more (up to ADAPT_ROUNDS) while each refit still raises the chain's acceptance by ADAPT_GAIN x. An independence
# sampler's acceptance is its proposal's overlap with the posterior; on the 1080p triplet's decentred poly3 it went
# 0.04, 0.19, 0.29, 0.35, 0.35 over rounds 0-4. Stopping at round 2 (0.29) left walkers stuck for up to 170 steps where
# the t was still too narrow: tau 126 and a 6500-step chain (4.6 s of a 12 s calibration); from round 4, ~420 steps.
MIN_ADAPT_ROUNDS = 2
ADAPT_ROUNDS = 6
ADAPT_GAIN = 1.1


def _emcee():
    """emcee, imported without scipy.stats.

    emcee's package import loads all its moves, and ``emcee.moves.kde`` imports ``scipy.stats.gaussian_kde``
    inside ``try ... except ImportError`` (KDEMove is optional there): scipy.stats is 0.35-0.5 s of CPU on the
    serial path of a standard calibration (the whole of its import, nothing else in fieldcal needs it), and no
    move used here needs it. Here only: scipy.stats is marked unimportable while emcee loads, then unmarked, so a
    later ``import scipy.stats`` anywhere works as usual; if it is already loaded nothing changes.
    """
    import sys

    if "emcee" in sys.modules:
        return sys.modules["emcee"]
    blocked = "scipy.stats" not in sys.modules
    if blocked:
        sys.modules["scipy.stats"] = None  # type: ignore[assignment]  # import -> ImportError (Python's rule)
    try:
        import emcee
    finally:
        if blocked and sys.modules.get("scipy.stats", False) is None:
            del sys.modules["scipy.stats"]
    return emcee


@dataclass(frozen=True)
class Effort:
    """What an effort level changes (docs/fitting.md "Effort")."""

    name: str
    method: str            # "laplace" or "emcee"
    max_order: int         # highest rho^2 order among the candidates
    initial_steps: int = 0
    max_steps: int = 0
    # Decentred candidates are fitted only as siblings of the best `decentre_top` centred structures (a
    # decentre refines a structure; its fits cost 5x a centred one); None: every decentred candidate.
    decentre_top: int | None = None
    # > 0: a differential-evolution pilot of this many steps fits the independence proposal of the chain
    # proper (module docstring); 0: differential-evolution moves throughout from a small ball.
    pilot_steps: int = 0


EFFORTS = {
    "quick": Effort("quick", "laplace", 3, decentre_top=3),
    # initial_steps: the chain after the pilot (tau ~ 1.5-2 steps there, so 50 tau is met at ~100 steps)
    "standard": Effort("standard", "emcee", 3, initial_steps=200, max_steps=8000, decentre_top=4,
                       pilot_steps=200),
    # rho^8 candidates were dropped from thorough: chosen on the triplet at 640x360, they put the corners
    # 4.6-5.3 µm off (RMS 0.43-0.53 µm against 0.09-0.11 µm for the rho^4 model standard effort chose)
    "thorough": Effort("thorough", "emcee", 3, initial_steps=1000, max_steps=40000, pilot_steps=400),
}


@dataclass
class PosteriorResult:
    samples: np.ndarray
    method: str
    diagnostics: dict = field(default_factory=dict)


def _pinned(model: SurfaceModel, theta: np.ndarray) -> np.ndarray:
    """Nonlinear parameters sitting on a bound (e.g. dof at its Gaussian limit): held at the MAP."""
    lo, hi = model.nonlinear_bounds()
    nl = theta[model.n_linear:]
    tol = 1e-3 * (hi - lo)
    pin = np.zeros(theta.size, dtype=bool)
    pin[model.n_linear:] = (nl - lo < tol) | (hi - nl < tol)
    return pin


def numerical_hessian(f, x: np.ndarray, h: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Central-difference Hessian of a batch-vectorised scalar function f: (B, p) -> (B,)."""
    p = x.size
    pts = [x]
    idx = []
    for i in range(p):
        for j in range(i, p):
            for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                d = np.zeros(p)
                d[i] += si * h[i]
                d[j] += sj * h[j]
                pts.append(x + d)
            idx.append((i, j))
    P = np.array(pts)
    vals = np.concatenate([f(P[k:k + chunk]) for k in range(0, len(P), chunk)])
    H = np.zeros((p, p))
    k = 1
    for i, j in idx:
        fpp, fpm, fmp, fmm = vals[k:k + 4]
        H[i, j] = H[j, i] = (fpp - fpm - fmp + fmm) / (4.0 * h[i] * h[j])
        k += 4
    return H


def laplace(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, n_samples: int = MAX_SAMPLES,
            seed: int = 0) -> PosteriorResult:
    """Gaussian approximation at the MAP: covariance = inverse Hessian of -log posterior (numerical)."""
    pin = _pinned(model, theta_map)
    free = ~pin

    def neg_lp(sub):
        # the smooth log-posterior without the box indicator: a Hessian step may cross a bound
        full = np.tile(theta_map, (sub.shape[0], 1))
        full[:, free] = sub
        beta = full[:, :model.n_linear]
        return -(np.sum(model.log_likelihood(full, rows), axis=-1)
                 - 0.5 * np.sum((beta / COEF_PRIOR_SD) ** 2, axis=-1))

    x0 = theta_map[free]
    h = np.full(x0.size, 1e-4)  # normalised units: coefficients and log-scales are O(1)
    ok_pd = False
    cov = None
    axes = np.eye(x0.size)
    for _ in range(2):
        # Second pass: steps of a tenth of the first pass's sd along its principal axes. Along the coordinate
        # axes (the marginal sds) a step in one of strongly correlated coefficients (rho^0, rho^2, rho^4 over
        # tiles that stop short of the corners) is ~1 sd of that coefficient with the others held, and the
        # Student-t's departure from a quadratic over that step is ~4 % of entries ~1e5 times the smallest
        # eigenvalue (~30): the triplet's poly2+tilt Hessian read -240 there (+181 by a 1-D second difference
        # along that direction), and the best-scoring model was dropped as "unidentified".
        H = axes @ numerical_hessian(lambda u: neg_lp(x0 + u @ axes.T), np.zeros(x0.size), h) @ axes.T
        if not np.all(np.isfinite(H)):
            break
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        ok_pd = bool(w.min() > 0)
        wpos = np.maximum(w, 1e-12 * max(w.max(), 1e-300))
        cov = (V / wpos) @ V.T
        axes = V
        h = np.clip(0.1 / np.sqrt(wpos), 1e-7, 1e-2)
    if cov is None:
        cov = np.diag(np.full(x0.size, 1e-12))
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(x0, cov, size=n_samples, method="eigh")
    samples = np.tile(theta_map, (n_samples, 1))
    samples[:, free] = draws
    lo, hi = model.nonlinear_bounds()
    diag = {"method": "laplace", "hessian_positive_definite": ok_pd,
            "pinned_at_bound": [n for n, p in zip(model.names, pin) if p],
            "n_samples": int(n_samples)}
    if model.decentre:
        # The surface is linear in its coefficients given the centre, but not jointly: one Gaussian in
        # (coefficients, centre) moves the centre without re-fitting the coefficients, and a centre on its
        # prior bound or weakly located has no Gaussian at all (bands of mm were seen; a threshold on the
        # centre's sd then put a member in or out of the average on a few tenths of a µm of the data).
        # Instead the centre's marginal posterior is computed on a grid over its prior box (the coefficients
        # integrated out exactly, scales at the MAP), centres are drawn from it, and the coefficients from
        # their exact conditional Gaussian at each drawn centre: the surface stays pinned where the tiles are
        # and spreads where the model only extrapolates.
        samples[:, model.n_linear:] = np.clip(samples[:, model.n_linear:], lo, hi)
        scales = slice(model.n_linear + 2, None)
        if not ok_pd or not np.all(np.isfinite(samples[:, scales])) or np.any(samples[:, scales].std(axis=0) > 1.0):
            samples[:, scales] = theta_map[scales]          # the scales' own Gaussian broke with the centre's
        samples[:, model.n_linear:model.n_linear + 2], grid_note = centre_marginal_draws(model, rows, theta_map,
                                                                                        n_samples, rng)
        samples[:, :model.n_linear] = conditional_coefficients(model, rows, theta_map, samples[:, model.n_linear:],
                                                               rng)
        diag["centre"] = grid_note
    samples[:, model.n_linear:] = np.clip(samples[:, model.n_linear:], lo, hi)
    return PosteriorResult(samples, "laplace", diag)


CENTRE_GRID = 13  # points per axis of the centre's marginal: a coarse grid over the box, then a fine one on its mass
CENTRE_MASS_FLOOR = 1e-6  # coarse cells below this fraction of the peak density are outside the fine grid


def _linear_fit_parts(model: SurfaceModel, rows: Rows, theta_map: np.ndarray):
    """The MAP's Student-t E-step weights u_i: with them the log-posterior is a weighted least-squares problem in the
    coefficients at any centre."""
    beta0, centre0, log_s0, log_sa0, log_nu0 = model.split(theta_map)
    X0 = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre0)
    sig0 = model.sigma_eff(rows, log_s0, log_sa0)
    nu = math.exp(float(log_nu0))
    return (nu + 1.0) / (nu + ((rows.target - X0 @ beta0) / sig0) ** 2)


def _normal_equations(model, rows, centre, w):
    """A = X^T W X + prior precision and b = X^T W y at a batch of centres (B, 2); W = diag(w) (B, n) or (n,)."""
    p = model.n_linear
    X = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)          # (B, n, p)
    Xw = X * np.broadcast_to(w, X.shape[:2])[..., None]
    A = np.einsum("bnp,bnq->bpq", Xw, X) + np.eye(p) / COEF_PRIOR_SD ** 2
    b = np.einsum("bnp,n->bp", Xw, rows.target)
    return A, b


def centre_marginal_draws(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, n: int,
                          rng: np.random.Generator, chunk: int = 128):
    """Draws of the optical centre from its marginal posterior on a grid over the prior box.

    At the MAP's E-step weights and scales the coefficients enter a Gaussian, so they integrate out exactly:
    log p(c | y) = 1/2 b^T A^-1 b - 1/2 log|A| + const (flat prior on the box). A coarse grid over the box finds
    where the mass is, a fine grid over that region tabulates it; each draw is a fine cell chosen with that
    probability, placed uniformly within the cell.
    """
    lo, hi = model.nonlinear_bounds()
    u = _linear_fit_parts(model, rows, theta_map)
    _, _, log_s, log_sa, _ = model.split(theta_map)
    w = u / model.sigma_eff(rows, log_s, log_sa) ** 2

    def log_density(cs):
        lp = np.empty(cs.shape[0])
        for a in range(0, cs.shape[0], chunk):
            A, b = _normal_equations(model, rows, cs[a:a + chunk], w)
            L = np.linalg.cholesky(A)
            v = np.linalg.solve(L, b[..., None])[..., 0]
            lp[a:a + chunk] = 0.5 * np.sum(v * v, axis=-1) - np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
        return lp

    def grid(x0, x1, y0, y1):
        gx, gy = np.linspace(x0, x1, CENTRE_GRID), np.linspace(y0, y1, CENTRE_GRID)
        cx, cy = np.meshgrid(gx, gy, indexing="ij")
        return np.column_stack([cx.ravel(), cy.ravel()]), gx[1] - gx[0], gy[1] - gy[0]

    # coarse: the whole box; fine: the coarse cells that hold the mass, one cell of margin
    cs, hx, hy = grid(lo[0], hi[0], lo[1], hi[1])
    lp = log_density(cs)
    mass = cs[lp >= lp.max() + math.log(CENTRE_MASS_FLOOR)]
    x0, x1 = max(lo[0], mass[:, 0].min() - hx), min(hi[0], mass[:, 0].max() + hx)
    y0, y1 = max(lo[1], mass[:, 1].min() - hy), min(hi[1], mass[:, 1].max() + hy)
    cs, hx, hy = grid(x0, x1, y0, y1)
    lp = log_density(cs)
    prob = np.exp(lp - lp.max())
    prob /= prob.sum()
    k = rng.choice(cs.shape[0], size=n, p=prob)
    draws = np.clip(cs[k] + np.array([hx, hy]) * rng.uniform(-0.5, 0.5, size=(n, 2)), lo[:2], hi[:2])
    sd = draws.std(axis=0)
    note = {"method": f"marginal on {CENTRE_GRID}x{CENTRE_GRID} grids (the prior box, then its mass), "
                      "coefficients integrated out", "sd": [float(v) for v in sd],
            "at_bound_fraction": float(np.mean(np.any((cs[k] <= lo[:2]) | (cs[k] >= hi[:2]), axis=1)))}
    return draws, note


def conditional_coefficients(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, nl: np.ndarray,
                             rng: np.random.Generator, chunk: int = 256) -> np.ndarray:
    """Coefficient draws from their Gaussian conditional on each row of nonlinear parameters ``nl``.

    Given the centre and the error scales the log-posterior is, at the MAP's Student-t E-step weights u_i,
    a weighted least-squares problem: beta | nl ~ N(A^-1 X^T W y, A^-1) with W = u / (s sigma)^2 and
    A = X^T W X + I / COEF_PRIOR_SD^2.
    """
    p = model.n_linear
    u = _linear_fit_parts(model, rows, theta_map)
    out = np.empty((nl.shape[0], p))
    for a in range(0, nl.shape[0], chunk):
        th = np.concatenate([np.zeros((min(chunk, nl.shape[0] - a), p)), nl[a:a + chunk]], axis=1)
        _, centre, log_s, log_sa, _ = model.split(th)
        A, b = _normal_equations(model, rows, centre, u / model.sigma_eff(rows, log_s, log_sa) ** 2)
        L = np.linalg.cholesky(A)
        mean = np.linalg.solve(A, b[..., None])[..., 0]
        z = rng.standard_normal(mean.shape)
        # A = L L^T: L^-T z has covariance A^-1
        out[a:a + chunk] = mean + np.linalg.solve(np.swapaxes(L, -1, -2), z[..., None])[..., 0]
    return out


def run_emcee(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, effort: Effort, seed: int = 0,
              ball_cov: np.ndarray | None = None, quiet: bool = False, n_walkers: int | None = None,
              moves=None) -> PosteriorResult:
    """Affine-invariant ensemble MCMC around the MAP, extended until 50 tau or the cap.

    Without a pilot (``effort.pilot_steps == 0``) the walkers start in a small ball (0.1 Laplace sd) and use
    differential-evolution moves throughout. With one, they start from the Laplace approximation
    (``ball_cov``), a pilot of ``pilot_steps`` differential-evolution steps gives the mean and covariance the
    independence proposal of the chain proper is fitted to, and only the chain proper is kept and judged.
    """
    emcee = _emcee()
    p = theta_map.size
    n_walkers = max(32, 2 * p + 2) if n_walkers is None else max(int(n_walkers), 2 * p + 2)
    n_walkers += n_walkers % 2
    rng = np.random.default_rng(seed)
    if ball_cov is not None:
        sd = np.sqrt(np.clip(np.diag(ball_cov), 0, None))
    else:
        sd = np.full(p, 1e-3)
    lo, hi = model.nonlinear_bounds()
    span = hi - lo
    pilot = effort.pilot_steps > 0 and moves is None
    log_prob = model.log_posterior_fn(rows)
    if pilot and ball_cov is not None:
        start = _laplace_start(model, log_prob, theta_map, np.asarray(ball_cov, dtype=np.float64), n_walkers, rng)
    else:
        # a small ball: a tenth of the Laplace sd, never degenerate (pinned parameters get 1e-3)
        ball = np.maximum(0.1 * sd, 1e-3)
        start = theta_map + ball * rng.standard_normal((n_walkers, p))
    nl = start[:, model.n_linear:]
    start[:, model.n_linear:] = np.clip(nl, lo + 1e-4 * span, hi - 1e-4 * span)
    # DEMove alone: emcee 3.1's DESnookerMove leaves the chain too narrow (its direction delta / sqrt(|delta|)
    # is not a unit vector; on an 11-d Gaussian its samples had 0.78 of the true sd, DEMove's 1.00)
    de_moves = [(emcee.moves.DEMove(), 1.0)]
    random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()  # reproducible
    pilot_info = None
    if pilot:
        warm = emcee.EnsembleSampler(n_walkers, p, log_prob, vectorize=True, moves=de_moves)
        warm.random_state = random_state
        state = warm.run_mcmc(start, effort.pilot_steps, progress=False)
        half = warm.get_chain(discard=effort.pilot_steps // 2, flat=True)
        pilot_acc = float(np.mean(warm.acceptance_fraction))
        # The chain proper; when it misses the rule at its first length (a proposal fitted to too short a
        # pilot, e.g. where tilt and decentre trade off), it is refitted to that chain's second half and
        # restarted, MIN_ADAPT_ROUNDS times and then while the refits still raise the acceptance (up to
        # ADAPT_ROUNDS); only the last chain (one fixed proposal) is kept.
        acc_prev = None
        for rnd in range(ADAPT_ROUNDS + 1):
            proposal = _TProposal(half.mean(axis=0), np.cov(half.T), PROPOSAL_DOF, PROPOSAL_SCALE)
            sampler = emcee.EnsembleSampler(n_walkers, p, log_prob, vectorize=True,
                                            moves=[(emcee.moves.MHMove(proposal), INDEPENDENCE_WEIGHT),
                                                   (emcee.moves.DEMove(), 1.0 - INDEPENDENCE_WEIGHT)])
            sampler.random_state = random_state
            state = sampler.run_mcmc(state, effort.initial_steps, progress=False)
            if rnd == ADAPT_ROUNDS or effort.initial_steps > AUTOCORR_FACTOR * np.max(_tau(sampler)):
                break
            acc = float(np.mean(sampler.acceptance_fraction))
            if rnd >= MIN_ADAPT_ROUNDS and acc < ADAPT_GAIN * acc_prev:
                break  # the proposal has stopped improving: extend this chain
            acc_prev = acc
            half = sampler.get_chain(discard=effort.initial_steps // 2, flat=True)
            random_state = sampler.random_state
        pilot_info = {"steps": int(effort.pilot_steps), "moves": "DEMove", "acceptance_fraction": pilot_acc,
                      "proposal_refits": int(rnd),
                      "proposal": f"multivariate t, {PROPOSAL_DOF:g} dof, scale {PROPOSAL_SCALE:g} x the "
                                  f"covariance of the pilot's second half; chosen with probability "
                                  f"{INDEPENDENCE_WEIGHT:g} (else DEMove)"}
    else:
        sampler = emcee.EnsembleSampler(n_walkers, p, log_prob, vectorize=True, moves=moves or de_moves)
        sampler.random_state = random_state
        state = sampler.run_mcmc(start, effort.initial_steps, progress=False)
    n = effort.initial_steps
    tau = _tau(sampler)
    while n <= AUTOCORR_FACTOR * np.max(tau) and n < effort.max_steps:
        more = int(min(effort.max_steps - n, max(100 if pilot else 500, AUTOCORR_FACTOR * np.max(tau) * 1.2 - n)))
        status(f"emcee: {n} steps < {AUTOCORR_FACTOR} x tau = {AUTOCORR_FACTOR * np.max(tau):.0f}; "
               f"extending by {more}", quiet=quiet)
        state = sampler.run_mcmc(state, more, progress=False)
        n += more
        tau = _tau(sampler)
    tau_max = float(np.max(tau))
    converged = bool(n > AUTOCORR_FACTOR * tau_max)
    discard = int(min(n // 2, math.ceil(3 * tau_max)))
    thin = max(1, int(tau_max // 2))
    flat = sampler.get_chain(discard=discard, thin=thin, flat=True)
    if flat.shape[0] > MAX_SAMPLES:
        flat = flat[rng.choice(flat.shape[0], MAX_SAMPLES, replace=False)]
    n_eff = float(n_walkers * (n - discard) / tau_max)
    diag = {"method": "emcee", "converged": converged, "n_steps": int(n), "n_walkers": int(n_walkers),
            "discard": discard, "thin": thin,
            "tau": {nm: float(t) for nm, t in zip(model.names, tau)}, "tau_max": tau_max,
            "acceptance_fraction": float(np.mean(sampler.acceptance_fraction)),
            "effective_sample_size": n_eff, "n_samples": int(flat.shape[0]),
            "rule": f"chain length > {AUTOCORR_FACTOR} x integrated autocorrelation time, cap {effort.max_steps}"}
    if pilot_info is not None:
        diag["pilot"] = pilot_info
    if not converged:
        status(f"emcee did NOT converge: {n} steps <= {AUTOCORR_FACTOR} x tau_max = "
               f"{AUTOCORR_FACTOR * tau_max:.0f} (cap {effort.max_steps}); bands may be too narrow",
               quiet=quiet)
    return PosteriorResult(flat, "emcee", diag)


def _laplace_start(model: SurfaceModel, log_prob, theta_map: np.ndarray, cov: np.ndarray, n_walkers: int,
                   rng: np.random.Generator, n_grid: int = 64) -> np.ndarray:
    """Walkers drawn from the Laplace approximation, for the pilot.

    A parameter the Laplace fit pinned at a bound (zero variance: typically log nu at its Gaussian end) is
    drawn from its conditional posterior at the MAP, tabulated on ``n_grid`` points across its bounds: its
    posterior is one-sided and often wide (log nu: sd ~0.8 of a 4.6 range), which a small ball around the
    bound would leave the pilot to discover step by step. A 1e-3 jitter keeps the ensemble non-degenerate
    where the Laplace covariance is (tilt and decentre nearly trade off).
    """
    p = theta_map.size
    var = np.clip(np.diag(cov), 0.0, None)
    start = rng.multivariate_normal(theta_map, cov + np.diag(np.where(var > 0, 0.0, 1e-12)), size=n_walkers,
                                    method="eigh")
    start += 1e-3 * np.sqrt(var + 1e-6) * rng.standard_normal((n_walkers, p))
    lo, hi = model.nonlinear_bounds()
    for j in np.flatnonzero(_pinned(model, theta_map)):
        k = j - model.n_linear
        grid = np.linspace(lo[k], hi[k], n_grid + 2)[1:-1]
        pts = np.tile(theta_map, (n_grid, 1))
        pts[:, j] = grid
        lp = np.asarray(log_prob(pts), dtype=np.float64)
        if not np.any(np.isfinite(lp)):
            continue
        w = np.exp(lp - np.max(lp[np.isfinite(lp)]))
        w[~np.isfinite(w)] = 0.0
        cdf = np.cumsum(w) / np.sum(w)
        cell = np.minimum(np.searchsorted(cdf, rng.random(n_walkers)), n_grid - 1)
        step = grid[1] - grid[0]
        start[:, j] = grid[cell] + step * (rng.random(n_walkers) - 0.5)
    return start


class _TProposal:
    """Independence proposal for :class:`emcee.moves.MHMove`: a multivariate t (``dof``) with the given mean
    and ``scale^2 x cov``, drawn regardless of the walkers' positions.

    Returns the proposals and the Hastings log-ratio ``ln q(x) - ln q(x')`` (the proposal does not depend on
    the current point, so the ratio is of its density at the two points). A direction the pilot did not move
    in (zero variance) keeps a tiny spread, so the density stays finite.
    """

    def __init__(self, mean: np.ndarray, cov: np.ndarray, dof: float, scale: float):
        cov = 0.5 * (np.atleast_2d(cov) + np.atleast_2d(cov).T) * scale * scale
        w, V = np.linalg.eigh(cov)
        w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300) + 1e-24)
        self.mean, self.dof = np.asarray(mean, dtype=np.float64), float(dof)
        self.root = V * np.sqrt(w)           # x = mean + root @ z
        self.inv_root = (V / np.sqrt(w)).T   # z = inv_root @ (x - mean)

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """ln q up to a constant (cancels in the ratio)."""
        z = (x - self.mean) @ self.inv_root.T
        return -0.5 * (self.dof + self.mean.size) * np.log1p(np.sum(z * z, axis=1) / self.dof)

    def __call__(self, coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        k, d = coords.shape
        z = random.standard_normal((k, d))
        g = random.chisquare(self.dof, size=k) / self.dof
        q = self.mean + (z / np.sqrt(g)[:, None]) @ self.root.T
        return q, self.log_density(coords) - self.log_density(q)


def _tau(sampler) -> np.ndarray:
    emcee = _emcee()
    chain = sampler.get_chain()
    # tol=0: always return the estimate; convergence is judged by the caller's rule.
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = np.asarray(emcee.autocorr.integrated_time(chain, c=5, tol=0, quiet=True), dtype=float)
    # A parameter whose walkers do not move has no defined autocorrelation (0/0 -> NaN): count it as mixing
    # no faster than the whole chain, so the chain is extended to its cap and reported not converged rather
    # than crashing on int(NaN) (seen at 320x180 standard effort).
    return np.where(np.isfinite(tau), tau, float(chain.shape[0]))
