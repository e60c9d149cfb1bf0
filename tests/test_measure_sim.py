"""Measurement on small simulated stacks against the simulator's truth (fieldcal.measure)."""

import dataclasses
import math

import numpy as np
import pytest

from fieldcal.errors import ParameterError
from fieldcal.simulate.lens import ChannelSpec, LensSpec
from fieldcal.measure import ArrayStack, GeometryMeasurements, measure_geometry, measure_stack, measure_tiles
from fieldcal.simulate import Renderer
from fieldcal.charts.targets import chart_image
from fieldcal.simulate.truth import TruthProfile

STEP_UM = 4.0
WAVELENGTH = {"R": 656.3, "G": 546.1, "B": 486.1, "Y": 546.1}
OFFSET = {"R": 8.0, "G": 0.0, "B": -6.0, "Y": 0.0}


def small_lens(models_dir, W=256, H=160, pitch=3.45, N=2.8, curv=-60.0, channels=("R", "G", "B"), cfa=None,
               exit_pupil_mm=19.0, tilt_mrad=(0.5, -0.3)):
    """The paper triplet's camera scaled to a small sensor: same pitch, field curvature over the small field."""
    base = LensSpec.load(models_dir / "triplet-uncorrected.json")
    hmax = 0.5 * math.hypot(W, H) * pitch / 1000.0
    chans = tuple(ChannelSpec(c, WAVELENGTH[c], OFFSET[c], (curv,), 0.0, 0.0) for c in channels)
    sensor = dataclasses.replace(base.sensor, width_px=W, height_px=H, pixel_pitch_um=pitch, cfa=cfa)
    return dataclasses.replace(base, f_number=N, image_height_max_mm=hmax, channels=chans, sensor=sensor,
                               exit_pupil_mm=exit_pupil_mm, stage_axis_tilt_mrad=tilt_mrad, residual_blur_um=1.0)


def render_stack(spec, z_um, seed=1):
    W, H = spec.sensor.width_px, spec.sensor.height_px
    r = Renderer(spec, chart_image("texture", W, H, 0), seed=seed)
    frames = [r.render(float(z)) for z in z_um]
    s = spec.sensor
    return ArrayStack(frames, z_um, pixel_pitch_um=s.pixel_pitch_um, channels=spec.channel_names, cfa=s.cfa,
                      black_level=s.black_level_dn, white_level=s.white_level_dn)


def fs_for(spec, cycles_per_px=0.2):
    return cycles_per_px / (spec.sensor.pixel_pitch_um * 1e-3)


