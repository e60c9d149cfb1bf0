"""Geometry maps (issue 16): simulator distortion and its truth, the map fit, ChArUco and texture recovery,
profiles with and without maps, schemas."""

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fieldcal.errors import FieldcalError, SpecError
from fieldcal.fit.geometry_map import Correspondences, GeometryMap, fit_geometry_map
from fieldcal.simulate.lens import Distortion, LensSpec, brown_conrady, brown_conrady_inverse
from fieldcal.simulate.truth import TruthProfile

REPO = Path(__file__).resolve().parents[1]
DIST = Distortion(k1=-0.04, k2=0.008, p1=5e-4, p2=-3e-4, dk1_dz_per_um=3e-5, dp1_dz_per_um=1e-6)


def distorted_lens(size=(320, 240), curvature=0.3, distortion=DIST) -> LensSpec:
    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json").with_sensor_size(*size)
    lc = {"R": 4e-4, "G": 0.0, "B": -5e-4}
    chs = tuple(dataclasses.replace(c, lateral_colour=lc[c.name],
                                    curvature_um=tuple(a * curvature for a in c.curvature_um)) for c in spec.channels)
    return dataclasses.replace(spec, channels=chs, distortion=distortion)


def field_rms(a: GeometryMap | object, truth: TruthProfile, z, channel, size) -> float:
    w, h = size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    tx, ty = truth.warp_px(xs, ys, z, channel)
    fx, fy = a.warp_px(xs, ys, z, channel)
    return float(np.sqrt(np.mean((tx - fx) ** 2 + (ty - fy) ** 2)))


# ----------------------------------------------------------------------------------------------- simulator
def test_brown_conrady_inverse_round_trip():
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, (2, 500))
    dx, dy = brown_conrady(u[0], u[1], -0.05, 0.01, 1e-3, -2e-3)
    ix, iy = brown_conrady_inverse(dx, dy, -0.05, 0.01, 1e-3, -2e-3)
    assert np.max(np.abs(ix - u[0])) < 1e-11 and np.max(np.abs(iy - u[1])) < 1e-11
    # barrel (k1 < 0) pulls a corner point towards the centre by k1 r^2 of its radius
    x, _ = brown_conrady(np.array([0.5]), np.array([0.0]), -0.04, 0.0, 0.0, 0.0)
    assert x[0] == pytest.approx(0.5 * (1 - 0.04 * 0.25))


def test_folding_distortion_is_refused():
    with pytest.raises(SpecError) as e:
        brown_conrady_inverse(np.array([1.0]), np.array([0.0]), -0.2, 0.0, 0.0, 0.0)
    assert "folds" in str(e.value)


def test_spec_round_trip_and_old_specs():
    spec = distorted_lens()
    d = spec.to_dict()
    assert d["distortion"]["k1"] == -0.04
    assert LensSpec.from_dict(json.loads(json.dumps(d))).distortion == DIST
    plain = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    assert plain.distortion.is_zero and "distortion" not in plain.to_dict()  # old documents stay as they were


def test_spec_schema_rejects_bad_distortion():
    d = distorted_lens().to_dict()
    d["distortion"]["k9"] = 1.0
    with pytest.raises(SpecError) as e:
        LensSpec.from_dict(d)
    assert "distortion" in str(e.value)
    d["distortion"] = {"k1": "big"}
    with pytest.raises(SpecError):
        LensSpec.from_dict(d)


def test_schema_copies_identical():
    for name in ("fieldcal-lens-1", "fieldcal-stack-1", "fieldcal-profile-1", "fieldcal-geometry-map-1"):
        a = (REPO / "fieldcal" / "formats" / "schemas" / f"{name}.schema.json").read_bytes()
        assert a == (REPO / "docs" / "schemas" / f"{name}.schema.json").read_bytes(), name


