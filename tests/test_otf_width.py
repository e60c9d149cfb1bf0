"""The band-pass through-focus width does not depend on where the scan's samples fall (fieldcal.measure.otf_width).

Closed-form curves: the band energy of a geometric-defocus blur seen through the log-Gabor ring of
:func:`fieldcal.measure.focus.bandpass` (D^2 averaged over the ring's frequencies, a flat chart spectrum per
log-frequency), so the ``"otf"`` model (D^2 at one frequency) is close to, not exactly, the curve: the case of
every measured curve. The same curve is sampled with the scan started at 16 fractions of a step.
"""

import math

import numpy as np
import pytest

from fieldcal.measure import otf_width
from fieldcal.measure.focus import LOG_GABOR_SIGMA_RATIO
from fieldcal.measure.throughfocus import analyse_curves
from fieldcal.optics.defocus import disc_otf, disc_x_at_contrast

FS = 16.0                                    # cycles/mm
STEP = 20.0
Z = np.arange(-400.0, 100.0 + 1e-9, STEP)    # the triplet's scan of the profile-diff benchmark
PHASES = np.arange(16) / 16.0
_S = np.exp(np.linspace(-1.2, 1.2, 241))     # frequency / fs over the ring
_W = np.exp(-(np.log(_S) / math.log(LOG_GABOR_SIGMA_RATIO)) ** 2)   # the ring's power (|G|^2)
_W /= _W.sum()


def band_energy(dz_um, k):
    """Energy through the ring of a blur disc of diameter k |dz| (the geometric defocus of an F/(1/k) lens)."""
    x = math.pi * FS * 1e-3 * k * np.abs(np.asarray(dz_um, float))[:, None] * _S[None, :]
    return (disc_otf(x) ** 2 * _W).sum(axis=1)


def true_width_um(k, q=0.05):
    return disc_x_at_contrast(1.0 - q) / (math.pi * FS * 1e-3 * k)


def widths(z_centre, k, noise=0.0, repeat=1, seed=0):
    V = np.array([band_energy(Z - (z_centre + p * STEP), k) + 0.02 for p in PHASES])
    V = np.repeat(V, repeat, axis=0)
    if noise:
        V = V + np.random.default_rng(seed).normal(0.0, noise, V.shape)
    fits = analyse_curves(Z, V, "otf", FS, 0.05)
    assert all(f.status == "ok" for f in fits)
    return np.array([f.width_um for f in fits])


@pytest.fixture
def hard_window(monkeypatch):
    """The estimator before the fix: the main fit's width (hard window)."""
    monkeypatch.setattr(otf_width, "tapered_widths", lambda z, V, pres, fits, step, x_q, out: out)


@pytest.mark.parametrize("z_centre, k, limit", [(-150.0, 0.5, 1e-3), (-150.0, 0.35, 1e-3), (-320.0, 0.5, 2e-3)])
def test_width_does_not_depend_on_the_sampling_phase(z_centre, k, limit):
    # -320: the lobe runs off the scan's start (the ramps at the ends keep the estimate continuous there).
    w = widths(z_centre, k)
    assert np.ptp(w) / w.mean() < limit
    # and it is the width of the curve, as well as the hard-window fit was (its bias is the band's, not ours)
    assert abs(w.mean() / true_width_um(k) - 1.0) < 0.04


@pytest.mark.parametrize("z_centre, k, limit", [(-150.0, 0.5, 1e-3), (-320.0, 0.5, 2e-3)])
def test_the_hard_window_fails_the_phase_test(hard_window, z_centre, k, limit):
    # The same test on the estimator before the fix: its width swings with the phase by several times the limit.
    w = widths(z_centre, k)
    assert np.ptp(w) / w.mean() > 3.0 * limit


def test_tapered_width_is_no_noisier_than_the_hard_window(monkeypatch):
    dev = {}
    for name in ("tapered", "hard"):
        if name == "hard":
            monkeypatch.setattr(otf_width, "tapered_widths", lambda z, V, pres, fits, step, x_q, out: out)
        clean = widths(-150.0, 0.5)
        noisy = widths(-150.0, 0.5, noise=0.01, repeat=12, seed=3)
        dev[name] = float(np.std(noisy - np.repeat(clean, 12)))
    assert dev["tapered"] < 1.05 * dev["hard"]


def test_exact_model_curves_keep_their_exact_width():
    # a curve that is the model itself: every phase gives the closed-form width to 1e-4
    for k in (0.35, 0.9):
        x = lambda dz: math.pi * FS * 1e-3 * k * dz  # noqa: E731
        V = np.array([disc_otf(x(Z - (-150.0 + p * STEP))) ** 2 + 0.02 for p in PHASES])
        w = np.array([f.width_um for f in analyse_curves(Z, V, "otf", FS, 0.05)])
        np.testing.assert_allclose(w, true_width_um(k), rtol=1e-4)


def test_taper_and_end_ramps_are_continuous_weights():
    x = np.linspace(0.0, 6.0, 6001)
    t = otf_width.taper(x)
    assert t[0] == 1.0 and t[-1] == 0.0
    assert np.all(np.diff(t) <= 0.0) and np.max(np.abs(np.diff(t))) < 2e-3     # no jump
    assert otf_width.taper(otf_width.X_FLAT) == 1.0 and otf_width.taper(otf_width.X_EDGE) == 0.0
    e = otf_width.end_weights(10)
    np.testing.assert_allclose(e, e[::-1])
    assert e[0] == 0.0 and e[otf_width.END_RAMP] == 1.0
