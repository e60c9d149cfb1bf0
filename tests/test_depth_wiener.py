"""Scenes with depth and a lens model: occlusion-aware best focus and the multi-frame Wiener combination."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from fieldcal.composite.depth_wiener import occlusion_focus_um, probe_plane_sigma, wiener_composite
from fieldcal.composite.source import ArrayStack
from fieldcal.composite.stack_profile import blend_kernel, composite_with_map
from fieldcal.errors import ParameterError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.render import Renderer
from fieldcal.simulate.scene import colour_leaves
from fieldcal.simulate.truth import TruthProfile

W, H = 128, 96


def test_occlusion_focus_is_the_upper_envelope_of_blur_cones():
    """A near square (depth D) on a far background: beside it the best focus is D - c d at axis distance d and
    D - c sqrt(2) k at diagonal steps k (the octagonal distance is exact there), never below the background."""
    d, c = 100.0, 30.0
    z = np.zeros((40, 40), np.float32)
    z[15:25, 15:25] = d
    out = occlusion_focus_um(z, c)
    assert np.all(out[15:25, 15:25] == d)
    for k in range(1, 6):
        assert out[20, 24 + k] == pytest.approx(max(0.0, d - c * k), abs=1e-4)
        assert out[24 + k, 24 + k] == pytest.approx(max(0.0, d - c * np.sqrt(2) * k), abs=1e-4)
    assert np.all(out >= z) and out[0, 0] == 0.0
    # a slope gentler than c per pixel (field curvature) is left as it is
    ramp = np.tile(np.linspace(0, 0.5 * c * 39, 40, dtype=np.float32), (40, 1))
    assert np.allclose(occlusion_focus_um(ramp, c), ramp)
    # per channel for H x W x C
    assert occlusion_focus_um(np.dstack([z, z + 5]), c)[20, 26, 1] == pytest.approx(d + 5 - 2 * c, abs=1e-4)
    with pytest.raises(ParameterError):
        occlusion_focus_um(z, 0.0)


def _occlusion_by_3x3_steps(z: np.ndarray, c: float) -> np.ndarray:
    """The definition: a 3x3 step (edge neighbours less c, diagonal ones less c sqrt 2) repeated until nothing
    changes, in float64 (the reference the doubling shifts must reach)."""
    out = z.astype(np.float64)
    while True:
        p = np.pad(out, 1, mode="edge")
        nxt = out.copy()
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                cost = c * np.hypot(dy, dx)
                nxt = np.maximum(nxt, p[1 + dy:1 + dy + out.shape[0], 1 + dx:1 + dx + out.shape[1]] - cost)
        if np.array_equal(nxt, out):
            return out
        out = nxt


def test_occlusion_focus_reaches_the_repeated_3x3_steps_limit():
    """Far spikes (cones wider than the image's short side), knight-move offsets and ties: the same map as the
    3x3 step repeated to convergence, and around a lone spike the octagonal distance's closed form
    ``D - c (max(|dx|, |dy|) + (sqrt 2 - 1) min(|dx|, |dy|))``."""
    rng = np.random.default_rng(3)
    for shape, c in (((37, 53), 0.7), ((64, 9), 2.5), ((1, 30), 1.0), ((30, 1), 1.0)):
        z = (rng.random(shape) * 3.0).astype(np.float32)
        z.flat[rng.choice(z.size, 4, replace=False)] += np.float32(60.0)
        assert np.allclose(occlusion_focus_um(z, c), _occlusion_by_3x3_steps(z, c), atol=1e-3)
    d, c = 50.0, 1.3
    z = np.zeros((41, 57), np.float32)
    z[13, 40] = d
    yy, xx = np.mgrid[0:41, 0:57]
    ay, ax = np.abs(yy - 13), np.abs(xx - 40)
    dist = np.maximum(ay, ax) + (np.sqrt(2.0) - 1.0) * np.minimum(ay, ax)
    assert np.allclose(occlusion_focus_um(z, c), np.maximum(0.0, d - c * dist), atol=1e-4)


@pytest.fixture(scope="module")
def flat_world():
    spec = LensSpec.load(Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json").with_sensor_size(W, H)
    fs = 0.25 / (spec.sensor.pixel_pitch_um * 1e-3)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    r = Renderer(spec, colour_leaves(W, H, 3), seed=4)
    lo, hi = spec.focus_range_um()
    z = np.arange(lo - 2 * tol, hi + 2 * tol, 1.5 * tol)
    prof = TruthProfile(spec, W, H)
    xx, yy = np.meshgrid(np.arange(W), np.arange(H))
    zb = np.stack([prof.best_focus_um(xx, yy, c) for c in spec.channel_names], -1).astype(np.float32)
    return spec, r, z, prof, zb


def _stack(spec, r, z, noise):
    return ArrayStack([r.render(float(v), noise=noise) for v in z], z, spec.channel_names,
                      black_level=spec.sensor.black_level_dn, white_level=spec.sensor.white_level_dn)


def _stack_and_blend(spec, r, z, prof, zb, noise):
    """The flat world's stack, all its frames and the depth map's blend of them (the Wiener filter's reference)."""
    st = _stack(spec, r, z, noise)
    frames = np.arange(len(st))
    return st, frames, composite_with_map(st, zb, blend_kernel(st, prof, frames), prof, frames, quiet=True)


@pytest.mark.parametrize("noise", [False, True])
def test_wiener_combination_beats_the_nearest_frame(flat_world, noise):
    """Every frame is the in-focus image through a known OTF: noise-free, the combination (sum H_k Y_k H_0 /
    sum H_k^2 = H_0 X) undoes the defocus of the nearest frame, up to half a spacing out of focus (not exactly:
    the renderer interpolates between blur levels and each frame is warped back from its own breathing, neither
    of which is a pure OTF); with the camera's noise it also averages the frames' noise (> 1 dB)."""
    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, noise)
    out, info = wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True)
    truth = r.truth().astype(np.float64)
    m = 8

    def rms(img):
        return float(np.sqrt(np.mean((np.asarray(img, np.float64)[m:-m, m:-m] - truth[m:-m, m:-m]) ** 2)))

    assert info["filters"] >= 2 and info["frames_per_label"] >= 2
    if noise:
        assert 20 * np.log10(rms(blend) / rms(out)) > 1.0, (rms(blend), rms(out))
    else:
        assert rms(out) < 0.9 * rms(blend), (rms(out), rms(blend))