def tile_truth(spec, table, rows, z_ref_um=None):
    """Truth best focus averaged over each tile (the tile measures an average over its pixels), in the
    geometry of the measurement's reference frame (default: the middle frame, as measure_stack chooses)."""
    if z_ref_um is None:
        z_ref_um = float(table.z_um[table.z_um.size // 2])
    tp = TruthProfile(spec, z_ref_um=z_ref_um)
    o = np.arange(table.tile_px) - (table.tile_px - 1) / 2.0
    ox, oy = np.meshgrid(o, o)
    return np.array([tp.best_focus_um(table.x_px[i] + ox, table.y_px[i] + oy, str(table.channel[i])).mean()
                     for i in rows])


@pytest.fixture(scope="module")
def colour(request):
    from conftest import MODELS
    spec = small_lens(MODELS)
    z = np.arange(-90.0, 40.0 + 1e-9, STEP_UM)
    return spec, render_stack(spec, z)


@pytest.mark.parametrize("measure", ["bandpass", "sml"])
def test_best_focus_accuracy_colour(colour, measure):
    spec, stack = colour
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs_for(spec), measure=measure, quiet=True)
    assert table.tile_px == 32 and len(table) == 3 * 28
    assert table.ok.mean() > 0.9
    for ch in spec.channel_names:
        rows = np.flatnonzero(table.ok & (table.channel == ch))
        err = table.z_best_um[rows] - tile_truth(spec, table, rows)
        rms = float(np.sqrt(np.mean(err ** 2)))
        # target: <= 0.1 x the scan step (measured: ~0.13 um band-pass, ~0.2-0.25 um SML)
        assert rms <= 0.1 * STEP_UM, (ch, rms)
        assert np.all(table.z_sigma_um[rows] > 0)


def test_widths_follow_the_lens_model(colour):
    spec, stack = colour
    fs = fs_for(spec)
    table = measure_tiles(stack, fs_cyc_per_mm=fs, q=0.05, quiet=True)
    for ch in spec.channel_names:
        w = table.width_um[(table.channel == ch) & np.isfinite(table.width_um)]
        assert w.size > 20
        assert np.median(w) == pytest.approx(spec.focus_tolerance_um(fs, 0.05, ch), rel=0.05)


def test_geometry_matches_the_spec(colour):
    spec, stack = colour
    geo = measure_geometry(stack, quiet=True)
    assert geo.z_um.size == len(stack) and geo.ref_index == len(stack) // 2
    assert np.all(geo.magnification[geo.ref_index] == 1.0)
    slope_true = 1.0 / (spec.exit_pupil_mm * 1000.0)
    sx_true, sy_true = (np.polyfit(geo.z_um, v, 1)[0] for v in spec.shift_px(geo.z_um))
    for c, ch in enumerate(geo.channels):
        slope = np.polyfit(geo.z_um, geo.magnification[:, c], 1)[0]
        assert slope == pytest.approx(slope_true, rel=0.05), ch
        assert abs(np.polyfit(geo.z_um, geo.shift_x_px[:, c], 1)[0] - sx_true) < 5e-4
        assert abs(np.polyfit(geo.z_um, geo.shift_y_px[:, c], 1)[0] - sy_true) < 5e-4
        m_true = spec.magnification(geo.z_um) / spec.magnification(geo.z_ref_um)
        # errors within a few reported sigmas (sigma grows away from the reference frame)
        err = np.abs(geo.magnification[:, c] - m_true)
        assert np.all(err <= 4.0 * geo.mag_sigma[:, c] + 2e-5)
    # no lateral colour in this lens: every channel at the same scale (despite different blur per channel)
    assert set(geo.lateral_colour_scale) == {"R", "G", "B"}
    for ch, s in geo.lateral_colour_scale.items():
        assert s == pytest.approx(1.0, abs=5e-4), ch


def test_thorough_effort_gives_tangential_and_sagittal_foci(colour):
    # The simulator blurs isotropically (astigmatism as an equivalent defocus), so both directional foci
    # must agree with the isotropic band-pass focus; synthetic stripes test the direction split itself.
    spec, stack = colour
    table = measure_tiles(stack, fs_cyc_per_mm=fs_for(spec), measure="bandpass", effort="thorough", quiet=True)
    ok = table.ok & np.isfinite(table.z_tan_um) & np.isfinite(table.z_sag_um)
    assert ok.sum() >= 0.7 * table.ok.sum()
    assert np.median(np.abs(table.z_tan_um[ok] - table.z_best_um[ok])) < 0.5
    assert np.median(np.abs(table.z_sag_um[ok] - table.z_best_um[ok])) < 0.5


def test_tiles_follow_the_image(models_dir):
    # Strong focus breathing (exit pupil 4 mm) and a tilted stage axis (0.1 rad): the corners move several px
    # over the scan. The measured geometry places each tile where the truth says the image went, to a
    # fraction of a pixel, and the best focus keeps close to the target. (Much stronger breathing biases
    # z_best: the texture's power at fixed fs changes with the image scale, tilting the curve.)
    spec = small_lens(models_dir, W=224, H=160, channels=("Y",), exit_pupil_mm=4.0, curv=-40.0,
                      tilt_mrad=(100.0, -80.0))
    z = np.arange(-60.0, 28.0 + 1e-9, STEP_UM)
    stack = render_stack(spec, z)
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs_for(spec), measure="bandpass", quiet=True)
    xs, ys = np.array([0.0, 223.0, 0.0, 223.0]), np.array([0.0, 0.0, 159.0, 159.0])
    cx, cy = spec.optical_centre_px()
    m0 = spec.magnification(geo.z_ref_um)
    s0x, s0y = spec.shift_px(geo.z_ref_um)
    moved = 0.0
    for k, zk in enumerate(geo.z_um):
        m = spec.magnification(zk) / m0
        sx, sy = spec.shift_px(zk)
        tx, ty = cx + m * (xs - cx) + sx - m * s0x, cy + m * (ys - cy) + sy - m * s0y
        gx, gy = geo.map_points(k, "Y", xs, ys)
        assert np.max(np.hypot(gx - tx, gy - ty)) < 0.3
        moved = max(moved, float(np.max(np.hypot(tx - xs, ty - ys))))
    assert moved > 2.5  # the corners really move
    assert geo.max_displacement_px() == pytest.approx(moved, abs=0.3)
    rows = np.flatnonzero(table.ok)
    assert np.sqrt(np.mean((table.z_best_um[rows] - tile_truth(spec, table, rows)) ** 2)) <= 0.15 * STEP_UM


