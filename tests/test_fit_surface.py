"""Surface fits against simulated truth: selection (flat stays flat, tilt gets tilt), recovery, errors, I/O."""

import json
from dataclasses import replace

import numpy as np
import pytest

from fieldcal.fit import FitError, ImageGeometry, SurfaceFit, TileData, fit_surfaces
from fieldcal.fit.synthetic import base_lens, field_points, surface_rms_error_um, synthetic_tiles


def _fit(spec, seed=0, effort="quick", **kw):
    rng = np.random.default_rng(seed)
    kw.setdefault("directional", False)
    tiles, geom, truth = synthetic_tiles(spec, rng, nx=7, ny=5, **kw)
    return fit_surfaces(tiles, geom, effort=effort, quiet=True), truth


def test_flat_mono_lens_comes_out_flat():
    f, truth = _fit(base_lens(("Y",)))
    assert f.model.order == 0 and not f.model.tilt and not f.model.decentre
    x, y = field_points(f.geometry, 7)
    lo, hi = f.interval(x, y, "Y")
    z = truth.best_focus_um(x, y, "Y")
    assert np.max(np.abs(f.predict(x, y, "Y") - z)) < 1.0
    # a plane known to < 1 µm from 35 tiles of ~1.5 µm noise; corners wider (curved models averaged in)
    assert np.all(hi - lo < 4.0) and np.median(hi - lo) < 2.0


def test_tilted_flat_sensor_gets_tilt_and_nothing_else():
    spec = replace(base_lens(("R", "G", "B")), tilt_um_per_mm=(6.0, -4.0))
    f, truth = _fit(spec, seed=1)
    assert f.model.tilt and f.model.order == 0 and not f.model.decentre
    c = f.coefficients_um("G")
    assert c["tilt_x_um_per_mm"] == pytest.approx(6.0, abs=0.6)
    assert c["tilt_y_um_per_mm"] == pytest.approx(-4.0, abs=0.6)


def test_curved_decentred_colour_lens_recovered():
    spec = base_lens(("R", "G", "B"))
    chans = tuple(replace(c, focus_offset_um=o, curvature_um=(-150.0 * (1 + 0.02 * i), 30.0))
                  for i, (c, o) in enumerate(zip(spec.channels, (12.0, 0.0, -8.0))))
    spec = replace(spec, channels=chans, decentre_mm=(0.25, -0.15))
    f, truth = _fit(spec, seed=2)
    assert f.model.order >= 2 and f.model.decentre
    assert surface_rms_error_um(f, truth) < 1.5  # tile noise 0.5-3 µm, 105 tiles
    cx, cy = f.optical_centre_px()
    tcx, tcy = truth.optical_centre_px()
    assert abs(cx - tcx) < 3.0 and abs(cy - tcy) < 3.0  # px (truth: 16 and -10 px off centre)
    assert f.diagnostics["condition_number"] > 1 and np.isfinite(f.diagnostics["condition_number"])
    assert all("bic" in c for c in f.candidates) and sum(c["chosen"] for c in f.candidates) == 1


def test_error_scale_recovers_underestimated_sigmas():
    spec = replace(base_lens(("G",)), channels=(replace(base_lens(("G",)).channels[0], curvature_um=(-100.0,)),))
    f, _ = _fit(spec, seed=3, underestimate=2.0)
    assert 1.5 < f.error_scale() < 2.7
    f1, _ = _fit(spec, seed=3, underestimate=1.0)
    assert 0.7 < f1.error_scale() < 1.35


def test_astigmatism_selected_and_recovered_only_when_present():
    spec = base_lens(("G",))
    ch = replace(spec.channels[0], curvature_um=(-120.0,), astigmatism_um=20.0)
    f, truth = _fit(replace(spec, channels=(ch,)), seed=4, directional=True)
    assert f.model.astig
    corner = f.astigmatism_um(0.0, 0.0, "G")
    rho2 = truth.spec.rho(*truth.spec.pixel_to_mm(0.0, 0.0)) ** 2
    assert corner == pytest.approx(20.0 * rho2, abs=3.0)
    f0, _ = _fit(replace(spec, channels=(replace(ch, astigmatism_um=0.0),)), seed=4, directional=True)
    assert not f0.model.astig


def test_outlier_tiles_do_not_drag_the_surface():
    spec = replace(base_lens(("G",)), channels=(replace(base_lens(("G",)).channels[0], curvature_um=(-80.0,)),))
    f, truth = _fit(spec, seed=5, outlier_fraction=0.08)
    assert surface_rms_error_um(f, truth) < 1.5
    assert f.diagnostics["student_t_nu"] < 10  # heavy tails chosen