def test_wiener_needs_an_f_number(flat_world):
    spec, r, z, prof, zb = flat_world
    st = _stack(spec, r, z[:3], False)

    class NoF:
        f_number = None
        pixel_pitch_um = prof.pixel_pitch_um

    with pytest.raises(ParameterError, match="F-number"):
        wiener_composite(st, zb, NoF(), np.arange(3), zb)


def test_tiles_agree_with_one_whole_image_filter(flat_world, monkeypatch):
    """Filtering tile by tile (a margin of real neighbours, only the tile's labels) is the same linear filter as
    one pass over the whole image: the two agree to a small fraction of the pixel noise."""
    import fieldcal.composite.depth_wiener as dw

    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    from fieldcal.composite import source

    monkeypatch.setattr(dw, "TILE_BLOCK_MAX_SAMPLES", 4096 * 4096)
    monkeypatch.setattr(source, "default_workers", lambda: 1)  # one thread: the whole image is one tile
    whole, info_w = wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True)
    monkeypatch.setattr(dw, "TILE_BLOCK_MAX_SAMPLES", 100 * 100)
    tiled, info_t = wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True)
    assert info_w["tiles"] == 1 and info_t["tiles"] == 12
    sigma = float(np.mean(info_w["noise_sigma"]))
    d = np.abs(whole.astype(np.float64) - tiled)
    assert np.sqrt(np.mean(d ** 2)) < 0.005 * sigma and d.max() < 0.02 * sigma, (d.max(), sigma)


