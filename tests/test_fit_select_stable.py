"""Stability of the surface-model choice and honesty of the band where a decentred model extrapolates
(issue #16's profile diff, issue #14's corner bands): closed forms and invariances, small synthetic tile sets."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fieldcal.fit import fit_surfaces
from fieldcal.fit.map import fit_map
from fieldcal.fit.posterior import laplace
from fieldcal.fit.select import _whiten_blocks, build_rows, tile_groups
from fieldcal.fit.surface import CENTRE_BOUND, SurfaceModel
from fieldcal.fit.synthetic import base_lens, synthetic_tiles


def _lens(decentre_mm=(0.0, 0.0), tilt=(0.0, 0.0)):
    spec = base_lens()
    chans = tuple(replace(c, focus_offset_um=o, curvature_um=(-200.0, -20.0), astigmatism_um=0.0)
                  for c, o in zip(spec.channels, (8.0, -4.0, -6.0)))
    return replace(spec, channels=chans, decentre_mm=decentre_mm, tilt_um_per_mm=tilt)


def test_equicorrelated_whitening_is_the_dense_inverse():
    rng = np.random.default_rng(0)
    sizes = np.array([3, 2, 3, 1, 3])
    starts = np.r_[0, np.cumsum(sizes)[:-1]]
    n = int(sizes.sum())
    X, y = rng.standard_normal((n, 4)), rng.standard_normal(n)
    for rho in (0.0, 0.5, 0.9):
        C = np.zeros((n, n))
        for s, k in zip(starts, sizes):
            C[s:s + k, s:s + k] = (1.0 - rho) * np.eye(k) + rho
        Xw, yw, logdet = _whiten_blocks(X, y, starts, sizes, rho)
        Ci = np.linalg.inv(C)
        np.testing.assert_allclose(Xw.T @ Xw, X.T @ Ci @ X, atol=1e-10)
        np.testing.assert_allclose(Xw.T @ yw, X.T @ Ci @ y, atol=1e-10)
        assert logdet == pytest.approx(np.linalg.slogdet(C)[1], abs=1e-10)


def test_tile_groups_join_the_channels_of_one_tile():
    gx, gy = np.meshgrid(np.linspace(-0.6, 0.6, 5), np.linspace(-0.4, 0.4, 4))
    x, y = np.tile(gx.ravel(), 3), np.tile(gy.ravel(), 3)
    ch = np.repeat([0, 1, 2], gx.size)
    for shift in (0.0, 0.004):                     # identical positions, and lateral colour moving B and R apart
        g = tile_groups(x + shift * (ch - 1), y, ch)
        assert len(np.unique(g)) == gx.size
        assert np.all(g[ch == 0] == g[ch == 1]) and np.all(g[ch == 1] == g[ch == 2])
    # a tile missing in one channel still joins the other two
    keep = ~((ch == 2) & (np.arange(x.size) % gx.size == 3))
    g = tile_groups(x[keep], y[keep], ch[keep])
    assert len(np.unique(g)) == gx.size


def test_a_uniform_shift_of_a_channel_leaves_the_choice_and_the_shape():
    """The focus offset is a free parameter per channel: shifting every tile of a channel (as quick's band-pass
    offset does) must change only that channel's offset, never the chosen model or the surface's shape."""
    rng = np.random.default_rng(3)
    tiles, geom, _ = synthetic_tiles(_lens(), rng, nx=7, ny=5, sigma_um=(0.3, 1.5), underestimate=2.0,
                                     directional=False)
    base = fit_surfaces(tiles, geom, effort="quick", quiet=True)
    x, y = np.array([0.0, geom.width_px - 1.0, 160.0]), np.array([0.0, geom.height_px - 1.0, 120.0])
    for ch, dz in (("R", 0.4), ("G", -0.25)):
        z = tiles.z_best_um + dz * (tiles.channel == ch)
        fit = fit_surfaces(replace(tiles, z_best_um=z), geom, effort="quick", quiet=True)
        assert fit.model.name == base.model.name
        for c in ("R", "G", "B"):
            d = fit.predict(x, y, c) - base.predict(x, y, c)
            np.testing.assert_allclose(d - d[-1], 0.0, atol=0.02)       # shape unchanged
            assert d[-1] == pytest.approx(dz if c == ch else 0.0, abs=0.05)


def test_a_centre_on_its_bound_still_spreads_the_band_where_the_model_extrapolates():
    """A decentred fit whose centre sits on its prior bound has no Gaussian posterior in the centre (its Hessian
    is not positive definite there). The centre is drawn from its marginal on a grid over the box and the
    coefficients from their conditional at each drawn centre: the surface stays pinned where the tiles are, the
    centre's uncertainty widens the band only where the model extrapolates."""
    spec = _lens(decentre_mm=(0.0, 1.2))          # 0.4 of the half-diagonal: beyond the 0.25 box
    rng = np.random.default_rng(1)
    tiles, geom, _ = synthetic_tiles(spec, rng, nx=6, ny=4, sigma_um=(0.3, 0.6), directional=False)
    # the tiles cover only the central part of the frame: the corners are extrapolated
    inner = (np.abs(tiles.x_px - 159.5) < 120) & (np.abs(tiles.y_px - 119.5) < 90)
    tiles = tiles.subset(inner)
    chans = ("R", "G", "B")
    rows, zc, zs = build_rows(tiles, geom, chans)
    model = SurfaceModel(chans, 2, False, True, False, False, 0)
    res = fit_map(model, rows)
    lap = laplace(model, rows, res.theta, seed=0)
    c = lap.samples[:, model.n_linear:model.n_linear + 2]
    assert np.all(np.abs(c) <= CENTRE_BOUND + 1e-12)
    assert np.all(c.std(axis=0) > 0.0)           # the centre is not held at its MAP
    xh, yh = geom.normalise(tiles.x_px, tiles.y_px)
    at_tiles = zs * model.surface(lap.samples, xh, yh, 1).std(axis=0)
    s = float(np.exp(model.split(res.theta)[2]))
    # at the tiles: no wider than one tile's own error (the fit of ~24 tiles per channel is at least as good)
    assert np.median(at_tiles) <= s * float(np.median(tiles.z_sigma_um))
    cx, cy = geom.normalise(np.array([0.0, 319.0]), np.array([0.0, 239.0]))
    at_corners = zs * model.surface(lap.samples, cx, cy, 1).std(axis=0)
    assert np.all(at_corners > 2.0 * np.median(at_tiles))



