"""Unit and property tests of the compositing building blocks against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.composite import ArrayStack, read_composite_metadata, write_composite_tiff
from fieldcal.composite.dff import FocusVolume, fit_surface, peak_depth, peak_is_significant
from fieldcal.composite.stack_profile import to_input_dtype
from fieldcal.composite.surface import dense_map, output_best_focus_um
from fieldcal.composite.sweep import estimate_noise_sigma, wiener_deconvolve
from fieldcal.optics.sweep import integrated_otf, rfft_radial_grid
from fieldcal.composite.warp import FrameMap, affine_for, source_box, warp_region
from fieldcal.composite.weights import BlendKernel, SweepKernel
from fieldcal.errors import FieldcalError, ParameterError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import TruthProfile

positions = st.lists(st.floats(-500, 500, allow_nan=False), min_size=1, max_size=12, unique=True).map(
    lambda v: np.array(sorted(v))).filter(lambda z: len(z) < 2 or np.min(np.diff(z)) > 1e-3)


# ------------------------------------------------------------------------------------------ weights
@settings(max_examples=60, deadline=None)
@given(positions, st.floats(0, 50), st.floats(0, 1), st.lists(st.floats(-700, 700), min_size=1, max_size=20))
def test_blend_weights_partition_unity_and_prefer_nearest(z, tol, band, zb):
    k = BlendKernel(z, tol, min_band=band)
    zb = np.array(zb)
    w = np.stack([k.weight(i, zb) for i in range(len(z))])
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-6)
    nearest = np.argmin(np.abs(z[:, None] - zb[None, :]), axis=0)
    assert np.all(w[nearest, np.arange(len(zb))] >= 0.5 - 1e-6)  # the nearest frame always dominates
    lo, hi = k.support(float(zb.min()), float(zb.max()))
    outside = np.ones(len(z), bool)
    outside[lo:hi + 1] = False
    assert np.all(w[outside] == 0)  # support() never misses a contributing frame


def test_fast_blend_weights_match_the_piecewise_reference():
    rng = np.random.default_rng(4)
    z = np.sort(rng.uniform(-300, 20, 25))
    zb = rng.uniform(-350, 60, 50000)
    for tol, band in ((5.0, 0.25), (0.0, 0.25), (30.0, 0.0)):
        k = BlendKernel(z, tol, min_band=band)
        for i in range(len(z)):
            np.testing.assert_allclose(k.weight(i, zb), k.weight_exact(i, zb), atol=2e-4)


def test_blend_weights_hard_and_continuous():
    z = np.array([0.0, 10.0, 20.0])
    hard = BlendKernel(z, 0.0, min_band=0.0)
    zb = np.array([-5, 0, 4.9, 5.1, 14.9, 15.1, 25])
    w = np.stack([hard.weight(i, zb) for i in range(3)])
    np.testing.assert_array_equal(np.argmax(w, axis=0), [0, 0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(w.max(axis=0), 1.0)
    # A tolerance of 10 µm on 10 µm spacing: both frames are in tolerance everywhere -> linear-like smooth blend
    soft = BlendKernel(z, 10.0)
    zz = np.linspace(-5, 25, 3001)
    ws = np.stack([soft.weight(i, zz) for i in range(3)])
    assert np.max(np.abs(np.diff(ws, axis=1))) < 3 * 1.5 * (zz[1] - zz[0]) / 10.0  # smoothstep slope <= 1.5/dz
    # Tolerance of 6 µm: only [4, 6] around the midpoint has both frames in tolerance
    mid = BlendKernel(z, 6.0, min_band=0.0)
    assert mid.weight(1, np.array([3.9]))[0] == 0.0 and mid.weight(0, np.array([6.1]))[0] == 0.0
    assert 0 < mid.weight(1, np.array([4.5]))[0] < 0.5


def test_sweep_weights_closed_form():
    z = np.arange(0.0, 101.0, 4.0)
    k = SweepKernel(z, alpha_um=8.0)  # window 16 µm = 4 frame cells: frames at +-8 get half a cell
    w = np.array([k.weight(i, np.array([48.0]))[0] for i in range(len(z))])
    expect = np.zeros(len(z))
    expect[[10, 11, 13, 14]] = 0.25
    expect[12] = 0.25
    expect[[10, 14]] = 0.125
    np.testing.assert_allclose(w, expect, atol=1e-7)
    # Off-grid and at the ends the weights still sum to 1
    zb = np.array([-30.0, -2.0, 1.3, 50.7, 99.0, 130.0])
    ws = np.stack([k.weight(i, zb) for i in range(len(z))])
    np.testing.assert_allclose(ws.sum(axis=0), 1.0, atol=1e-6)
    assert ws[0, 0] == 1.0 and ws[-1, -1] == 1.0
    with pytest.raises(ParameterError):
        SweepKernel(z, 0.0)


@settings(max_examples=40, deadline=None)
@given(positions, st.floats(0.5, 100), st.lists(st.floats(-700, 700), min_size=1, max_size=10))
def test_sweep_weights_partition_unity(z, alpha, zb):
    k = SweepKernel(z, alpha)
    zb = np.array(zb)
    w = np.stack([k.weight(i, zb) for i in range(len(z))])
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-6)
    lo, hi = k.support(float(zb.min()), float(zb.max()))
    assert np.all(w[:lo] == 0) and np.all(w[hi + 1:] == 0)


def test_kernels_reject_bad_input():
    with pytest.raises(ParameterError):
        BlendKernel([0.0, 0.0], 1.0)
    with pytest.raises(ParameterError):
        BlendKernel([0.0, 1.0], -1.0)
    with pytest.raises(ParameterError):
        BlendKernel([], 1.0)


# --------------------------------------------------------------------------------------------- warp
def test_warp_inverts_the_renderer_geometry():
    import cv2
    from fieldcal.simulate.warp import scale_shift

    rng = np.random.default_rng(1)
    scene = cv2.GaussianBlur(rng.random((120, 180), dtype=np.float32), (0, 0), 1.5)
    a = affine_for(1.015, (89.5, 59.5), (0.37, -0.61))
    frame = scale_shift(scene, a[0, 0], a[0, 2], a[1, 2])
    s = ArrayStack([frame], [0.0], ["Y"])
    ident = ArrayStack([scene], [0.0], ["Y"])
    for interp in ("keys", "cv2"):
        out = warp_region(s, 0, FrameMap(a, (0,)), 0, 0, 180, 120, interp)[..., 0]
        err = np.sqrt(np.mean((out - scene)[8:-8, 8:-8] ** 2))
        unwarped = np.sqrt(np.mean((frame - scene)[8:-8, 8:-8] ** 2))
        assert err < 0.1 * unwarped  # the residual is interpolation error only
        roi = warp_region(s, 0, FrameMap(a, (0,)), 50, 20, 130, 90, interp)[..., 0]
        np.testing.assert_allclose(roi, out[20:90, 50:130], atol=1e-5)  # regions agree with the whole
    eye = FrameMap(affine_for(1.0, (0, 0), (0, 0)), (0,))
    np.testing.assert_array_equal(warp_region(ident, 0, eye, 3, 4, 50, 60)[..., 0], scene[4:60, 3:50])


def test_source_box_covers_the_mapped_region():
    a = affine_for(0.97, (100.0, 80.0), (3.2, -1.7))
    x0, y0, x1, y1 = source_box(a, 10, 20, 60, 70, 200, 160, margin=0)
    for px, py in [(10, 20), (59, 69), (10, 69), (59, 20)]:
        qx, qy = a[:, :2] @ [px, py] + a[:, 2]
        assert x0 <= qx <= x1 and y0 <= qy <= y1


# ------------------------------------------------------------------------------------------ surfaces
def test_dense_map_is_exact_bilinear_and_close_for_quadratics():
    lin = dense_map(lambda x, y: 3.0 + 0.5 * x - 0.25 * y, 101, 77, step=8)
    yy, xx = np.mgrid[0:77, 0:101]
    np.testing.assert_allclose(lin, 3.0 + 0.5 * xx - 0.25 * yy, atol=0.02)  # cv2 1/32 px weights
    quad = dense_map(lambda x, y: 1e-3 * (x * x + y * y), 101, 77, step=8)
    assert np.max(np.abs(quad - 1e-3 * (xx * xx + yy * yy))) <= 2 * 1e-3 * 64 / 8 + 0.02


def test_output_best_focus_solves_the_breathing_fixed_point(triplet_path):
    p = TruthProfile(LensSpec.load(triplet_path), 384, 216)
    x = np.array([0.0, 100.0, 383.0])
    y = np.array([0.0, 50.0, 215.0])
    for ch in p.channels:
        z = output_best_focus_um(p, x, y, ch)
        cx, cy = p.optical_centre_px()
        m = p.magnification(z, ch)
        dx, dy = p.shift_px(z, ch)
        np.testing.assert_allclose(z, p.best_focus_um(cx + m * (x - cx) + dx, cy + m * (y - cy) + dy, ch),
                                   atol=1e-4)
        # at the corner breathing moves the in-focus position by several µm: the naive surface is wrong
        assert abs(z[0] - p.best_focus_um(x[:1], y[:1], ch)[0]) > 2.0


# ------------------------------------------------------------------------------------------------ DFF
def test_peak_depth_subframe_accuracy_and_confidence():
    z = np.arange(-40.0, 41.0, 8.0)
    true = np.array([[-13.0, 2.5], [17.7, 30.1]])
    v = np.exp(-0.5 * ((z[:, None, None] - true[None]) / 9.0) ** 2)[..., None] + 0.1
    v[:, 1, 1, 0] = 0.5  # a flat (textureless) block
    zb, conf = peak_depth(FocusVolume(z, v.astype(np.float32), 8, np.zeros(2), np.zeros(2)))
    for (i, j) in [(0, 0), (0, 1), (1, 0)]:
        assert abs(zb[i, j, 0] - true[i, j]) < 1.2  # a parabola through 3 samples of a Gaussian: < 0.15 step
    assert conf[1, 1, 0] == 0.0 and conf[0, 0, 0] > 1.0


def test_peak_significance_rejects_noise_and_keeps_real_peaks():
    """A textureless block's through-focus curve is noise about a floor: its maximum stands ~2 sigma above the
    median (8 sigma with probability ~2e-4 at 19 frames), where the relative confidence alone reads 0.1-0.5. Real
    peaks 1-8 frames wide (FWHM), Gaussian or Lorentzian, with noise of 1 % of their height, all count."""
    rng = np.random.default_rng(3)
    n = 19
    noise = 1.0 + 0.05 * rng.standard_normal((n, 40, 50))
    sig = peak_is_significant(noise, np.argmax(noise, axis=0))
    assert sig.mean() < 0.005  # expected 2e-4 of 2000
    z = np.arange(n, dtype=np.float64)[:, None]
    fwhm = np.array([1.0, 1.5, 2.0, 3.0, 5.0, 8.0])[None]
    z0 = 9.3
    peaks = np.concatenate([np.exp(-4.0 * np.log(2.0) * ((z - z0) / fwhm) ** 2),
                            1.0 / (1.0 + (2.0 * (z - z0) / fwhm) ** 2)], axis=1) + 0.2
    peaks = peaks + 0.01 * rng.standard_normal(peaks.shape)
    assert peak_is_significant(peaks, np.argmax(peaks, axis=0)).all()
    # peak_depth: the noise blocks carry no confidence, the peaks keep theirs
    v = np.concatenate([noise[:, :1, :12], peaks[:, None]], axis=1).astype(np.float32)[..., None]
    _, conf = peak_depth(FocusVolume(np.arange(n) * 4.0, v, 8, np.zeros(12), np.zeros(2)))
    assert np.mean(conf[0] > 0) <= 1 / 12 and np.all(conf[1] > 0.5)


def test_fit_surface_is_robust_to_outliers_and_drops_degree():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 400, 300), rng.uniform(0, 300, 300)
    c, s = (200.0, 150.0), 250.0
    u, v = (x - c[0]) / s, (y - c[1]) / s
    z = -120.0 * (u * u + v * v) + 8.0 * u - 3.0 + rng.normal(0, 0.3, 300)
    bad = rng.random(300) < 0.3
    z[bad] = rng.uniform(-300, 100, bad.sum())  # textureless blocks pick random frames
    fit = fit_surface(x, y, z, np.ones(300), c, s)
    gx, gy = np.meshgrid(np.linspace(0, 400, 9), np.linspace(0, 300, 7))
    gu, gv = (gx - c[0]) / s, (gy - c[1]) / s
    np.testing.assert_allclose(fit(gx, gy), -120.0 * (gu * gu + gv * gv) + 8.0 * gu - 3.0, atol=1.0)
    few = fit_surface(x[:10], y[:10], z[:10] * 0 + 5.0, np.ones(10), c, s)
    assert few.degree <= 1
    with pytest.raises(ParameterError):
        fit_surface(x, y, z, np.zeros(300), c, s)


# ---------------------------------------------------------------------------------------------- sweep
def test_noise_estimate_on_flat_and_textured_images():
    rng = np.random.default_rng(5)
    flat = 1000.0 + rng.normal(0, 7.0, (256, 256))
    assert estimate_noise_sigma(flat) == pytest.approx(7.0, rel=0.05)
    yy, xx = np.mgrid[0:256, 0:256]
    smooth = 1000 + 300 * np.sin(xx / 15.0) * np.cos(yy / 21.0) + rng.normal(0, 7.0, (256, 256))
    assert estimate_noise_sigma(smooth) == pytest.approx(7.0, rel=0.1)


def test_wiener_restores_a_sweep_and_reports_the_noise_gain(triplet_path):
    from scipy import fft

    p = TruthProfile(LensSpec.load(triplet_path))
    rng = np.random.default_rng(7)
    n = 256
    # A 1/f^2-spectrum scene (natural-image statistics), blurred by the in-focus OTF: the truth.
    f = rfft_radial_grid((n, n), p.pixel_pitch_um)
    spec = fft.rfft2(rng.normal(size=(n, n))) / np.maximum(f, 2.0)
    h0 = p.defocus_otf(f, 0.0, "G")
    hs = integrated_otf(p, f, 20.0, "G")
    latent = fft.irfft2(spec, s=(n, n))
    latent = 2000 + 800 * latent / latent.std()
    truth = fft.irfft2(fft.rfft2(latent) * h0, s=(n, n))
    sigma = 4.0
    observed = fft.irfft2(fft.rfft2(latent) * hs, s=(n, n)) + rng.normal(0, sigma, (n, n))
    out, info = wiener_deconvolve(observed, p, 20.0, "G", p.pixel_pitch_um)
    m = slice(24, -24)

    def rms(a):
        return np.sqrt(np.mean((a - truth)[m, m] ** 2))

    assert rms(out) < 0.6 * rms(observed)
    # Texture at the pixel scale inflates the image-based noise estimate (never deflates it).
    assert sigma * 0.9 < info["noise_sigma"] < sigma * 3.0
    assert 1.0 < info["noise_gain"] < 10.0
    # With the true noise the filter does at least as well, and the reported gain predicts what the
    # filter does to noise alone: run it on (observed + extra noise) - observed.
    out2, info2 = wiener_deconvolve(observed, p, 20.0, "G", p.pixel_pitch_um, noise_sigma=sigma)
    assert rms(out2) <= rms(out) * 1.02
    extra = rng.normal(0, sigma, (n, n))
    out3, _ = wiener_deconvolve(observed + extra, p, 20.0, "G", p.pixel_pitch_um, noise_sigma=sigma)
    # same filter up to the (tiny) change of the fitted spectrum: the difference is filtered noise
    measured_gain = np.std((out3 - out2)[m, m]) / sigma
    assert measured_gain == pytest.approx(info2["noise_gain"], rel=0.15)


# ------------------------------------------------------------------------------------------------ I/O
def test_to_input_dtype_keeps_scale_and_clips_to_white():
    acc = np.array([[-3.2, 100.4, 4094.6, 4200.0]], dtype=np.float32)
    np.testing.assert_array_equal(to_input_dtype(acc, np.uint16, 4095), [[0, 100, 4095, 4095]])
    assert to_input_dtype(acc, np.float32, 1.0).dtype == np.float32


def test_tiff_round_trip_and_atomicity(tmp_path, monkeypatch):
    img = (np.arange(24 * 32 * 3) % 4096).astype(np.uint16).reshape(24, 32, 3)
    out = write_composite_tiff(tmp_path / "a.tiff", img, ["R", "G", "B"], {"method": "profile", "x": np.float32(1)})
    import tifffile
    back = tifffile.imread(out)
    np.testing.assert_array_equal(back, img)
    meta = read_composite_metadata(out)
    assert meta["format"] == "fieldcal-composite/1" and meta["method"] == "profile" and meta["channels"] == list("RGB")

    def boom(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr(tifffile, "imwrite", boom)
    with pytest.raises(OSError):
        write_composite_tiff(tmp_path / "b.tiff", img, ["R", "G", "B"], {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tiff"]  # nothing half-written, no temp left
    with pytest.raises(FieldcalError, match="not a TIFF"):
        write_composite_tiff(tmp_path / "c.png", img, ["R", "G", "B"], {})


def test_array_stack_validates():
    with pytest.raises(ParameterError):
        ArrayStack([np.zeros((4, 4, 3))], [0.0, 1.0], "RGB")
    with pytest.raises(ParameterError):
        ArrayStack([np.zeros((4, 4, 3)), np.zeros((4, 4, 3))], [1.0, 1.0], "RGB")
    s = ArrayStack([np.zeros((4, 5), np.uint16)], [0.0], ["Y"])
    assert s.shape == (4, 5) and s.read(0, (1, 1, 2, 3)).shape == (3, 2, 1) and s.white_level == 65535


# ------------------------------------------------------------------------------ whole-stack closed forms
def _static_lens(path, **changes):
    import dataclasses as dc
    spec = LensSpec.load(path)
    return dc.replace(spec, exit_pupil_mm=float("inf"), stage_axis_tilt_mrad=(0.0, 0.0), **changes)


def test_identical_frames_composite_to_themselves(models_dir):
    """Weights sum to one and, without breathing, nothing is resampled: a static scene comes back exactly."""
    from fieldcal.composite import composite_stack
    spec = _static_lens(models_dir / "doublet-mono.json").with_sensor_size(96, 72)
    prof = TruthProfile(spec)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 4096, (72, 96, 1)).astype(np.uint16)
    lo, hi = spec.focus_range_um()
    z = np.linspace(lo - 10, hi + 10, 9)
    stack = ArrayStack([frame] * len(z), z, ["Y"], white_level=4095)
    res = composite_stack(stack, prof, "profile", quiet=True)
    np.testing.assert_array_equal(res.image, frame)
    assert res.image.dtype == np.uint16


def test_lateral_colour_correction_registers_channels(models_dir):
    """Frames whose R and B channels are scaled about the centre (lateral colour) come back registered to G."""
    import dataclasses as dc
    import cv2
    from fieldcal.composite import composite_stack
    from fieldcal.simulate.warp import scale_shift

    spec = _static_lens(models_dir / "singlet-colour.json").with_sensor_size(128, 96)
    # exaggerate the lateral colour (x1.02 on top of +-0.25 %) so the effect is pixels wide at the edge
    spec = dc.replace(spec, channels=tuple(dc.replace(c, lateral_colour=1.02 * (1 + c.lateral_colour) - 1)
                                           for c in spec.channels))
    prof2 = TruthProfile(spec)
    rng = np.random.default_rng(2)
    scene = cv2.GaussianBlur(rng.random((96, 128), dtype=np.float32), (0, 0), 2.0) * 3000 + 500
    cx, cy = prof2.optical_centre_px()
    chans = []
    for ch in ("R", "G", "B"):
        s = prof2.lateral_colour_scale(ch)
        chans.append(scale_shift(scene, s, cx * (1 - s), cy * (1 - s)))
    frame = np.stack(chans, axis=-1)
    lo, hi = spec.focus_range_um()
    z = np.linspace(lo - 10, hi + 10, 6)
    stack = ArrayStack([frame] * len(z), z, ["R", "G", "B"], white_level=4095.0)
    keep = composite_stack(stack, prof2, "profile", quiet=True).image
    fixed = composite_stack(stack, prof2, "profile", lateral_colour=True, quiet=True).image
    m = (slice(12, -12), slice(12, -12))

    def err(img, c):
        return np.sqrt(np.mean((img[..., c][m] - scene[m]) ** 2))

    for c in (0, 1, 2):
        assert err(fixed, c) < 0.1 * scene.std()
    assert err(keep, 0) > 3 * err(fixed, 0)  # by default the z_ref geometry (with lateral colour) is kept


def test_richardson_lucy_reaches_scikit_images_restoration():
    # fieldcal's RL is scikit-image's iteration started from the observed image (faster to converge) with
    # OpenCV's mirrored convolutions; on the same PSF both restore the in-focus image and agree with each other
    import cv2
    from skimage import restoration

    from fieldcal.composite.sweep import rl_deconvolve
    from fieldcal.optics.sweep import sweep_psf_kernel
    from fieldcal.plan.synthetic import SyntheticProfile

    prof = SyntheticProfile(64, 64, pixel_pitch_um=5.0, f_number=2.0)
    rng = np.random.default_rng(3)
    latent = cv2.GaussianBlur(rng.uniform(0.2, 0.8, (96, 96)).astype(np.float32), (0, 0), 0.8)
    alpha, size = 30.0, 2 * int(np.ceil(1.5 * 30.0 / 2.0 / 5.0)) + 9  # the kernel size rl_deconvolve uses
    psf = sweep_psf_kernel(prof, alpha, "G", 5.0, size).astype(np.float32)
    focus = sweep_psf_kernel(prof, 0.0, "G", 5.0, 15).astype(np.float32)
    observed = cv2.filter2D(latent, -1, psf, borderType=cv2.BORDER_REFLECT)
    target = cv2.filter2D(latent, -1, focus, borderType=cv2.BORDER_REFLECT)
    ours, _ = rl_deconvolve(observed, prof, alpha, "G", 5.0, 0.0, 1.0, 100)
    sk = restoration.richardson_lucy(np.pad(observed, size, mode="symmetric"), psf, num_iter=100,
                                     clip=False)[size:-size, size:-size]
    sk = cv2.filter2D(sk.astype(np.float32), -1, focus, borderType=cv2.BORDER_REFLECT)
    m = slice(12, -12)

    def rms(a, b):
        return float(np.sqrt(np.mean((a - b)[m, m] ** 2)))

    before = rms(observed, target)
    assert rms(ours, target) < 0.2 * before and rms(sk, target) < 0.2 * before
    assert rms(ours, sk) < 0.2 * before