def test_needed_pixels_get_the_full_filter_and_the_rest_the_reference(flat_world, monkeypatch):
    """Filtering only where the combination is needed (each label inverted on the rows its needed pixels use)
    gives those pixels the same values as filtering everywhere, and every other pixel the reference's."""
    import fieldcal.composite.depth_wiener as dw

    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    monkeypatch.setattr(dw, "TILE_BLOCK_MAX_SAMPLES", 100 * 100)
    full, _ = wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True)
    h, w = zb.shape[:2]
    yy, xx = np.mgrid[:h, :w]
    needed = ((xx + 2 * yy) % 7 < 3) & (yy % 11 < 6)  # scattered pixels in every tile, whole rows without any
    part, info = wiener_composite(st, zb, prof, frames, blend, geometry=prof, needed=needed, quiet=True)
    sigma = float(np.mean(info["noise_sigma"]))
    assert np.abs(part[needed].astype(np.float64) - full[needed]).max() < 1e-3 * sigma
    assert np.array_equal(part[~needed], np.asarray(blend, np.float32)[~needed])


def test_mixed_planes_are_the_channels_filter_when_the_mix_picks_channels(flat_world):
    """``mix`` filters weighted sums of the channels with each plane's heaviest channel's OTF and depth: rows
    that pick single channels (permuted) give those channels' filtered images, and a row that does not match
    the channels is refused."""
    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    full, info = wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True)
    perm = [2, 0, 1]
    planes, info_p = wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=np.eye(3)[perm], quiet=True)
    assert planes.shape == full.shape and info_p["filters"] == info["filters"]
    sigma = float(np.mean(info["noise_sigma"]))
    assert np.abs(planes.astype(np.float64) - full[..., perm]).max() < 1e-3 * sigma
    with pytest.raises(ParameterError, match="plane weights"):
        wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=np.ones((1, 2)), quiet=True)


def test_probe_plane_sigma_measures_known_noise_per_mixed_plane():
    """Flat frames with independent Gaussian noise of known sigma per channel: each plane's estimate is that
    sigma, and a weighted sum's is sqrt(sum w^2 sigma^2) (independent channels)."""
    rng = np.random.default_rng(3)
    sig = np.array([2.0, 5.0, 3.0])
    frames = [(100.0 + rng.normal(0.0, 1.0, (96, 128, 3)) * sig).astype(np.float32) for _ in range(4)]
    st = ArrayStack(frames, [0.0, 10.0, 20.0, 30.0], ["R", "G", "B"])
    mix = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.5, -0.5, 0.0]])
    got = probe_plane_sigma(st, np.arange(4), mix=mix)
    want = np.sqrt((mix ** 2) @ sig ** 2)
    # the least over the probe frames sits a little below the truth
    assert np.allclose(got, want, rtol=0.08), (got, want)
    assert np.allclose(probe_plane_sigma(st, np.arange(4)), sig, rtol=0.08)


def test_probe_noise_of_8_bit_frames_on_a_flat_background_is_at_least_their_rounding():
    """A subject on a black background: more than half of each 8-bit frame is exactly 0, so Immerkaer's median
    read 0 and the Wiener step filtered "without noise" (the real board put on a black canvas: noise 0.0, the
    composite's board noisier than the board composited alone). Rounding to whole DN is noise of sd 1/sqrt(12)
    in each channel, and a weighted sum's is sqrt(sum w^2) times it; float frames have none."""
    rng = np.random.default_rng(4)
    frames = []
    for _ in range(4):
        f = np.zeros((96, 128, 3), np.float64)
        f[30:60, 40:80] = 120.0 + rng.normal(0.0, 0.2, (30, 40, 3))  # a quarter of the frame: the subject
        frames.append(np.clip(np.rint(f), 0, 255).astype(np.uint8))
    st = ArrayStack(frames, [0.0, 10.0, 20.0, 30.0], ["R", "G", "B"])
    mix = np.array([[0.299, 0.587, 0.114], [0.5, -0.5, 0.0]])
    q = 1.0 / np.sqrt(12.0)
    assert np.allclose(probe_plane_sigma(st, np.arange(4)), q)
    assert np.allclose(probe_plane_sigma(st, np.arange(4), mix=mix), q * np.sqrt((mix ** 2).sum(axis=1)))
    st_float = ArrayStack([f.astype(np.float32) for f in frames], [0.0, 10.0, 20.0, 30.0], ["R", "G", "B"])
    assert probe_plane_sigma(st_float, np.arange(4)) == [0.0, 0.0, 0.0]



