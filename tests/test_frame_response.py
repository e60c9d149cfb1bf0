"""Stage frame errors in the pooled skew shift and sml@fs offset (fieldcal.measure.throughfocus.pooled_skew,
apply_measure_offset): every tile's curve is sampled at the same frames, so one pattern of frame-position errors
moves every tile's estimate at once. The frame responses must predict those moves, and the pooled values' sd and
evidence must carry them: a frame pattern on symmetric curves is not a skew; a real skew still is."""

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from test_measure_curves import _sa_curves  # noqa: E402  (pupil-FFT through-focus curves, W040 in waves)

from fieldcal.measure.throughfocus import (analyse_curves, apply_pooled_skew, offset_sd_um,  # noqa: E402
                                           pooled_skew_var_um2)

FS = 80.0
STEP = 4.0
R_UM = 0.2  # the stage's repeatability: 5 % of a step (the band benchmark's lens 14: 0.48 µm at 29.6 µm, 1.6 %)


def _channel(w040, e_um, rng, n=40, noise=0.002, kind="bp"):
    """(z, curves, offsets, sharpest position): ``n`` tiles of one channel, band-pass ("bp") or SML ("sml")
    curves of a pupil with W040 = ``w040`` peaking at random positions, taken at ``z + e_um`` (the frames' true
    positions) and recorded at z."""
    zd, c, zt = _sa_curves(w040, "bp")
    z = np.arange(zt - 60.0, zt + 40.0, STEP)
    offs = rng.uniform(-15.0, 15.0, n)
    if kind == "sml":
        zd, c, _ = _sa_curves(w040, "sml")
    V = np.array([np.interp(z + e_um - o, zd, c) * (1 + noise * rng.standard_normal(z.size)) + 0.02 * c.max()
                  for o in offs])
    return z, V, offs, zt


def test_frame_responses_predict_how_each_estimate_moves():
    # Noise-free curves taken 0-0.05 µm away from their recorded positions: each tile's centre and skew shift
    # move by their frame responses dotted with the errors (linear response; the responses use the fitted
    # model's slope, so on pupil curves the models do not describe exactly they are good to ~10-20 %), a common
    # offset of every frame moves the centre by -1 and not the skew shift.
    rng = np.random.default_rng(3)
    for w040 in (0.0, 0.6):
        e = rng.normal(0.0, 0.05, 25)
        z, V0, offs, _ = _channel(w040, 0.0, np.random.default_rng(1), n=12, noise=0.0)
        _, V1, _, _ = _channel(w040, e[:z.size], np.random.default_rng(1), n=12, noise=0.0)
        f0, f1 = (analyse_curves(z, V, "otf", FS, 0.05) for V in (V0, V1))
        moved, pred, moved_s, pred_s = [], [], [], []
        for a, b in zip(f0, f1):
            assert a.status == "ok" and b.status == "ok"
            assert a.centre_resp is not None and a.skew_resp is not None
            assert abs(a.centre_resp.sum() + 1.0) < 1e-6 and abs(a.skew_resp.sum()) < 1e-4
            moved.append(b.z_centre_um - a.z_centre_um)
            pred.append(a.centre_resp @ e[:z.size])
            moved_s.append(b.skew_shift_um - a.skew_shift_um)
            pred_s.append(a.skew_resp @ e[:z.size])
        for m, p in ((moved, pred), (moved_s, pred_s)):
            m, p = np.array(m), np.array(p)
            assert np.sqrt(np.mean((m - p) ** 2)) < 0.25 * np.sqrt(np.mean(m ** 2)) + 1e-4, (w040, m, p)


def _draws(w040, told_um, n_draws=30, seed=7):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_draws):
        e = rng.normal(0.0, R_UM, 25)
        z, V, offs, zt = _channel(w040, e[:25], rng)
        fits, info = apply_pooled_skew(analyse_curves(z, V, "otf", FS, 0.05), repeatability_um=told_um)
        err = float(np.mean([f.z_best_um - o - zt for f, o in zip(fits, offs) if f.status == "ok"]))
        out.append((info, err))
    return out