def test_mono_stack_at_f4(models_dir):
    # depth of focus grows with N: 6 um steps over a wider scan
    spec = small_lens(models_dir, W=192, H=128, N=4.0, channels=("Y",), curv=-80.0)
    z = np.arange(-126.0, 60.0 + 1e-9, 6.0)
    stack = render_stack(spec, z)
    table = measure_tiles(stack, fs_cyc_per_mm=fs_for(spec), measure="bandpass", quiet=True)
    rows = np.flatnonzero(table.ok)
    assert rows.size >= 0.8 * len(table), table.counts()
    err = table.z_best_um[rows] - tile_truth(spec, table, rows)
    assert np.sqrt(np.mean(err ** 2)) <= 0.1 * 6.0


def test_bayer_stack_uses_each_colour_sub_lattice(models_dir):
    spec = small_lens(models_dir, W=256, H=192, cfa="RGGB")
    z = np.arange(-88.0, 36.0 + 1e-9, STEP_UM)
    stack = render_stack(spec, z)
    assert stack.read(0).ndim == 2  # a raw mosaic
    # fs at 0.15 cycles per full-resolution px = 0.3 per sub-lattice px
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs_for(spec, 0.15), measure="bandpass", quiet=True)
    assert set(table.channel) == {"R", "G", "B"}
    for ch in ("R", "G", "B"):
        rows = np.flatnonzero(table.ok & (table.channel == ch))
        assert rows.size >= 20
        err = table.z_best_um[rows] - tile_truth(spec, table, rows)
        assert np.sqrt(np.mean(err ** 2)) <= 0.15 * STEP_UM, ch
    # the channels' own focus offsets (R +8, B -6 um) come out
    zc = {ch: np.median(table.z_best_um[table.ok & (table.channel == ch)] - tile_truth(
        spec, table, np.flatnonzero(table.ok & (table.channel == ch))) * 0) for ch in ("R", "G", "B")}
    assert zc["R"] - zc["G"] == pytest.approx(8.0, abs=1.5)
    assert zc["B"] - zc["G"] == pytest.approx(-6.0, abs=1.5)
    slope = np.polyfit(geo.z_um, geo.magnification[:, 1], 1)[0]
    assert slope == pytest.approx(1.0 / 19000.0, rel=0.1)


def test_fs_above_the_sub_lattice_nyquist_is_a_clear_error(models_dir):
    spec = small_lens(models_dir, W=64, H=48, cfa="RGGB")
    stack = render_stack(spec, np.arange(-8.0, 9.0, 4.0))
    with pytest.raises(ParameterError, match="fs = .* sub-lattice"):
        measure_tiles(stack, fs_cyc_per_mm=fs_for(spec, 0.3), tile_px=16, quiet=True)


# ---------------------------------------------------------------------------------- rejection reasons
T = 32
MARGIN = 8