def test_sampled_rows_noise_is_the_whole_planes_estimate_through_every_block_row():
    """The probe's sampled-row estimate (only every s-th row filtered, the channels' responses mixed) is
    Immerkaer's estimate of the mixed plane from all its responses, to its sampling error, also when the noise
    differs by row within 8-px blocks (a JPEG's block edges): an odd row step visits every row of a block, where an
    even one (every 4th row: centre rows 1 and 5 of each block) puts a loud row into half its responses, not 3 in
    8, and reads ~8 % high here."""
    from fieldcal.composite.depth_wiener import _mixed, _plane_noise
    from fieldcal.composite.sweep import estimate_noise_sigma

    rng = np.random.default_rng(5)
    h, w = 400, 300
    yy, xx = np.mgrid[0:h, 0:w]
    row_sd = np.where(yy % 8 == 0, 6.0, 1.0)  # loud block-edge rows: 1 row in 8
    planes = [(50.0 * np.sin(xx / 17.0 + c) + row_sd * rng.normal(0.0, 1.0, (h, w))).astype(np.float32)
              for c in range(3)]
    mix = np.array([[0.299, 0.587, 0.114], [0.5, -0.4187, -0.0813]])
    want = [estimate_noise_sigma(p) for p in _mixed(planes, mix)]  # every response
    # ~1/4 of the responses: a step of 4 rows made odd (5)
    got = _plane_noise(planes, mix, (h - 2) * (w - 2) // 4)
    assert np.allclose(got, want, rtol=0.03), (got, want)
    assert _plane_noise(planes[:1], None, 10 ** 9)[0] == pytest.approx(estimate_noise_sigma(planes[0]), rel=1e-4)


def test_a_shared_noise_probe_gives_each_call_its_own_probe_result(flat_world):
    """The luma and chroma calls given their planes' levels from one probe of all three planes filter exactly as
    when each probes its own; a wrong number of levels is refused."""
    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    ycc = np.array([[0.299, 0.587, 0.114], [-0.1687, -0.3313, 0.5], [0.5, -0.4187, -0.0813]])
    sig = probe_plane_sigma(st, frames, geometry=prof, mix=ycc)
    for rows, ps in ((ycc[:1], sig[:1]), (ycc[1:], sig[1:])):
        own, info_own = wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=rows, quiet=True)
        shared, info = wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=rows, plane_sigma=ps,
                                        quiet=True)
        assert np.array_equal(own, shared) and info["noise_sigma"] == info_own["noise_sigma"]
    with pytest.raises(ParameterError, match="plane noise levels"):
        wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc[1:], plane_sigma=sig, quiet=True)


