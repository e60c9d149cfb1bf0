"""The sml@fs offset's stated sd under skewed (spherical-aberration) band-pass curves, against a Monte Carlo of the
estimator (measure.throughfocus.apply_pooled_skew -> apply_measure_offset -> offset_sd_um; issue 14).

The band-pass curves' sharpest positions are their symmetric centres moved by one pooled skew shift: that shift's
error is one draw for every tile of the channel, so the offset (mean over tiles of band-pass minus SML) carries it
whole, however many tiles there are. Summed into each tile's sd and pooled, it was divided by sqrt(n).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure.throughfocus import (CurveFit, apply_measure_offset, apply_pooled_skew, offset_sd_um,
                                           pooled_skew_var_um2)

N_TILES = 50
TRUE_OFFSET_UM = -1.0     # band-pass sharpest position minus SML peak, the same over the field (one pupil's SA)
SKEW_UM = -0.8            # band-pass sharpest position minus its symmetric centre
CENTRE_SD, SHIFT_SD, SML_SD = 0.1, 0.5, 0.1


def _fits(rng, z_true, skew_shift_sd=SHIFT_SD):
    """Band-pass fits of tiles whose sharpest position is ``z_true``: centres SKEW_UM below it, with noise; each
    tile's own skew shift measured with sd ``skew_shift_sd``."""
    c = z_true - SKEW_UM + rng.normal(0.0, CENTRE_SD, z_true.size)
    s = SKEW_UM + rng.normal(0.0, skew_shift_sd, z_true.size)
    return [CurveFit(float(ci), CENTRE_SD, math.nan, 1.0, 0.0, "ok", 9, 1.0, math.nan, float(ci), CENTRE_SD,
                     float(si), skew_shift_sd) for ci, si in zip(c, s)]


def _sml(rng, z_true):
    z = z_true - TRUE_OFFSET_UM + rng.normal(0.0, SML_SD, z_true.size)
    return [CurveFit(float(v), SML_SD, math.nan, 1.0, 0.0, "ok", 9) for v in z]


def _draw(rng):
    z_true = rng.uniform(-20.0, 20.0, N_TILES)
    bp, skew = apply_pooled_skew(_fits(rng, z_true))
    out, info = apply_measure_offset(_sml(rng, z_true), bp, ref_skew=skew)
    return info, float(np.mean([f.z_best_um for f in out]) - np.mean(z_true))


def test_offset_sd_matches_a_monte_carlo_of_the_estimator_under_skewed_curves():
    rng = np.random.default_rng(3)
    draws = [_draw(rng) for _ in range(400)]
    err = np.array([e for _, e in draws])
    stated = np.array([offset_sd_um(i) for i, _ in draws])
    assert np.all([i["offset_weight"] > 0.999 for i, _ in draws])
    # closed form: the pooled shift's error (SHIFT_SD / sqrt(n)) is shared; the centres' and SMLs' average down
    expect = math.sqrt(SHIFT_SD ** 2 / N_TILES + (CENTRE_SD ** 2 + SML_SD ** 2) / N_TILES)
    assert float(np.sqrt(np.mean(err ** 2))) == pytest.approx(expect, rel=0.12)
    assert float(np.median(stated)) == pytest.approx(expect, rel=0.12)
    # honest 90 % interval: the error within 1.645 stated sd in ~90 % of draws (400 draws: sd of the rate 0.015)
    assert 0.85 <= float(np.mean(np.abs(err) <= 1.645 * stated)) <= 0.95


def test_without_the_shared_term_the_pooled_sd_is_sqrt_n_too_small():
    """The failure the shared term fixes: the same offset pooled with the pooled shift's variance inside each
    tile's sd (no ``ref_skew``) states about 1/3 of its real error here."""
    rng = np.random.default_rng(4)
    z_true = rng.uniform(-20.0, 20.0, N_TILES)
    bp, skew = apply_pooled_skew(_fits(rng, z_true))
    main = _sml(rng, z_true)
    _, old = apply_measure_offset(main, bp)
    _, new = apply_measure_offset(main, bp, ref_skew=skew)
    assert new["offset_skew_sd_um"] ** 2 == pytest.approx(pooled_skew_var_um2(skew))
    assert new["offset_sd_um"] > 2.5 * old["offset_sd_um"]