def _blocks_stack():
    """Eight 32-px tiles, each a constructed case; identity geometry so the tile grid is known."""
    import cv2
    rng = np.random.default_rng(0)
    z = np.arange(-40.0, 40.0 + 1e-9, STEP_UM)
    nx, ny = 4, 2
    W, H = nx * T + 2 * MARGIN, ny * T + 2 * MARGIN
    tex = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 0.7)
    tex = np.clip(0.5 + (tex - tex.mean()) * (0.25 / tex.std()), 0.0, 1.0)
    ramp = np.tile(np.linspace(0.2, 0.8, W, dtype=np.float32), (H, 1))
    cases = ["ok", "low_texture", "saturated", "peak_outside_range", "peak_at_edge", "flat", "multi_peak", "ok2"]

    def sigma(case, zz):
        if case == "peak_outside_range":
            return 0.4 + abs(zz - 48.0) / 8.0
        if case == "peak_at_edge":
            return 0.4 + abs(zz - (z[0] + 2.0)) / 25.0
        if case == "multi_peak":
            return 0.4 + min(abs(zz + 22.0), abs(zz - 22.0)) / 8.0
        return 0.4 + abs(zz - (3.0 if case == "ok" else -9.0)) / 8.0

    # each block fades into the grey surround over its outer 3 px: a sharp seam between blocks is texture that no
    # defocus blurs, and the SML's energy (focus.sml(energy=True)) counts it fully in every frame
    ramp1 = lambda n: np.minimum(np.minimum(np.arange(n) + 0.5, n - 0.5 - np.arange(n)) / 3.0, 1.0)  # noqa: E731
    taper = np.outer(ramp1(T), ramp1(T)).astype(np.float32)

    def frame(i):
        zz = z[i]
        out = np.full((H, W), 0.5, np.float32)
        for k, case in enumerate(cases):
            bx, by = k % nx, k // nx
            sl = (slice(MARGIN + by * T, MARGIN + (by + 1) * T), slice(MARGIN + bx * T, MARGIN + (bx + 1) * T))
            if case == "low_texture":
                block = np.full((H, W), 0.5, np.float32)
            elif case == "flat":
                block = ramp
            else:
                block = 0.3 + 0.4 * cv2.GaussianBlur(tex, (0, 0), sigma(case, zz))
                if case == "saturated":
                    block = np.minimum(block * 2.2, 1.0)
            out[sl] = 0.5 + (block[sl] - 0.5) * taper
        noise = np.random.default_rng(i).normal(0.0, 0.003, out.shape).astype(np.float32)
        return np.clip(out + noise, 0.0, 1.0)

    return z, cases, ArrayStack([frame(i) for i in range(z.size)], z, ("Y",), pixel_pitch_um=5.0)


def test_every_rejection_reason_is_triggered_by_its_case():
    z, cases, stack = _blocks_stack()
    ident = GeometryMeasurements.identity(z, ("Y",), (stack.shape[1], stack.shape[0]))
    table = measure_tiles(stack, geometry=ident, fs_cyc_per_mm=0.2 / 5e-3, tile_px=T, measure="sml", quiet=True)
    assert len(table) == 8
    # rows are in grid order (row-major), like the blocks; rejected tiles keep the geometric centre
    order = np.arange(8)
    got = [str(s) for s in table.status]
    np.testing.assert_allclose(table.x_px[1], MARGIN - 0.5 + 1.5 * T)
    expect = [c if c not in ("ok2",) else "ok" for c in cases]
    assert got == expect
    ok = table.z_best_um[order]
    assert ok[0] == pytest.approx(3.0, abs=0.4) and ok[7] == pytest.approx(-9.0, abs=0.4)
    assert np.all(np.isnan(table.z_best_um[table.status != "ok"]))
    assert table.counts()["ok"] == 2