def test_row_bands_on_threads_give_the_single_threads_combination(flat_world, monkeypatch):
    """The power-law fit's per-frequency work and the per-pixel labels, made in row bands on several threads,
    give the one-thread result bit for bit (the fit's samples joined in row order are the same arrays), for the
    channels and for mixed planes with only some pixels needed."""
    import fieldcal.composite.depth_wiener as dw
    from fieldcal.composite import dff
    from fieldcal.composite import source

    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    h, w = zb.shape[:2]
    needed = (np.mgrid[:h, :w].sum(axis=0) % 5) < 3
    ycc = np.array([[0.299, 0.587, 0.114], [-0.169, -0.331, 0.5], [0.5, -0.419, -0.081]])
    monkeypatch.setattr(dff, "BAND_MIN_ROWS", 8)  # several bands on the small test image
    # the same tiles for any thread count (the tile rule balances tiles over the threads)
    monkeypatch.setattr(dw, "tile_grid", lambda w, h, margin, workers, real=dw.tile_grid, **kw: real(w, h, margin, 1,
                                                                                                   **kw))
    calls = [dict(), dict(mix=ycc[1:], needed=needed, noise_sigma=1.0)]
    results, real = {}, dw.row_bands
    for workers in (1, 3):
        monkeypatch.setattr(source, "default_workers", lambda n=workers: n)
        called = []
        monkeypatch.setattr(dw, "row_bands", lambda fn, n: called.append(n) or real(fn, n))
        results[workers] = [wiener_composite(st, zb, prof, frames, blend, geometry=prof, quiet=True, **kw)
                            for kw in calls]
        assert called  # the banded paths ran
    for (one, info_one), (many, info_many) in zip(results[1], results[3]):
        np.testing.assert_array_equal(many, one)
        assert info_many == info_one
    fns = [lambda t: prof.defocus_otf(t, 0.0, "G")]
    monkeypatch.setattr(source, "default_workers", lambda: 1)
    ref = dw._power_law(np.asarray(blend, np.float32)[..., 1:2], 20, prof.pixel_pitch_um, fns, [1.0])
    monkeypatch.setattr(source, "default_workers", lambda: 3)
    assert dw._power_law(np.asarray(blend, np.float32)[..., 1:2], 20, prof.pixel_pitch_um, fns, [1.0]) == ref


