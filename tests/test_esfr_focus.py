"""Through-focus MTF(fs): best focus (sub-step) and tolerance against closed-form curves with a known peak."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from fieldcal.measure.esfr_focus import analyse_track, defocus_peak, link_tracks, through_focus_peak
from fieldcal.measure.esfr_synth import analytic_mtf, render_edge

FS = 0.2  # cycles/px


def _mtf_fs(d_px: np.ndarray, sigma_px: float = 0.5) -> np.ndarray:
    return np.array([analytic_mtf(np.array([FS]), sigma_px=sigma_px, defocus_d_px=abs(d), normal_deg=5.0)[0]
                     for d in np.atleast_1d(d_px)])


# blur diameter (px) against defocus u = z - z0 (µm); the peak is at u = 0 in every case
CURVES = {
    "symmetric": lambda u: 0.12 * u,
    "asymmetric-smooth": lambda u: 0.12 * u * (1 + 0.008 * u),      # blur grows faster behind focus
    "asymmetric-kink": lambda u: np.where(u < 0, 0.12 * u, 0.18 * u),  # 1.5x the blur rate on one side
}


def _true_tolerance(dfun, q: float) -> float:
    peak = _mtf_fs(0.0)[0]
    g = lambda u: _mtf_fs(dfun(u))[0] - (1 - q) * peak  # noqa: E731
    return brentq(g, 0.0, 60.0) - brentq(g, -60.0, 0.0)


@pytest.mark.parametrize("name", list(CURVES))
def test_best_focus_and_tolerance_from_exact_series(name):
    dfun = CURVES[name]
    step = 2.5
    rng = np.random.default_rng(7)
    errs, tol = [], []
    for _ in range(12):
        z0 = rng.uniform(-step, step)
        z = np.arange(-50.0, 50.1, step)
        tf = analyse_track(z, _mtf_fs(dfun(z - z0)), q=0.05, sigma=0.0)
        assert tf.ok, tf.reason
        errs.append((tf.z_best_um - z0) / step)
        tol.append(tf.depth_um)
    assert np.sqrt(np.mean(np.square(errs))) <= 0.1, errs
    true_depth = _true_tolerance(dfun, 0.05)
    assert np.max(np.abs(np.asarray(tol) / true_depth - 1)) <= 0.03, (tol, true_depth)


def test_tolerance_keeps_the_asymmetry():
    """Each half-width on its own against the closed form (blur grows 1.5x faster on one side)."""
    dfun = CURVES["asymmetric-kink"]
    z = np.arange(-50.0, 50.1, 2.0)
    tf = analyse_track(z, _mtf_fs(dfun(z)), q=0.1, sigma=0.0)
    peak = _mtf_fs(0.0)[0]
    g = lambda u: _mtf_fs(dfun(u))[0] - 0.9 * peak  # noqa: E731
    left, right = -brentq(g, -60.0, 0.0), brentq(g, 0.0, 60.0)
    assert right / left == pytest.approx(1 / 1.5, rel=1e-6)  # the curve's own asymmetry
    # each side within 3 % of the total depth (the kink biases the peak by < 0.1 step, moving both ends)
    assert abs(tf.tol_left_um - left) <= 0.03 * (left + right)
    assert abs(tf.tol_right_um - right) <= 0.03 * (left + right)
    assert tf.tol_right_um < tf.tol_left_um


@pytest.mark.parametrize("noise", [0.003, 0.01])
@pytest.mark.parametrize("known", [True, False])
def test_noise_uncertainty_describes_the_scatter(noise, known):
    """With noise on the samples, the bootstrap sigma is within a factor 2.5 of the real scatter (it sees
    noise, not the smoothing's own bias; docs/measurement.md gives the measured ratios)."""
    rng = np.random.default_rng(3)
    z = np.arange(-40.0, 40.1, 2.5)
    zs = []
    for _ in range(30):
        z0 = rng.uniform(-2.5, 2.5)
        v = _mtf_fs(CURVES["symmetric"](z - z0)) + rng.normal(0, noise, z.size)
        pk = through_focus_peak(z, v, sigma=noise if known else None)
        zs.append((pk.z_um - z0) / pk.sigma_um)
    assert 0.5 <= np.sqrt(np.mean(np.square(zs))) <= 2.5


def test_best_focus_is_unbiased_one_or_two_depths_of_field_from_a_scan_end():
    """The minimal reproduction of the per-channel bias on random lenses 0 and 2 (docs/measurement.md "Through
    focus"): broad F/3.7 curves (fs = 0.25 cy/px, 13.3 µm pixels: δ(0.05) ~ 40 µm) on a 20 µm scan that ends
    56 µm past the peak (or 120 µm after the start), MTF noise 0.01. A smoothing spline's maximum is pulled by
    the long flank's slope towards the nearer scan end; the fitted defocus law is not, and its sd is honest."""
    from fieldcal.optics.defocus import disc_otf

    n_f, fs_mm = 3.726, 0.25 / 13.333 * 1000.0
    z = np.arange(-193.9, 70.0, 20.0)
    rng = np.random.default_rng(1)
    for z0, towards in ((0.0, +1.0), (-120.0, -1.0)):
        spline, law, zs = [], [], []
        for _ in range(30):
            for ph in np.linspace(0.0, 20.0, 5, endpoint=False):
                t = z0 + ph
                v = 0.86 * np.abs(disc_otf(np.pi * fs_mm * 1e-3 * (z - t) / n_f)) + rng.normal(0.0, 0.01, z.size)
                spline.append(through_focus_peak(z, v, n_boot=0).z_um - t)
                fp = defocus_peak(z, v)
                assert fp.ok, fp.reason
                law.append(fp.z_um - t)
                zs.append((fp.z_um - t) / fp.sigma_um)
        assert towards * np.mean(spline) > 1.0          # the cause: > 0.05 step towards the nearer end
        assert abs(np.mean(law)) < 0.5                  # the law: < 0.025 step (its standard error ~0.15 µm)
        assert np.std(law) < 0.75 * np.std(spline)
        assert 0.7 <= np.sqrt(np.mean(np.square(zs))) <= 1.4


def test_no_tolerance_from_a_best_focus_outside_it():
    """A best focus (e.g. the law's) where the smoothed curve is already below (1 - q) of its maximum: no
    half-width is measured from there (NaN), never a root search without a sign change."""
    from dataclasses import replace

    from fieldcal.measure.esfr_focus import tolerance_half_widths
    z = np.arange(-40.0, 40.1, 2.5)
    v = _mtf_fs(CURVES["symmetric"](z))
    pk = through_focus_peak(z, v, sigma=0.0, n_boot=0)
    assert all(np.isfinite(tolerance_half_widths(z, v, 0.05, pk)))
    off = replace(pk, z_um=25.0)  # MTF there is far below 0.95 of the peak
    assert all(np.isnan(tolerance_half_widths(z, v, 0.05, off)))


def test_peak_at_the_end_of_the_scan_is_refused():
    z = np.arange(0.0, 50.0, 5.0)
    pk = through_focus_peak(z, np.linspace(0.2, 0.8, z.size))
    assert not pk.ok and "end of the scan" in pk.reason


def test_link_tracks_follows_drift_and_never_swaps():
    # two parallel edges 10 px apart drifting 3 px per frame (magnification change), one missed in frame 2
    frames, xs, ys, angs, zs = [], [], [], [], []
    for f in range(5):
        for k, x0 in enumerate((100.0, 110.0)):
            if f == 2 and k == 1:
                continue
            frames.append(f)
            xs.append(x0 + 3.0 * f)
            ys.append(50.0)
            angs.append(95.0)
            zs.append(10.0 * f)
    tr = link_tracks(np.array(frames), np.array(xs), np.array(ys), np.array(angs), np.array(zs), max_shift_px=6.0)
    xs = np.array(xs)
    for t in set(tr.tolist()):
        x_first = xs[tr == t][0]
        assert np.all(np.abs(xs[tr == t] - x_first - 3.0 * np.array(frames)[tr == t]) < 1e-9)
    assert len(set(tr.tolist())) == 2



def test_link_tracks_keeps_an_edge_whose_midpoint_slides_along_it():
    """The detection's position is the midpoint of the scan lines the e-SFR used, which slides along the edge
    as the blur changes: one edge (40 px long, 3 deg from vertical) whose midpoint moves 6-12 px along it between
    frames (0.3 px across) is one track, while a collinear neighbour 50 px further along the line (the next
    square's side) and a parallel edge 8 px across stay their own tracks."""
    rng = np.random.default_rng(3)
    th = np.radians(93.0)
    ux, uy = np.cos(th), np.sin(th)            # along the edge
    nx, ny = -uy, ux                           # across it
    frames, xs, ys, angs, zs, lens, truth = [], [], [], [], [], [], []
    slide = np.cumsum(rng.choice([-1.0, 1.0], 9) * rng.uniform(6.0, 12.0, 9))
    slide -= slide.mean()
    for f in range(9):
        for k, (a0, n0) in enumerate(((0.0, 0.0), (50.0, 0.0), (0.0, 8.0))):
            a = a0 + (np.clip(slide[f], -14.0, 14.0) if k == 0 else rng.uniform(-1.0, 1.0))
            n = n0 + rng.normal(0.0, 0.3)
            frames.append(f)
            xs.append(200.0 + a * ux + n * nx)
            ys.append(150.0 + a * uy + n * ny)
            angs.append(93.0 + rng.normal(0.0, 0.3))
            zs.append(10.0 * f)
            lens.append(40.0)
            truth.append(k)
    args = (np.array(frames), np.array(xs), np.array(ys), np.array(angs), np.array(zs))
    tr = link_tracks(*args, max_shift_px=6.0, length_px=np.array(lens))
    truth = np.array(truth)
    for k in range(3):
        assert len(set(tr[truth == k].tolist())) == 1, k   # each edge one track ...
    assert len(set(tr.tolist())) == 3                      # ... and never two edges in one
    # with the single 6 px radius (no lengths) the sliding edge breaks into fragments
    assert len(set(link_tracks(*args, max_shift_px=6.0)[truth == 0].tolist())) > 1

def test_end_to_end_through_focus_from_rendered_edges():
    """Slanted-edge frames rendered with a defocus disc growing with |z - z0|: e-SFR per frame, tracks, peak."""
    from fieldcal.measure.mtf import measure_mtf
    from fieldcal.formats.frames import ArrayStack

    z0, step = 3.7, 4.0
    z = np.arange(-40.0, 40.1, step)
    frames = [render_edge(160, 160, normal_deg=-6.0, sigma_px=0.5, defocus_d_px=0.15 * abs(zi - z0))
              for zi in z]
    stack = ArrayStack(frames, z, ("Y",), pixel_pitch_um=3.0)
    res = measure_mtf(stack)
    tracks = {e["track"] for e in res.edges}
    assert len(tracks) == 1
    m = res.mtf_at(FS)
    zz = np.array([e["z_um"] for e in res.edges])
    tf = analyse_track(zz, m, q=0.05)
    assert abs(tf.z_best_um - z0) <= 0.1 * step
    true = _true_tolerance(lambda u: 0.15 * u, 0.05)
    assert tf.depth_um == pytest.approx(true, rel=0.05)


@pytest.mark.parametrize("step_over_tol", [1.1, 1.3])
def test_tolerance_at_coarse_steps_with_noise(step_over_tol):
    """Scan step at or above the tolerance, noisy MTF: the measured tolerance within 3 % of the closed form
    (median of 30 tracks). The smoothed curve alone read 0.95-0.97 here: its q crossing lies within a step of
    the peak, where its shape is the roughness penalty's; the defocus law's blur rate comes from the whole
    peak (esfr_focus.analyse_track)."""
    dfun = CURVES["symmetric"]
    true = _true_tolerance(dfun, 0.05)
    step = step_over_tol * true / 2
    rng = np.random.default_rng(5)
    ratio = []
    for _ in range(30):
        z0 = rng.uniform(-step, step)
        z = np.arange(-6 * true, 6 * true, step)
        tf = analyse_track(z, _mtf_fs(dfun(z - z0)) + rng.normal(0, 0.01, z.size), q=0.05)
        ratio.append(tf.depth_um / true)
    assert np.all(np.isfinite(ratio))
    assert abs(np.median(ratio) - 1) <= 0.03, np.median(ratio)


def _pupil_channel(w040_waves: float, nu: float, n_tracks: int, noise: float, seed: int = 0):
    """A channel's edge tracks through focus from the exact pupil OTF (:mod:`fieldcal.optics.pupil`: defocus +
    W040, diffraction included) at ``nu = fs lambda N``, scan steps of about half the tolerance, and each track's
    exact sharpest position (the MTF(fs) peak on a fine grid). Returns (tracks, true peaks, step, fs, lambda)."""
    from fieldcal.optics import pupil

    lam, n_f = 0.55, 4.0
    fs = nu / (lam * n_f)  # cycles/µm
    per_wave = 8.0 * n_f ** 2 * lam  # µm of defocus per wave of W020
    zz = np.linspace(-4.0 * per_wave, 4.0 * per_wave, 16001)
    mm = np.abs(pupil.otf(nu, zz / per_wave, w040_waves))
    z_pk0 = float(zz[np.argmax(mm)])
    k = int(np.argmax(mm))
    lo = k - int(np.argmax(mm[:k][::-1] < 0.5 * mm[k]))  # the contiguous run above half maximum
    hi = k + int(np.argmax(mm[k:] < 0.5 * mm[k]))
    _pupil_channel.centre_offset_um = 0.5 * (zz[lo] + zz[hi]) - z_pk0  # half-maximum midpoint - peak
    step = 0.12 * per_wave
    rng = np.random.default_rng(seed)
    tracks, true = [], []
    for _ in range(n_tracks):
        z0 = rng.uniform(-2.0, 2.0) * step - z_pk0  # paraxial focus; the sharpest position is z0 + z_pk0
        z = (np.arange(31) - 15 + rng.uniform(-0.5, 0.5)) * step
        m = 0.6 * np.abs(pupil.otf(nu, (z - z0) / per_wave, w040_waves))
        v = np.hypot(m + rng.normal(0.0, noise, z.size), rng.normal(0.0, noise, z.size)) if noise else m
        tracks.append((z, v))
        true.append(z0 + z_pk0)
    return tracks, np.array(true), step, fs, lam


@pytest.mark.parametrize("w040,nu", [(0.5, 0.08), (0.8, 0.25)])
def test_pooled_spherical_aberration_finds_the_mtf_peak(w040, nu):
    """W040 = 0.5 waves at nu = 0.08 (the geometric-optics law is fitted) and 0.8 waves at nu = 0.25 (the exact
    pupil OTF is; diffraction makes the curve less skewed there), curves from the exact pupil OTF: the MTF(fs)
    peak lies off the curve's half-maximum midpoint by > 0.2 step. With the asymmetry pooled over the channel the
    best focus is the peak within 0.1 step (noise-free: 0.01 step), and its sd is honest."""
    from fieldcal.measure.esfr_focus import analyse_tracks

    tracks, true, step, fs, lam = _pupil_channel(w040, nu, 6, 0.0)
    res, shape = analyse_tracks(tracks, 0.05, fs_cyc_per_um=fs, wavelength_um=lam)
    assert shape.selected and (shape.nu > 0) == (nu > 0.15)
    err = np.array([r.z_best_um for r in res]) - true
    assert np.all(np.abs(err) < 0.01 * step), err / step
    tracks, true, step, fs, lam = _pupil_channel(w040, nu, 30, 0.005, seed=3)
    res, shape = analyse_tracks(tracks, 0.05, fs_cyc_per_um=fs, wavelength_um=lam)
    err = np.array([r.z_best_um for r in res]) - true
    assert abs(_pupil_channel.centre_offset_um) > 0.2 * step  # the curve's centre is not its peak
    assert abs(np.mean(err)) < 0.1 * step and np.sqrt(np.mean(err ** 2)) < 0.2 * step, err / step
    zs = err / np.array([r.z_sigma_um for r in res])
    assert 0.5 <= np.sqrt(np.mean(zs ** 2)) <= 2.0


def test_symmetric_channel_keeps_the_symmetric_width():
    """No aberration (W040 = 0): the pooled asymmetry is not selected or is negligible, and every track's width is
    the symmetric law's (what the pair-width forward model, edge_tiles.track_width_model, assumes) within 0.5 %."""
    from fieldcal.measure.esfr_focus import analyse_tracks

    tracks, true, step, fs, lam = _pupil_channel(0.0, 0.08, 30, 0.01, seed=5)
    res, shape = analyse_tracks(tracks, 0.05, fs_cyc_per_um=fs, wavelength_um=lam)
    new = np.array([r.depth_um for r in res])
    old = np.array([analyse_track(z, v).depth_um for z, v in tracks])
    assert np.all(np.isfinite(new)) and np.all(np.isfinite(old))
    assert abs(np.mean(new) / np.mean(old) - 1.0) < 0.005
    assert np.max(np.abs(new / old - 1.0)) < 0.005 or not shape.selected


def test_track_position_is_where_its_peak_was_measured_in_the_reference_frame():
    """A track's records slide along the edge (the usable scan lines change with blur) while the frame breathes
    (m(z), s(z) about the centre): the row's position is the MTF(fs)^2-weighted mean of the records at >= half
    the highest MTF, each mapped back into the reference frame — the closed form of the generating positions."""
    from fieldcal.measure.edge_tiles import peak_position_px
    from fieldcal.measure.geometry import GeometryMeasurements

    z = np.arange(-40.0, 41.0, 10.0)
    m = 1.0 + 2e-4 * z                                  # 1.6 % breathing over the scan
    sx, sy = 0.01 * z, -0.02 * z
    geo = GeometryMeasurements(z, ("G",), m[:, None], np.zeros((z.size, 1)), sx[:, None], sy[:, None],
                               np.zeros((z.size, 1)), int(np.argmin(np.abs(z - 20.0))), (500.0, 300.0), (1000, 600))
    along = np.array([0.0, 0.0, 2.0, 4.0, 8.0, 12.0, 14.0, 16.0, 16.0])   # the midpoint's slide (px, reference)
    ref = np.column_stack([900.0 + 0.05 * along, 500.0 + along])          # a sagittal-ish edge, reference px
    mtf = np.exp(-0.5 * ((z + 10.0) / 15.0) ** 2)                           # peak at z = -10, MTF(fs) in (0, 1]
    recs = []
    for k in range(z.size):
        x = 500.0 + m[k] * (ref[k, 0] - 500.0) + sx[k]
        y = 300.0 + m[k] * (ref[k, 1] - 300.0) + sy[k]
        recs.append({"z_um": z[k], "x_px": x, "y_px": y, "channel": "G"})
    use = mtf >= 0.5 * mtf.max()
    w = mtf[use] ** 2 / np.sum(mtf[use] ** 2)
    x, y = peak_position_px(recs, mtf, geo, z_ref_um=20.0)
    assert abs(x - w @ ref[use, 0]) < 1e-9 and abs(y - w @ ref[use, 1]) < 1e-9
    # the record nearest z_ref (the old position) is 9 px along the edge from where the peak was read
    assert abs(recs[6]["y_px"] - y) > 5.0
    # without the breathing the position falls back to the z_ref record's
    assert peak_position_px(recs, mtf, None, z_ref_um=20.0) == (recs[6]["x_px"], recs[6]["y_px"])