def test_truth_warp_identity_and_scalar_limit():
    spec = distorted_lens()
    t = TruthProfile(spec, z_ref_um=-20.0)
    x, y = np.meshgrid(np.arange(0, 320, 40.0), np.arange(0, 240, 40.0))
    gx, gy = t.warp_px(x, y, -20.0, "G")
    assert np.max(np.abs(gx - x)) < 1e-9 and np.max(np.abs(gy - y)) < 1e-9
    # without distortion the map is DESIGN's c + m(z) L (p - c) + s(z)
    plain = TruthProfile(dataclasses.replace(spec, distortion=Distortion()), z_ref_um=-20.0)
    qx, qy = plain.warp_px(x, y, 30.0, "R")
    cx, cy = spec.optical_centre_px()
    m = plain.magnification(30.0) * spec.lateral_colour_scale("R")
    sx, sy = plain.shift_px(30.0)
    assert np.allclose(qx, cx + m * (x - cx) + sx, atol=1e-9) and np.allclose(qy, cy + m * (y - cy) + sy, atol=1e-9)
    # constant distortion cancels out of frame-to-frame maps; a changing one does not
    const = TruthProfile(dataclasses.replace(spec, distortion=Distortion(k1=-0.05)), z_ref_um=-20.0)
    assert np.allclose(const.warp_px(x, y, 30.0, "G")[0], plain.warp_px(x, y, 30.0, "G")[0], atol=1e-9)
    assert np.max(np.abs(t.warp_px(x, y, 30.0, "G")[0] - plain.warp_px(x, y, 30.0, "G")[0])) > 0.05


def test_renderer_moves_a_dot_where_the_truth_says():
    from fieldcal.simulate.render import Renderer
    spec = dataclasses.replace(distorted_lens((160, 120), curvature=0.0),
                               distortion=Distortion(k1=-0.05, dk1_dz_per_um=5e-4))
    scene = np.zeros((120, 160), np.float32)
    yy, xx = np.mgrid[0:120, 0:160]
    scene += np.exp(-((xx - 30.0) ** 2 + (yy - 25.0) ** 2) / (2 * 2.0 ** 2)).astype(np.float32)
    r = Renderer(spec, scene, seed=0)
    img = r.render_float(40.0)[..., 1]
    sub = img[5:50, 5:60]
    ys, xs = np.mgrid[5:50, 5:60]
    cx, cy = np.sum(sub * xs) / sub.sum(), np.sum(sub * ys) / sub.sum()
    tx, ty = spec.sensor_px(30.0, 25.0, 40.0, "G")
    assert abs(cx - tx) < 0.05 and abs(cy - ty) < 0.05
    assert np.hypot(tx - 30.0, ty - 25.0) > 0.5  # the distortion moved it measurably


# ---------------------------------------------------------------------------------------------------- fit
def synthetic_correspondences(truth, z, size, sigma_px=0.02, seed=0):
    w, h = size
    xs, ys = np.meshgrid(np.linspace(10, w - 10, 12), np.linspace(10, h - 10, 9))
    xs, ys = xs.ravel(), ys.ravel()
    rng = np.random.default_rng(seed)
    P, Q, Z, C = [], [], [], []
    for c in truth.channels:
        for zz in z:
            qx, qy = truth.warp_px(xs, ys, zz, c)
            P.append(np.c_[xs, ys])
            Q.append(np.c_[qx, qy] + rng.normal(0, sigma_px, (xs.size, 2)))
            Z += [zz] * xs.size
            C += [c] * xs.size
    n = len(Z)
    return Correspondences(np.concatenate(P), np.concatenate(Q), np.array(Z), np.array(C), np.ones(n),
                           np.full(n, -1))


def test_map_fit_recovers_truth_with_honest_sd():
    size = (320, 240)
    z = np.linspace(-120, 40, 9)
    truth = TruthProfile(distorted_lens(size), z_ref_um=z[4])
    g = fit_geometry_map(synthetic_correspondences(truth, z, size), z[4], size)
    w, h = size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    zscores = []
    for c in "RGB":
        for zz in z:
            assert field_rms(g, truth, zz, c, size) < 0.02
            tx, _ = truth.warp_px(xs, ys, zz, c)
            fx, _ = g.warp_px(xs, ys, zz, c)
            sx, _ = g.warp_sd_px(xs, ys, zz, c)
            if zz != z[4] or c != "G":
                zscores.append(np.mean(((fx - tx) / sx) ** 2))
    # the covariance is neither far too small nor far too large (errors are correlated over the field)
    assert 0.05 < np.sqrt(np.mean(zscores)) < 3.0
    assert all(k == 0 or k >= 1 for _, k in g.channels["R"].columns)
    assert all(k >= 1 for _, k in g.channels["G"].columns)  # the reference channel is the identity at z_ref


def test_map_fit_bic_prefers_no_distortion_terms_without_distortion():
    size = (320, 240)
    z = np.linspace(-60, 60, 7)
    truth = TruthProfile(distorted_lens(size, distortion=Distortion()), z_ref_um=0.0)
    g = fit_geometry_map(synthetic_correspondences(truth, z, size, sigma_px=0.05), 0.0, size)
    terms = {t for t, _ in g.channels["G"].columns}
    assert terms == {"scale", "shift_x", "shift_y"}


