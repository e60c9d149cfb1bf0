"""MAP fit of one surface model: variable projection with nlopt's LN_BOBYQA over the few nonlinear parameters.

Why this optimiser: given the nonlinear parameters (optical centre, error scales, Student-t dof) the
surface is *linear* in its coefficients, and the Student-t likelihood's conditional maximum over those is
found reliably by iteratively reweighted least squares (the EM algorithm of the t distribution). So the
MAP is ``max_theta  max_beta log p(beta, theta | data)``: an outer problem of 2-5 bounded, smooth parameters
(BOBYQA: derivative-free, builds a quadratic model, honours bounds) over an inner problem solved exactly.
There are no starting values to guess for the 5-20 coefficients and no badly scaled joint gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import nlopt
import numpy as np
from scipy.linalg.lapack import dposv as _dposv

from .surface import COEF_PRIOR_SD, Rows, SurfaceModel, student_t_loglik

# Condition number above which a candidate's design is called degenerate (column-scaled, weighted).
MAX_CONDITION = 1.0e8
_IRLS_MAX_ITER = 200
_IRLS_TOL = 1.0e-7


@dataclass
class MapResult:
    """MAP of one candidate: full parameter vector, log-likelihood/-posterior and diagnostics."""

    model: SurfaceModel
    theta: np.ndarray
    log_likelihood: float
    log_posterior: float
    condition_number: float
    n_evals: int
    nlopt_result: int


def design_condition(model: SurfaceModel, rows: Rows, centre=(0.0, 0.0)) -> float:
    """Condition number of the weighted design with unit-norm columns (scale-free)."""
    X = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, np.asarray(centre, float))
    Xw = X / rows.sigma[:, None]
    norms = np.linalg.norm(Xw, axis=0)
    if np.any(norms == 0.0):
        return math.inf
    s = np.linalg.svd(Xw / norms, compute_uv=False)
    return math.inf if s[-1] <= s[0] * 1e-15 else float(s[0] / s[-1])


def conditional_beta(model: SurfaceModel, rows: Rows, nl: np.ndarray, beta0: np.ndarray | None = None,
                     X: np.ndarray | None = None) -> np.ndarray:
    """Coefficients maximising the posterior for fixed nonlinear parameters (Student-t IRLS / EM).

    ``beta0`` warm-starts the EM iterations (the optimiser's previous point); ``X`` reuses a design matrix
    when the centre is fixed.
    """
    p = model.n_linear
    theta = np.concatenate([np.zeros(p), nl])
    _, centre, log_s, log_sa, log_nu = model.split(theta)
    if X is None:
        X = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
    sig = model.sigma_eff(rows, log_s, log_sa)
    nu = math.exp(float(log_nu))
    ridge = np.eye(p) / COEF_PRIOR_SD ** 2  # the Gaussian coefficient prior, exactly
    w = 1.0 / sig ** 2
    beta = _weighted_solve(X, rows.target, w, ridge) if beta0 is None else beta0
    y = rows.target
    for _ in range(_IRLS_MAX_ITER):
        r2 = ((y - X @ beta) / sig) ** 2
        u = (nu + 1.0) / (nu + r2)  # E-step: expected precision multiplier of each row
        new = _weighted_solve(X, y, u * w, ridge)
        step = np.abs(new - beta).max()
        beta = new
        if step <= _IRLS_TOL * (1.0 + np.abs(new).max()):
            break
    return beta


def _weighted_solve(X, y, w, ridge):
    Xw = X.T * w
    A = Xw @ X + ridge
    b = Xw @ y
    _, x, info = _dposv(A, b)  # Cholesky solve of the (positive definite) normal equations, low overhead
    if info != 0:
        return np.linalg.lstsq(A, b, rcond=None)[0]
    return x


def fit_map(model: SurfaceModel, rows: Rows, max_eval: int = 600, start_from: MapResult | None = None) -> MapResult:
    """MAP of ``model`` on ``rows`` (normalised units).

    ``start_from``: the MAP of the same structure without a decentre; a decentred fit then starts at its
    error scales and dof (the centre still starts at the best of a 3 x 3 grid).
    """
    lo, hi = model.nonlinear_bounds()
    k = lo.size
    cond = design_condition(model, rows)

    X_fixed = None if model.decentre else model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind,
                                                       np.zeros(2))
    warm = [None]
    p = model.n_linear

    def neg_log_post(nl):
        nl = np.clip(nl, lo, hi)
        theta = np.concatenate([np.zeros(p), nl])
        _, centre, log_s, log_sa, log_nu = model.split(theta)
        X = X_fixed if X_fixed is not None else model.design(rows.x_hat, rows.y_hat, rows.ch_index,
                                                             rows.kind, centre)
        beta = conditional_beta(model, rows, nl, beta0=warm[0], X=X)
        sig = model.sigma_eff(rows, log_s, log_sa)
        ll = float(np.sum(student_t_loglik(rows.target - X @ beta, sig, math.exp(float(log_nu)))))
        v = ll - 0.5 * float(np.sum((beta / COEF_PRIOR_SD) ** 2))  # + flat prior inside the bounds
        if not math.isfinite(v):
            return 1e300
        warm[0] = beta
        return -v

    # Start: Gaussian-ish dof, error scale from a first weighted fit, centre from a coarse grid. A decentred fit
    # started from its centred sibling's error scale and dof is also run from the cold start: the Student-t
    # posterior has two basins in (scale, dof) (heavy tails with a small scale, or Gaussian with a large one), and
    # which one BOBYQA ends in depended on 1e-3-step details of the data (a uniform 0.015 µm piston of every
    # tile flipped a 320 px lens's model choice, its corners 2.8 µm off); the better posterior is kept.
    starts = [_initial(model, rows, lo, hi)]
    if model.decentre and start_from is not None and not start_from.model.decentre:
        starts.append(np.clip(np.concatenate([[0.0, 0.0], start_from.theta[start_from.model.n_linear:]]), lo, hi))
    return min((_optimise(model, rows, lo, hi, k, neg_log_post, s, max_eval, warm, X_fixed, cond) for s in starts),
               key=lambda r: -r.log_posterior)


def _optimise(model, rows, lo, hi, k, neg_log_post, start, max_eval, warm, X_fixed, cond) -> MapResult:
    """BOBYQA on the nonlinear parameters from ``start`` (its centre from a 3 x 3 grid for a decentred model)."""
    if model.decentre:
        best = None
        for cx in (-0.1, 0.0, 0.1):
            for cy in (-0.1, 0.0, 0.1):
                trial = start.copy()
                trial[0], trial[1] = cx, cy
                f = neg_log_post(trial)
                if best is None or f < best[0]:
                    best = (f, trial)
        start = best[1]

    n_evals = 0
    best_seen = [math.inf, np.clip(start, lo, hi)]

    def objective(x, grad):
        nonlocal n_evals
        n_evals += 1
        x = np.asarray(x)
        f = neg_log_post(x)
        if f < best_seen[0]:
            best_seen[0], best_seen[1] = f, x.copy()
        return f

    opt = nlopt.opt(nlopt.LN_BOBYQA, k)
    opt.set_lower_bounds(lo.tolist())
    opt.set_upper_bounds(hi.tolist())
    opt.set_min_objective(objective)
    opt.set_xtol_abs(1e-5)
    opt.set_ftol_abs(1e-6)
    opt.set_maxeval(max_eval)
    step = np.minimum(0.25 * (hi - lo), 0.5)
    if model.decentre:
        step[:2] = 0.03
    opt.set_initial_step(step.tolist())
    try:
        x = np.asarray(opt.optimize(np.clip(start, lo, hi).tolist()))
        res = int(opt.last_optimize_result())
    except nlopt.RoundoffLimited:  # the best point so far is still a valid optimum to within roundoff
        x = best_seen[1]
        res = int(nlopt.ROUNDOFF_LIMITED)
    if best_seen[0] < neg_log_post(x):
        x = best_seen[1]
    x = np.clip(x, lo, hi)
    beta = conditional_beta(model, rows, x, beta0=warm[0], X=X_fixed)
    theta = np.concatenate([beta, x])
    ll = float(np.sum(model.log_likelihood(theta, rows)))
    lp = float(model.log_posterior(theta, rows))
    return MapResult(model, theta, ll, lp, cond, n_evals, res)


def _initial(model: SurfaceModel, rows: Rows, lo, hi) -> np.ndarray:
    nl = []
    if model.decentre:
        nl += [0.0, 0.0]
    nl.append(0.0)
    if model.astig_rows:
        nl.append(0.0)
    nl.append(math.log(20.0))
    nl = np.array(nl)
    # Gaussian weighted fit at s = 1, then the error scale from the robust spread of the residuals.
    beta = conditional_beta(model, rows, np.concatenate([nl[:-1], [hi[-1]]]))
    theta = np.concatenate([beta, nl])
    _, centre, *_ = model.split(theta)
    X = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
    z = (rows.target - X @ beta) / rows.sigma
    i_s = 2 if model.decentre else 0
    for kind, idx in ((0, i_s), (1, i_s + 1)):
        m = rows.kind == kind
        if kind == 1 and not model.astig_rows:
            continue
        if m.sum() >= 3:
            mad = 1.4826 * float(np.median(np.abs(z[m] - np.median(z[m]))))
            if mad > 0:
                nl[idx] = math.log(mad)
    return np.clip(nl, lo, hi)
