"""The e-SFR peaks' field-wide error, measured on the tracks (measure.esfr_focus.law_common_mode), against a
Monte-Carlo truth.

Tracks follow the defocus law (the disc's |D|, fieldcal.optics.defocus) with independent noise per sample and,
in one case, a multiplicative error per frame shared by every track (a frame-level error: exposure, flicker,
a renderer's frame). The truth of the field-wide error is the spread, over many draws of the frame errors, of
the channel's mean peak with those errors minus the same tracks without them. The delete-one-frame jackknife
must find it from one draw (averaged over a few draws: one channel's jackknife has ~K degrees of freedom), and
must find ~nothing where the frames share no error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure import esfr_focus as ef

N_TRACKS, N_FRAMES = 40, 17
NOISE = 0.004     # MTF(fs) noise per sample (SNR ~ 100 at the peak)
FRAME_SD = 0.02   # the frames' shared multiplicative error


def _tracks(rng, frame_err: np.ndarray, noise: np.ndarray):
    from fieldcal.optics.defocus import disc_otf, disc_x_at_contrast

    z = np.arange(N_FRAMES, dtype=np.float64)  # steps; tolerance 1 step
    xq = disc_x_at_contrast(0.95)
    z0 = np.linspace(6.0, 10.0, N_TRACKS)  # the field's foci: many sampling phases
    out = []
    for i in range(N_TRACKS):
        v = 0.6 * np.abs(disc_otf(xq * (z - z0[i]) / 1.0)) * (1.0 + frame_err) + noise[i]
        out.append((z, v))
    return out


def _mean_centre(tracks) -> float:
    return float(np.nanmean([ef.symmetric_centre_um(z, v) for z, v in tracks]))


def _draw(rng, shared: bool):
    e = rng.normal(0.0, FRAME_SD, N_FRAMES) if shared else np.zeros(N_FRAMES)
    return e, rng.normal(0.0, NOISE, (N_TRACKS, N_FRAMES))


@pytest.fixture(scope="module")
def truth_sd():
    """Monte-Carlo sd of the channel's mean peak that the shared frame errors cause (steps)."""
    rng = np.random.default_rng(7)
    d = []
    for _ in range(16):
        e, n = _draw(rng, True)
        d.append(_mean_centre(_tracks(rng, e, n)) - _mean_centre(_tracks(rng, np.zeros(N_FRAMES), n)))
    return float(np.std(d, ddof=1))


def test_jackknife_finds_the_frames_shared_error(truth_sd):
    rng = np.random.default_rng(11)
    var = []
    for _ in range(6):
        e, n = _draw(rng, True)
        sd, used = ef.frame_jackknife_sd_um(_tracks(rng, e, n))
        assert used == N_TRACKS
        var.append(sd * sd)
    ratio = math.sqrt(float(np.mean(var))) / truth_sd
    assert truth_sd > 0.01  # the case is not trivial: the frames move the mean peak by ~0.02 step
    assert 0.6 < ratio < 1.6, (ratio, truth_sd)


def test_jackknife_reads_no_shared_error_from_independent_noise(truth_sd):
    rng = np.random.default_rng(12)
    sds = []
    for _ in range(6):
        e, n = _draw(rng, False)
        sds.append(ef.frame_jackknife_sd_um(_tracks(rng, e, n))[0])
    # the tracks' own noise is subtracted: what is left is a small fraction of a real frame-level error
    assert math.sqrt(float(np.mean(np.square(sds)))) < 0.35 * truth_sd, (sds, truth_sd)


def test_symmetric_law_has_no_law_term():
    rng = np.random.default_rng(3)
    e, n = _draw(rng, False)
    tracks = _tracks(rng, e, n)
    res = [ef.analyse_track(z, v, 0.05) for z, v in tracks]
    shape = ef.PooledShape(0.0, 0.1, N_TRACKS, 0.0, False)
    cm = ef.law_common_mode(tracks, res, shape)
    assert cm.law_um == 0.0 and cm.shape_um == 0.0
    assert cm.sd_um == pytest.approx(cm.frames_um)


def _sa_tracks(rng, s_true: float, noise: float, n_tracks: int = 40):
    """Tracks of the defocus + primary-SA law (the ray integral, ``esfr_focus._law``) with asymmetry
    ``s_true``, 13 frames one step apart, tolerance about one step, many sampling phases; the true sharpest
    position of each is its ``z0`` moved by the law's own peak."""
    from fieldcal.optics.defocus import disc_x_at_contrast

    z = np.arange(13, dtype=np.float64)
    k = disc_x_at_contrast(0.95)  # x per step: the q = 5 % half-width is one step at s = 0
    z0 = np.linspace(5.0, 7.0, n_tracks)
    x_peak = ef.model_points(s_true, 0.05)[0] if s_true != 0 else 0.0
    tracks = [(z, 0.6 * np.abs(ef._law(k * (z - z0[i]), s_true, math.nan)) + noise * rng.standard_normal(z.size))
              for i in range(n_tracks)]
    return tracks, z0 + x_peak / k


def test_unmodelled_asymmetry_term_is_what_the_symmetric_law_misses():
    """A channel whose asymmetry is too small to select the shaped law (the BIC keeps the symmetric one) is read
    with s = 0, so every peak is off by dz/ds x s; the term states |dz/ds| x sd(s). The sensitivity dz/ds,
    probed on the noisy channel's own tracks, must be the true one: noise-free curves with an asymmetry of
    one to two sd(s), read by the symmetric law, miss their true sharpest positions (the law's own peak) by
    dz/ds x s (ratio 0.6-1.5); the peak itself moves 20x more (the symmetric fit follows most of it). Where the
    law is selected the term is 0 (the peaks are read at s)."""
    rng = np.random.default_rng(11)
    noisy, _ = _sa_tracks(rng, 0.0, 0.01)
    shape = ef.channel_shape(noisy, 0.05)
    assert not shape.selected and shape.sd > 0 and shape.sym_dz_ds > 0
    stated = ef.unmodelled_asymmetry_sd_um(noisy, shape)
    assert stated == pytest.approx(shape.sym_dz_ds * shape.sd)  # 1 step = 1 unit
    res, _ = ef.analyse_tracks(noisy, 0.05, shape=shape)
    cm = ef.law_common_mode(noisy, res, shape)
    assert cm.shape_um == pytest.approx(stated) and cm.sd_um >= stated
    for s_true in (shape.sd, 2.0 * shape.sd):
        clean, truth = _sa_tracks(rng, s_true, 0.0)
        # read as that channel is, by the symmetric law (noise-free curves would also give the skew test's
        # spline full weight: analyse_track; on the noisy channel its median weight is ~0.04)
        err = float(np.mean([ef.symmetric_centre_um(z, v) - t for (z, v), t in zip(clean, truth)]))
        assert 0.6 <= abs(err) / (shape.sym_dz_ds * s_true) <= 1.5, (err, shape.sym_dz_ds * s_true)
    # a clearly asymmetric channel selects the law and reads each peak at its s: this term is not added
    tracks, _ = _sa_tracks(rng, 3.0, 0.004)
    shape = ef.channel_shape(tracks, 0.05)
    assert shape.selected and ef.unmodelled_asymmetry_sd_um(tracks, shape) == 0.0