def test_bad_parameters_are_clear_errors():
    z, _, stack = _blocks_stack()
    for kwargs, field in [({"fs_cyc_per_mm": -1.0}, "fs_cyc_per_mm"), ({"q": 1.5}, "q"),
                          ({"tile_px": 8}, "tile_px"), ({"measure": "tenengrad"}, "measure"),
                          ({"effort": "max"}, "effort")]:
        with pytest.raises(ParameterError) as e:
            measure_tiles(stack, quiet=True, **kwargs)
        assert e.value.field == field and e.value.fix
    few = ArrayStack([stack.read(i) for i in range(3)], z[:3], ("Y",), pixel_pitch_um=5.0)
    with pytest.raises(ParameterError, match="too few frames"):
        measure_tiles(few, quiet=True)
    other = GeometryMeasurements.identity(z[:-1], ("Y",), (stack.shape[1], stack.shape[0]))
    with pytest.raises(ParameterError, match="another stack"):
        measure_tiles(stack, geometry=other, quiet=True)


def test_on_disk_stack_quick_effort(tmp_path, models_dir):
    from fieldcal.simulate import simulate_stack
    from fieldcal.formats.stack import Stack
    spec = small_lens(models_dir, W=192, H=128, channels=("R", "G", "B"))
    z = np.arange(-84.0, 44.0 + 1e-9, STEP_UM)
    simulate_stack(spec, tmp_path / "s", z, seed=2, progress=False)
    stack = Stack.open(tmp_path / "s")
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs_for(spec), effort="quick", quiet=True)
    assert table.tile_px == 32
    assert table.ok.mean() > 0.8, table.counts()
    # quick, measure "auto": the SML moved by the offset measured on a strip of tiles through the middle
    # (measure/fs_strip.py: speed); the strip's widths are kept on their grid tiles (a frame this small
    # band-passes every tile row, so every accepted tile has one); geometry of G copied to every channel
    assert table.measure == "sml@fs" and np.all(np.isfinite(table.width_um[table.ok]))
    assert all(r["from"] == "strip" and r["n_tiles"] >= 2 for r in table.skew.values()), table.skew
    np.testing.assert_array_equal(geo.magnification[:, 0], geo.magnification[:, 1])
    sml, _ = measure_stack(stack, fs_cyc_per_mm=fs_for(spec), effort="quick", measure="sml", geometry=geo,
                           quiet=True)
    assert sml.measure == "sml" and np.all(np.isnan(sml.width_um))
    # quick asked for the SML moved to the band-pass at fs: widths on every channel
    atfs, _ = measure_stack(stack, fs_cyc_per_mm=fs_for(spec), effort="quick", measure="sml@fs", geometry=geo,
                            quiet=True)
    assert atfs.measure == "sml@fs" and np.all(np.isfinite(atfs.width_um[atfs.ok]))
    for t in (table, atfs, sml):
        rows = np.flatnonzero(t.ok)
        err = t.z_best_um[rows] - tile_truth(spec, t, rows)
        assert np.sqrt(np.mean(err ** 2)) <= 0.1 * STEP_UM


def test_focus_breathing_does_not_bias_best_focus(tmp_path):
    """A flat lens with the triplet's focus breathing: best focus is measured without the ~0.05-step bias
    that a per-pixel mean SML (window growing with the image) or a phase-dependent warp produced."""
    import dataclasses
    import math

    import fieldcal
    from conftest import MODELS
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack, z_grid

    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    chans = tuple(dataclasses.replace(c, focus_offset_um=3.3, curvature_um=(), astigmatism_um=0.0)
                  for c in base.channels[1:2])
    spec = dataclasses.replace(base, channels=chans, stage_axis_tilt_mrad=(0.0, 0.0))
    assert math.isfinite(spec.exit_pupil_mm)
    simulate_stack(spec, tmp_path / "s", z_grid(-60, 60, 10.0), scene="chart", seed=1, size=(320, 180),
                   progress=False, noise=False)
    table, _ = measure_stack(fieldcal.Stack.open(tmp_path / "s"), fs_cyc_per_mm=10, measure="sml",
                             effort="standard", quiet=True)
    err = table.z_best_um[table.ok] - 3.3
    assert table.ok.sum() >= 10
    # was -0.47 (per-pixel mean) and -0.9 (with the cubic warp too). The SML's absolute values also scattered
    # the tiles by sd 1.2 µm (the image crossing the pixel grid as it breathes, focus.sml): its energy gives
    # 0.42, median -0.12; four tiles at the frame's edge are still 1.2-1.5 µm low (mean -0.18)
    assert abs(np.median(err)) < 0.15
    assert err.std() < 0.6