def test_a_frame_error_pattern_on_symmetric_curves_is_not_read_as_a_skew():
    # W040 = 0: no skew; the frames' errors make every tile's curve look skewed the same way. Not told the
    # repeatability (the behaviour before), the evidence took the tiles as independent and applied that pattern
    # as a skew in a sixth of the draws, and the pooled shift's sd (tile scatter / sqrt(n)) held the shift it
    # measured (all of it error) in too few; told, the shift carries the frames' coherent share: seldom applied,
    # and its sd holds it.
    runs = {told: _draws(0.0, told) for told in (0.0, R_UM)}
    applied = {t: float(np.mean([i["weight"] > 0.5 for i, _ in v])) for t, v in runs.items()}
    held = {t: float(np.mean([abs(i["shift_um"]) <= 1.645 * i["sd_um"] for i, _ in v])) for t, v in runs.items()}
    assert applied[0.0] >= 0.1 and held[0.0] < 0.75
    assert applied[R_UM] <= 0.04 and held[R_UM] >= 0.85
    # the frames' share is what the told sd adds, and it is what the frames moved the shift by
    fr = np.array([i["frames_sd_um"] for i, _ in runs[R_UM]])
    shifts = np.array([i["shift_um"] for i, _ in runs[R_UM]])
    assert np.all(fr > 0) and 0.5 < np.sqrt(np.mean(shifts ** 2)) / np.sqrt(np.mean(fr ** 2)) < 2.0


def test_a_real_skew_still_reads_as_evidence_under_frame_errors():
    # W040 = 0.3 wave: every tile skewed the same way (-0.28 µm), which no frame pattern of 0.2 µm makes: the
    # shift applies at full weight and the tiles land on their sharpest positions (mean within 0.05 step).
    runs = _draws(0.3, R_UM)
    assert np.mean([i["weight"] > 0.99 for i, _ in runs]) >= 0.9
    errs = np.array([e for _, e in runs])
    assert np.sqrt(np.mean(errs ** 2)) < 0.05 * STEP
    # its variance for the tiles includes the frames' share (pooled_skew_var_um2)
    info = runs[0][0]
    assert pooled_skew_var_um2(info) > pooled_skew_var_um2(info, frames=False)


def _sml_at_fs(w040, told_um, seed):
    from fieldcal.measure.tiles import TileRules, _analyse
    rng = np.random.default_rng(seed)
    e = rng.normal(0.0, R_UM, 25)
    z, B, offs, zt_bp = _channel(w040, e[:25], np.random.default_rng(seed + 1000))
    _, S, _, _ = _channel(w040, e[:25], np.random.default_rng(seed + 1000), kind="sml")
    cc = {"sml": S, "bandpass": B, "sum": np.full_like(S, 0.5), "sum2": np.full_like(S, 0.5 ** 2 * 1.01),
          "sat": np.zeros_like(S)}
    res = _analyse(cc, z, fs_cyc_per_mm=FS, q=0.05, measure="sml@fs", rules=TileRules(stage_repeatability_um=told_um))
    ok = res["status"] == "ok"
    return res["skew"], float(np.mean(res["z_best_um"][ok] - offs[ok] - zt_bp))


def test_the_sml_at_fs_offset_carries_the_frames_and_keeps_a_real_offset():
    # The SML and the band-pass weigh the frames differently, so one frame pattern moves them apart in every tile.
    # Symmetric curves: the offset and the band-pass skew are seldom applied when the repeatability is told, and
    # what is applied lies within the offset's stated error. W040 = 0.6: the real offset (the SML peaks away
    # from the band-pass's sharpest position) is applied at full weight and the tiles land on the band-pass's
    # sharpest positions.
    sym = [_sml_at_fs(0.0, R_UM, s) for s in range(12)]
    assert np.mean([r["offset_weight"] > 0.5 for r, _ in sym]) <= 0.1
    assert np.mean([r["bp_skew_weight"] > 0.5 for r, _ in sym]) <= 0.1
    assert all(r.get("offset_frames_sd_um", 0.0) > 0 for r, _ in sym)
    assert np.mean([abs(r["offset_weight"] * r["offset_um"]) <= 1.645 * offset_sd_um(r) + 1e-9
                    for r, _ in sym]) >= 0.8
    sa = [_sml_at_fs(0.6, R_UM, s) for s in range(6)]
    assert all(r["offset_weight"] > 0.99 and r["bp_skew_weight"] > 0.99 for r, _ in sa)
    assert math.sqrt(np.mean([e * e for _, e in sa])) < 0.1 * STEP
