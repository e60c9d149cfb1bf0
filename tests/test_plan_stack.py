"""Stack plans against known truth: the paper's counts, simulated lenses on the full pixel grid, confidence,
ROI/channels/object distance, frame and time budgets, and clear errors."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from fieldcal.errors import ParameterError
from fieldcal.simulate.lens import LensSpec
from fieldcal.plan import Scene, StackRequest, plan_stack
from fieldcal.plan.cover import min_cover, nearest_index
from fieldcal.plan.planfile import read_plan, validate_plan, write_plan
from fieldcal.plan.scene import full_grid
from fieldcal.plan.stack_plan import check_coverage, optimal_uniform_count, paper_stack_count
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.simulate.truth import TruthProfile


def full_grid_optimum(profile, plan):
    """Fewest frames for the exact pixel set: min cover of every pixel's interval (all channels)."""
    x, y = full_grid(plan.field.roi)
    lo, hi = [], []
    for c in plan.field.channels:
        z = profile.best_focus_um(x, y, c).ravel() + plan.field.refocus_um
        tol = np.asarray(profile.focus_tolerance_um(x, y, c, plan.request.fs_cyc_per_mm, plan.q_used)).ravel()
        lo.append(z - tol)
        hi.append(z + tol)
    return min_cover(np.concatenate(lo), np.concatenate(hi)).n


# ------------------------------------------------------------------------------ the paper's arithmetic
def test_paper_simulation_count_D332_d4():
    assert paper_stack_count(332, 4) == 42
    prof = SyntheticProfile(97, 65, a_um=-332.0, tolerance_um=4.0)
    for placement in ("optimal", "paper"):
        plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=80, q=0.05, placement=placement, grid_step_px=4))
        assert abs(plan.field.range_um - 332.0) < 1e-6
        assert plan.n_frames == 42


def test_optimal_cover_can_need_one_frame_less_than_the_paper():
    # D = 336 = 42 * 2d: the paper's placement (first frame on axis) needs 1 + 336/8 = 43, the optimum 42
    prof = SyntheticProfile(97, 65, a_um=-336.0, tolerance_um=4.0)
    opt = plan_stack(prof, StackRequest(placement="optimal", grid_step_px=4))
    pap = plan_stack(prof, StackRequest(placement="paper", grid_step_px=4))
    assert opt.n_frames == optimal_uniform_count(336, 4) == 42
    assert pap.n_frames == paper_stack_count(336, 4) == 43
    assert np.isclose(pap.frames_um.max(), 0.0)  # the on-axis best focus is a frame
    assert np.allclose(np.diff(pap.frames_um), 8.0, atol=0.05)


def test_paper_experiment_count_reads_d_as_whole_band():
    # V.A: D = 468 µm, d = 16 µm, 30 images = 1 + floor(D/d): d is the frame spacing, i.e. half-width 8 µm
    assert paper_stack_count(468, 16 / 2) == 30
    prof = SyntheticProfile(97, 65, a_um=-468.0, tolerance_um=8.0)
    for placement in ("optimal", "paper"):
        assert plan_stack(prof, StackRequest(placement=placement, grid_step_px=4)).n_frames == 30
    # read as a half-width, d = 16 would give 15 frames, not the paper's 30
    assert paper_stack_count(468, 16) == 15


# ------------------------------------------------------------------------------ simulated lenses
@pytest.mark.parametrize("model,size", [("triplet-uncorrected", (128, 72)), ("doublet-mono", (96, 72)),
                                        ("singlet-colour", (96, 72))])
def test_truth_plans_cover_every_pixel_with_at_most_one_extra_frame(models_dir, model, size):
    prof = TruthProfile(LensSpec.load(models_dir / f"{model}.json"), *size)
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=80, q=0.05, grid_step_px=8))
    x, y = full_grid(plan.field.roi)
    margins = check_coverage(prof, plan, x, y)
    assert min(margins.values()) >= -1e-6, margins
    opt = full_grid_optimum(prof, plan)
    assert opt <= plan.n_frames <= opt + 1
    assert plan.lower_bound <= plan.n_frames
    d = plan.to_dict()
    validate_plan(d)
    assert d["tolerance"][plan.field.channels[0]]["source"].startswith("defocus model")
    assert d["coverage"]["worst_mtf_loss"] <= 0.05 + 1e-6


