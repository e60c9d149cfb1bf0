"""Posterior of the chosen surface model: Laplace approximation ("quick") or emcee ("standard"/"thorough").

Both return parameter samples (a few thousand at most) plus diagnostics; the surface bands are quantiles of
the surface evaluated at those samples (:class:`fieldcal.fit.result.SurfaceFit`).

emcee convergence rule (docs/fitting.md): walkers start in a small ball around the MAP; the chain is
converged when its length exceeds 50 integrated autocorrelation times of every parameter
(``emcee.autocorr.integrated_time``). Otherwise the chain is extended, up to a cap; if the cap is reached
the result says ``converged: False`` and keeps the samples (no silent pretence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..progress import status
from .surface import COEF_PRIOR_SD, Rows, SurfaceModel

MAX_SAMPLES = 2000
AUTOCORR_FACTOR = 50


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


EFFORTS = {
    "quick": Effort("quick", "laplace", 3, decentre_top=3),
    "standard": Effort("standard", "emcee", 3, initial_steps=1500, max_steps=8000, decentre_top=4),
    # rho^8 candidates were dropped from thorough: chosen on the triplet at 640x360, they put the corners
    # 4.6-5.3 µm off (RMS 0.43-0.53 µm against 0.09-0.11 µm for the rho^4 model standard effort chose)
    "thorough": Effort("thorough", "emcee", 3, initial_steps=4000, max_steps=40000),
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
    for _ in range(2):  # second pass with steps matched to the first pass's standard deviations
        H = numerical_hessian(neg_lp, x0, h)
        if not np.all(np.isfinite(H)):
            break
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        ok_pd = bool(w.min() > 0)
        wpos = np.maximum(w, 1e-12 * max(w.max(), 1e-300))
        cov = (V / wpos) @ V.T
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        h = np.clip(0.1 * sd, 1e-7, 1e-2)
    if cov is None:
        cov = np.diag(np.full(x0.size, 1e-12))
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(x0, cov, size=n_samples, method="eigh")
    samples = np.tile(theta_map, (n_samples, 1))
    samples[:, free] = draws
    lo, hi = model.nonlinear_bounds()
    samples[:, model.n_linear:] = np.clip(samples[:, model.n_linear:], lo, hi)
    diag = {"method": "laplace", "hessian_positive_definite": ok_pd,
            "pinned_at_bound": [n for n, p in zip(model.names, pin) if p],
            "n_samples": int(n_samples)}
    return PosteriorResult(samples, "laplace", diag)


def run_emcee(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, effort: Effort, seed: int = 0,
              ball_cov: np.ndarray | None = None, quiet: bool = False, n_walkers: int | None = None,
              moves=None) -> PosteriorResult:
    """Affine-invariant ensemble MCMC from a small ball around the MAP, extended until 50 tau or the cap."""
    import emcee  # here: its import pulls in scipy.stats (~0.8 s), which quick effort never needs
    p = theta_map.size
    n_walkers = max(32, 2 * p + 2) if n_walkers is None else max(int(n_walkers), 2 * p + 2)
    n_walkers += n_walkers % 2
    rng = np.random.default_rng(seed)
    if ball_cov is not None:
        sd = np.sqrt(np.clip(np.diag(ball_cov), 0, None))
    else:
        sd = np.full(p, 1e-3)
    # a small ball: a tenth of the Laplace sd, never degenerate (pinned parameters get 1e-3)
    ball = np.maximum(0.1 * sd, 1e-3)
    lo, hi = model.nonlinear_bounds()
    start = theta_map + ball * rng.standard_normal((n_walkers, p))
    nl = start[:, model.n_linear:]
    span = hi - lo
    start[:, model.n_linear:] = np.clip(nl, lo + 1e-4 * span, hi - 1e-4 * span)

    log_prob = model.log_posterior_fn(rows)

    if moves is None:
        moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(n_walkers, p, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()  # reproducible
    state = sampler.run_mcmc(start, effort.initial_steps, progress=False)
    n = effort.initial_steps
    tau = _tau(sampler)
    while n <= AUTOCORR_FACTOR * np.max(tau) and n < effort.max_steps:
        more = int(min(effort.max_steps - n, max(500, AUTOCORR_FACTOR * np.max(tau) * 1.2 - n)))
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
    if not converged:
        status(f"emcee did NOT converge: {n} steps <= {AUTOCORR_FACTOR} x tau_max = "
               f"{AUTOCORR_FACTOR * tau_max:.0f} (cap {effort.max_steps}); bands may be too narrow",
               quiet=quiet)
    return PosteriorResult(flat, "emcee", diag)


def _tau(sampler) -> np.ndarray:
    import emcee

    chain = sampler.get_chain()
    # tol=0: always return the estimate; convergence is judged by the caller's rule.
    return emcee.autocorr.integrated_time(chain, c=5, tol=0, quiet=True)
