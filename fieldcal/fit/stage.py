"""Per-frame stage position errors as nuisance parameters of the surface fit.

Why: every tile's through-focus curve is sampled at the same frames, so a frame taken at ``z_k + e_k`` but
recorded at ``z_k`` moves the best focus of every tile that uses frame k. The tiles' errors are therefore
correlated through the frames: tiles whose curves peak near the same z share them almost fully, tiles far apart
in z share little. A constant "stage sd" over the whole field (the RMS per-tile gain times the repeatability)
ignores both that correlation and the averaging the surface fit does, and on the benchmark lenses it made
stage-dominated bands 2-5x wider than the errors.

Model (docs/fitting.md "Stage errors"): the best focus of tile i is shifted by ``sum_k c_ik e_k`` with

* ``c_ik = -g_i w_ik / |w_i|``, ``w_ik = J_ik^2 / sum_k J_ik^2``: the least-squares shift sensitivity of the
  tile's own measured curve (``J`` = its slope at frame k; a frame on a steep flank moves the peak most, one at
  the top or on the floor hardly), scaled to ``g_i``, the sensitivity norm the measurement's own peak
  estimator reports (``TileTable.stage_gain``; the shape alone when it is absent);
* ``e_k ~ N(0, r^2)`` independent, ``r`` the stage's stated repeatability (``--stage-repeatability-um``).

The frame errors are fitted jointly with the surface (:class:`fieldcal.fit.discrepancy.Discrepancy`: extra
coefficients with prior sd ``r``): what the tiles' residuals tell about them is removed, the rest is
marginalised into the band with its correlation over the field. A common offset of every frame and a scale
error of the stage axis are degenerate with the surface's piston and a scaling of z: the profile is relative to
the stage's own zero and scale (its commanded positions), as a profile is used with the same stage.
"""

from __future__ import annotations

import numpy as np


def _slope_weights(curve: np.ndarray, z_um: np.ndarray) -> np.ndarray | None:
    """``J^2 / sum J^2`` of one measured curve (J = dv/dz by central differences of the 3-point smoothed curve),
    restricted to where the curve stands above its floor; None for a curve with no usable slope."""
    v = np.asarray(curve, dtype=np.float64)
    if v.size < 3 or not np.all(np.isfinite(v)):
        return None
    vs = np.convolve(np.pad(v, 1, mode="edge"), np.ones(3) / 3.0, mode="valid")
    floor, top = float(np.min(vs)), float(np.max(vs))
    if not top > floor:
        return None
    J = np.gradient(vs, z_um)
    # the floor's slope is noise, not signal: only samples in the peak (above a tenth of its height) count
    J = np.where(vs - floor > 0.1 * (top - floor), J, 0.0)
    s = float(np.sum(J * J))
    return J * J / s if s > 0 else None


def stage_sensitivity(table, ok: np.ndarray | None = None) -> np.ndarray | None:
    """Per accepted tile (rows in table order, ``status == "ok"``), the best-focus change per µm of each
    frame's position error (n_ok x n_frames, frames in ``table.z_um`` order); None without per-tile curves.

    Works on whatever curves the measurement produced (``TileTable.curves["sml"]``, any focus measure whose
    best focus moves with its flanks) and on the gain its estimator reports.
    """
    curves = (getattr(table, "curves", None) or {}).get("sml")
    z = np.asarray(getattr(table, "z_um", np.zeros(0)), dtype=np.float64)
    if curves is None or z.size < 3:
        return None
    curves = np.asarray(curves, dtype=np.float64)
    if ok is None:
        ok = np.asarray(table.ok, dtype=bool)
    if curves.ndim != 2 or curves.shape[0] != ok.size or curves.shape[1] != z.size or not np.all(np.diff(z) > 0):
        return None
    gains = getattr(table, "stage_gain", None)
    gains = np.full(ok.size, np.nan) if gains is None else np.asarray(gains, dtype=np.float64)
    rows = np.flatnonzero(ok)
    C = np.zeros((rows.size, z.size))
    for j, t in enumerate(rows):
        w = _slope_weights(curves[t], z)
        if w is None:
            continue
        norm = float(np.sqrt(np.sum(w * w)))
        g = gains[t] if np.isfinite(gains[t]) and gains[t] > 0 else norm
        C[j] = -g * w / norm
    return C if np.any(C) else None


def fit_stage_errors(surf, table, repeatability_um: float) -> dict:
    """Fit the frames' position errors with the surface of ``surf`` (in place) and return the profile's record.

    Without a discrepancy posterior, per-tile curves or a stated repeatability, the band keeps the field-wide
    stage term ``surf.stage_sd_um`` (:func:`fieldcal.fit.tiles.stage_sd_um`) and the record says so.
    """
    d = getattr(surf, "discrepancy", None)
    rec = {"repeatability_um": float(repeatability_um)}
    if repeatability_um <= 0:
        return {**rec, "method": "none (no stated repeatability)"}
    C = stage_sensitivity(table) if d is not None else None
    if C is None or C.shape[0] != d.target.size:
        return {**rec, "method": "field-wide term: RMS per-tile gain x repeatability (no per-tile curves to fit "
                                 "the frames with)"}
    zs = float(surf.z_scale_um)
    d.attach_stage(C, float(repeatability_um) / zs)  # replaces the common-mode term (Discrepancy.attach_stage)
    est, sd = d.stage_errors
    # what the frames still add to the band at the tiles, per channel (µm): the variance with them minus without
    per_channel = {}
    for ci, c in enumerate(d.model.channels):
        m = d.ch_index == ci
        if not m.any():
            continue
        _, v_with = d.predict(d.x_hat[m], d.y_hat[m], ci)
        bare = d.without_nuisances()
        _, v_without = bare.predict(d.x_hat[m], d.y_hat[m], ci)
        per_channel[c] = float(zs * np.sqrt(max(float(np.mean(v_with - v_without)), 0.0)))
    surf.stage_sd_um = per_channel
    return {**rec, "method": "per-frame position errors fitted with the surface (prior sd = the repeatability), "
                             "the rest marginalised into the band (docs/fitting.md 'Stage errors')",
            "n_frames": int(C.shape[1]), "frame_error_um": [round(float(v) * zs, 4) for v in est],
            "frame_error_sd_um": [round(float(v) * zs, 4) for v in sd],
            "band_sd_um": per_channel}
