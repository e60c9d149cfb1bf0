"""The batched paths of the slanted-edge calibration give what one call per curve, track or edge gives.

Speed work (issue 13: 41 frames of 1920x1080 in <= 20 s) batched the edge tracks' through-focus fits although
every track has its own z positions (the frames where its edge was measured), and made the batched
Levenberg-Marquardt iterate only its unconverged curves. Neither may change a result: each batched answer is
compared with the one-at-a-time answer (the code path the batch replaced) on curves with known peaks.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pytest

from fieldcal.measure import spherical
from fieldcal.measure.esfr_focus import (EDGE_CURVE_RULES, analyse_track, analyse_tracks, defocus_fits,
                                         track_shape, track_shapes)
from fieldcal.measure.throughfocus import CurveRules, _fit_batch, _precheck, analyse_curve, analyse_curve_list
from fieldcal.optics import pupil

LAM_UM, N_F = 0.55, 4.0


def _ragged_tracks(w040_waves: float, nu: float, n_tracks: int, noise: float, seed: int):
    """MTF(fs) tracks of the exact pupil OTF (defocus + W040), each on its own z: a random run of a 41-position
    scan with random frames missing (as edge tracks are). Returns tracks, fs (cycles/mm), step (µm)."""
    rng = np.random.default_rng(seed)
    per_wave = 8.0 * N_F ** 2 * LAM_UM  # µm of defocus per wave of W020
    step = 0.12 * per_wave
    grid = (np.arange(41) - 20) * step
    tracks = []
    for _ in range(n_tracks):
        z0 = rng.uniform(-4.0, 4.0) * step
        lo = int(rng.integers(0, 8))
        hi = 41 - int(rng.integers(0, 8))
        keep = np.arange(lo, hi)
        keep = keep[rng.random(keep.size) > 0.15]  # holes: frames where the edge failed its checks
        z = grid[keep]
        m = 0.6 * np.abs(pupil.otf(nu, (z - z0) / per_wave, w040_waves))
        v = np.hypot(m + rng.normal(0.0, noise, z.size), rng.normal(0.0, noise, z.size)) if noise else m
        tracks.append((z, v))
    return tracks, 1000.0 * nu / (LAM_UM * N_F), step


def _same(a, b, what: str, rtol: float = 1e-9) -> None:
    """Equal to round-off (NaN where NaN; batches pad their windows, which reorders sums: ~1e-12 relative);
    dataclasses field by field."""
    if hasattr(a, "__dataclass_fields__"):
        for f in fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{what}.{f.name}", rtol)
        return
    if isinstance(a, (float, int, np.floating, np.integer, np.ndarray)) and not isinstance(a, (bool, np.bool_)):
        x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        assert x.shape == y.shape and np.array_equal(np.isnan(x), np.isnan(y)), what
        scale = max(1.0, float(np.max(np.abs(np.nan_to_num(x)), initial=0.0)))
        assert np.allclose(x, y, rtol=rtol, atol=rtol * scale, equal_nan=True), (what, a, b)
    elif callable(a) or a is None:
        return
    else:
        assert a == b, (what, a, b)


@pytest.mark.parametrize("w040,nu", [(0.0, 0.08), (1.5, 0.25)])
def test_curve_list_equals_one_curve_at_a_time(w040, nu, monkeypatch):
    """analyse_curve_list on curves of different lengths and z grids = analyse_curve of each. At W040 1.5 waves,
    nu 0.25 the band-pass skew model takes its exact-pupil branch for some curves (counted), whose quadrature
    depends on its batch: the list keeps each such curve its own batch."""
    calls = []
    wave_peak = spherical.wave_peak_u
    monkeypatch.setattr(spherical, "wave_peak_u", lambda *a, **k: calls.append(1) or wave_peak(*a, **k))
    tracks, fs_mm, _ = _ragged_tracks(w040, nu, 20, 0.004, seed=11)
    curves = [(z, v * v) for z, v in tracks]
    rules = CurveRules()
    batch = analyse_curve_list(curves, "otf", fs_mm, 0.05, rules)
    n_wave = len(calls)
    one = [analyse_curve(z, e, "otf", fs_mm, 0.05, rules) for z, e in curves]  # the path the list replaces
    assert sum(f.status == "ok" for f in batch) >= 8
    for k, (a, b) in enumerate(zip(one, batch)):
        _same(a, b, f"curve {k}")
    if w040 > 0:
        assert n_wave > 0  # the exact-pupil branch was exercised
    # one grid: the list is analyse_curves' answer too (the edge tracks' law, as esfr_focus.defocus_peak fits it)
    z, e = curves[0]
    _same(analyse_curve(z, e, "otf", 1.0, 0.05, EDGE_CURVE_RULES),
          analyse_curve_list([(z, e)], "otf", 1.0, 0.05, EDGE_CURVE_RULES)[0], "one grid")


def test_batched_fit_iterates_only_its_unconverged_curves():
    """_fit_batch of many windows = each window fitted alone (a converged curve's state is frozen, so the batch
    evaluates only the others): the symmetric law and the Pearson peak on curves of different widths."""
    tracks, _, step = _ragged_tracks(0.0, 0.08, 12, 0.003, seed=5)
    z = tracks[0][0]
    grid_tracks = [(z, np.interp(z, t[0], t[1])) for t in tracks]  # one z grid, as the texture path's tiles
    V = np.stack([v * v for _, v in grid_tracks])
    # every window the whole curve: no padding, so the batch must give each curve's numbers exactly
    pres = [(t, replace(p, lo=0, hi=z.size - 1)) for t, p in
            ((t, _precheck(z, V[t], EDGE_CURVE_RULES)) for t in range(len(V))) if hasattr(p, "lo")]
    assert len(pres) >= 8
    for model in ("otf", "peak"):
        batch = _fit_batch(z, V, pres, float(np.median(np.diff(z))), model)
        for (t, pre), fb in zip(pres, batch):
            fa = _fit_batch(z, V, [(t, pre)], float(np.median(np.diff(z))), model)[0]
            assert (fa is None) == (fb is None)
            if fa is not None:
                _same(fa, fb, f"{model} window {t}", rtol=1e-14)


def test_track_batches_equal_one_track_at_a_time():
    """defocus_fits + analyse_track(fit=...) = analyse_track, track_shapes = track_shape (geometric and exact
    pupil law), on a channel of ragged noisy tracks with spherical aberration, whose pooled asymmetry is then
    selected from the batched shapes."""
    tracks, fs_mm, step = _ragged_tracks(0.8, 0.25, 16, 0.004, seed=3)
    fits = defocus_fits(tracks, 0.05)
    for k, ((z, v), f) in enumerate(zip(tracks, fits)):
        _same(analyse_track(z, v, 0.05), analyse_track(z, v, 0.05, fit=f), f"track {k}")
    c_nu = math.pi * (fs_mm * 1e-3) ** 2 * LAM_UM * step
    for cn in (math.nan, c_nu):
        many = track_shapes(tracks, cn)
        assert sum(s.ok for s in many) >= 10
        for k, ((z, v), s) in enumerate(zip(tracks, many)):
            _same(track_shape(z, v, cn), s, f"shape {k} c_nu {cn}")
    res, shape = analyse_tracks(tracks, 0.05, fs_cyc_per_um=fs_mm * 1e-3, wavelength_um=LAM_UM)
    assert shape.selected and sum(r.ok for r in res) >= 12


def test_esfr_noise_median_and_quality_record_are_the_plain_ones():
    """The e-SFR's one-selection median is np.median (odd and even sizes, ties), and a quality record's dict is
    its fields in order."""
    from fieldcal.measure.esfr import EdgeQuality, _median_1d

    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 4, 7, 8, 999, 1000):
        for x in (rng.normal(size=n), rng.integers(0, 3, size=n).astype(np.float64)):
            assert _median_1d(x.copy()) == float(np.median(x))
    q = EdgeQuality(True, "ok", 5.0, 0.8, 0.7, 0.01, 70.0, 0.0, 64, 16.0, 1.2, 0.01, 0.05, 0)
    assert q.to_dict() == {f.name: getattr(q, f.name) for f in fields(q)}
    assert list(q.to_dict()) == [f.name for f in fields(q)]