def test_geometry_map_round_trip_and_schema():
    from fieldcal.formats import documents
    size = (320, 240)
    z = np.linspace(-60, 60, 5)
    truth = TruthProfile(distorted_lens(size), z_ref_um=0.0)
    g = fit_geometry_map(synthetic_correspondences(truth, z, size), 0.0, size)
    d = json.loads(json.dumps(g.to_dict()))
    documents.validate(d, "geometry-map")
    g2 = GeometryMap.from_dict(d)
    assert np.allclose(g2.warp_px(100.0, 50.0, 30.0, "B"), g.warp_px(100.0, 50.0, 30.0, "B"))
    d["channels"]["G"]["columns"][0][0] = "k7"
    with pytest.raises(FieldcalError):
        documents.validate(d, "geometry-map")


# ------------------------------------------------------------------------------------------- measurement
def render_frames(spec, scene, z):
    from fieldcal.simulate.render import Renderer
    r = Renderer(spec, scene, seed=1)
    return [r.render(float(zz)) for zz in z]


def test_charuco_recovers_the_simulated_geometry():
    from fieldcal.charts.targets import charuco_image, charuco_spec
    from fieldcal.measure.charuco import charuco_correspondences
    size = (320, 240)
    spec = distorted_lens(size)
    z = np.linspace(-100.0, 20.0, 5)
    board = charuco_spec(*size, squares_short=6)
    frames = render_frames(spec, charuco_image(board), z)
    corr = charuco_correspondences(lambda k, ci: frames[k][..., ci], z, spec.channel_names, board, 2, "G")
    g = fit_geometry_map(corr, z[2], size)
    truth = TruthProfile(spec, z_ref_um=z[2])
    worst = max(field_rms(g, truth, zz, c, size) for c in "RGB" for zz in z)
    assert worst < 0.05


def test_corner_refinement_does_not_lock_to_pixels():
    """A 1e-3 scale change of the (aliased) board is measured in full, not pulled to the pixel grid."""
    from fieldcal.charts.targets import charuco_image, charuco_spec
    from fieldcal.measure.charuco import charuco_corners
    from fieldcal.simulate.warp import scale_shift
    w, h = 320, 240
    board = charuco_spec(w, h, squares_short=6)
    a = 1.001
    img = scale_shift(charuco_image(board), a, (1 - a) * (w - 1) / 2, (1 - a) * (h - 1) / 2)
    q, ids = charuco_corners(img, board)
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    p = board.corner_px(ids)
    u = p - c
    measured = np.sum((q - c) * u) / np.sum(u * u) - 1.0
    assert measured == pytest.approx(a - 1.0, rel=0.03)


def test_texture_recovers_the_simulated_geometry():
    from fieldcal.charts.targets import chart_image
    from fieldcal.measure.charuco import texture_correspondences
    size = (256, 192)
    spec = distorted_lens(size)
    z = np.linspace(-80.0, 20.0, 4)
    frames = render_frames(spec, chart_image("texture", *size, 0), z)
    corr = texture_correspondences(lambda k, ci: frames[k][..., ci], z, spec.channel_names, 2, "G", step_px=20)
    g = fit_geometry_map(corr, z[2], size, source="texture")
    truth = TruthProfile(spec, z_ref_um=z[2])
    worst = max(field_rms(g, truth, zz, c, size) for c in "RGB" for zz in z)
    assert worst < 0.15


# --------------------------------------------------------------------------------- stacks, profiles, CLI
@pytest.fixture(scope="module")
def charuco_world(tmp_path_factory):
    """A ChArUco stack of the distortion lens (stack.json records the board) and its calibrated profile.

    The scan passes best focus everywhere with margin (the field's focus spans -70 µm at the corners to +11 µm,
    R at the centre): over -120..40 µm the centre's and corners' curves did not close, and the surface fitted to
    the board's few remaining tiles was an extrapolation (R 35-374 µm RMS), which calibrate rightly refuses once
    the rejected tiles' brackets contradict it."""
    from fieldcal.cli import main
    root = tmp_path_factory.mktemp("charuco")
    spec = distorted_lens((320, 240))
    spec.save(root / "lens.json")
    assert main(["simulate", str(root / "lens.json"), str(root / "S"), "--z", "-160", "80", "20", "--scene",
                 "charuco", "--quiet"]) == 0
    assert main(["calibrate", str(root / "S"), "--out", str(root / "p.json"), "--fs", "12", "--effort", "quick",
                 "--z-ref", "-40", "-q"]) == 0
    return root