def test_held_out_residuals_are_those_of_a_refit_without_the_block():
    from fieldcal.fit.select import held_out_residuals

    rng = np.random.default_rng(5)
    X, y = rng.standard_normal((30, 4)), rng.standard_normal(30)
    ridge = np.array([1e-6, 0.5, 0.0, 2.0])
    beta = np.linalg.solve(X.T @ X + np.diag(ridge), X.T @ y)
    members = [np.arange(0, 7), np.arange(7, 8), np.arange(8, 30, 2), np.arange(9, 30, 2)]
    for idx, r in zip(members, held_out_residuals(X, y - X @ beta, ridge, members)):
        keep = np.setdiff1d(np.arange(30), idx)
        b = np.linalg.solve(X[keep].T @ X[keep] + np.diag(ridge), X[keep].T @ y[keep])
        np.testing.assert_allclose(r, y[idx] - X[idx] @ b, atol=1e-10)


def test_spatial_blocks_follow_the_field_and_keep_a_tile_whole():
    from fieldcal.fit.select import spatial_blocks

    gx, gy = np.meshgrid(np.linspace(-0.8, 0.8, 9), np.linspace(-0.6, 0.6, 7))
    x, y = np.tile(gx.ravel(), 3), np.tile(gy.ravel(), 3)      # three channels of each tile
    b = spatial_blocks(x, y)
    assert len(np.unique(b)) == 12                             # 4 x 3 on a 4:3 field
    n = gx.size
    assert np.all(b[:n] == b[n:2 * n]) and np.all(b[:n] == b[2 * n:])
    sizes = np.bincount(b[:n])
    assert sizes.min() >= 4 and sizes.max() <= 9


def test_paired_test_keeps_the_simplest_model_not_significantly_worse_than_the_best():
    from scipy.stats import t as student_t

    from fieldcal.fit.select import paired_test_choice

    rng = np.random.default_rng(3)
    best = rng.uniform(10.0, 30.0, 10)                 # 10 blocks of 12 rows
    rows = np.full(10, 12)
    noise = rng.standard_normal(10)
    # a richer model's gain with this spread: SE of the total difference, Nadeau-Bengio inflated (1 + 10/9)
    se = math.sqrt(10 * np.var(noise, ddof=1) * (1.0 + 10 * 12 / 108))
    margin = student_t.ppf(0.95, 9) * se
    shift = lambda total: noise - noise.mean() + total / 10.0
    losses = {"rich": best, "mid": best + shift(margin - 0.01), "simple": best + shift(margin + 0.01)}
    k = {"rich": 5, "mid": 3, "simple": 1}
    name, stats = paired_test_choice(losses, k, rows)
    assert name == "mid"
    assert stats["simple"][0] == pytest.approx(margin + 0.01)
    assert stats["simple"][1] == pytest.approx(se) and stats["simple"][2] == pytest.approx(margin)
    assert stats["rich"] == (0.0, 0.0, 0.0)
    # the same total gain spread evenly over the blocks (a consistent difference) is significant
    losses["mid"] = best + (margin - 0.01) / 10.0
    assert paired_test_choice(losses, k, rows)[0] == "rich"
    # one block: no test is possible, nothing is shown worse, so the simplest is kept
    assert paired_test_choice({n: v[:1] for n, v in losses.items()}, k, rows[:1])[0] == "simple"


def _decentred_rho4(amp_um: float):
    spec = base_lens(("G",))
    return replace(spec, channels=(replace(spec.channels[0], curvature_um=(-60.0, amp_um)),),
                   decentre_mm=(0.6, -0.36))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_decentred_rho4_surface_gets_a_decentre_and_a_flat_one_no_terms(seed):
    """The choice over seeds: a real decentred rho^4 (10 µm at rho = 1, centre 0.7 mm off) is chosen decentred
    and followed; a flat lens gets no term at all."""
    from fieldcal.fit.synthetic import surface_rms_error_um, synthetic_tiles

    rng = np.random.default_rng(seed)
    tiles, geom, truth = synthetic_tiles(_decentred_rho4(10.0), rng, nx=9, ny=7, directional=False)
    f = fit_surfaces(tiles, geom, effort="quick", quiet=True)
    assert f.model.decentre and f.model.order >= 1
    assert surface_rms_error_um(f, truth) < 1.0          # tile noise 0.5-4.5 µm, 63 tiles
    for s in (seed, seed + 3):
        rng = np.random.default_rng(100 + s)
        tiles, geom, _ = synthetic_tiles(base_lens(("G",)), rng, nx=9, ny=7, directional=False)
        m = fit_surfaces(tiles, geom, effort="quick", quiet=True).model
        assert m.order == 0 and not m.tilt and not m.decentre, m.name