def _flat_lens_stack(exit_pupil_mm, z_um, size=(320, 180)):
    """The triplet's camera with a flat best-focus surface at +3.3 um (G only), noise-free, in memory."""
    from conftest import MODELS
    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    chans = tuple(dataclasses.replace(c, focus_offset_um=3.3, curvature_um=(), astigmatism_um=0.0)
                  for c in base.channels[1:2])
    spec = dataclasses.replace(base, channels=chans, stage_axis_tilt_mrad=(0.0, 0.0),
                               exit_pupil_mm=exit_pupil_mm).with_sensor_size(*size)
    r = Renderer(spec, chart_image("texture", *size, 1), seed=1)
    s = spec.sensor
    return spec, ArrayStack([r.render(float(z), noise=False) for z in z_um], z_um, pixel_pitch_um=s.pixel_pitch_um,
                            channels=spec.channel_names, black_level=s.black_level_dn, white_level=s.white_level_dn)


def test_focus_breathing_does_not_bias_band_pass_best_focus_or_width():
    """Exaggerated breathing (exit pupil 4 mm: the image scale changes by 7.5 % over the scan) on a flat lens.

    A band-pass at a fixed frequency in cycles/px sees a different scene frequency in every frame; the
    dead-leaves texture's power there falls as ~m^-1.4 and pulled best focus by -2.75 um (0.18 step) here,
    -0.2 um on the triplet's own breathing. The filter follows the image's magnification instead (at the
    measured geometry, or at a given one), the width is reported at fs itself, and the directional measures
    split that invariant band energy by each cell's radial gradient fraction.
    """
    z = np.arange(-150.0, 150.0 + 1e-9, 15.0)
    fs = 10.0  # 0.2 cycles/px at 320 px
    spec, stack = _flat_lens_stack(4.0, z)
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs, measure="bandpass", quiet=True)
    assert geo.magnification[-1, 0] / geo.magnification[0, 0] > 1.07  # the breathing is really there
    assert table.ok.sum() >= 40
    err = table.z_best_um[table.ok] - 3.3
    assert abs(err.mean()) < 0.5, err.mean()
    # the same with the geometry given: the filter follows it rather than the registration in the pass
    given = measure_tiles(stack, geometry=geo, fs_cyc_per_mm=fs, measure="bandpass", quiet=True)
    np.testing.assert_allclose(given.z_best_um[table.ok], table.z_best_um[table.ok], atol=0.05)
    # the directional foci too (thorough): they were -2.0 um off with gradient energies of the followed band
    th = measure_tiles(stack, geometry=geo, fs_cyc_per_mm=fs, measure="bandpass", effort="thorough", quiet=True)
    ok = th.ok & np.isfinite(th.z_tan_um) & np.isfinite(th.z_sag_um)
    assert ok.sum() >= 30
    assert abs(np.mean(th.z_tan_um[ok]) - 3.3) < 0.5 and abs(np.mean(th.z_sag_um[ok]) - 3.3) < 0.5
    # widths as without any breathing (frequency followed, then referred back to fs at the peak), to 1.5 %: the
    # PSF stays at the sensor's scale (the renderer since session 6), so the followed frequency fs m(z0)/m(z)
    # meets the defocus blur at a frequency that drifts 7.5 % over this scan and skews the curve's flanks
    # (1.1 % here; ~0.1 % at a real lens's breathing; with the PSF magnified with the scene it held to 0.8 %)
    _, still = _flat_lens_stack(math.inf, z)
    ref = measure_tiles(still, fs_cyc_per_mm=fs, measure="bandpass", quiet=True)
    w_breath, w_still = np.median(table.width_um[table.ok]), np.median(ref.width_um[ref.ok])
    assert w_breath == pytest.approx(w_still, rel=0.015)
    assert abs(np.mean(ref.z_best_um[ref.ok]) - 3.3) < 0.1