def test_stack_records_the_board_and_calibrate_uses_it(charuco_world):
    """The board's map is accurate where the board is, and honest where it is extrapolated.

    Inside the hull of the board's corners every channel's map is within 0.05 px RMS of the truth at every
    frame (measured 0.004 px). The frame's corners lie 77 px beyond the outermost board corner (r 123 -> 200 px
    from the centre), where the z-varying distortion (dk1/dz) is extrapolated as r^3: there the truth must lie
    within 3 of the map's stated sd (measured 2.3 sd at most; 2.55 on the stack rendered with the level blend
    before session 8). A whole-frame 0.05 px bound (until session 8) measured that extrapolation's luck: with
    the disc-squared level blend the corners' changes inside the board (<= 0.002 px) moved B's frame corner to
    0.25 px at z = -160 µm (stated sd 0.13): 0.058 px RMS over the frame, 0.003 px inside the board."""
    from scipy.spatial import Delaunay

    from fieldcal.charts.targets import board_from_record
    from fieldcal.formats.stack import Stack, stack_chart
    from fieldcal.measure.charuco import charuco_corners
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.truth import load_truth
    st = Stack.open(charuco_world / "S")
    chart = stack_chart(st.meta)
    assert chart["kind"] == "charuco" and chart["squares_x"] > 2 and chart["marker_mm"] < chart["square_mm"]
    prof = LensProfile.load(charuco_world / "p.json")
    assert prof.has_geometry_map and prof.geometry_map.source == "charuco"
    t = load_truth(charuco_world / "S")
    truth = TruthProfile(t.spec, *t.image_size_px, z_ref_um=prof.z_ref_um)
    w, h = prof.image_size_px
    ref = st.read_normalized(int(np.argmin(np.abs(np.asarray(st.z_um) - prof.z_ref_um))))
    corners, _ = charuco_corners(ref[..., list(st.channels).index("G")], board_from_record(chart, w, h))
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    inside = Delaunay(corners).find_simplex(np.column_stack([xs.ravel(), ys.ravel()])).reshape(xs.shape) >= 0
    assert 0.2 * inside.size < inside.sum() < 0.8 * inside.size
    for zz in st.z_um:
        for c in prof.channels:
            tx, ty = truth.warp_px(xs, ys, zz, c)
            fx, fy = prof.warp_px(xs, ys, zz, c)
            err = np.hypot(fx - tx, fy - ty)
            assert np.sqrt(np.mean(err[inside] ** 2)) < 0.05, (zz, c)
            sd = np.hypot(*prof.warp_sd_px(xs, ys, zz, c))
            stated = sd > 0      # G at z_ref is the reference itself (error and sd 0)
            assert np.all(err[stated] < 3.0 * sd[stated]), (zz, c, float(np.max(err[stated] / sd[stated])))
    sx, sy = prof.warp_sd_px([10.0, 160.0], [10.0, 120.0], 20.0, "R")
    assert np.all(sx > 0) and np.all(sy > 0) and np.all(sx < 0.2)


def test_old_profiles_without_maps_load_and_answer_with_the_scalar_model(charuco_world, tmp_path):
    from fieldcal.profile.lens_profile import LensProfile
    d = json.loads((charuco_world / "p.json").read_text())
    d.pop("geometry_map")
    (tmp_path / "old.json").write_text(json.dumps(d))
    shutil.copy(charuco_world / d["sidecar"]["file"], tmp_path / d["sidecar"]["file"])
    old = LensProfile.load(tmp_path / "old.json")
    assert not old.has_geometry_map
    x, y = np.array([5.0, 200.0]), np.array([7.0, 150.0])
    cx, cy = old.optical_centre_px()
    m = old.magnification(20.0, "B") * old.lateral_colour_scale("B")
    sx, sy = old.shift_px(20.0, "B")
    qx, qy = old.warp_px(x, y, 20.0, "B")
    assert np.allclose(qx, cx + m * (x - cx) + sx) and np.allclose(qy, cy + m * (y - cy) + sy)
    assert np.all(np.isfinite(old.warp_sd_px(x, y, 20.0, "B")[0]))


