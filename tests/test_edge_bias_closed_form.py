"""The slanted-edge best focus on the closed form of an edge through focus (issue 13, session 15).

Each edge is exact (:func:`fieldcal.measure.esfr_synth.through_focus_edge`: Gaussian x geometric defocus disc x
pixel aperture; each row its own focus, so a field curved or sloped along the edge is modelled): the MTF(fs) of
a row peaks where its disc vanishes. fieldcal's e-SFR core and through-focus estimator then read a best focus
whose error is theirs alone (benchmarks/bench_edge_bias.py, docs/benchmarks.md ``bench_edge_bias_s15``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure.esfr import esfr_regions, esfr_roi
from fieldcal.measure.esfr_focus import analyse_tracks, channel_shape, window_r_of
from fieldcal.measure.esfr_synth import (analytic_mtf, edge_focus_rows, edge_mtf_fs_curve, render_edge_rows,
                                         through_focus_edge)

F_NUMBER, PITCH_UM, FS, STEP_UM, N_FRAMES = 4.0, 3.0, 0.24, 6.2, 31   # the clean room's sym-f4
ROWS, WIDTH, HALF_PX = 13, 17, 8.0


def _tracks(phase: float, *, slants=(5.0, 7.0, 9.5), x_phases=(0.0, 0.5), **opts):
    """Best focus of each edge (the channel's estimator as edge_tiles.track_foci runs it), the truth at the
    position the e-SFR reports (MTF(fs)^2-weighted over the records near the peak, edge_tiles.peak_position_px)
    and the rows' length the e-SFR binned."""
    z = (np.arange(N_FRAMES) - (N_FRAMES - 1) / 2.0 + phase) * STEP_UM
    g = float(opts.get("gradient_um_per_px", 0.0))
    c = float(opts.get("curvature_um_per_px2", 0.0))
    curves, truth, lengths = [], [], []
    for slant in slants:
        for xp in x_phases:
            res = esfr_regions(through_focus_edge(z, z_focus_um=0.0, f_number=F_NUMBER, pitch_um=PITCH_UM,
                                                  slant_deg=slant, rows=ROWS, width_px=WIDTH, x_phase_px=xp, **opts),
                               half_width_px=HALF_PX)
            v = np.array([np.interp(FS, r.freq_cy_per_px, r.mtf[0]) for r in res])
            assert all(r.quality[0].ok for r in res)
            y = np.array([float(r.y_mid[0]) for r in res])
            use = v >= 0.5 * v.max()
            t = (float(np.dot(v[use] ** 2, y[use]) / np.sum(v[use] ** 2)) - (ROWS - 1) / 2.0) \
                / math.cos(math.radians(slant))
            truth.append(g * t + 0.5 * c * t * t)
            lengths.append(float(np.median([r.quality[0].rows for r in res])) / math.cos(math.radians(slant)))
            curves.append((z, v))
    shape = channel_shape(curves, 0.05, fs_cyc_per_um=FS / PITCH_UM, wavelength_um=0.54,
                          window_r=window_r_of(HALF_PX, FS))
    res, _ = analyse_tracks(curves, 0.05, shape=shape)
    return np.array([t.z_best_um for t in res]), np.array(truth), np.array(lengths)


def test_closed_form_edge_mtf_matches_the_analytic_one():
    """The rendering: a row-uniform edge's e-SFR is the analytic Gaussian x disc x pixel MTF (the core's own
    accuracy, issue 13's 0.02)."""
    img = render_edge_rows(40, 33, normal_deg=6.0, x_mid_px=16.2, sigma_px=0.5, defocus_d_px=2.0)
    r = esfr_roi(img)
    f = np.linspace(0.05, 0.45, 9)
    ref = analytic_mtf(f, sigma_px=0.5, defocus_d_px=2.0, normal_deg=6.0)
    assert np.max(np.abs(np.interp(f, r.freq_cy_per_px, r.mtf[0]) - ref)) < 0.02


@pytest.mark.parametrize("rows", [12, 13])
def test_reported_position_is_the_middle_of_the_rows_binned(rows):
    """Phase trimming keeps whole cycles of rows, centred: the e-SFR's MTF belongs to the middle of those rows,
    which for an even count (or an odd trim) is half a row off the region's middle row. The reported point must
    be the binned rows' middle, on the edge line (the region's middle row read -0.12 µm at 0.4 µm/px below)."""
    slant = 5.0
    xc = (WIDTH - 1) / 2.0 + 0.3
    img = render_edge_rows(rows, WIDTH, normal_deg=slant, x_mid_px=xc, sigma_px=0.5, defocus_d_px=1.0)
    r = esfr_roi(img, half_width_px=HALF_PX)
    n = r.quality[0].rows
    y_used = (rows - n) // 2 + (n - 1) / 2.0
    assert y_used != (rows - 1) // 2  # the cases where the binned rows' middle is not the region's middle row
    assert r.y_mid[0] == pytest.approx(y_used, abs=1e-9)
    # the edge line: dist = (x - xc) cos + (y - yc) sin = 0
    yc = (rows - 1) / 2.0
    x_line = xc - (y_used - yc) * math.tan(math.radians(slant))
    assert r.x_mid[0] == pytest.approx(x_line, abs=0.03)


def test_flat_edge_best_focus_has_no_bias():
    """A flat field through focus, noise-free, two sampling phases: every edge's peak within 0.03 µm of 0 and
    their mean within 0.015 µm (0.0025 step; measured +0.006 µm over 96 tracks)."""
    errs = np.concatenate([_tracks(ph)[0] for ph in (0.13, 0.61)])
    assert np.all(np.isfinite(errs))
    assert np.max(np.abs(errs)) < 0.03
    assert abs(float(np.mean(errs))) < 0.015


def test_gradient_along_the_edge_is_read_at_the_reported_position():
    """Focus rising 0.4 µm/px along the edge (a sagittal edge at the triplet's corners): the peak is the focus
    at the point the e-SFR reports: mean within 0.05 µm, RMS under 0.1 µm (measured +0.03 and 0.06; where the
    number of rows kept flips between frames the records mix two positions); the region's middle row read
    -0.12 µm mean, 0.18 RMS on the benchmark's 24 edges."""
    zb, truth, _ = _tracks(0.37, gradient_um_per_px=0.4)
    e = zb - truth
    assert abs(float(np.mean(e))) < 0.05
    assert float(np.sqrt(np.mean(e ** 2))) < 0.1


@pytest.mark.parametrize("curvature", [0.026, -0.026])
def test_curvature_along_the_edge_is_the_window_term(curvature):
    """Focus curved along the edge: the e-SFR averages the rows' OTFs, so its peak is the mean focus along the
    rows it binned, ``c L^2 / 24`` above the middle (what the fit removes, edge_tiles.edge_window_px), to 0.04 µm
    (measured -0.009 / +0.028 µm; the benchmark's 24 edges -0.009 / +0.016);
    and the term is real (>= 0.1 µm here), so a fit without it would be biased by its sign."""
    zb, truth, length = _tracks(0.37, curvature_um_per_px2=curvature)
    window = curvature * length ** 2 / 24.0
    assert abs(float(np.mean(window))) > 0.1
    assert abs(float(np.mean(zb - truth - window))) < 0.04


def test_exact_curve_of_a_curved_edge_peaks_at_its_mean_focus():
    """The closed form's own truth: the mean of the rows' OTFs peaks at the rows' mean focus (to 2nd order)."""
    zf = edge_focus_rows(13, z_focus_um=0.0, slant_deg=6.0, curvature_um_per_px2=0.05)
    z = np.linspace(-3, 3, 6001)
    m = edge_mtf_fs_curve(z, FS, f_number=F_NUMBER, pitch_um=PITCH_UM, slant_deg=6.0, z_focus_rows_um=zf)
    assert float(z[np.argmax(m)]) == pytest.approx(float(np.mean(zf)), abs=0.02)
