"""The fitted best-focus surface against the tiles the fit could not use (docs/fitting.md "Bracket check").

A tile whose through-focus curve has one clear maximum but does not fall to half its height on both sides inside
the scan is rejected (``peak_at_edge``, ``peak_outside_range``: no extrapolated peak is fitted), yet its curve
still *brackets* its best focus: a unimodal curve sampled at z_0 < ... < z_n-1 with its sampled maximum at z_k
peaks between z_k-1 and z_k+1 (beyond z_1 or z_n-2 when k is an end). Where the accepted tiles leave a part of
the field unmeasured (a ChArUco board's flat squares, a scan that ends close to the sharpest zone), the surface
is extrapolated there; the rejected tiles' brackets show whether the extrapolation is physically possible.
Noise widens a bracket: every sample within 3 noise sd (MAD of second differences) of the maximum may be it, so
the bracket runs from the step below the first such sample to the step above the last.

A surface whose 90 % band misses many brackets, by more than the accepted tiles' own best foci miss theirs
(:func:`sampling_margin_um`: an asymmetric curve's best focus is not its maximum), is wrong where it was not
measured, so the calibration refuses it.

Where the brackets allow the surface but the optical centre -- the *calibrated focus*, the field's sharpest
point on a rotationally symmetric lens -- is far from every fitted tile, the surface there is an extrapolation
and the calibration says so (:func:`centre_support`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldcal.errors import StackError
from fieldcal.measure.throughfocus import noise_sigma

BRACKETED = ("peak_at_edge", "peak_outside_range")
# A few contradicted tiles are what noise and an occasional two-peaked curve give; a tenth of the bracketed
# tiles is a systematic contradiction (the surface's shape is wrong there), not scatter.
MAX_CONTRADICTED_FRACTION = 0.1
MIN_CONTRADICTED = 3
#: samples this many noise sd (throughfocus.noise_sigma) below a curve's maximum could still be its maximum
NOISE_SIGMAS = 3.0


@dataclass(frozen=True)
class BracketCheck:
    """Bracketed tiles the surface contradicts; ``worst`` describes the largest miss (or None)."""

    n_bracketed: int
    n_contradicted: int
    worst: dict | None
    margin_um: float = 0.0   # the accepted tiles' largest best focus outside their own bracket

    @property
    def failed(self) -> bool:
        return (self.n_contradicted >= MIN_CONTRADICTED
                and self.n_contradicted > MAX_CONTRADICTED_FRACTION * self.n_bracketed)

    def to_dict(self) -> dict:
        return {"n_bracketed": self.n_bracketed, "n_contradicted": self.n_contradicted, "worst": self.worst,
                "margin_um": self.margin_um, "failed": self.failed}


def curve_brackets(z_um, curves, status, statuses=BRACKETED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(index, lo_um, hi_um): the best-focus interval each rejected-but-unimodal tile's curve brackets.

    ``curves`` has one row per tile in ``z_um``'s order (any order of z); lo/hi are -inf/+inf beyond an end.
    """
    z = np.asarray(z_um, dtype=np.float64)
    st = np.asarray(status).astype(str)
    idx = np.flatnonzero(np.isin(st, statuses))
    if curves is None or z.size < 3 or idx.size == 0:
        return idx[:0], np.zeros(0), np.zeros(0)
    order = np.argsort(z)
    zs = np.concatenate([[-np.inf], z[order], [np.inf]])
    v = np.asarray(curves, dtype=np.float64)[idx][:, order]
    good = np.all(np.isfinite(v), axis=1)
    idx, v = idx[good], v[good]
    # every sample within NOISE_SIGMAS of the maximum may be the true maximum (a flat-topped curve has several)
    sig = np.array([noise_sigma(r) for r in v])
    near = v >= (v.max(axis=1) - NOISE_SIGMAS * sig)[:, None]
    first = np.argmax(near, axis=1) + 1                                # indices into the padded grid
    last = near.shape[1] - np.argmax(near[:, ::-1], axis=1)
    return idx, zs[first - 1], zs[last + 1]