def _grid_cost(w, h, margin, workers, nx, ny):
    """tile_grid's stated model, written out independently: an even split into nx x ny tiles, every tile on the
    block of the largest core plus its margins (scipy's fast real length), slots rounded up to the workers."""
    from scipy import fft

    import fieldcal.composite.depth_wiener as dw

    by = fft.next_fast_len(-(-h // ny) + 2 * margin, real=True)
    bx = fft.next_fast_len(-(-w // nx) + 2 * margin, real=True)
    n = nx * ny
    slots = -(-n // workers) * workers
    return by * bx, slots * (by * bx * np.log2(by * bx) + dw.TILE_OVERHEAD)


@pytest.mark.parametrize("w,h", [(1, 1), (7, 5), (37, 23), (401, 299), (1919, 1081), (2048, 1536)])
@pytest.mark.parametrize("workers", [1, 2, 3])
def test_tile_grid_covers_the_image_once_at_the_least_modelled_cost(w, h, workers):
    """The tiles cover every pixel exactly once (odd sizes too), cores differ by at most a pixel, every core
    with its margins fits the block, the block is within the sample bound, and no other even split within the
    bound has a lower modelled cost (brute force over all splits)."""
    from fieldcal.composite.depth_wiener import TILE_BLOCK_MAX_SAMPLES, tile_grid

    margin = 34
    ex, ey, nb_y, nb_x = tile_grid(w, h, margin, workers)
    cover = np.zeros((h, w), int)
    for y0, y1 in pairwise(ey):
        for x0, x1 in pairwise(ex):
            assert x1 > x0 and y1 > y0
            assert x1 - x0 + 2 * margin <= nb_x and y1 - y0 + 2 * margin <= nb_y
            cover[y0:y1, x0:x1] += 1
    assert np.all(cover == 1)
    assert np.ptp(np.diff(ex)) <= 1 and np.ptp(np.diff(ey)) <= 1
    assert nb_y * nb_x <= TILE_BLOCK_MAX_SAMPLES
    nx, ny = len(ex) - 1, len(ey) - 1
    _, cost = _grid_cost(w, h, margin, workers, nx, ny)
    for kx in range(1, max(1, min(w // 8, 128)) + 1):
        for ky in range(1, max(1, min(h // 8, 128)) + 1):
            samples, other = _grid_cost(w, h, margin, workers, kx, ky)
            if samples <= TILE_BLOCK_MAX_SAMPLES:
                assert cost <= other * (1 + 1e-12), ((nx, ny), (kx, ky))


def test_tile_grid_sizes_for_common_frames():
    """The rule on frame sizes it was not tuned on: a 2048 x 1536 frame on two threads is split 3 x 2 (768 x 864
    blocks, not twelve 600 x 600 ones), a 1920 x 1080 one 3 x 2 (no 56-row strip of partial tiles), and 24 MP
    frames into tile counts the threads share evenly, all within the block bound."""
    from fieldcal.composite.depth_wiener import TILE_BLOCK_MAX_SAMPLES, tile_grid

    ex, ey, nb_y, nb_x = tile_grid(2048, 1536, 34, 2)
    assert (len(ex) - 1, len(ey) - 1, nb_y, nb_x) == (3, 2, 864, 768)
    ex, ey, nb_y, nb_x = tile_grid(1920, 1080, 34, 2)
    assert (len(ex) - 1, len(ey) - 1) == (3, 2)
    for w, h in ((4000, 3000), (6000, 4000)):
        for workers in (2, 4):
            ex, ey, nb_y, nb_x = tile_grid(w, h, 34, workers)
            assert ((len(ex) - 1) * (len(ey) - 1)) % workers == 0 and nb_y * nb_x <= TILE_BLOCK_MAX_SAMPLES
    # a small image: one tile for one thread, a tile per thread for two (one tile's FFTs on two threads left the
    # rest serial)
    assert tile_grid(320, 240, 34, 1)[:2] == ([0, 320], [0, 240])
    assert len(tile_grid(320, 240, 34, 2)[0]) + len(tile_grid(320, 240, 34, 2)[1]) == 5


def test_tile_grid_with_labels_follows_where_the_depth_varies():
    """With each cell's labels given: where every cell holds every label the split is the label-blind one; where
    the labels change across the columns only (a slope), the split cuts columns (strips whose tiles each use few
    labels), at a lower labelled cost than the label-blind split, and cells with no needed pixel cost nothing."""
    from fieldcal.composite.depth_wiener import tile_grid

    w, h, margin, cell = 2048, 1536, 34, 16
    ys, xs = np.arange(0, h, cell), np.arange(0, w, cell)
    shape = (len(ys), len(xs))
    blind = tile_grid(w, h, margin, 2)
    full = [np.zeros(shape, int), np.full(shape, 48)]
    assert tile_grid(w, h, margin, 2, label_maps=(ys, xs, [full[0]], [full[1]], 21)) == blind
    slope = np.broadcast_to((xs * 48) // w, shape)
    ex, ey, by, bx = tile_grid(w, h, margin, 2, label_maps=(ys, xs, [slope], [slope], 21))
    assert len(ex) - 1 > len(ey) - 1 and (ex, ey) != (blind[0], blind[1])

    def labelled(grid):  # filters of each tile (labels lo .. hi + 1 of its cells) + 21 forward, x N log2 N
        gx, gy, nb_y, nb_x = grid
        total = 0
        for y0, y1 in pairwise(gy):
            for x0, x1 in pairwise(gx):
                cols = (xs + cell - 1 >= x0) & (xs < x1)
                labs = set()
                for v in np.unique(slope[0][cols]):
                    labs |= {int(v), int(v) + 1}
                total += len(labs) + 21
        n_t = (len(gx) - 1) * (len(gy) - 1)
        total *= -(-n_t // 2) * 2 / n_t
        return total * nb_y * nb_x * np.log2(nb_y * nb_x)

    assert labelled((ex, ey, by, bx)) < labelled(blind)
    none = [np.ones(shape, int)], [np.zeros(shape, int)]  # lo > hi everywhere: nothing needed
    assert tile_grid(w, h, margin, 2, label_maps=(ys, xs, *none, 21)) == blind


def test_one_pass_over_luma_and_chroma_labels_equals_a_call_per_group(flat_world, monkeypatch):
    """Planes on two label spacings filtered in one pass over the tiles (each tile's frames read once) give each
    group's call of its own bit for bit: the luma on fine labels and the chroma on coarse ones, several tiles,
    only some pixels needed; the per-group info is the group call's; a spacing per plane of the wrong count is
    refused."""
    import fieldcal.composite.depth_wiener as dw

    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    h, w = zb.shape[:2]
    monkeypatch.setattr(dw, "TILE_BLOCK_MAX_SAMPLES", 100 * 100)  # several tiles on the small image
    needed = ((np.mgrid[:h, :w].sum(axis=0) % 7) < 4) & (np.arange(h)[:, None] % 13 < 9)
    ycc = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
    fine, coarse = 3.0, 25.0
    from fieldcal.composite import warp

    read, real_warp_region = [], warp.warp_region  # (imported by the Wiener step at its call)

    def counting(*a, **k):
        read.append(a[1])
        return real_warp_region(*a, **k)

    monkeypatch.setattr(warp, "warp_region", counting)
    sep = [wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=rows, label_um=lab, needed=needed,
                            quiet=True) for rows, lab in ((ycc[:1], fine), (ycc[1:], coarse))]
    n_sep = len(read)
    read.clear()
    one, info = wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc, label_um=[fine, coarse, coarse],
                                 needed=needed, quiet=True)
    assert 0 < len(read) < n_sep  # fewer frame reads than the two calls'
    assert info["tiles"] > 1 and info["filters"] == sep[0][1]["filters"] + sep[1][1]["filters"]
    np.testing.assert_array_equal(one, np.concatenate([sep[0][0], sep[1][0]], axis=2))
    for g, (_, info_g) in zip(info["groups"], sep):
        assert {k: v for k, v in g.items() if k != "plane_index"} == info_g
    assert [g["plane_index"] for g in info["groups"]] == [[0], [1, 2]]
    with pytest.raises(ParameterError, match="label spacings"):
        wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc, label_um=[fine, coarse], quiet=True)


def test_reference_signal_made_beforehand_is_the_calls_own(flat_world):
    """The reference's planes and power laws made apart (reference_signal, as the composite makes them on a thread
    beside the cones) give the call's output bit for bit, and the reference is then not read; a signal made for
    other planes or another noise is refused."""
    from fieldcal.composite.depth_wiener import reference_signal

    spec, r, z, prof, zb = flat_world
    st, frames, blend = _stack_and_blend(spec, r, z, prof, zb, True)
    ycc = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
    labels, sigma = [3.0, 25.0, 25.0], [0.01, 0.004, 0.004]
    own, _ = wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc, label_um=labels,
                              plane_sigma=sigma, quiet=True)
    sig = reference_signal(blend, prof, st.channels, sigma, mix=ycc, label_um=labels)
    assert len(sig.planes) == 3 and all(p.shape == zb.shape[:2] for p in sig.planes)
    np.testing.assert_allclose(sig.planes[0], blend @ ycc[0].astype(np.float32), rtol=1e-6, atol=1e-6)
    made, _ = wiener_composite(st, zb, prof, frames, None, geometry=prof, mix=ycc, label_um=labels,
                               plane_sigma=sigma, signal=sig, quiet=True)
    np.testing.assert_array_equal(made, own)
    with pytest.raises(ParameterError, match="reference signal"):
        wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc, label_um=labels,
                         plane_sigma=[0.02, 0.004, 0.004], signal=sig, quiet=True)
    with pytest.raises(ParameterError, match="reference signal"):  # made for other label spacings
        wiener_composite(st, zb, prof, frames, blend, geometry=prof, mix=ycc, label_um=[3.0, 3.0, 25.0],
                         plane_sigma=sigma, signal=sig, quiet=True)
    with pytest.raises(ParameterError, match="noise levels"):
        reference_signal(blend, prof, st.channels, sigma[:2], mix=ycc, label_um=labels)
