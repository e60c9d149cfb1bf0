"""Extremes of measurement: through-focus curves that are flat, too short, non-finite, peaked at or beyond the
scan edge, of extreme scale; chart stacks that are textureless, black, saturated, tiny, of one frame; q -> 1.

A curve either gives a best focus matching the closed-form peak or a named rejection reason; a stack no tile
can be measured on gives a TileTable whose every row says why. RuntimeWarnings are errors here."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import FieldcalError
from fieldcal.measure import ArrayStack, analyse_curve, measure_stack

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

Z = np.arange(-40.0, 40.1, 8.0)  # 11 frames


def lorentz(z, z0, w=10.0, a=1.0, b=0.1):
    return a / (1.0 + ((z - z0) / w) ** 2) + b


@pytest.mark.parametrize("n", [1, 2, 4])
def test_one_two_four_frames_are_too_few(n):
    r = analyse_curve(Z[:n], lorentz(Z[:n], 0.0))
    assert r.status == "too_few_frames" and np.isnan(r.z_best_um)


@pytest.mark.parametrize("values", [np.zeros(Z.size), np.ones(Z.size), np.full(Z.size, 1e-300)])
def test_flat_curves_are_rejected_as_flat(values):
    r = analyse_curve(Z, values)
    assert r.status == "flat" and np.isnan(r.z_best_um)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_values_are_rejected_not_propagated(bad):
    v = lorentz(Z, 0.0)
    v[4] = bad
    r = analyse_curve(Z, v)
    assert r.status != "ok" and np.isnan(r.z_best_um)


@pytest.mark.parametrize("z0", [40.0, 44.0, 80.0, -40.0, -200.0])
def test_peak_at_or_beyond_the_scan_edge_is_rejected(z0):
    """Curvature beyond the scanned range: never extrapolated into a best focus."""
    r = analyse_curve(Z, lorentz(Z, z0))
    assert r.status in ("peak_outside_range", "peak_at_edge", "flat")
    assert np.isnan(r.z_best_um)


@pytest.mark.parametrize("scale", [1e-300, 1e-30, 1.0, 1e30, 1e300])
def test_extreme_scales_give_the_same_best_focus(scale):
    r = analyse_curve(Z, scale * lorentz(Z, 3.0))
    assert r.status == "ok"
    assert r.z_best_um == pytest.approx(3.0, abs=0.05)
    assert np.isfinite(r.z_sigma_um) and r.peak == pytest.approx(scale, rel=1e-3)


@settings(max_examples=40, deadline=None)
@given(z0=st.floats(-40.0, 40.0), w=st.floats(4.0, 30.0), noise=st.floats(0.0, 0.02), seed=st.integers(0, 1000))
def test_any_peak_is_found_inside_or_rejected_at_the_edge(z0, w, noise, seed):
    v = lorentz(Z, z0, w) + np.random.default_rng(seed).normal(0.0, noise, Z.size)
    r = analyse_curve(Z, v)
    if r.status == "ok":
        assert Z[1] <= r.z_best_um <= Z[-2]  # never extrapolated
        assert abs(r.z_best_um - z0) < 2.0 + 200.0 * noise  # a few µm on an 8 µm grid
        assert np.isfinite(r.z_sigma_um) and r.z_sigma_um > 0
    else:
        assert np.isnan(r.z_best_um)
        # only peaks near the edge, or drowned in noise / too broad for the scan, are rejected
        assert abs(z0) > 24.0 or noise > 0.005 or w > 15.0 or r.status in ("flat", "multi_peak")


def test_q_close_to_one_gives_the_first_otf_zero_width():
    """q -> 1: the width where contrast is fully lost is the first zero of 2 J1(x)/x (no root-finder error)."""
    from fieldcal.measure.throughfocus import otf_model
    z = np.arange(-40.0, 40.1, 4.0)
    v = otf_model(z, 1.0, 2.0, 0.25, 0.01, 40.0)
    r = analyse_curve(z, v, model="otf", fs_cyc_per_mm=40.0, q=1 - 1e-12)
    assert r.status == "ok" and np.isfinite(r.width_um)


def _stack(frames, white=1.0, z=Z):
    return ArrayStack(frames, z, ["Y"], pixel_pitch_um=4.0, white_level=white)


H, W = 96, 128


@pytest.mark.parametrize("kind,reason", [("textureless", "low_texture"), ("black", "low_texture"),
                                         ("saturated", "saturated")])
@pytest.mark.parametrize("dtype,white", [(np.float32, 1.0), (np.uint8, 255.0), (np.uint16, 4095.0)])
def test_every_tile_rejected_with_the_reason(kind, reason, dtype, white):
    level = {"textureless": 0.5, "black": 0.0, "saturated": 1.0}[kind] * white
    frames = [np.full((H, W, 1), level, dtype) for _ in Z]
    table, _ = measure_stack(_stack(frames, white), fs_cyc_per_mm=40.0, quiet=True)
    assert len(table) > 0 and not table.ok.any()
    assert set(table.status) == {reason}
    assert np.all(np.isnan(table.z_best_um))


def test_tiny_16x16_stack_is_a_clear_error():
    frames = [np.random.default_rng(i).random((16, 16, 1)).astype(np.float32) for i in range(Z.size)]
    with pytest.raises(FieldcalError) as e:
        measure_stack(_stack(frames), fs_cyc_per_mm=40.0, quiet=True)
    assert e.value.field == "tile_px" and e.value.fix


def test_one_frame_stack_is_a_clear_error():
    with pytest.raises(FieldcalError) as e:
        measure_stack(_stack([np.zeros((H, W, 1), np.float32)], z=[0.0]), fs_cyc_per_mm=40.0, quiet=True)
    assert "too few frames" in str(e.value)