def test_directional_foci_separate_blur_along_and_across_the_radius():
    """Synthetic astigmatism on a wide strip: blur along x (the radius, for tiles left and right of the centre)
    is smallest at z = -12, blur along y at z = +10. Thorough effort finds z_tan near -12 and z_sag near +10
    there, while the isotropic band-pass curve has two peaks."""
    import cv2
    rng = np.random.default_rng(3)
    W, H = 512, 96
    tex = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 0.6)
    tex = 0.5 + (tex - tex.mean()) * (0.2 / tex.std())
    z = np.arange(-40.0, 40.0 + 1e-9, 4.0)
    frames = [np.clip(cv2.GaussianBlur(tex, (0, 0), sigmaX=0.4 + abs(zz + 12.0) / 10.0,
                                       sigmaY=0.4 + abs(zz - 10.0) / 10.0), 0.0, 1.0) for zz in z]
    stack = ArrayStack(frames, z, ("Y",), pixel_pitch_um=5.0)
    ident = GeometryMeasurements.identity(z, ("Y",), (W, H))
    t = measure_tiles(stack, geometry=ident, fs_cyc_per_mm=0.2 / 5e-3, tile_px=32, measure="bandpass",
                      effort="thorough", quiet=True)
    side = np.abs(t.x_px - (W - 1) / 2.0) > 3.0 * np.abs(t.y_px - (H - 1) / 2.0) + 48.0
    assert side.sum() >= 12
    assert np.all(np.isfinite(t.z_tan_um[side])) and np.all(np.isfinite(t.z_sag_um[side]))
    # (measured: -11.6 and +9.1-9.2, the same before and after the directional split was made scale-invariant;
    # each directional curve holds a little of the other orientation's energy, which pulls it inwards)
    assert np.median(t.z_tan_um[side]) == pytest.approx(-12.0, abs=1.0)
    assert np.median(t.z_sag_um[side]) == pytest.approx(10.0, abs=1.5)
    # the isotropic band-pass sees both foci: two peaks 22 um apart, rejected as ambiguous
    assert np.mean(t.status[side] == "multi_peak") > 0.5


def _steep_edge_errors(models_dir, curv, z):
    spec = small_lens(models_dir, curv=curv, channels=("G",))
    table, _ = measure_stack(render_stack(spec, z), fs_cyc_per_mm=fs_for(spec), quiet=True)
    rows = np.flatnonzero(table.ok)
    err = table.z_best_um[rows] - tile_truth(spec, table, rows)
    rho = np.hypot(table.x_px[rows] - 127.5, table.y_px[rows] - 79.5) / np.hypot(128.0, 80.0)
    return table, rows, err, rho > 0.6


def test_tiles_across_a_steep_surface_are_placed_where_they_measure(models_dir):
    """Where a tile spans several depths of focus (here ~60 µm of best focus across a 32 px edge tile at
    10 µm steps, curves ~14 µm wide), its best focus belongs to its texture's weighted centre. The geometric
    centre, or weighting by the sharpest frame, put edge tiles 4.2 µm RMS off (measured)."""
    table, rows, err, edge = _steep_edge_errors(models_dir, -250.0, np.arange(-280.0, 40.0 + 1e-9, 10.0))
    assert rows.size >= 24
    assert edge.sum() >= 5
    # measured with the scan's summed weights: 1.6 µm, one tile (x 32, y 61) 4.3 µm off and the other seven
    # within 1.2 µm; weights interpolated at the fitted best focus gave 1.37 µm here (they follow the strip
    # sharp at best focus, which in this regime, tile spread >> curve width, is what picks the peak), but moved
    # with where the frames fall (test below)
    assert np.sqrt(np.mean(err[edge] ** 2)) <= 0.2 * 10.0
    assert np.median(np.abs(err[edge])) <= 0.1 * 10.0
    assert np.sqrt(np.mean(err ** 2)) <= 0.15 * 10.0