def test_round_trip_json_and_sidecar_samples():
    spec = replace(base_lens(("R", "G")), tilt_um_per_mm=(3.0, 0.0))
    f, _ = _fit(spec, seed=6)
    d = json.loads(json.dumps(f.to_dict(include_samples=False)))
    g = SurfaceFit.from_dict(d, samples=f.samples)
    x, y = field_points(f.geometry, 5)
    np.testing.assert_allclose(g.predict(x, y, "R"), f.predict(x, y, "R"))
    np.testing.assert_allclose(g.interval(x, y, "G"), f.interval(x, y, "G"))
    h = SurfaceFit.from_dict(json.loads(json.dumps(f.to_dict())))
    np.testing.assert_allclose(h.sd(x, y, "G"), f.sd(x, y, "G"))
    with pytest.raises(Exception, match="samples"):
        SurfaceFit.from_dict(d)


def test_interval_contains_map_and_checks_level():
    f, _ = _fit(base_lens(("Y",)), seed=7)
    x, y = field_points(f.geometry, 5)
    lo, hi = f.interval(x, y, "Y", 0.9)
    z = f.predict(x, y, "Y")
    assert np.all(lo <= z + 1e-9) and np.all(z <= hi + 1e-9)
    lo5, hi5 = f.interval(x, y, "Y", 0.5)
    assert np.all(hi5 - lo5 < hi - lo)
    with pytest.raises(FitError.__mro__[1], match="level"):
        f.interval(x, y, "Y", 1.5)
    with pytest.raises(FitError.__mro__[1], match="channel"):
        f.predict(x, y, "Q")


def test_all_tiles_at_one_radius_is_refused_clearly():
    geom = ImageGeometry(200, 200, 5.0)
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    x, y = 99.5 + 60 * np.cos(a), 99.5 + 60 * np.sin(a)
    tiles = TileData.from_arrays(["G"] * 24, x, y, np.zeros(24), np.ones(24))
    with pytest.raises(FitError, match="one radius") as e:
        fit_surfaces(tiles, geom, effort="quick", quiet=True, source="tiles.json")
    assert e.value.fix and "tiles.json" in str(e.value)


def test_too_few_tiles_and_bad_values_are_clear_errors():
    geom = ImageGeometry(100, 80, 5.0)
    tiles = TileData.from_arrays(["G"] * 4, [0, 50, 99, 20], [0, 40, 79, 60], np.zeros(4), np.ones(4))
    with pytest.raises(FitError, match="at least"):
        fit_surfaces(tiles, geom, effort="quick", quiet=True)
    with pytest.raises(FitError, match="z_sigma_um"):
        TileData.from_arrays(["G"] * 2, [0, 1], [0, 1], [0, 0], [1, 0])
    with pytest.raises(FitError, match="non-finite"):
        TileData.from_arrays(["G"] * 2, [0, np.nan], [0, 1], [0, 0], [1, 1])
    with pytest.raises(FitError, match="outside"):
        fit_surfaces(TileData.from_arrays(["G"] * 8, np.linspace(0, 300, 8), np.linspace(0, 79, 8),
                                          np.zeros(8), np.ones(8)), geom, effort="quick", quiet=True)
    with pytest.raises(FitError, match="effort"):
        fit_surfaces(tiles, geom, effort="fast")


def test_from_table_keeps_only_ok_rows():
    t = {"channel": ["G"] * 3, "x_px": [1.0, 2.0, 3.0], "y_px": [1.0, 2.0, 3.0], "z_best_um": [0.0, np.nan, 1.0],
         "z_sigma_um": [1.0, np.nan, 1.0], "status": ["ok", "no peak", "ok"]}
    d = TileData.from_table(t)
    assert len(d) == 2 and np.all(np.isnan(d.z_tan_um))
    with pytest.raises(FitError, match="z_best_um"):
        TileData.from_table({"channel": ["G"], "x_px": [1.0], "y_px": [1.0], "z_sigma_um": [1.0]})


def test_fast_log_posterior_equals_the_reference_one():
    """emcee's precomputed log-posterior gives the same numbers as SurfaceModel.log_posterior (and -inf
    outside the bounds) for every structure, with and without astigmatism rows."""
    from fieldcal.fit.select import build_rows, candidate_models

    rng = np.random.default_rng(3)
    tiles, geom, _ = synthetic_tiles(replace(base_lens(), name="t"), rng, nx=6, ny=4, directional=True)
    rows, _, _ = build_rows(tiles, geom, tiles.channels)
    for astig in (False, True):
        for m in candidate_models(tiles.channels, 3, astig):
            theta = rng.normal(0.0, 0.1, (12, m.n_params))
            lo, hi = m.nonlinear_bounds()
            theta[:, m.n_linear:] += 0.5 * (lo + hi)
            theta[0, -1] = hi[-1] + 1.0  # outside the dof bound
            a = m.log_posterior(theta, rows)
            b = m.log_posterior_fn(rows)(theta)
            assert np.isneginf(a[0]) and np.isneginf(b[0])
            np.testing.assert_allclose(b[1:], a[1:], rtol=1e-11, atol=1e-9)


