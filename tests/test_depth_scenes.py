"""Scenes with depth: the layered renderer against the flat one, and depth from focus against the known depth."""

from __future__ import annotations

import numpy as np
import pytest

from fieldcal.composite.fusion import depth_map, fuse_pyramid
from fieldcal.composite.source import ArrayStack
from fieldcal.composite.stack_profile import blend_kernel, composite_with_map
from fieldcal.simulate.depth import LAYOUTS, DepthRenderer, DepthScene, depth_edges, depth_scene
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.render import Renderer
from fieldcal.simulate.truth import TruthProfile

W, H = 160, 120


@pytest.fixture(scope="module")
def spec(request):
    from pathlib import Path
    return LensSpec.load(Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json").with_sensor_size(W, H)


def _tol(spec):
    fs = 0.25 / (spec.sensor.pixel_pitch_um * 1e-3)
    return min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_layouts_span_the_depth_range(layout):
    s = depth_scene(layout, W, H, 100.0, seed=2)
    assert s.image.shape == (H, W, 3) and s.depth_um.shape == (H, W)
    assert s.depth_um.min() == 0.0 and s.depth_um.max() == pytest.approx(100.0, rel=0.02)
    assert 0.0 <= s.image.min() and s.image.max() <= 1.0
    assert depth_edges(s.depth_um, 5.0).any()


def test_a_flat_scene_renders_exactly_as_the_flat_renderer(spec):
    s = depth_scene("steps", W, H, 0.0, seed=1)
    layered = DepthRenderer(spec, s, seed=3)
    flat = Renderer(spec, s.image, seed=3)
    for z in (-200.0, 0.0):
        assert np.array_equal(layered.render(z), flat.render(z))


def test_each_layer_is_sharp_at_its_own_focus(spec):
    """Two halves, the right one 6 tolerances nearer: at the left's focus the left is sharper, and vice versa."""
    tol = _tol(spec)
    d = np.zeros((H, W), np.float32)
    d[:, W // 2:] = 6 * tol
    base = depth_scene("steps", W, H, 0.0, seed=4)
    r = DepthRenderer(spec, DepthScene(base.image, d, "halves"), seed=0)
    x, y = W // 2 - 30, H // 2
    z_left = float(spec.best_focus_um(*spec.pixel_to_mm(float(x), float(y)), "G"))

    def sharpness(img, x0, x1):
        g = img[20:-20, x0:x1, 1].astype(np.float64)
        return np.mean(np.diff(g, axis=1) ** 2)

    at_left = r.render_float(z_left)
    at_right = r.render_float(z_left + 6 * tol)
    assert sharpness(at_left, 10, W // 2 - 10) > 2 * sharpness(at_right, 10, W // 2 - 10)
    assert sharpness(at_right, W // 2 + 10, W - 10) > 2 * sharpness(at_left, W // 2 + 10, W - 10)


@pytest.fixture(scope="module")
def steps_stack(spec):
    tol = _tol(spec)
    scene = depth_scene("steps", W, H, 6 * tol, seed=1)
    r = DepthRenderer(spec, scene, seed=2)
    lo, hi = spec.focus_range_um()
    z = np.arange(lo - tol, hi + 6 * tol + tol, 1.5 * tol)
    frames = [r.render(float(v)) for v in z]
    st = ArrayStack(frames, z, spec.channel_names,
                    black_level=spec.sensor.black_level_dn, white_level=spec.sensor.white_level_dn)
    return st, r, scene, tol


def test_depth_map_follows_the_steps(spec, steps_stack):
    st, r, scene, tol = steps_stack
    truth = TruthProfile(spec, W, H)
    dm = depth_map(st, truth, quiet=True)
    xx, yy = np.meshgrid(np.arange(W), np.arange(H))
    z_true = np.mean([r.best_focus_um(xx, yy, c) for c in spec.channel_names], axis=0)
    err = np.abs(dm.z_um - z_true)
    import cv2
    far = cv2.distanceTransform((~depth_edges(scene.depth_um, 0.5 * tol)).astype(np.uint8), cv2.DIST_L2, 3) > 4
    inner = far.copy()
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    assert np.mean(err[inner] < 0.5 * tol) > 0.95, np.mean(err[inner] < 0.5 * tol)


def test_depth_map_composite_is_near_the_oracle_and_beats_a_smooth_surface(spec, steps_stack):
    from fieldcal.composite.api import composite_stack

    st, r, scene, tol = steps_stack
    truth_p = TruthProfile(spec, W, H)
    truth = r.truth().astype(np.float64)
    white = float(spec.sensor.white_level_dn)

    def psnr(img):
        m = 8
        return 10 * np.log10(white ** 2 / np.mean((img[m:-m, m:-m].astype(np.float64) - truth[m:-m, m:-m]) ** 2))

    xx, yy = np.meshgrid(np.arange(W), np.arange(H))
    frames = np.arange(len(st))
    kernel = blend_kernel(st, truth_p, frames, None, 0.05, 0.25)
    zb_true = np.stack([r.best_focus_um(xx, yy, c) for c in spec.channel_names], -1).astype(np.float32)
    oracle = psnr(composite_with_map(st, zb_true, kernel, truth_p, frames, quiet=True))
    dm = depth_map(st, truth_p, quiet=True)
    offs = zb_true - zb_true.mean(axis=2, keepdims=True)  # the lens's own channel offsets (a profile's)
    ours = psnr(composite_with_map(st, (dm.z_um[..., None] + offs).astype(np.float32), kernel, truth_p, frames,
                                   quiet=True))
    surface = psnr(composite_stack(st, truth_p, method="dff", depth="flat", quiet=True).image)
    auto = composite_stack(st, truth_p, method="dff", quiet=True)
    assert ours > oracle - 1.0, (ours, oracle)
    assert ours > surface + 1.0, (ours, surface)
    # the scene's depth is found from the data, and the public path does what the pieces above do
    assert auto.info["scene"] == "3d" and psnr(auto.image) > surface + 1.0, (auto.info, psnr(auto.image))


def test_a_flat_chart_is_found_flat(spec):
    """Depth from focus on a flat chart keeps the smooth surface (no per-pixel noise where there is no depth)."""
    from fieldcal.charts.targets import chart_image
    from fieldcal.composite.api import composite_stack

    r = Renderer(spec, chart_image("texture", W, H, 3), seed=1)
    tol = _tol(spec)
    lo, hi = spec.focus_range_um()
    z = np.arange(lo - tol, hi + tol, 1.5 * tol)
    st = ArrayStack([r.render(float(v)) for v in z], z, spec.channel_names,
                    black_level=spec.sensor.black_level_dn, white_level=spec.sensor.white_level_dn)
    res = composite_stack(st, TruthProfile(spec, W, H), method="dff", quiet=True)
    assert res.info["scene"] == "flat", res.info


def test_fusion_keeps_the_sharp_frame_everywhere():
    rng = np.random.default_rng(0)
    sharp = rng.random((64, 96, 3)).astype(np.float32)
    import cv2
    blurred = cv2.GaussianBlur(sharp, (0, 0), 3.0)
    left = np.where(np.arange(96)[None, :, None] < 48, sharp, blurred).astype(np.float32)
    right = np.where(np.arange(96)[None, :, None] < 48, blurred, sharp).astype(np.float32)
    st = ArrayStack([left, right], [0.0, 50.0], ["R", "G", "B"])
    out = fuse_pyramid(st, quiet=True)
    err = np.abs(out.image - sharp)[8:-8]
    assert err[:, :40].mean() < 0.1 * np.abs(blurred - sharp)[8:-8, :40].mean()
    assert err[:, 56:].mean() < 0.1 * np.abs(blurred - sharp)[8:-8, 56:].mean()
    assert np.all(out.depth_index[8:-8, 8:40] == 0) and np.all(out.depth_index[8:-8, 56:-8] == 1)
