"""e-SFR against the closed-form MTF (Gaussian x defocus disc x pixel aperture along the edge normal)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure.esfr import esfr_roi
from fieldcal.measure.esfr_synth import analytic_mtf, analytic_mtf50, render_edge
from fieldcal.measure.mtf import classify_orientation, measure_mtf

BAND = np.linspace(0.05, 0.45, 81)
# one blur per channel: Gaussian sigma (px) and defocus disc diameter (px)
BLUR = {"R": (0.8, 2.0), "G": (0.5, 1.0), "B": (1.0, 3.0)}
HALF_WIDTH_PX = 24


def _rgb_edge(rows: int, slant_deg: float, *, noise: float = 0.0, seed: int = 0, horizontal: bool = False):
    """A near-vertical edge slanted by ``slant_deg`` (normal at slant_deg from +x), channels with BLUR."""
    width = int(2 * HALF_WIDTH_PX + rows * math.tan(math.radians(slant_deg)) + 8)
    chans = [render_edge(rows, width, normal_deg=slant_deg, sigma_px=s, defocus_d_px=d) for s, d in BLUR.values()]
    img = np.stack(chans, axis=2)
    if noise:
        img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.swapaxes(img, 0, 1) if horizontal else img


def _errors(res, slant_deg):
    out = []
    m = res.mtf_at(BAND)
    for k, (s, d) in enumerate(BLUR.values()):
        ref = analytic_mtf(BAND, sigma_px=s, defocus_d_px=d, normal_deg=slant_deg)
        ref50 = analytic_mtf50(sigma_px=s, defocus_d_px=d, normal_deg=slant_deg)
        out.append((float(np.max(np.abs(m[k] - ref))), float(res.mtf50_cy_per_px[k] / ref50 - 1.0)))
    return out


@pytest.mark.parametrize("slant_deg", [3.0, 5.0, 8.0, 10.0, 15.0])
def test_noise_free_matches_closed_form(slant_deg):
    res = esfr_roi(_rgb_edge(128, slant_deg), half_width_px=HALF_WIDTH_PX)
    for (err, rel50), q in zip(_errors(res, slant_deg), res.quality):
        assert q.ok, q.reason
        assert err <= 0.01, err          # method bias, no noise
        assert abs(rel50) <= 0.01, rel50
        assert q.slant_deg == pytest.approx(slant_deg, abs=0.05)


def test_near_horizontal_edge_is_the_same_measurement():
    v = esfr_roi(_rgb_edge(128, 8.0), half_width_px=HALF_WIDTH_PX)
    h = esfr_roi(_rgb_edge(128, 8.0, horizontal=True), vertical=False, half_width_px=HALF_WIDTH_PX)
    assert np.allclose(v.mtf_at(BAND), h.mtf_at(BAND), atol=1e-9)
    # normal at +8 deg (y down) -> the edge runs along (-sin 8, cos 8): 98 deg from +x; transposed: 172 deg
    assert v.angle_deg[0] == pytest.approx(98.0, abs=0.05)
    assert h.angle_deg[0] == pytest.approx(172.0, abs=0.05)


@pytest.mark.parametrize("slant_deg", [3.0, 8.0, 15.0])
def test_snr50_accuracy(slant_deg):
    """SNR 50 (noise sigma = step / 50), 256 rows x +-24 px: the statistic the docs report."""
    step = 0.6
    errs, rels = [], []
    for seed in range(4):
        res = esfr_roi(_rgb_edge(256, slant_deg, noise=step / 50, seed=seed), half_width_px=HALF_WIDTH_PX)
        for (err, rel50), q in zip(_errors(res, slant_deg), res.quality):
            assert q.snr == pytest.approx(50, rel=0.15)
            errs.append(err)
            rels.append(rel50)
    assert np.median(errs) <= 0.02, errs
    assert np.sqrt(np.mean(np.square(rels))) <= 0.02, rels


def test_a_batch_measures_each_region_as_alone():
    """esfr_regions pads regions of different sizes into one batch: no region may see its neighbours' padding,
    rows or columns (each equals its own esfr_roi call), and the pixel-exact closed form still holds."""
    from fieldcal.measure.esfr import esfr_regions
    rois = [_rgb_edge(64, 4.0, noise=0.01, seed=1), _rgb_edge(128, 12.0, noise=0.01, seed=2),
            _rgb_edge(96, 7.0, noise=0.01, seed=3, horizontal=True), _rgb_edge(128, 8.0)]
    vert = [True, True, False, True]
    hws = [HALF_WIDTH_PX, 20.0, HALF_WIDTH_PX, HALF_WIDTH_PX]
    batch = esfr_regions(rois, vertical=vert, half_width_px=hws)
    for roi, v, hw, b in zip(rois, vert, hws, batch):
        one = esfr_roi(roi, vertical=v, half_width_px=hw)
        assert np.allclose(b.mtf, one.mtf, rtol=0, atol=1e-12, equal_nan=True)
        assert np.allclose(b.x_mid, one.x_mid, atol=1e-9) and np.allclose(b.angle_deg, one.angle_deg, atol=1e-9)
        for qb, qo in zip(b.quality, one.quality):
            assert qb.reason == qo.reason and qb.rows == qo.rows and qb.noise_rms == pytest.approx(qo.noise_rms)
    for (err, rel50), q in zip(_errors(batch[3], 8.0), batch[3].quality):
        assert q.ok and err <= 0.01 and abs(rel50) <= 0.01


def test_quality_flags_clipping_low_contrast_and_shallow_slant():
    img = render_edge(96, 72, normal_deg=6.0, sigma_px=0.6)
    clipped = esfr_roi(np.clip(img * 1.5, 0, 1), half_width_px=24).quality[0]
    assert not clipped.ok and "clipped" in clipped.reason
    faint = esfr_roi(0.5 + 0.01 * (img - 0.5), half_width_px=24).quality[0]
    assert not faint.ok and "contrast" in faint.reason
    shallow = esfr_roi(render_edge(96, 72, normal_deg=1.0, sigma_px=0.6), half_width_px=24).quality[0]
    assert not shallow.ok and "slant" in shallow.reason


def test_cfa_planes_measured_on_their_own_grid():
    """An RGGB mosaic: each plane's MTF in cycles per sensor pixel matches the full-resolution closed form."""
    H = W = 192
    chans = {c: render_edge(H, W, normal_deg=6.0, sigma_px=s, defocus_d_px=d) for c, (s, d) in BLUR.items()}
    mos = np.empty((H, W))
    mos[0::2, 0::2] = chans["R"][0::2, 0::2]
    mos[0::2, 1::2] = chans["G"][0::2, 1::2]
    mos[1::2, 0::2] = chans["G"][1::2, 0::2]
    mos[1::2, 1::2] = chans["B"][1::2, 1::2]
    res = measure_mtf(mos, cfa="RGGB")
    planes = sorted(e["plane"] for e in res.edges)
    assert planes == ["B", "Gb", "Gr", "R"]
    f = res.frequencies_cy_per_px
    band = (f >= 0.05) & (f <= 0.45)
    for e in res.edges:
        s, d = BLUR[e["channel"]]
        ref = analytic_mtf(f[band], sigma_px=s, defocus_d_px=d, normal_deg=6.0)
        assert np.max(np.abs(np.asarray(e["mtf"])[band] - ref)) <= 0.02, e["plane"]
        assert e["mtf50_cy_per_px"] == pytest.approx(analytic_mtf50(sigma_px=s, defocus_d_px=d, normal_deg=6.0),
                                                     rel=0.02)
        assert abs(e["x_px"] - (W - 1) / 2) < 1.0  # positions in sensor pixels