def test_skewed_curves_are_evidence_for_the_offset():
    """An offset at ~2 sd of its own is shrunk to ~0 by the prior for symmetric curves; where the band-pass curves
    are measured skewed (weight 1) the SML and the band-pass at fs cannot peak together, and it applies whole.
    Symmetric curves (skew weight below 1/2) keep the offset's own weight."""
    rng = np.random.default_rng(5)
    z_true = rng.uniform(-20.0, 20.0, N_TILES)
    sml = [CurveFit(float(v), 1.0, math.nan, 1.0, 0.0, "ok", 9) for v in z_true + 0.3 + rng.normal(0, 1.0, N_TILES)]
    bp = [CurveFit(float(v), 0.3, math.nan, 1.0, 0.0, "ok", 9) for v in z_true + rng.normal(0, 0.3, N_TILES)]
    _, sym = apply_measure_offset(sml, bp, ref_skew={"shift_um": 0.0, "sd_um": 0.05, "weight": 0.3})
    _, skewed = apply_measure_offset(sml, bp, ref_skew={"shift_um": -0.8, "sd_um": 0.05, "weight": 1.0})
    assert sym["offset_own_weight"] < 0.5 and sym["offset_weight"] == sym["offset_own_weight"]
    assert skewed["offset_weight"] == 1.0
    # applied whole, its sd is the pooled sd with the skew's shared part: no "applies or not" mixture term
    assert offset_sd_um(skewed) == pytest.approx(skewed["offset_sd_um"])


def _shift_fits(rng, d_mean, n=40, noise=0.05):
    """Curves whose two skew estimators differ by ``d_mean`` on average (per-curve noise ``noise``)."""
    out = []
    for _ in range(n):
        s = -0.8 + rng.normal(0.0, 0.1)
        alt = s - d_mean + rng.normal(0.0, noise)
        out.append(CurveFit(0.0, 0.1, math.nan, 1.0, 0.0, "ok", 9, 1.0, math.nan, 0.8, 0.1, s, noise, alt))
    return out


def test_skew_model_error_is_the_estimators_shared_disagreement():
    """A disagreement every curve shares is a model error (its size, less its noise); one that is only noise
    averages to ~0 and adds nothing. It enters the variance the pooled shift gives each curve (and the offset)."""
    from fieldcal.measure.throughfocus import skew_model_sd_um
    rng = np.random.default_rng(6)
    assert skew_model_sd_um(_shift_fits(rng, 0.3)) == pytest.approx(0.3, abs=0.03)
    assert skew_model_sd_um(_shift_fits(rng, 0.0)) < 0.02
    # no second estimate (the local peak only, or symmetric curves): nothing to compare, 0
    plain = [CurveFit(0.0, 0.1, math.nan, 1.0, 0.0, "ok", 9, 1.0, math.nan, 0.8, 0.1, -0.8, 0.05) for _ in range(5)]
    assert skew_model_sd_um(plain) == 0.0
    fits, info = apply_pooled_skew(_shift_fits(rng, 0.3))
    assert info["model_sd_um"] == pytest.approx(0.3, abs=0.03)
    assert pooled_skew_var_um2(info) == pytest.approx(info["weight"] * (info["sd_um"] ** 2 + info["model_sd_um"] ** 2)
                                                     + info["weight"] * (1 - info["weight"]) * info["shift_um"] ** 2)
    assert fits[0].z_sigma_um ** 2 == pytest.approx(0.1 ** 2 + pooled_skew_var_um2(info))


def test_channels_share_the_strongest_band_pass_skew_weight():
    """One pupil skews every channel: a channel whose own evidence is weaker is analysed again with the strongest
    channel's weight; channels without band-pass fits (NaN) and the strongest one are not redone."""
    from fieldcal.measure.tiles import _analyse_channels
    own = {"R": 0.1, "G": 1.0, "B": math.nan, "Y": 0.8}
    calls = []

    def run(ch, w):
        calls.append((ch, w))
        return {"skew": {"bp_own_weight": own[ch], "bp_skew_weight": own[ch] if w is None else w}}
    res = _analyse_channels(run, ["R", "G", "B", "Y"])
    assert calls == [("R", None), ("G", None), ("B", None), ("Y", None), ("R", 1.0)]  # Y (0.8) agrees: kept
    assert res["R"]["skew"]["bp_skew_weight"] == 1.0 and res["G"]["skew"]["bp_skew_weight"] == 1.0