def test_bands_partition_the_best_focus_axis(models_dir):
    prof = TruthProfile(LensSpec.load(models_dir / "singlet-colour.json"), 96, 72)
    plan = plan_stack(prof, StackRequest(grid_step_px=4))
    d = plan.to_dict()
    x, y = full_grid(plan.field.roi)
    for c in plan.field.channels:
        bands = [f["bands"][c] for f in d["frames"]]
        used = [b for b in bands if b is not None]
        lo, hi = d["range_um"][c]
        assert math.isclose(min(b[0] for b in used), lo, abs_tol=1e-3)
        assert math.isclose(max(b[1] for b in used), hi, abs_tol=1e-3)
        ub = sorted(used)
        assert all(math.isclose(a[1], b[0], abs_tol=1e-3) for a, b in zip(ub, ub[1:]))  # contiguous
        # the band rule selects, for each pixel, a frame within its tolerance
        z = prof.best_focus_um(x, y, c).ravel()
        tol = prof.spec.focus_tolerance_um(80, 0.05, c)
        for f in d["frames"]:
            b = f["bands"][c]
            if b is not None:
                inside = (z >= b[0] - 1e-3) & (z <= b[1] + 1e-3)
                assert np.all(np.abs(z[inside] - f["z_um"]) <= tol + 1e-3)
    # R is far from B (longitudinal colour): some frames serve only one colour
    assert any(f["bands"]["R"] is None for f in d["frames"])


def test_field_varying_tolerance_full_grid():
    tol = lambda rho, fs, q: 3.0 + 4.0 * rho ** 2  # noqa: E731  wider tolerance off axis
    prof = SyntheticProfile(81, 61, a_um=-200.0, tolerance_fn=tol, centre_px=(30.3, 25.7))
    plan = plan_stack(prof, StackRequest(grid_step_px=8))
    x, y = full_grid(plan.field.roi)
    assert check_coverage(prof, plan, x, y)["G"] >= -1e-6
    opt = full_grid_optimum(prof, plan)
    assert opt <= plan.n_frames <= opt + 1
    assert plan.n_frames < optimal_uniform_count(200, 3.0)  # the wider tolerance off axis is used


# ------------------------------------------------------------------------------ uncertainty
def test_confidence_shrinks_tolerance_by_the_band_and_covers_any_surface_in_it():
    prof = SyntheticProfile(97, 65, a_um=-120.0, tolerance_um=4.0, band_um=1.0)
    plain = plan_stack(prof, StackRequest(grid_step_px=4, coverage=None))
    conf = plan_stack(prof, StackRequest(confidence=0.9, grid_step_px=4, coverage=None))
    assert plain.n_frames == 15 and conf.n_frames == 20  # ceil(120/8), ceil(120/6)
    assert conf.stats["probability"] >= 0.9
    # without --confidence the band does not place the frames, but the stated probability still uses it: the
    # worst pixel sits on a band's edge (its true focus is beyond the tolerance half the time)
    assert plain.stats["probability"] == pytest.approx(0.5, abs=0.01)
    x, y = full_grid(conf.field.roi)
    for shift in (-1.0, -0.5, 0.5, 1.0):  # the true surface anywhere inside the band
        true = SyntheticProfile(97, 65, a_um=-120.0, z0_um=shift, tolerance_um=4.0)
        assert check_coverage(true, conf, x, y)["G"] >= -1e-6
        # the plan without confidence fails for the surfaces at the edge of the band
    edge = SyntheticProfile(97, 65, a_um=-120.0, z0_um=1.0, tolerance_um=4.0)
    assert check_coverage(edge, plain, x, y)["G"] < -0.5
    assert 0.0 < conf.stats["expected_worst_mtf_loss"] < 0.05 + 1e-9


def test_confidence_impossible_when_band_wider_than_tolerance():
    prof = SyntheticProfile(33, 33, a_um=-50.0, tolerance_um=2.0, band_um=2.5)
    with pytest.raises(ParameterError) as e:
        plan_stack(prof, StackRequest(confidence=0.95))
    assert e.value.field == "confidence" and e.value.fix


# ------------------------------------------------------------------------------ what the scene asks
def test_roi_and_channels_reduce_the_plan(models_dir):
    prof = TruthProfile(LensSpec.load(models_dir / "triplet-uncorrected.json"), 128, 72)
    full = plan_stack(prof, StackRequest())
    centre = plan_stack(prof, StackRequest(scene=Scene(roi=(48, 24, 32, 24))))
    g = plan_stack(prof, StackRequest(scene=Scene(channels=("G",))))
    assert centre.n_frames < full.n_frames and g.n_frames <= full.n_frames
    assert g.field.channels == ("G",) and list(g.to_dict()["frames"][0]["bands"]) == ["G"]
    x, y = full_grid(centre.field.roi)
    assert min(check_coverage(prof, centre, x, y).values()) >= -1e-6
    zc = prof.best_focus_um(x, y, "R")
    assert math.isclose(centre.field.samples["R"].z_min_um, zc.min(), abs_tol=1e-6)


def test_object_distance_refocuses_by_the_thin_lens_shift():
    prof = SyntheticProfile(65, 49, a_um=-100.0, tolerance_um=4.0, focal_length_mm=17.6, object_distance_mm=1000.0)
    base = plan_stack(prof, StackRequest())
    near = plan_stack(prof, StackRequest(scene=Scene(object_distance_mm=500.0)))
    f = 17.6
    dv_um = (f * 500 / (500 - f) - f * 1000 / (1000 - f)) * 1000.0  # ≈ +322 µm: image moves away from the lens
    assert math.isclose(near.field.refocus_um, dv_um, rel_tol=1e-9)
    np.testing.assert_allclose(near.frames_um, base.frames_um + dv_um, atol=1e-6)
    with pytest.raises(ParameterError):
        plan_stack(prof, StackRequest(scene=Scene(object_distance_mm=10.0)))