def test_orientation_convention():
    # right of the centre the radius is +x: a near-vertical edge (normal ~ +x) is tangential
    assert classify_orientation(900, 500, 95.0, (500, 500))[0] == "tangential"
    assert classify_orientation(900, 500, 5.0, (500, 500))[0] == "sagittal"
    # below the centre the radius is +y: a near-horizontal edge is tangential
    assert classify_orientation(500, 900, 5.0, (500, 500))[0] == "tangential"
    orient, phi = classify_orientation(800, 800, 135.0, (500, 500))  # edge across the diagonal radius
    assert orient == "tangential" and phi == pytest.approx(0.0, abs=1e-9)


def test_tangential_edges_see_the_radial_blur():
    """Squares left/right of the centre, blur stronger along x (the radius there): the edges classified
    tangential (normal along x) must measure the lower MTF; and every edge is classified as the geometry says."""
    import cv2
    from fieldcal.charts.targets import slanted_edge_image, slanted_edge_spec
    spec = slanted_edge_spec(480, 160, cells_short=2)
    img = cv2.GaussianBlur(slanted_edge_image(spec), (0, 0), sigmaX=1.6, sigmaY=0.6)
    res = measure_mtf(img, centre_px=(239.5, 79.5))
    far = [e for e in res.edges if abs(e["x_px"] - 239.5) > 100 and abs(e["y_px"] - 79.5) < 40]
    assert len(far) >= 8
    for e in far:
        normal_along_x = abs(math.cos(math.radians(e["angle_deg"] + 90.0))) > 0.7
        assert e["orientation"] == ("tangential" if normal_along_x else "sagittal")
    t = [e["mtf50_cy_per_px"] for e in far if e["orientation"] == "tangential"]
    s = [e["mtf50_cy_per_px"] for e in far if e["orientation"] == "sagittal"]
    assert max(t) < min(s)
    ref_t = analytic_mtf50(sigma_px=1.6, normal_deg=5.0)  # the Gaussian is separable: along x sigma 1.6
    assert np.median(t) == pytest.approx(ref_t, rel=0.05)
