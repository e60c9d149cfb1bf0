"""The band's block covariance (``discrepancy.block_jackknife_cov``) against the exact covariance of the fit.

Rows on an 18 x 10 layout (a slanted-edge chart's spread of edges over a 16:9 field), per-row noise sds 0.5-1.5,
a poly3 + tilt surface (the corner blocks carry its rho^4 and rho^6 terms), weighted least squares with the
stated weights. The exact covariance of the coefficients is ``A^-1 X'W Sigma W X A^-1``; the estimator's mean over
many draws, divided by its small-sample inflation (t_{0.95, B-1} / z_{0.95})^2, must match it at the centre,
the middle and the corners of the field — with independent noise (what the kriging variance also states) and
with an error shared by every row of a block (what the block covariance is there to see).

The delete-one-block jackknife it replaced (session 16) read 1.22-1.48x the exact variance with independent
noise and 1.28-1.42x with block-shared errors (its (I - H_gg)^-1 where CR2 takes (I - H_gg)^-1/2): it fails the
upper bound below at every point.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtri, stdtrit

from fieldcal.fit.discrepancy import JK_BLOCKS, block_jackknife_cov
from fieldcal.fit.selfcheck import block_labels
from fieldcal.fit.surface import COEF_PRIOR_SD

POINTS = np.array([[0.0, 0.0], [0.5, 0.2], [0.85, 0.47], [-0.85, 0.47], [0.85, 0.0], [0.0, 0.47]])


def _design(x, y):
    r2 = x * x + y * y
    return np.column_stack([np.ones_like(x), r2, r2 ** 2, r2 ** 3, x, y])


@pytest.mark.parametrize("block_sd", [0.0, 0.5])
def test_block_covariance_matches_the_exact_covariance(block_sd):
    rng = np.random.default_rng(3)
    x, y = (a.ravel() for a in np.meshgrid(np.linspace(-0.82, 0.82, 18), np.linspace(-0.44, 0.44, 10)))
    X = _design(x, y)
    sd = rng.uniform(0.5, 1.5, x.size)
    w = 1.0 / sd ** 2
    lab = block_labels(x, y)
    assert np.unique(lab).size == JK_BLOCKS[0] * JK_BLOCKS[1]
    sigma = np.diag(sd ** 2) + block_sd ** 2 * (lab[:, None] == lab[None, :])
    A_inv = np.linalg.inv((X.T * w) @ X + np.eye(X.shape[1]) / COEF_PRIOR_SD ** 2)
    exact = A_inv @ (X.T * w) @ sigma @ (w[:, None] * X) @ A_inv
    chol = np.linalg.cholesky(sigma)
    beta = np.array([1.0, -2.0, 0.5, 0.1, 0.3, -0.2])
    n = 300
    mean = np.zeros_like(exact)
    for _ in range(n):
        cov, blocks = block_jackknife_cov(X, X @ beta + chol @ rng.standard_normal(x.size), w, x, y)
        assert blocks == 12
        mean += cov / n
    infl = (float(stdtrit(11, 0.95)) / float(ndtri(0.95))) ** 2
    H = _design(POINTS[:, 0], POINTS[:, 1])
    ratio = (np.einsum("mp,pq,mq->m", H, mean, H) / infl) / np.einsum("mp,pq,mq->m", H, exact, H)
    # Monte Carlo sd of each ratio ~0.03 (11 degrees of freedom per draw, 300 draws)
    assert np.all(ratio > 0.80), ratio
    assert np.all(ratio < 1.15), ratio


def test_the_jackknife_the_texture_path_keeps_is_the_delete_one_block_one():
    """``leverage_corrected=False`` is the delete-one-block jackknife: the blocks' refits, their spread times
    (B - 1) / B, t-inflated — and on this layout it reads more than the exact variance at the corner blocks."""
    rng = np.random.default_rng(5)
    x, y = (a.ravel() for a in np.meshgrid(np.linspace(-0.82, 0.82, 18), np.linspace(-0.44, 0.44, 10)))
    X = _design(x, y)
    w = np.full(x.size, 4.0)
    yv = X @ np.array([1.0, -2.0, 0.5, 0.1, 0.3, -0.2]) + 0.5 * rng.standard_normal(x.size)
    lab = block_labels(x, y)
    A = (X.T * w) @ X + np.eye(X.shape[1]) / COEF_PRIOR_SD ** 2
    est = np.array([np.linalg.solve(A - (X[lab == k].T * w[lab == k]) @ X[lab == k],
                                    (X.T * w) @ yv - (X[lab == k].T * w[lab == k]) @ yv[lab == k])
                    for k in np.unique(lab)])
    d = est - est.mean(axis=0)
    infl = (float(stdtrit(11, 0.95)) / float(ndtri(0.95))) ** 2
    jk, blocks = block_jackknife_cov(X, yv, w, x, y, leverage_corrected=False)
    assert blocks == 12
    np.testing.assert_allclose(jk, infl * 11 / 12 * d.T @ d, rtol=1e-8)
    cr2, _ = block_jackknife_cov(X, yv, w, x, y)
    assert not np.allclose(jk, cr2)


def test_block_covariance_needs_enough_blocks():
    x = np.linspace(-0.5, 0.5, 20)
    y = np.zeros(20)                     # one row of blocks: 4 of them, fewer than MIN_JK_BLOCKS
    cov, blocks = block_jackknife_cov(_design(x, y)[:, :3], np.ones(20), np.ones(20), x, y)
    assert cov is None and blocks == 4
