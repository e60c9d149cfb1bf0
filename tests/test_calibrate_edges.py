"""Calibration from a slanted-edge chart: the chart is recognised, best focus comes from e-SFR edge tracks, and
the surface is checked against the simulator's truth; a chart with neither edges nor texture is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fieldcal.errors import FieldcalError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.stackgen import simulate_stack, z_grid
from fieldcal.simulate.truth import TruthProfile
from fieldcal.validation.run import surface_metrics

STEP_UM = 20.0
TRIPLET = Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json"


@pytest.fixture(scope="module")
def edge_stack(tmp_path_factory):
    """The paper's triplet through a slanted-edge chart, 480x270 px, 20 µm steps across its whole field."""
    spec = LensSpec.load(TRIPLET)
    out = tmp_path_factory.mktemp("edges") / "stack"
    simulate_stack(spec, out, z_grid(-370.0, 50.0, STEP_UM), scene="slanted-edge", seed=0, size=(480, 270),
                   progress=False)
    return spec, out


def test_slanted_edge_stack_is_calibrated_from_edges(edge_stack):
    import fieldcal

    spec, path = edge_stack
    # fs = 19 cycles/mm = 0.25 cycles/px at these 13 µm pixels (80 would be above Nyquist)
    prof = fieldcal.calibrate(path, effort="quick", fs_cyc_per_mm=19.0, quiet=True)
    assert prof.calibration["measurement"] == "esfr"
    assert prof.calibration["chart"]["edges_ok"] >= 24
    w, h = prof.image["width_px"], prof.image["height_px"]
    metrics, _, _ = surface_metrics(prof, TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um))
    for c, m in metrics.items():
        # the target is surface RMS <= 0.1 scan step (the texture path gave 2.9-3.3 µm on this stack, the
        # smoothing spline's peak 0.075 step); the defocus law's peak gives ~0.02 step
        assert m["rms_um"] <= 0.05 * STEP_UM, (c, m)
        assert abs(m["bias_um"]) <= 0.03 * STEP_UM, (c, m)
    # each row's sd is honest against the truth at its position (the law fit's covariance, unscaled)
    t = prof.tiles
    ok = np.asarray(t["status"]) == "ok"
    ch = np.asarray(t["channel"])[ok]
    x, y, zb, sd = (np.asarray(t[k], dtype=float)[ok] for k in ("x_px", "y_px", "z_best_um", "z_sigma_um"))
    truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um)
    z_err = np.concatenate([(zb[ch == c] - truth.best_focus_um(x[ch == c], y[ch == c], c)) / sd[ch == c]
                            for c in prof.channels])
    assert 0.6 <= float(np.sqrt(np.mean(z_err ** 2))) <= 1.5
    # every row carries its stage-position sensitivity (the band's stage term reads it)
    assert np.all(np.isfinite(np.asarray(t["stage_gain"], dtype=float)[ok]))
    # tangential/sagittal pairs reach the fit as z_tan/z_sag (the astigmatism rows)
    zt = np.array([np.nan if v is None else v for v in prof.tiles["z_tan_um"]], dtype=float)
    zs = np.array([np.nan if v is None else v for v in prof.tiles["z_sag_um"]], dtype=float)
    assert (np.isfinite(zt) & np.isfinite(zs)).sum() >= 3 * 12
    assert prof.tiles["measure"] == "esfr"
    # the band's field-wide term is the one the peak estimator measured on this stack (frames, law, pooled
    # asymmetry; measure.esfr_focus.law_common_mode), not a fraction of the per-edge noise
    cm = prof.diagnostics["esfr"]["common_mode"]
    d = prof.surfaces.discrepancy
    for c, v in zip(d.model.channels, d.common_sd):
        assert float(v) * prof.surfaces.z_scale_um == pytest.approx(cm[c]["sd_um"], abs=1e-9)
        assert cm[c]["sd_um"] == pytest.approx(np.sqrt(cm[c]["law_um"] ** 2 + cm[c]["shape_um"] ** 2
                                                       + cm[c]["frames_um"] ** 2))
    assert prof.calibration["systematic"]["common_mode_source"].startswith("measured by the e-SFR")
    # the tolerance comes from the edges' widths as measured: an edge mixes focus only along itself, and a pair's
    # width is its tangential track's, which the radial field gradient does not spread; the square-tile window
    # correction of texture tiles (the whole gradient across a tile) narrowed it at the corners of this steep
    # field
    assert prof.tolerance_fit.diagnostics["width_window"]["rule"].startswith("none")
    gx, gy = np.meshgrid(np.linspace(0.05, 0.95, 9) * (w - 1), np.linspace(0.05, 0.95, 5) * (h - 1))
    ratio = np.concatenate([prof.focus_tolerance_um(gx, gy, c, 19.0, 0.05).ravel()
                            / truth.focus_tolerance_um(gx, gy, c, 19.0, 0.05).ravel() for c in prof.channels])
    print("delta ratio", np.percentile(ratio, [0, 50, 100]))
    assert 0.93 <= ratio.min() and ratio.max() <= 1.07, np.percentile(ratio, [0, 50, 100])