def test_row_predictor_equals_the_design_product():
    """The decentred log-posterior's gathered-coefficient predictor gives design(centre) @ beta per walker, for
    every term layout (shared high orders, tilt, astigmatism to rho^6, rows of both kinds)."""
    from fieldcal.fit.surface import Rows, SurfaceModel

    rng = np.random.default_rng(5)
    n, walkers = 300, 7
    rows = Rows(rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.integers(0, 3, n), rng.integers(0, 2, n),
                rng.normal(size=n), np.ones(n))
    for order in (1, 2, 3):
        for tilt in (False, True):
            for astig, astig_order in ((False, 1), (True, 1), (True, 3)):
                for kc in (None, 1):
                    m = SurfaceModel(("R", "G", "B"), order, tilt, True, astig, True, kc, astig_order)
                    beta = rng.normal(size=(walkers, m.n_linear))
                    centre = rng.uniform(-0.2, 0.2, (walkers, 2))
                    X = m.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
                    np.testing.assert_allclose(m.row_predictor(rows)(beta, centre),
                                               np.einsum("bnp,bp->bn", X, beta), rtol=1e-12, atol=1e-12)


def test_pruned_decentre_search_picks_what_the_exhaustive_search_picks():
    """Quick/standard fit decentred candidates only beside the best centred structures; on decentred random
    lenses that changes neither the chosen model nor the surface."""
    from fieldcal.fit import posterior
    from fieldcal.fit.synthetic import random_lens

    for seed in (1, 4, 6):
        rng = np.random.default_rng(seed)
        spec = random_lens(rng)
        tiles, geom, _ = synthetic_tiles(spec, rng, nx=8, ny=6, directional=False)
        pruned = fit_surfaces(tiles, geom, effort="quick", quiet=True)
        exhaustive_effort = replace(posterior.EFFORTS["quick"], decentre_top=None)
        old = posterior.EFFORTS["quick"]
        posterior.EFFORTS["quick"] = exhaustive_effort
        try:
            full = fit_surfaces(tiles, geom, effort="quick", quiet=True)
        finally:
            posterior.EFFORTS["quick"] = old
        assert pruned.model.name == full.model.name
        assert sum(e.get("bic") is not None for e in pruned.candidates) < sum(
            e.get("bic") is not None for e in full.candidates)
        x, y = field_points(geom, 7)
        for c in spec.channel_names:
            np.testing.assert_allclose(pruned.predict(x, y, c), full.predict(x, y, c), atol=0.05)


def test_directional_rows_that_identify_no_astigmatism_fall_back_to_the_mean_surface():
    """T/S pairs all at the optical centre (rho = 0: an astigmatism term in rho^2 has no column) made every
    candidate's design singular, and a stack with sound mean-surface rows was refused; the mean surface is
    fitted from the focus rows alone, as with too few pairs."""
    spec = base_lens(("G",))
    tiles, geom, truth = synthetic_tiles(spec, np.random.default_rng(3), nx=7, ny=5, directional=False)
    n = len(tiles)
    cx, cy = (geom.width_px - 1) / 2.0, (geom.height_px - 1) / 2.0
    k = 8
    x = np.concatenate([tiles.x_px, np.full(k, cx)])
    y = np.concatenate([tiles.y_px, np.full(k, cy)])
    z0 = float(truth.best_focus_um(np.array([cx]), np.array([cy]), "G")[0])
    zb = np.concatenate([tiles.z_best_um, np.full(k, z0)])
    sd = np.concatenate([tiles.z_sigma_um, np.full(k, float(np.median(tiles.z_sigma_um)))])
    zt = np.concatenate([np.full(n, np.nan), np.full(k, z0)])
    both = TileData.from_arrays(["G"] * (n + k), x, y, zb, sd, z_tan_um=zt, z_sag_um=zt.copy())
    f = fit_surfaces(both, geom, effort="quick", quiet=True)
    assert not f.model.astig
    xg, yg = field_points(f.geometry, 7)
    assert np.sqrt(np.mean((f.predict(xg, yg, "G") - truth.best_focus_um(xg, yg, "G")) ** 2)) < 1.5
