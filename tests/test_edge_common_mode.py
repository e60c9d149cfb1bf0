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