def test_profile_with_a_bad_map_block_is_refused(charuco_world, tmp_path):
    from fieldcal.profile.lens_profile import LensProfile
    d = json.loads((charuco_world / "p.json").read_text())
    d["geometry_map"]["channels"]["G"]["columns"] = [["scale", "one"]]
    (tmp_path / "bad.json").write_text(json.dumps(d))
    shutil.copy(charuco_world / d["sidecar"]["file"], tmp_path / d["sidecar"]["file"])
    with pytest.raises(FieldcalError) as e:
        LensProfile.load(tmp_path / "bad.json")
    assert "geometry_map" in str(e.value)


def test_chart_record_from_targets_and_record_chart(tmp_path, charuco_world):
    from fieldcal.charts.targets import chart_record_from_targets, write_targets
    from fieldcal.formats.stack import Stack, record_chart, stack_chart
    write_targets(tmp_path / "t", 200.0, 150.0, 100.0, kinds=["charuco"], formats=("png",))
    rec = chart_record_from_targets(tmp_path / "t" / "targets.json")
    assert rec["kind"] == "charuco" and rec["square_mm"] > rec["marker_mm"] > 0
    st = tmp_path / "S"
    shutil.copytree(charuco_world / "S", st)
    record_chart(st, rec)
    assert stack_chart(Stack.open(st).meta)["squares_x"] == rec["squares_x"]
    with pytest.raises(FieldcalError):
        record_chart(st, {"kind": "charuco", "dictionary": "DICT_4X4_50", "squares_x": 5, "squares_y": 5,
                          "square_mm": 10, "marker_mm": 7})
    with pytest.raises(FieldcalError):
        chart_record_from_targets(charuco_world / "lens.json")


def test_compositor_follows_the_dense_map():
    """frame_maps of a distorted lens carry the non-affine residual, and warp_from samples where warp_px says."""
    from fieldcal.composite.warp import frame_maps, warp_from
    size = (160, 120)
    truth = TruthProfile(distorted_lens(size), z_ref_um=0.0)
    maps = frame_maps(truth, 60.0, truth.channels, lateral_colour=True)
    assert len(maps) == 3 and all(m.residual is not None for m in maps)
    yy, xx = np.mgrid[0:120, 0:160].astype(np.float32)
    src = np.dstack([xx, yy])  # a frame whose value is its own coordinate
    fm = maps[1]
    out = warp_from(src, 0, 0, fm.matrix, 20, 10, 140, 110, residual=fm.residual)
    px, py = np.meshgrid(np.arange(20, 140.0), np.arange(10, 110.0))
    qx, qy = truth.warp_px(px, py, 60.0, "G")
    # cv2's bicubic kernel (a = -0.75, the affine path's too) reads a ramp up to ~0.06 px off at sub-pixel phases
    assert np.max(np.abs(out[..., 0] - qx)) < 0.08 and np.max(np.abs(out[..., 1] - qy)) < 0.08
    assert np.sqrt(np.mean((out[..., 0] - qx) ** 2 + (out[..., 1] - qy) ** 2)) < 0.06
    plain = TruthProfile(dataclasses.replace(truth.spec, distortion=Distortion()), z_ref_um=0.0)
    assert all(m.residual is None for m in frame_maps(plain, 60.0, plain.channels))


def test_import_and_simulate_record_a_chart_from_targets(tmp_path, charuco_world):
    from fieldcal.charts.targets import write_targets
    from fieldcal.cli import main
    from fieldcal.formats.stack import Stack, stack_chart
    write_targets(tmp_path / "t", 200.0, 150.0, 100.0, kinds=["charuco"], formats=("png",))
    frames = sorted((charuco_world / "S" / "frames").iterdir())
    assert main(["import", *map(str, frames), "--out", str(tmp_path / "I"), "--z", "-100", "30",
                 "--pixel-pitch-um", "5", "--chart", str(tmp_path / "t" / "targets.json"), "--quiet"]) == 0
    chart = stack_chart(Stack.open(tmp_path / "I").meta)
    assert chart["kind"] == "charuco" and chart["square_mm"] > 0
    # a file that is no chart description is refused before anything is written
    assert main(["import", *map(str, frames), "--out", str(tmp_path / "J"), "--z", "-100", "30",
                 "--pixel-pitch-um", "5", "--chart", str(charuco_world / "lens.json"), "--quiet"]) != 0
    assert not (tmp_path / "J").exists()