def check_brackets(profile, table) -> BracketCheck:
    """Compare ``profile``'s best focus (and its 90 % band) with the brackets of ``table``'s rejected tiles."""
    z = np.asarray(table.z_um, dtype=np.float64)
    all_curves = getattr(table, "curves", None) or {}
    curves = all_curves.get(getattr(table, "measure", "sml"), all_curves.get("sml"))
    idx, lo, hi = curve_brackets(z, curves, table.status)
    if idx.size == 0:
        return BracketCheck(0, 0, None)
    x = np.asarray(table.x_px, dtype=np.float64)[idx]
    y = np.asarray(table.y_px, dtype=np.float64)[idx]
    ch = np.asarray(table.channel).astype(str)[idx]
    pred = np.full(idx.size, np.nan)
    half = np.full(idx.size, np.nan)
    for c in np.unique(ch):
        m = ch == c
        if c not in profile.channels:
            continue
        pred[m] = profile.best_focus_um(x[m], y[m], c)
        a, b = profile.best_focus_interval_um(x[m], y[m], c, level=0.9)
        half[m] = 0.5 * (np.asarray(b) - np.asarray(a))
    miss = np.maximum(lo - pred, pred - hi)           # > 0 outside the bracket
    margin = sampling_margin_um(z, curves, table)
    bad = np.isfinite(miss) & (miss > margin + np.nan_to_num(half, nan=np.inf))
    worst = None
    if bad.any():
        j = int(np.argmax(np.where(bad, miss, -np.inf)))
        worst = {"x_px": float(x[j]), "y_px": float(y[j]), "channel": str(ch[j]), "surface_um": float(pred[j]),
                 "bracket_um": [float(lo[j]), float(hi[j])], "band_half_um": float(half[j])}
    return BracketCheck(int(idx.size), int(bad.sum()), worst, margin)


def sampling_margin_um(z_um, curves, table) -> float:
    """How far the fitted tiles' own best foci lie outside their curves' brackets (the largest, µm; 0 if none).

    The bracket locates the curve's maximum; the best focus is the fitted centre moved by the skew correction
    (throughfocus.py), which on an asymmetric curve (spherical aberration) lies up to a step or more from it.
    The accepted tiles measure that gap on this stack, so the check allows it instead of assuming it away."""
    idx, lo, hi = curve_brackets(z_um, curves, table.status, statuses=("ok",))
    if idx.size == 0:
        return 0.0
    zb = np.asarray(table.z_best_um, dtype=np.float64)[idx]
    m = np.maximum(lo - zb, zb - hi)
    m = m[np.isfinite(m)]
    return float(max(0.0, m.max())) if m.size else 0.0


def refuse_contradicted_surface(check: BracketCheck, stack_path, z_range_um) -> None:
    """Raise a :class:`StackError` naming the stack, where the surface is wrong, and what to change."""
    if not check.failed:
        return
    w = check.worst
    lo, hi = z_range_um
    where = (f"e.g. {w['channel']} at ({w['x_px']:.0f}, {w['y_px']:.0f}) px the curve peaks between "
             f"{w['bracket_um'][0]:g} and {w['bracket_um'][1]:g} µm but the surface gives {w['surface_um']:.1f} "
             f"± {w['band_half_um']:.1f} µm")
    raise StackError(
        f"the best-focus surface is extrapolated where no tile was fitted and contradicts {check.n_contradicted} of "
        f"{check.n_bracketed} rejected tiles whose through-focus curves bracket their best focus ({where}); the "
        f"accepted tiles do not constrain the surface there", path=stack_path,
        fix=f"scan further past the sharpest zone (the scan is {lo:g}..{hi:g} µm; each tile's curve must fall to "
            f"half its height on both sides inside the scan) and/or in finer steps; a ChArUco board's flat squares "
            f"and straight edges give few, broad curves: calibrate the surface on a random-texture or "
            f"slanted-edge chart (fieldcal targets) and use the board for geometry")


def centre_support(profile, table, channel: str) -> dict:
    """Distance (px, and in tile sizes) from the optical centre to the nearest fitted tile of ``channel``, with
    a warning when it exceeds two tile sizes: the calibrated focus is then extrapolated from the tiles around
    it (the usual cause: a chart without texture at the centre, or curves there that the scan does not close)."""
    cx, cy = (float(v) for v in profile.optical_centre_px())
    ok = np.asarray(table.ok, bool) & (np.asarray(table.channel).astype(str) == channel)
    tile = float(table.tile_px)
    if not ok.any():
        return {"channel": channel, "nearest_tile_px": None, "warning": None}
    d = float(np.min(np.hypot(np.asarray(table.x_px, float)[ok] - cx, np.asarray(table.y_px, float)[ok] - cy)))
    out = {"channel": channel, "nearest_tile_px": round(d, 1), "tile_px": tile, "warning": None}
    if d > 2.0 * tile:
        z = float(np.ravel(profile.best_focus_um(cx, cy, channel))[0])
        lo, hi = (float(v) for v in np.ravel(profile.best_focus_interval_um(cx, cy, channel, level=0.9)))
        out["warning"] = (f"the calibrated focus ({channel} at the optical centre ({cx:.0f}, {cy:.0f}) px: {z:.1f} µm, "
                          f"90 % band {lo:.1f}..{hi:.1f} µm) is extrapolated: no fitted tile within {d:.0f} px "
                          f"({d / tile:.1f} tiles) of it. Calibrate the surface on a chart with texture at the "
                          f"centre (random texture or slanted edges) over a scan that passes best focus there with "
                          f"margin")
    return out