def test_chart_kind_tells_edges_from_texture(edge_stack):
    from fieldcal.formats.stack import Stack
    from fieldcal.measure.edge_tiles import chart_kind

    _, path = edge_stack
    st = Stack.open(path)
    mid = int(st.order_by_z[len(st) // 2])
    frame = st.read_normalized(mid)
    assert chart_kind(frame, tuple(st.channels)).kind == "esfr"
    # the same frame's pixels shuffled: the same levels and noise, no edges
    rng = np.random.default_rng(1)
    flat = rng.permutation(frame.reshape(-1, frame.shape[2])).reshape(frame.shape)
    k = chart_kind(flat, tuple(st.channels))
    assert k.kind == "focus-measure" and k.edges_ok < 24


def test_blank_chart_is_refused(tmp_path, triplet_path):
    import cv2
    import fieldcal

    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full((90, 160, 3), 128, np.uint8))
    out = tmp_path / "stack"
    simulate_stack(LensSpec.load(triplet_path), out, z_grid(-300.0, 0.0, 50.0), scene=str(grey), seed=0,
                   size=(160, 90), progress=False)
    with pytest.raises(FieldcalError) as e:
        fieldcal.calibrate(out, effort="quick", fs_cyc_per_mm=10.0, quiet=True)
    msg = str(e.value)
    assert "stack" in msg and "chart" in msg
    assert str(out.name) in msg


def test_short_edge_stack_is_refused_without_numpy_warnings(tmp_path):
    """Five frames 20 µm apart cannot put a peak inside most tracks: the refusal names the chart and the fix, and
    the track diagnostics of channels whose tracks all lack a width spread or floor are recorded as missing, not
    computed through NumPy's all-NaN warning (seen on a 5-frame 320 x 240 edge stack)."""
    import warnings

    import fieldcal

    out = tmp_path / "stack"
    simulate_stack(LensSpec.load(TRIPLET), out, z_grid(-40.0, 40.0, STEP_UM), scene="slanted-edge", seed=0,
                   size=(320, 240), progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(FieldcalError) as e:
            fieldcal.calibrate(out, effort="quick", fs_cyc_per_mm=13.0, quiet=True)
    msg = str(e.value)
    assert "slanted-edge" in msg and "too few edges" in msg and out.name in msg


class _Widths:
    """A profile with a measured width of 20 µm everywhere, from the given measurement."""

    f_number = 4.0  # the defocus model's δ (~40 µm at 20 cycles/mm) above the widths: no cap binds
    has_measured_tolerance = True

    def __init__(self, measurement):
        self.calibration = {} if measurement is None else {"measurement": measurement}

    def focus_tolerance_um(self, x, y, channel, fs, q):
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, 20.0)


@pytest.mark.parametrize("measurement, factor", [("esfr", 1.0), ("focus-measure", None), (None, None)])
def test_plans_use_the_measured_tolerance(measurement, factor):
    """Edge widths measure MTF(fs) and are used as they are; texture widths (or profiles that do not say) are
    narrowed by their measured bias, and the plan's source says so."""
    from fieldcal.optics import MTFCriterion
    from fieldcal.plan.tolerance import TEXTURE_WIDTH, tolerance_um

    tol, src = tolerance_um(_Widths(measurement), np.arange(3.0), np.zeros(3), "G", MTFCriterion(20.0, 0.05))
    want = 20.0 / (TEXTURE_WIDTH.factor(None) if factor is None else factor)  # fs unknown: the narrowest δ
    np.testing.assert_allclose(tol, want)
    assert src.startswith("measured") and (("texture" in src) == (factor is None))
