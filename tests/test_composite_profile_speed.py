"""Compositing with a calibrated profile (issue 18): the discrepancy's fast path agrees with the exact evaluation.

The fast path (``FocusEvaluator``: polynomial exact, kriged discrepancy gridded once and interpolated) is checked
against the exact kriging mean at every pixel, against its own rigorous error bound, and end to end: the composite
from the fast best-focus map against the one from the exact map. Correctness only; timings are in
benchmarks/bench_composite_profile.py.
"""

from dataclasses import replace

import numpy as np
import pytest

from fieldcal.composite.source import image_size
from fieldcal.composite.stack_profile import blend_kernel, composite_with_map, select_frames
from fieldcal.composite.surface import FocusEvaluator, output_best_focus_um, profile_focus_map
from fieldcal.formats.stack import Stack


@pytest.fixture(scope="module")
def calibrated(small_chart_stack):
    from fieldcal.calibration.pipeline import calibrate

    stack = Stack.open(small_chart_stack)
    prof = calibrate(stack, fs_cyc_per_mm=8.0, effort="quick", z_ref_um=0.0, quiet=True)
    assert prof.surfaces.discrepancy is not None
    return stack, prof


def _rough(prof, tau_factor=10.0):
    """The same profile with a 10x larger discrepancy, at least 3x the tiles' noise sd, correlated over at most one
    tile spacing: the kriged residual then follows the tiles' own residuals from tile to tile (a fit whose tiles
    show little discrepancy, as since the SML became phase-invariant, would otherwise give a trivial one)."""
    d = prof.surfaces.discrepancy
    floor = 3.0 * float(np.sqrt(np.median(d.noise_var)))
    spacing = float(d.diagnostics.get("tile_spacing") or d.length_scale)
    rough = replace(d, tau=np.maximum(d.tau * tau_factor, floor) + 1e-3, length_scale=min(d.length_scale, spacing),
                    _cache={})
    out = replace(prof, surfaces=replace(prof.surfaces, discrepancy=rough))
    assert np.ptp(out.surfaces.predict_parts(np.arange(0.0, 256.0, 7.0), 70.0, "G")[1]) > 0.05  # not trivial
    return out


def test_mean_only_prediction_is_bit_identical(calibrated):
    _, prof = calibrated
    d = prof.surfaces.discrepancy
    rng = np.random.default_rng(0)
    xh, yh = rng.uniform(-1, 1, 300), rng.uniform(-0.6, 0.6, 300)
    for ci in range(len(d.model.channels)):
        mean, var = d.predict(xh, yh, ci)
        fast, none = d.predict(xh, yh, ci, with_variance=False)
        assert none is None and var.shape == mean.shape
        np.testing.assert_array_equal(fast, mean)
        np.testing.assert_allclose(d.trend(xh, yh, ci) + d.residual(xh, yh, ci), mean, rtol=0, atol=1e-12)


def test_parts_sum_to_the_prediction(calibrated):
    _, prof = calibrated
    s = prof.surfaces
    x, y = np.meshgrid(np.linspace(-30, 285, 17), np.linspace(-30, 173, 11))
    for ch in s.channels:
        trend, res = s.predict_parts(x, y, ch)
        np.testing.assert_allclose(trend + res, s.predict(x, y, ch), rtol=0, atol=1e-9)


@pytest.mark.parametrize("rough", [False, True])
def test_evaluator_within_its_bounds_of_the_exact_surface(calibrated, rough):
    _, prof = calibrated
    prof = _rough(prof) if rough else prof
    w, h = prof.image_size_px
    yy, xx = np.mgrid[-20:h + 20:1.0, -20:w + 20:1.0]  # every pixel, and a margin breathing can reach
    for ch in prof.channels:
        f = FocusEvaluator(prof, ch, w, h)
        exact = prof.best_focus_um(xx, yy, ch)
        err = np.abs(f(xx, yy) - exact).max()
        assert f.step_px > 0
        assert err <= f.error_bound_um + 1e-9          # the rigorous bound holds
        assert err <= max(2.0 * f.error_estimate_um, 1e-6)  # and the estimate is close to the truth
        assert err < 0.01


def test_points_outside_the_grid_are_evaluated_exactly(calibrated):
    _, prof = calibrated
    f = FocusEvaluator(prof, "G", 256, 144, margin_px=0)
    x, y = np.array([-50.0, 300.0, 100.0]), np.array([-40.0, 10.0, 200.0])
    np.testing.assert_allclose(f(x, y), prof.best_focus_um(x, y, "G"), rtol=0, atol=1e-9)


def test_truth_profile_is_evaluated_exactly(triplet_path):
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile

    p = TruthProfile(LensSpec.load(triplet_path), 160, 90)
    f = FocusEvaluator(p, "G", 160, 90)
    x, y = np.array([0.0, 80.0, 159.0]), np.array([0.0, 45.0, 89.0])
    assert f.step_px == 0
    np.testing.assert_array_equal(f(x, y), p.best_focus_um(x, y, "G"))


def test_budget_falls_back_to_exact(calibrated):
    _, prof = calibrated
    f = FocusEvaluator(prof, "G", 256, 144, budget_points=100)
    assert f.step_px == 0
    x, y = np.array([0.0, 128.0]), np.array([0.0, 72.0])
    np.testing.assert_array_equal(f(x, y), prof.best_focus_um(x, y, "G"))


@pytest.mark.parametrize("lateral_colour", [False, True])
def test_fast_map_and_composite_match_the_exact_path(calibrated, lateral_colour, monkeypatch):
    stack, prof = calibrated
    prof = _rough(prof)
    w, h = image_size(stack)
    # this small image's own budget would choose the exact path: lift it so the grid is what is tested
    import fieldcal.composite.surface as surface
    monkeypatch.setattr(surface, "FIXED_POINT_ITERATIONS", 1000)
    fast = profile_focus_map(prof, w, h, stack.channels, lateral_colour)
    monkeypatch.undo()
    exact = profile_focus_map(prof, w, h, stack.channels, lateral_colour, exact=True)
    assert np.abs(fast - exact).max() < 0.01  # µm
    # at the map's grid nodes the exact path is the exact fixed point (between them both interpolate alike)
    for ci, ch in enumerate(stack.channels):
        x, y = np.array([0.0, 128.0, 248.0]), np.array([0.0, 72.0, 136.0])
        z = output_best_focus_um(prof, x, y, ch, lateral_colour)
        np.testing.assert_allclose(exact[y.astype(int), x.astype(int), ci], z, atol=1e-3)
    frames = select_frames(stack)
    kernel = blend_kernel(stack, prof, frames)
    a = composite_with_map(stack, fast, kernel, prof, frames, lateral_colour=lateral_colour, quiet=True)
    b = composite_with_map(stack, exact, kernel, prof, frames, lateral_colour=lateral_colour, quiet=True)
    rms = float(np.sqrt(np.mean((a.astype(float) - b.astype(float)) ** 2)))
    assert rms < 0.1  # DN