def test_frame_budget_reports_the_q_achieved(models_dir):
    prof = TruthProfile(LensSpec.load(models_dir / "doublet-mono.json"), 96, 72)
    free = plan_stack(prof, StackRequest(q=0.05))
    cap = free.n_frames - 6
    plan = plan_stack(prof, StackRequest(q=0.05, max_frames=cap))
    assert plan.n_frames <= cap and plan.q_used > 0.05 and plan.warnings
    # the q achieved is the MTF loss at the worst pixel: it reaches (almost) the q the budget forced
    assert plan.q_used - 0.01 < plan.stats["worst_mtf_loss"] <= plan.q_used + 1e-6
    x, y = full_grid(plan.field.roi)
    assert check_coverage(prof, plan, x, y)["Y"] >= -1e-6
    # one frame fewer would not have reached that q
    assert plan_stack(prof, StackRequest(q=plan.q_used * 0.98)).n_frames > cap
    timed = plan_stack(prof, StackRequest(q=0.05, max_time_ms=cap * 25.0, exposure_ms=20.0, frame_overhead_ms=5.0))
    assert timed.n_frames == plan.n_frames and timed.to_dict()["total_time_ms"] <= cap * 25.0


def test_direction_and_plan_file_roundtrip(tmp_path):
    prof = SyntheticProfile(49, 33, a_um=-60.0, tolerance_um=4.0)
    for direction in ("+z", "-z"):
        plan = plan_stack(prof, StackRequest(direction=direction))
        d = plan.to_dict({"path": "synthetic"})
        zs = [f["z_um"] for f in d["frames"]]
        assert zs == sorted(zs, reverse=(direction == "-z"))
        write_plan(tmp_path / "p.json", d)
        back = read_plan(tmp_path / "p.json")
        assert back["frames"] == d["frames"] and back["direction"] == direction
    d["frames"] = d["frames"][::-1]
    from fieldcal.errors import SpecError
    with pytest.raises(SpecError) as e:
        write_plan(tmp_path / "bad.json", d)
    assert e.value.field == "frames"
    assert not (tmp_path / "bad.json").exists()


@pytest.mark.parametrize("kw,field", [({"q": 0.0}, "q"), ({"q": 1.0}, "q"), ({"q": float("nan")}, "q"),
                                      ({"fs_cyc_per_mm": 0.0}, "fs_cyc_per_mm"), ({"fs_cyc_per_mm": float("nan")}, "fs_cyc_per_mm"),
                                      ({"fs_cyc_per_mm": -5.0}, "fs_cyc_per_mm"), ({"confidence": 1.0}, "confidence"),
                                      ({"scene": Scene(roi=(10, 10, 0, 5))}, "roi"),
                                      ({"scene": Scene(roi=(500, 0, 5, 5))}, "roi"),
                                      ({"scene": Scene(channels=("Q",))}, "channels"),
                                      ({"max_frames": 0}, "max_frames"), ({"max_time_ms": 1.0}, "max_time_ms"),
                                      ({"placement": "spiral"}, "placement")])
def test_invalid_parameters_give_clear_errors(kw, field):
    prof = SyntheticProfile(33, 33, a_um=-40.0)
    with pytest.raises(ParameterError) as e:
        plan_stack(prof, StackRequest(**kw))
    assert e.value.field == field and e.value.fix


@settings(max_examples=25, deadline=None)
@given(fs=st.floats(5, 400), q=st.floats(0.001, 0.9), a=st.floats(-600, 600),
       cx=st.floats(-20, 60), step=st.integers(1, 16))
def test_any_valid_request_covers_the_full_grid(fs, q, a, cx, step):
    # tolerance from the defocus model (F/2), surfaces of any sign and a centre anywhere (even off the image)
    from fieldcal.optics import MTFCriterion, focus_tolerance_um
    tol = lambda rho, f, qq: np.full(np.shape(rho), focus_tolerance_um(MTFCriterion(f, qq), 2.0))  # noqa: E731
    prof = SyntheticProfile(41, 31, a_um=a, tolerance_fn=tol, centre_px=(cx, 14.0))
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=fs, q=q, grid_step_px=step))
    x, y = full_grid(plan.field.roi)
    assert check_coverage(prof, plan, x, y)["G"] >= -1e-6
    # optimum for the continuous surface: ceil(D / 2δ) over the pixels' range of best focus. (The optimum for the
    # bare set of pixel values can be lower on coarse grids, where values jump between pixels: a lower bound.)
    z = prof.best_focus_um(x, y, "G")
    d = focus_tolerance_um(MTFCriterion(fs, q), 2.0)
    assert full_grid_optimum(prof, plan) <= plan.n_frames <= optimal_uniform_count(float(np.ptp(z)), d) + 1
    assert np.all(np.diff(plan.frames_um) > 0)
