"""Sweep plans through the profile's geometry (issue 16): each sensor pixel's window is centred on the best focus
of the scene point it images at that stage position (breathing, shift, distortion), not on the z_ref-geometry
surface read at the sensor pixel."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fieldcal.plan import masks as mk
from fieldcal.plan.surfaces import inverse_warp_px, sensor_focus_correction, sensor_focus_um
from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.simulate.lens import Distortion, LensSpec
from fieldcal.simulate.truth import TruthProfile

MODELS = Path(__file__).resolve().parents[1] / "models"
DIST = Distortion(k1=-0.04, k2=0.008, p1=5e-4, p2=-3e-4, dk1_dz_per_um=3e-5, dp1_dz_per_um=1e-6)
W, H = 96, 72
ALPHA = 50.0


def _spec(breathing: bool) -> LensSpec:
    base = LensSpec.load(MODELS / "triplet-uncorrected.json").with_sensor_size(W, H)
    if not breathing:
        return dataclasses.replace(base, exit_pupil_mm=math.inf, stage_axis_tilt_mrad=(0.0, 0.0))
    # exit pupil 8x shorter (breathing up to ~17 % over the range), distortion changing with z, a tilted stage axis
    return dataclasses.replace(base, exit_pupil_mm=base.exit_pupil_mm / 8, distortion=DIST,
                               stage_axis_tilt_mrad=(3.0, -2.0))


def _centres_um(plan) -> np.ndarray:
    """Stage position at the centre of each pixel's window: the sweep (+z) passes start + v t."""
    return plan.start_um + plan.velocity_um_per_ms * plan.window_start_ms.astype(np.float64) + plan.request.alpha_um


def _focus_error_um(truth, centres, channel, xs, ys) -> np.ndarray:
    """|centre - true best focus of the scene point the pixel images at the centre| (the truth's exact maps)."""
    out = []
    for x, y in zip(xs, ys):
        zc = float(centres[y, x])
        qx, qy = inverse_warp_px(truth, np.array([float(x)]), np.array([float(y)]), zc, channel, tol_px=1e-9)
        # the inverse is exact: the truth's forward map lands the point back on the pixel
        fx, fy = truth.warp_px(qx, qy, zc, channel)
        assert abs(fx[0] - x) < 1e-6 and abs(fy[0] - y) < 1e-6
        out.append(zc - float(truth.best_focus_um(qx, qy, channel)[0]))
    return np.abs(np.asarray(out))


@pytest.fixture(scope="module")
def breathing_plans():
    truth = TruthProfile(_spec(True))
    plan = plan_sweep(truth, SweepRequest(alpha_um=ALPHA, pixel_exposure_ms=16.0, trade_alphas_um=()))
    blind = mk.window_starts(truth, plan.field, plan.planes, plan.cfa, plan.velocity_um_per_ms, "+z",
                             sensor_geometry=False)
    return truth, plan, blind


def test_windows_are_centred_on_the_true_focus_of_the_imaged_point(breathing_plans):
    truth, plan, blind = breathing_plans
    rng = np.random.default_rng(5)
    xs = np.r_[0, W - 1, 0, W - 1, rng.integers(0, W, 30)]   # the corners (strongest breathing) and the field
    ys = np.r_[0, 0, H - 1, H - 1, rng.integers(0, H, 30)]
    blind_centres = plan.start_um + plan.velocity_um_per_ms * blind.astype(np.float64) + ALPHA
    for p, ch in enumerate(plan.planes):
        err = _focus_error_um(truth, _centres_um(plan)[p], ch, xs, ys)
        err_blind = _focus_error_um(truth, blind_centres[p], ch, xs, ys)
        # the map-aware windows: within 0.2 µm (measured 0.002: float32 times, a coarse grid interpolated) of a 50 µm half-window
        assert err.max() < 0.2, (ch, err.max())
        # the map-blind ones miss by tens of µm in the corners, a good part of α
        assert err_blind.max() > 20.0 and err_blind.max() > 50 * err.max(), (ch, err_blind.max(), err.max())
    # every window lies inside the sweep: the range was found on the sensor's geometry too
    t = plan.window_start_ms[np.isfinite(plan.window_start_ms)]
    assert t.min() >= -1e-3 and t.max() + 16.0 <= plan.total_time_ms + 1e-3


def test_sensor_focus_is_the_fixed_point_through_the_maps():
    truth = TruthProfile(_spec(True))
    xs, ys = np.array([0.0, 47.0, 95.0]), np.array([0.0, 71.0])
    z = sensor_focus_um(truth, xs, ys, "G")
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            qx, qy = inverse_warp_px(truth, np.array([x]), np.array([y]), float(z[j, i]), "G", tol_px=1e-9)
            assert abs(float(truth.best_focus_um(qx, qy, "G")[0]) - z[j, i]) < 0.05


def test_without_breathing_the_windows_are_unchanged():
    truth = TruthProfile(_spec(False))
    req = SweepRequest(alpha_um=ALPHA, pixel_exposure_ms=16.0, trade_alphas_um=())
    plan = plan_sweep(truth, req)
    assert all(sensor_focus_correction(truth, plan.field.roi, ch) is None for ch in plan.planes)
    blind = mk.window_starts(truth, plan.field, plan.planes, plan.cfa, plan.velocity_um_per_ms, "+z",
                             sensor_geometry=False)
    np.testing.assert_array_equal(plan.window_start_ms, blind)


def test_a_model_without_warp_px_uses_its_scalar_breathing():
    class Breathing(SyntheticProfile):  # m(z) = 1 + z / 10 mm about the centre, no warp_px
        def magnification(self, z_um, channel=None):
            return 1.0 + np.asarray(z_um, dtype=np.float64) / 10000.0

    prof = Breathing(width_px=64, height_px=48, a_um=-300.0)
    xs, ys = np.array([0.0, 63.0]), np.array([0.0, 47.0])
    z = sensor_focus_um(prof, xs, ys, "G")
    cx, cy = prof.optical_centre_px()
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            m = 1.0 + z[j, i] / 10000.0
            q = (cx + (x - cx) / m, cy + (y - cy) / m)
            assert abs(float(prof.best_focus_um(np.array([q[0]]), np.array([q[1]]), "G")[0]) - z[j, i]) < 0.05
