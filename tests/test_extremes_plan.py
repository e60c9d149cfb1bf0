"""Extremes of planning: a flat field (one frame), q -> 0 and q -> 1, fs beyond the lens's cut-off, α -> 0 and
α >> D, one-pixel ROIs, and 8000x6000 px geometry planned without allocating a full frame.

Counts are checked against the closed forms N = ceil(D / 2δ) (uniform tolerance) and T = (D/2α + 1) t_s
(paper eq. 3); impossible requests end in a ParameterError naming the field. RuntimeWarnings are errors."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import ParameterError
from fieldcal.optics import MTFCriterion, focus_tolerance_um
from fieldcal.simulate.lens import LensSpec
from fieldcal.plan import Scene, StackRequest, SweepRequest, check_coverage, plan_stack, plan_sweep
from fieldcal.plan import ipsf
from fieldcal.plan.stack_plan import MAX_FRAMES
from fieldcal.plan.surfaces import sample_field
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.simulate.truth import TruthProfile

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


@pytest.fixture(scope="module")
def triplet(tmp_path_factory):
    from tests.conftest import MODELS
    return TruthProfile(LensSpec.load(MODELS / "triplet-uncorrected.json"), 96, 64)


def test_flat_field_needs_exactly_one_frame_at_the_focus():
    prof = SyntheticProfile(a_um=0.0, z0_um=12.5, tolerance_um=4.0)
    plan = plan_stack(prof, StackRequest())
    assert plan.n_frames == 1 and plan.lower_bound == 1
    assert abs(plan.frames_um[0] - 12.5) <= 4.0
    assert plan.stats["worst_mtf_loss"] <= 0.05 + 1e-9
    assert plan.to_dict()["frames"][0]["bands"]["G"] is not None


def test_flat_field_sweep_lasts_one_exposure_plus_nothing():
    plan = plan_sweep(SyntheticProfile(a_um=0.0, z0_um=0.0), SweepRequest(alpha_um=20.0, pixel_exposure_ms=16.0))
    assert plan.total_time_ms == pytest.approx(16.0)  # D = 0: T = t_s
    assert (plan.start_um, plan.stop_um) == (pytest.approx(-20.0), pytest.approx(20.0))
    assert np.all(np.isfinite(plan.window_start_ms))


@settings(max_examples=25, deadline=None)
@given(a_um=st.floats(-500.0, 500.0), tol_um=st.floats(0.5, 50.0))
def test_uniform_tolerance_gives_the_closed_form_count_and_covers_every_pixel(a_um, tol_um):
    prof = SyntheticProfile(width_px=48, height_px=32, a_um=a_um, tolerance_um=tol_um)
    plan = plan_stack(prof, StackRequest(grid_step_px=4))
    x, y = (v.ravel() for v in np.meshgrid(np.arange(48.0), np.arange(32.0)))
    z = prof.best_focus_um(x, y, "G")
    D = float(z.max() - z.min())  # over the pixels (the optical centre falls between pixels)
    assert plan.n_frames == max(1, math.ceil(D / (2 * tol_um) - 1e-9))
    assert check_coverage(prof, plan, x, y)["G"] >= -1e-6


def test_q_to_zero_is_a_clear_error_not_a_hang(triplet):
    with pytest.raises(ParameterError) as e:  # was: millions of frames in an O(frames x bins) loop
        plan_stack(triplet, StackRequest(q=1e-12))
    assert e.value.field == "q" and str(MAX_FRAMES) in str(e.value) and "--q" in e.value.fix
    # the same q with a frame budget gives the q the budget allows
    plan = plan_stack(triplet, StackRequest(q=1e-12, max_frames=10))
    assert plan.n_frames <= 10 and 1e-12 < plan.q_used < 0.99 and plan.warnings


def test_fs_beyond_the_cutoff_is_a_clear_error(triplet):
    with pytest.raises(ParameterError) as e:
        plan_stack(triplet, StackRequest(fs_cyc_per_mm=1e6))
    assert "--fs" in e.value.fix


def test_q_to_one_uses_the_first_otf_zero_and_fewest_frames(triplet):
    tol = focus_tolerance_um(MTFCriterion(80.0, 1 - 1e-12), 2.0)
    assert tol == pytest.approx(3.8317059702 / (math.pi * 80.0) * 2.0 * 1000.0, rel=1e-9)
    counts = [plan_stack(triplet, StackRequest(q=q)).n_frames for q in (0.01, 0.05, 0.5, 0.999, 1 - 1e-12)]
    assert counts == sorted(counts, reverse=True)  # N is non-increasing in q
    assert counts[-1] >= 1


def test_one_pixel_roi_single_channel_is_one_frame(triplet):
    plan = plan_stack(triplet, StackRequest(scene=Scene(roi=(10, 10, 1, 1), channels=("G",))))
    assert plan.n_frames == 1
    z = float(triplet.best_focus_um(np.array([10.0]), np.array([10.0]), "G")[0])
    assert abs(plan.frames_um[0] - z) <= plan.tolerance["G"]["min_um"] + 1e-9


def test_alpha_to_zero_is_refused_for_both_devices(triplet):
    with pytest.raises(ParameterError) as e:
        plan_sweep(triplet, SweepRequest(alpha_um=1e-9))
    assert e.value.field == "clock_us"
    with pytest.raises(ParameterError) as e:
        plan_sweep(triplet, SweepRequest(alpha_um=1e-9, device="lcos", scene=Scene(channels=("G",))))
    assert e.value.field == "alpha_um" and "--alpha-um" in e.value.fix
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ParameterError):
            plan_sweep(triplet, SweepRequest(alpha_um=bad))


def test_alpha_much_larger_than_D_tends_to_one_exposure_and_zero_mtf(triplet):
    plan = plan_sweep(triplet, SweepRequest(alpha_um=1e6, pixel_exposure_ms=16.0))
    D = plan.range_um
    assert plan.total_time_ms == pytest.approx((D / 2e6 + 1.0) * 16.0, rel=1e-12)
    s = plan.ipsf_summary
    assert all(np.isfinite(v) for v in (s["mtf_at_fs"], s["noise_gain"], s["in_focus_mtf_at_fs"]))
    assert s["mtf_at_fs"] < 1e-3 < s["in_focus_mtf_at_fs"]  # all contrast at fs is swept away
    row = [r for r in plan.trade if r["alpha_um"] == 1e6][0]
    assert np.isfinite(row["noise_gain_to_in_focus"])


def test_8000x6000_stack_plan_without_full_frames():
    from tests.conftest import MODELS
    big = TruthProfile(LensSpec.load(MODELS / "triplet-uncorrected.json"), 8000, 6000)
    full_frame_bytes = 8000 * 6000  # even one uint8 frame
    tracemalloc.start()
    try:
        plan = plan_stack(big, StackRequest(grid_step_px=64))
        fieldd = sample_field(big, Scene(channels=("G",)), 64)
        trade = ipsf.alpha_trade(big, fieldd.range_um, 16.0, [1e-3, 20.0, 1e5], "G", 80.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < full_frame_bytes / 4
    # the same lens and sensor area at 80x60 px (same 4:3 field) covers the same µm range: counts agree
    small = plan_stack(TruthProfile(LensSpec.load(MODELS / "triplet-uncorrected.json"), 80, 60), StackRequest())
    assert abs(plan.n_frames - small.n_frames) <= 1
    # D from the surfaces at the corners and the optical centre (radially monotone curvature)
    cx, cy = big.optical_centre_px()
    zc = [float(big.best_focus_um(np.array([x]), np.array([y]), c)[0]) for c in big.channels
          for x, y in ((0.0, 0.0), (7999.0, 5999.0), (cx, cy))]
    assert plan.field.range_um == pytest.approx(max(zc) - min(zc), abs=0.05)
    for row in trade:
        assert row["total_time_ms"] == pytest.approx((fieldd.range_um / (2 * row["alpha_um"]) + 1) * 16.0)
        assert all(np.isfinite(v) for v in row.values())