def test_pooled_mean_is_not_taken_over_by_one_tile_with_an_understated_sd():
    """Per-tile sds are curve-fit / delta-method sds, and a few are far too small: one tile at +2.7 ± 0.5 among 58
    at -1.1 ± 1.9 (the F/6.9 lens of the band benchmark) moved the inverse-variance mean by half its distance to
    that tile. The Huber M-estimate stays within its stated sd of the true value, and on normal data it is the
    inverse-variance mean with the Birge-inflated sd (closed form) to within a few per cent of that sd."""
    from fieldcal.measure.throughfocus import pooled_mean
    rng = np.random.default_rng(11)
    hits, n_draw, err_plain, err_robust = 0, 300, [], []
    for _ in range(n_draw):
        sd = np.r_[np.full(58, 1.9), 0.5]
        d = np.r_[-1.1 + rng.normal(0.0, 1.9, 58), 2.7]
        w = 1.0 / sd ** 2
        err_plain.append(float(np.sum(w * d) / np.sum(w)) + 1.1)
        mean, se, _ = pooled_mean(d, sd)
        err_robust.append(mean + 1.1)
        hits += abs(mean + 1.1) <= 1.645 * se
    # the plain mean's bias is (2.7 + 1.1) x 14.4 / (58 + 14.4) = 0.76, three times its noise (1.9 / sqrt(58));
    # the Huber weight (1.345 / 7.6) leaves the tile ~2.6 tiles' pull: bias ~0.16, RMS error ~0.3
    assert float(np.mean(err_plain)) == pytest.approx(3.8 * 14.44 / 72.44, abs=0.05)
    assert float(np.sqrt(np.mean(np.square(err_robust)))) < 0.5 * float(np.mean(err_plain))
    assert hits / n_draw >= 0.85
    diffs, ratios = [], []
    for _ in range(40):
        sd = rng.uniform(1.0, 3.0, 60)
        d = -1.0 + sd * rng.normal(0.0, 1.0, 60)
        w = 1.0 / sd ** 2
        m = float(np.sum(w * d) / np.sum(w))
        se = math.sqrt(max(1.0, float(np.sum(w * (d - m) ** 2)) / 59) / float(np.sum(w)))
        mean, sd_robust, _ = pooled_mean(d, sd)
        diffs.append((mean - m) / se)
        ratios.append(sd_robust / se)
    # 95 % efficiency: the two means differ by ~sqrt(1 / 0.95 - 1) = 0.23 of the sd
    assert float(np.sqrt(np.mean(np.square(diffs)))) < 0.35
    # the sandwich sd: the Birge sd within the noise of a variance estimated tile by tile (weights 1-9)
    assert 0.9 < float(np.median(ratios)) < 1.15 and float(np.max(ratios)) < 1.5


def test_an_sml_to_centre_offset_is_evidence_that_the_band_pass_curves_are_skewed():
    """Defocus alone peaks every frequency together: an SML peaking 6 µm from the band-pass curves' centres (at
    many sd) says the pupil is aberrated, so the band-pass skew shift applies whole even where its own evidence is
    weak (the curves' sharpest positions, not their centres); a lens whose SML and centres agree keeps the
    curves' own weight."""
    rng = np.random.default_rng(12)
    z_true = rng.uniform(-20.0, 20.0, N_TILES)

    def bp_fits(skew_sd):  # centres 0.8 above the sharpest position; each tile's shift very noisy
        c = z_true - SKEW_UM + rng.normal(0.0, CENTRE_SD, N_TILES)
        s = SKEW_UM + rng.normal(0.0, skew_sd, N_TILES)
        return [CurveFit(float(ci), CENTRE_SD, math.nan, 1.0, 0.0, "ok", 9, 1.0, math.nan, float(ci), CENTRE_SD,
                         float(si), skew_sd) for ci, si in zip(c, s)]
    bp, skew = apply_pooled_skew(bp_fits(6.0))
    assert skew["weight"] < 0.5   # too noisy to say skewed on its own
    out, info = apply_measure_offset(_sml(rng, z_true), bp, ref_skew=skew)   # SML 1 µm off the sharpest
    assert info["bp_skew_weight"] > 0.99 and info["offset_weight"] > 0.99
    err = float(np.mean([f.z_best_um for f in out]) - np.mean(z_true))
    # the whole pooled shift is applied: the error is its noise, within the stated offset sd
    assert abs(err) <= 1.645 * offset_sd_um(info)
    assert abs(err) < 0.5 * abs(SKEW_UM) + 1.645 * offset_sd_um(info)
    # SML peaking where the centres are: no offset, no lifted skew weight
    sml_at_centres = [CurveFit(float(f.z_centre_um + rng.normal(0.0, SML_SD)), SML_SD, math.nan, 1.0, 0.0, "ok", 9)
                      for f in bp]
    _, sym = apply_measure_offset(sml_at_centres, bp, ref_skew=skew)
    assert "bp_skew_from_offset_weight" not in sym
