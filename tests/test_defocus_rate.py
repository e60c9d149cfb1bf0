"""The blur-disc growth per frame step measured from a stack (fieldcal/composite/defocus_rate.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldcal.composite.defocus_rate import MeasuredDefocus, disc_otf, estimate_defocus_rate, fit_disc_px
from fieldcal.composite.source import ArrayStack

SIZE = 192


def disc_blur(img: np.ndarray, diameter_px: float) -> np.ndarray:
    """``img`` (periodic) blurred by a uniform disc of the given diameter, band-limited: its exact OTF
    ``2 J1(pi D rho) / (pi D rho)`` applied in the Fourier domain. (An area-sampled disc kernel would add a pixel's
    box blur to the defocused frames only, which the in-focus frame lacks: a camera's pixel aperture is common to
    every frame.)"""
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.rfftfreq(img.shape[1])[None, :]
    otf = disc_otf(np.hypot(fy, fx), diameter_px)
    return np.fft.irfft2(np.fft.rfft2(img) * otf, s=img.shape).astype(np.float32)


def disc_stack(rate_px: float, depths=(2.0, 4.0, 6.0), n_frames: int = 9, noise: float = 0.5, seed: int = 0):
    """Three vertical bands of random texture in focus at frames ``depths``; frame k blurs each band by a disc of
    ``rate_px * |k - depth|`` px, plus white noise. Returns the stack and the true depth index per pixel."""
    rng = np.random.default_rng(seed)
    scene = cv2.GaussianBlur(rng.random((SIZE, SIZE)).astype(np.float32), (0, 0), 0.7) * 200 + 20
    depth = np.empty((SIZE, SIZE), np.float32)
    bands = np.array_split(np.arange(SIZE), len(depths))
    for cols, d in zip(bands, depths):
        depth[:, cols] = d
    frames = []
    for k in range(n_frames):
        img = np.empty_like(scene)
        for cols, d in zip(bands, depths):
            blurred = disc_blur(scene, rate_px * abs(k - d))
            img[:, cols] = blurred[:, cols]
        img = img + rng.normal(0, noise, img.shape).astype(np.float32)
        frames.append(np.repeat(img[..., None], 3, axis=2))
    st = ArrayStack(frames, 50.0 * np.arange(n_frames), ["R", "G", "B"], black_level=0, white_level=255)
    return st, depth


def test_disc_otf_closed_form():
    # 2 J1(x)/x is 1 at 0 and has its first zero at x = 3.8317 (x = pi D rho)
    assert disc_otf(0.0, 5.0) == pytest.approx(1.0)
    assert disc_otf(3.8317 / (np.pi * 4.0), 4.0) == pytest.approx(0.0, abs=1e-4)
    # the DFT of the disc's point-spread function (supersampled, area-weighted) follows it below half the
    # sampling frequency
    r, o = 3.0, 8
    t = (np.arange(-4 * o, 4 * o) + 0.5) / o
    xx, yy = np.meshgrid(t, t)
    fine = (xx ** 2 + yy ** 2 <= r * r).reshape(8, o, 8, o).sum(axis=(1, 3)).astype(float)
    k = np.zeros((64, 64))
    k[:8, :8] = fine / fine.sum()
    otf = np.abs(np.fft.rfft2(k))[0, :16]
    pixel = np.abs(np.sinc(np.arange(16) / 64))  # the area weighting is a pixel's box
    assert np.allclose(otf, np.abs(disc_otf(np.arange(16) / 64, 2 * r)) * pixel, atol=0.01)


def test_fit_disc_recovers_a_known_disc():
    rng = np.random.default_rng(3)
    sharp = cv2.GaussianBlur(rng.random((48, 48)).astype(np.float32), (0, 0), 0.7) * 200
    for d in (2.0, 4.5, 7.0):
        blurred = disc_blur(sharp, d)
        assert fit_disc_px(sharp, blurred, 0.1) == pytest.approx(d, rel=0.08)


def test_fit_disc_tables_made_once_give_the_same_fits():
    """The patch-independent tables made once for many patches (the OTF grid at every bin, the bins' counts) give
    the fits made from scratch, to the bit, and still the known discs."""
    from fieldcal.composite.defocus_rate import _disc_fit_tables

    rng = np.random.default_rng(5)
    tables = _disc_fit_tables(48)
    for d in (1.0, 3.0, 6.0):
        sharp = cv2.GaussianBlur(rng.random((48, 48)).astype(np.float32), (0, 0), 0.7) * 200
        blurred = disc_blur(sharp, d) + rng.normal(0.0, 0.5, sharp.shape).astype(np.float32)
        alone = fit_disc_px(sharp, blurred, 0.5)
        assert fit_disc_px(sharp, blurred, 0.5, tables=tables) == alone
        assert alone == pytest.approx(d, rel=0.1)


@pytest.mark.parametrize("rate", [1.5, 3.0])
def test_rate_recovered_on_a_disc_defocus_stack(rate):
    st, depth = disc_stack(rate)
    est = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    assert est.reliable, est.reason
    assert est.disc_px_per_step == pytest.approx(rate, rel=0.06)
    # geometric defocus: the same rate at one and at two frames' distance; an honest uncertainty
    assert est.by_distance[1][0] == pytest.approx(est.by_distance[2][0], rel=0.1)
    assert 0 < est.sd_px_per_step < 0.1 * rate
    # the model handed to the Wiener combination: a one-step defocus is a disc of `rate` px
    model = MeasuredDefocus(est, pixel_pitch_um=2.0)
    f = np.array([0.0, 40.0, 90.0])  # cycles/mm at 2 µm pixels
    assert np.allclose(model.defocus_otf(f, 50.0), disc_otf(f * 2e-3, est.disc_px_per_step))
    assert model.f_number * model.pixel_pitch_um == pytest.approx(50.0 / est.disc_px_per_step)


def test_falls_back_without_depth_structure():
    # every frame the same picture (no focus change): the disc does not grow
    st, depth = disc_stack(0.0)
    est = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    assert not est.reliable and "barely change focus" in est.reason
    # nothing but noise: no texture to measure a blur on
    rng = np.random.default_rng(1)
    noise = [np.repeat(rng.normal(100, 1, (SIZE, SIZE, 1)).astype(np.float32), 3, axis=2) for _ in range(6)]
    st = ArrayStack(noise, 50.0 * np.arange(6), ["R", "G", "B"], black_level=0, white_level=255)
    est = estimate_defocus_rate(st, np.arange(6), np.full((SIZE, SIZE), 2.0, np.float32),
                                np.ones((SIZE, SIZE), np.float32))
    assert not est.reliable and "too little texture" in est.reason
    # the composite's metadata is written as JSON: a rate not measured must not be NaN there
    import json
    info = json.loads(json.dumps(est.info(), allow_nan=False))
    assert info["disc_px_per_step"] is None and info["reliable"] is False


def test_composite_without_profile_falls_back_and_says_so():
    from fieldcal.composite.api import composite_stack

    st, _ = disc_stack(0.0, n_frames=5)
    res = composite_stack(st, None, method="dff", register=False, depth="3d", quiet=True)
    assert res.info["defocus_rate"]["reliable"] is False
    assert res.info["defocus_rate"]["reason"]
    assert "wiener" not in res.info and "fine_detail" in res.info


def test_composite_without_profile_combines_with_the_measured_defocus():
    from fieldcal.composite.api import composite_stack

    st, _ = disc_stack(2.0)
    res = composite_stack(st, None, method="dff", register=False, depth="3d", quiet=True)
    assert res.info["defocus_rate"]["reliable"] is True
    assert res.info["defocus_rate"]["disc_px_per_step"] == pytest.approx(2.0, rel=0.1)
    assert res.info["wiener"]["filters"] > 0


def test_depth_error_measured_from_the_blur_on_either_side():
    # the depth map's error comes back from the blur towards the two neighbouring frames: ~0 with the true depth,
    # the offset with a depth map a quarter of a step off
    st, depth = disc_stack(2.0)
    exact = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    assert exact.depth_sd_steps < 0.08
    off = estimate_defocus_rate(st, np.arange(len(st)), depth + np.float32(0.25), np.ones_like(depth))
    assert off.depth_sd_steps == pytest.approx(0.25, abs=0.08)


def test_otf_moments_average_over_the_depth_error():
    st, depth = disc_stack(2.0)
    est = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    f = np.linspace(0.0, 250.0, 11)  # cycles/mm at 2 µm pixels: up to 0.5 cycles/px
    sure = MeasuredDefocus(est, pixel_pitch_um=2.0)
    m1, m2 = sure.defocus_otf_moments(f, 30.0)
    assert np.allclose(m1, sure.defocus_otf(f, 30.0)) and np.allclose(m2, m1 ** 2)
    # a Gaussian error of 0.3 steps: the quadrature against a dense Riemann sum of the same average
    unsure = MeasuredDefocus(est, pixel_pitch_um=2.0, depth_sd_steps=0.3)
    m1, m2 = unsure.defocus_otf_moments(f, 30.0)
    e = np.linspace(-6, 6, 2401) * 0.3 * est.spacing_um
    wts = np.exp(-0.5 * (e / (0.3 * est.spacing_um)) ** 2)
    wts /= wts.sum()
    h = np.array([sure.defocus_otf(f, 30.0 + v) for v in e])
    assert np.allclose(m1, wts @ h, atol=2e-3) and np.allclose(m2, wts @ (h * h), atol=2e-3)
    assert np.all(m2 >= m1 ** 2 - 1e-9)  # the mean square is at least the squared mean: the filter backs off


def test_noise_estimate_from_a_sample_of_the_responses():
    # white noise of a known sigma: the median over ~65 000 of the 2 million responses is within 2 % of it, as is
    # the median over all of them
    from fieldcal.composite.sweep import estimate_noise_sigma

    img = np.random.default_rng(5).normal(100.0, 3.0, (1000, 2000)).astype(np.float32)
    assert estimate_noise_sigma(img, max_samples=1 << 16) == pytest.approx(3.0, rel=0.02)
    assert estimate_noise_sigma(img) == pytest.approx(3.0, rel=0.02)


def test_discs_wider_than_the_patches_resolve_are_refused():
    # 192-px frames are measured on 32-px patches, whose Hann window is 16 px wide at half maximum: a disc growing
    # by 6 px per frame (12 px two frames apart) is resolved and measured right; one growing by 10 px (20 px two
    # frames apart) is not resolved, whatever the fit says, and the stack falls back to choosing frames (on real
    # bokeh such discs read short and the Wiener step with them rang beside depth edges, bench_ring_s14)
    st, depth = disc_stack(6.0)
    est = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    assert est.reliable, est.reason
    assert est.disc_px_per_step == pytest.approx(6.0, rel=0.06)
    st, depth = disc_stack(10.0)
    est = estimate_defocus_rate(st, np.arange(len(st)), depth, np.ones_like(depth))
    assert not est.reliable
    assert "patches resolve" in est.reason
    assert est.info()["reliable"] is False