def test_tile_positions_do_not_depend_on_where_the_frames_fall(models_dir):
    """Two scans of one lens, their frames shifted by a quarter step at a time: a tile's reported position is
    where its texture is, not where the frames fall. Weights interpolated at the fitted best focus moved the
    steep lens's tiles by up to 0.8 px (0.26 px sd, ~1.5 µm of best focus at 1.9 µm/px) and, on the 256x144
    triplet of bench_profile_diff, put a rho² mode of 1.4-2.8 µm between two scans; the scan's summed weights
    0.05 px sd (0.09 max)."""
    spec = small_lens(models_dir, curv=-250.0, channels=("G",))
    tables = [measure_stack(render_stack(spec, np.arange(-280.0, 40.0 + 1e-9, 10.0) + off),
                            fs_cyc_per_mm=fs_for(spec), quiet=True)[0] for off in (0.0, 2.5, 5.0, 7.5)]
    ok = np.logical_and.reduce([t.ok for t in tables])
    assert ok.sum() >= 20
    xs = np.array([t.x_px[ok] for t in tables])
    ys = np.array([t.y_px[ok] for t in tables])
    moved = np.sqrt(xs.var(axis=0) + ys.var(axis=0))
    # the reference frame (the middle one) moves with the scan: 7.5 µm at a 19 mm exit pupil is m - 1 = 4e-4,
    # up to 0.06 px at the corners; the rest is noise
    assert np.sqrt(np.mean(moved ** 2)) <= 0.1
    assert np.max(moved) <= 0.25


def test_breathing_sensitivity_predicts_the_shift_of_another_window_exponent(colour, monkeypatch):
    """z_dgamma_um is d z_best / d(exponent of a residual gain m^k on the SML): measuring with the SML's
    breathing exponent 0.5 higher moves each tile's best focus by 0.5 z_dgamma (the bias is linear in it); a
    telecentric stack has none."""
    from fieldcal.measure import focus as focus_mod

    spec, stack = colour
    fs = fs_for(spec)
    table, _ = measure_stack(stack, fs_cyc_per_mm=fs, measure="sml", quiet=True)
    sens = table.z_dgamma_um
    ok = table.ok & np.isfinite(sens)
    assert ok.sum() > 0.8 * table.ok.sum() and np.median(np.abs(sens[ok])) > 0.01
    plain = focus_mod.sml
    # x scale^0.5: the exponent 0.5 higher (the scan's scale is relative to frame 0, the sensitivity's to the
    # reference frame: a constant factor, no effect on best focus)
    monkeypatch.setattr(focus_mod, "sml", lambda plane, scale=1.0, energy=False: plain(plane, scale, energy)
                        * np.float32(scale ** 0.5))
    moved, _ = measure_stack(stack, fs_cyc_per_mm=fs, measure="sml", quiet=True)
    both = ok & moved.ok
    np.testing.assert_allclose(moved.z_best_um[both] - table.z_best_um[both], 0.5 * sens[both],
                               atol=0.02 + 0.1 * float(np.max(np.abs(sens[both]))))
    monkeypatch.undo()
    flat = dataclasses.replace(spec, exit_pupil_mm=math.inf)
    z = np.arange(-90.0, 40.0 + 1e-9, 2 * STEP_UM)
    t2, _ = measure_stack(render_stack(flat, z), fs_cyc_per_mm=fs, measure="sml", quiet=True)
    # the measured magnification of a telecentric stack is 1 to ~1e-5: its sensitivity is ~100x smaller
    assert np.max(np.abs(t2.z_dgamma_um[t2.ok])) < 0.05 * np.median(np.abs(sens[ok]))
