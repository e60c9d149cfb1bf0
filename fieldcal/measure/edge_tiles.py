"""Slanted-edge tracks through focus → a :class:`~fieldcal.measure.tiles.TileTable` the surface fit accepts.

Calibration on a slanted-edge chart (docs/measurement.md "Calibrating from slanted edges"):

* :func:`chart_kind` looks at one frame (the middle of the scan) and says whether it is a slanted-edge chart:
  enough edges that pass the e-SFR quality rules in every channel.
* :func:`edge_table` takes the e-SFR of every edge through the stack (:func:`fieldcal.measure.measure_mtf`),
  reads each track's MTF at fs, finds its best focus and measured half-widths (:func:`.esfr_focus.analyse_tracks`:
  a channel's tracks together, the asymmetry of spherical aberration pooled over them), and writes one row per
  track and channel in the columns of a texture tile table.

Tangential and sagittal. An edge measures the MTF across it, so a tangential edge gives the tangential focus
and a sagittal one the sagittal focus. A row of the tile table is the *mean* surface with its T and S foci
(``z_tan_um``, ``z_sag_um``): each tangential track is paired with the nearest sagittal track of the same
channel (optimal one-to-one assignment, at most ``pair_px`` apart: two sides of one chart square), and the
pair becomes one row at their midpoint, ``z_best = (z_T + z_S) / 2``, its width the mean of the two tracks'
widths, each freed of its along-edge focus spread and astigmatic blur floor (:func:`track_width_model`,
:func:`pair_width_um`: both tracks measure one defocus δ). An edge near 45 degrees from the
radius (``quality.orientation_clear`` false) sees both foci and its peak is near the mean: its own row, NaN
T/S. Lone T or S tracks are dropped when there are enough pairs (a lone T or S focus is off the mean surface
by half the astigmatism); otherwise kept with NaN T/S.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from .esfr_focus import (TOLERANCE_UNREACHED, analyse_track, analyse_tracks, channel_shape, law_common_mode,
                         pool_frame_term, window_r_of)
from .tiles import TileTable

# A frame is a slanted-edge chart when at least this many detected edges pass the e-SFR quality rules in every
# channel. A 480x270 frame of the default slanted-edge chart has ~160 (150+ ok); the random-texture chart 5
# (none ok), the ChArUco board 14 (none ok).
MIN_CHART_EDGES = 24
# The chart test looks at no more than this many pixels on a side (a crop, then the whole frame shrunk).
CHECK_SIDE_PX = 640
# A track's sd is the defocus-law fit's residual-scaled covariance (esfr_focus.defocus_peak): the MTF(fs) noise
# as the track's own residuals show it. Against the simulator's truth its error / sd has RMS 0.9-1.0 per channel
# (random lens 0, 480x270, 20 µm steps; docs/measurement.md "Calibrating from slanted edges"), so it enters the
# fit unscaled; the fit's error scale and the held-out-tile check learn what is left. The floor below keeps a
# noise-free curve from weighing like a perfect one: a sampled curve's peak carries a shape error of a few
# hundredths of a step (esfr_focus benchmarks)
SIGMA_FLOOR_STEP = 0.05
# Besides "ok", samples flagged only for a blur wider than the region still carry MTF(fs): they are the
# far-defocused ends of a track, which only the curve's tails see.
_BLUR_WIDER = "edge blur wider than the region"


@dataclass(frozen=True)
class ChartKind:
    """What one frame shows: ``kind`` "esfr" (slanted edges) or "focus-measure" (anything else)."""

    kind: str
    edges_found: int
    edges_ok: int
    frame_z_um: float

    def to_dict(self) -> dict:
        return {"kind": self.kind, "edges_found": self.edges_found, "edges_ok": self.edges_ok,
                "frame_z_um": self.frame_z_um, "min_edges": MIN_CHART_EDGES}


def _count_ok_edges(frame: np.ndarray, channels: tuple[str, ...], cfa: str | None) -> tuple[int, int]:
    """(edges found, edges whose e-SFR passes the quality rules in every channel) in one frame.

    The detection and the batched e-SFR of :func:`fieldcal.measure.mtf.measure_frame`, with its options, read
    for their quality flags only: the records it builds (MTF on the stored grid, orientation, positions) are
    not needed to count, and cost a third of a texture frame's check."""
    from .._numeric import channel_mean
    from .esfr import esfr_regions
    from .esfr_detect import find_edges
    from .mtf import _plane_stack

    planes, _ = _plane_stack(frame, channels, cfa)
    cands = find_edges(channel_mean(planes))
    if not cands:
        return 0, 0
    results = esfr_regions([planes[c.roi[0]:c.roi[1], c.roi[2]:c.roi[3], :] for c in cands],
                           vertical=[c.vertical for c in cands], line_init=[c.line_init for c in cands],
                           half_width_px=[c.half_width_px for c in cands],
                           **({"oversample": 8} if cfa is not None else {}))  # as measure_frame
    return len(cands), int(sum(all(q.ok for q in res.quality) for res in results))


def chart_kind(frame: np.ndarray, channels: tuple[str, ...], cfa: str | None = None,
               z_um: float = math.nan, max_side_px: int = CHECK_SIDE_PX) -> ChartKind:
    """Slanted edges or not, from one normalised frame (H x W x C; the e-SFR of each detected edge, all channels).

    The cost is bounded whatever the frame size (edge finding on a fine texture costs ~5 s at 1920x1080):
    first a central crop of at most ``max_side_px`` at full resolution (small chart squares keep their size),
    then, if that is not enough, the whole frame shrunk to ``max_side_px`` on its long side (large squares
    fit in it). A raw mosaic (``cfa``) is checked at full resolution.
    """
    frame = np.asarray(frame, dtype=np.float32)
    if frame.ndim == 2:
        frame = frame[:, :, None]
    h, w = frame.shape[:2]
    if cfa is not None or max(h, w) <= max_side_px:
        found, ok = _count_ok_edges(frame if cfa is None else frame[:, :, 0], channels, cfa)
    else:
        ch, cw = min(h, max_side_px), min(w, max_side_px)
        y0, x0 = (h - ch) // 2, (w - cw) // 2
        found, ok = _count_ok_edges(frame[y0:y0 + ch, x0:x0 + cw], channels, None)
        if ok < MIN_CHART_EDGES:
            import cv2
            f = max(h, w) / float(max_side_px)
            small = cv2.resize(frame, (max(1, round(w / f)), max(1, round(h / f))), interpolation=cv2.INTER_AREA)
            found2, ok2 = _count_ok_edges(small.reshape(small.shape[0], small.shape[1], -1), channels, None)
            if ok2 > ok:
                found, ok = found2, ok2
    kind = "esfr" if ok >= MIN_CHART_EDGES else "focus-measure"
    return ChartKind(kind, found, ok, float(z_um))


def _usable(rec: dict) -> bool:
    q = rec["quality"]
    return bool(q["ok"]) or str(q.get("reason", "")).startswith(_BLUR_WIDER)


def _edge_length_px(qual: dict) -> float:
    """Length of edge one e-SFR binned (px): its scan lines along the edge, ``rows / cos(slant)``."""
    rows, slant = qual.get("rows"), qual.get("slant_deg")
    if not rows or slant is None or not math.isfinite(float(slant)):
        return math.nan
    return float(rows) / math.cos(math.radians(float(slant)))


def _finite_median(values: np.ndarray) -> float:
    """Median of the finite entries; NaN (recorded as null) where there are none, without NumPy's warning: a
    short stack's tracks may all lack a spread or floor (too few frames), and a diagnostic must not warn."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else math.nan


def _median_length_px(recs) -> float:
    v = [x for x in (_edge_length_px(e["quality"]) for e in recs if _usable(e)) if math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def peak_position_px(recs, vals, geometry=None, z_ref_um: float = math.nan, half: float = 0.5):
    """Where a track's best focus was measured, in the reference frame's pixels: the mean position of the
    records that set its peak (MTF(fs) at least ``half`` of the track's highest, weighted by MTF(fs)^2, the
    quantity the peak's law is fitted to), each mapped from its own frame into the reference frame with the
    measured breathing (``geometry``, :class:`fieldcal.measure.geometry.GeometryMeasurements`: ``p_ref = c +
    (p - c - s(z)) / m(z)``).

    Why: a record's position is the midpoint of the scan lines its e-SFR used, and which lines are usable
    changes with the blur, so along one edge track the midpoint slides by up to half the edge's length. The
    peak is the focus *there*, and along a sagittal edge (on the radius) the field's whole gradient lies along
    the edge (0.1-0.5 µm/px radially on the 1920 x 1080 triplet's G): the record nearest ``z_ref`` sat up to 16 px
    from where the peak was read there (p90 4.5 px), and breathing moves a record up to 12 px at the corners. Without ``geometry`` (or when no record has a finite MTF) the record nearest ``z_ref_um``
    is returned (the reference frame's own position, no breathing to undo).
    """
    v = np.array([float(x) for x in vals], dtype=np.float64)
    near = min(recs, key=lambda e: abs(float(e["z_um"]) - z_ref_um))
    good = np.isfinite(v) & (v > 0)
    if geometry is None or not good.any():
        return float(near["x_px"]), float(near["y_px"])
    gz = np.asarray(geometry.z_um, dtype=np.float64)
    ch = str(recs[0]["channel"])
    ch = ch if ch in geometry.channels else geometry.channels[0]
    use = good & (v >= half * v[good].max())
    xs, ys, ws = [], [], []
    for e, val in zip((r for r, u in zip(recs, use) if u), v[use]):
        k = int(np.argmin(np.abs(gz - float(e["z_um"]))))
        xr, yr = geometry.unmap_points(k, ch, float(e["x_px"]), float(e["y_px"]))
        xs.append(float(xr))
        ys.append(float(yr))
        ws.append(val * val)
    w = np.asarray(ws) / np.sum(ws)
    return float(np.dot(w, xs)), float(np.dot(w, ys))


def track_foci(mtf, fs_cy_per_px: float, q: float, z_ref_um: float, *, min_frames: int = 5,
               shapes_out: dict | None = None, fs_cyc_per_um: float = math.nan,
               common_out: dict | None = None, geometry=None) -> dict:
    """Per (track, channel): best focus at fs, its sd, peak MTF, half-widths, orientation and the position
    where the peak was measured in the reference frame (:func:`peak_position_px`; with ``geometry`` None the
    position at the frame nearest ``z_ref_um``).

    Returns columns (dict of arrays): track, channel, x_px, y_px, orientation, z_best_um, z_sigma_um, peak,
    width_um, status, cos2phi (cos 2 phi of the median angle phi between the edge normal and the radius),
    stage_gain (best-focus sd per unit of per-frame stage-position noise), edge_angle_deg (the edge's direction
    from +x, y down: the axial mean of its records') and length_px (the median length of edge the e-SFR binned,
    ``rows / cos(slant)``; NaN when the records do not say). ``common_out`` (a dict) receives each channel's
    field-wide peak error (:func:`.esfr_focus.law_common_mode`), ``shapes_out`` its pooled asymmetry.
    """
    groups: dict[tuple[int, str], list[dict]] = {}
    for e in mtf.edges:
        if "track" in e and e.get("z_um") is not None:
            groups.setdefault((int(e["track"]), str(e["channel"])), []).append(e)
    vals = mtf.mtf_at(fs_cy_per_px)
    index = {id(e): i for i, e in enumerate(mtf.edges)}
    out = {k: [] for k in ("track", "channel", "x_px", "y_px", "orientation", "z_best_um", "z_sigma_um", "peak",
                           "width_um", "status", "cos2phi", "stage_gain", "edge_angle_deg", "length_px")}
    # each channel's tracks together: the asymmetry of spherical aberration is pooled over them
    curves: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}
    for (tr, ch), recs in groups.items():
        use = [e for e in recs if _usable(e) and np.isfinite(vals[index[id(e)]])]
        if len(use) >= min_frames:
            curves[(tr, ch)] = (np.array([float(e["z_um"]) for e in use]),
                                np.array([vals[index[id(e)]] for e in use]))
    from contextlib import ExitStack

    focus, shapes = {}, {}
    chans = sorted({k[1] for k in curves})
    with ExitStack() as scope:
        # the channels' track fits are independent: with enough tracks, all channels but the first run in worker
        # processes (started now: they import the fits' modules while this thread prepares the channels)
        pool = scope.enter_context(_fit_pool(len(chans), len(curves)))
        _channel_fits(curves, groups, chans, q, fs_cy_per_px, fs_cyc_per_um, shapes, focus, common_out, pool)
    for (tr, ch), recs in groups.items():
        xp, yp = peak_position_px(recs, [vals[index[id(e)]] if _usable(e) else math.nan for e in recs],
                                  geometry, z_ref_um)
        orient = [e["orientation"] for e in recs if e["quality"].get("orientation_clear")]
        status, zb, sz, pk, w, gain = "ok", math.nan, math.nan, math.nan, math.nan, math.nan
        if (tr, ch) not in focus:
            status = "few_frames"
        else:
            tk = focus[(tr, ch)]
            if not (tk.ok or tk.reason == TOLERANCE_UNREACHED):  # a peak without a measured width is a row
                status = ("peak_at_edge" if "end of the scan" in tk.reason else
                          tk.reason.split(": ", 1)[1] if tk.reason.startswith("defocus fit: ") else "no_peak")
            else:
                zb, sz, pk, gain = tk.z_best_um, tk.z_sigma_um, tk.peak_mtf, tk.stage_gain
                left, right = tk.tol_left_um, tk.tol_right_um
                if math.isfinite(left) and math.isfinite(right) and left > 0 and right > 0:
                    w = 0.5 * (left + right)
        out["track"].append(tr)
        out["channel"].append(ch)
        out["x_px"].append(xp)
        out["y_px"].append(yp)
        # near 45 deg from the radius (or near the centre) an edge sees both foci: "unclear", a mean-surface row
        out["orientation"].append(max(set(orient), key=orient.count) if orient else "unclear")
        out["z_best_um"].append(zb)
        out["z_sigma_um"].append(sz)
        out["peak"].append(pk)
        out["width_um"].append(w)
        out["status"].append(status)
        out["stage_gain"].append(gain)
        phi = [float(e["quality"]["radial_angle_deg"]) for e in recs
               if e["quality"].get("radial_angle_deg") is not None and math.isfinite(e["quality"]["radial_angle_deg"])]
        out["cos2phi"].append(math.cos(math.radians(2.0 * float(np.median(phi)))) if phi else math.nan)
        ang = np.radians([2.0 * float(e["angle_deg"]) for e in recs
                          if e.get("angle_deg") is not None and math.isfinite(float(e["angle_deg"]))])
        # directions are axial (theta and theta + 180 are one edge): average the doubled angle
        out["edge_angle_deg"].append(0.5 * math.degrees(math.atan2(np.sin(ang).mean(), np.cos(ang).mean()))
                                     if ang.size else math.nan)
        out["length_px"].append(_median_length_px(recs))
    cols = {k: np.asarray(v) for k, v in out.items()}
    if shapes_out is not None:
        shapes_out.update(shapes)
    return cols


#: tracks (all channels) from which the channels' fits run in worker processes: each worker's start-up (~0.5 s CPU
#: of imports, scipy's included) against ~1.3 s of fits per channel of the 1080p triplet's ~1400 tracks
FIT_PROCESS_MIN_TRACKS = 600


def _fit_pool(n_channels: int, n_tracks: int):
    """The track fits' process pool (:func:`fieldcal.measure.esfr_pool.fit_pool`) for all channels but the
    first, or a null context (this thread fits every channel) for a small job or where processes are not
    allowed."""
    import contextlib
    import os

    from . import esfr_pool
    workers = min(n_channels - 1, 2) if (os.cpu_count() or 1) >= 2 else 0
    if workers < 1 or n_tracks < FIT_PROCESS_MIN_TRACKS or not esfr_pool.processes_allowed():
        return contextlib.nullcontext(None)
    return esfr_pool.fit_pool(workers)


def _fit_channel(curves: list, q: float, shape, common: bool):
    """One channel's track fits (:func:`.esfr_focus.analyse_tracks`) and, with ``common``, its field-wide peak
    error (:func:`.esfr_focus.law_common_mode`); runs in this process or in a worker."""
    res, _ = analyse_tracks(curves, q, shape=shape)
    return res, (law_common_mode(curves, res, shape) if common else None)


def _channel_fits(curves, groups, chans, q, fs_cy_per_px, fs_cyc_per_um, shapes, focus, common_out, pool) -> None:
    """Each channel's pooled shape (into ``shapes``), then its tracks' foci (into ``focus``) and field-wide
    error (into ``common_out``): the first channel in this thread, the others in ``pool`` when there is one
    (the results are the same: each channel's fits depend only on its own tracks and shape)."""
    from dataclasses import replace

    from ..optics.defocus import default_wavelength_nm
    for ch in chans:
        shapes[ch] = channel_shape([curves[k] for k in curves if k[1] == ch], q, fs_cyc_per_um=fs_cyc_per_um,
                                   wavelength_um=default_wavelength_nm(ch) * 1e-3,
                                   window_r=window_r_of(window_half_px(
                                       [e for k, recs in groups.items() if k[1] == ch for e in recs]), fs_cy_per_px))
    # W040 is the lens's, shared by its colours (s = 16 pi fs N W040 carries no wavelength): the asymmetry is
    # taken only where every channel shows it. A skew seen in one channel alone is not spherical aberration (on
    # fieldcal's geometric simulator one channel of the triplet showed s = -0.5 +- 0.13, the others 0 +- 0.1)
    if not all(v.selected for v in shapes.values()):
        shapes.update({c: replace(v, selected=False) for c, v in shapes.items()})
    keys = {ch: [k for k in curves if k[1] == ch] for ch in chans}
    jobs = {ch: ([curves[k] for k in keys[ch]], q, shapes[ch], common_out is not None) for ch in chans}
    futures = {ch: pool.submit(_fit_channel, *jobs[ch]) for ch in chans[1:]} if pool is not None else {}
    for ch in chans:
        res, common = futures[ch].result() if ch in futures else _fit_channel(*jobs[ch])
        focus.update(zip(keys[ch], res))
        if common_out is not None:
            common_out[ch] = common


def window_half_px(recs) -> float:
    """The e-SFR window's half-length (px) over edge records: the median usable half-width across the edge
    projected on its normal (``half_width_px cos(slant)``: the ESF's span, over which the core centres its
    Hamming window; :func:`fieldcal.measure.esfr.esfr_regions`). NaN when the records do not say."""
    h = [float(e["quality"]["half_width_px"]) * math.cos(math.radians(float(e["quality"].get("slant_deg") or 0.0)))
         for e in recs if (e.get("quality") or {}).get("half_width_px")]
    return float(np.median(h)) if h else math.nan


def along_edge_spread_um(dzdx_um_per_px, dzdy_um_per_px, edge_angle_deg, length_px):
    """Range of best focus along the length of edge one e-SFR bins (µm): ``|grad z . e| L``.

    An e-SFR averages the edge-spread function over every scan line of its region, so its MTF(fs) through focus
    is the mean of the local curves along the edge: a linear focus gradient along it spreads their foci
    uniformly over this range. A sagittal edge lies along the radius, so a rotationally symmetric field's
    whole gradient is along it; a tangential edge lies across the radius and sees almost none.
    """
    a = np.radians(np.asarray(edge_angle_deg, dtype=np.float64))
    g = np.asarray(dzdx_um_per_px, dtype=np.float64) * np.cos(a) + np.asarray(dzdy_um_per_px, dtype=np.float64) * np.sin(a)
    return np.abs(g) * np.asarray(length_px, dtype=np.float64)


# spread / δ and floor / δ at which the forward model below is tabulated; a value beyond the last valid point
# is clipped there (at 1920x1080 the triplet's sagittal corners reach a spread of ~5 δ, its 45-degree edges a
# floor of ~1.4 δ)
SPREAD_GRID = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.5, 8.0)
FLOOR_GRID = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)


@dataclass(frozen=True)
class TrackWidthModel:
    """How wide :func:`.esfr_focus.analyse_track` reads a track of local δ whose foci are spread along the edge
    (``spread``) or whose blur across the edge never vanishes (``floor``, astigmatism seen off the T/S axes):
    the ratio (width read / δ) against spread / δ and floor / δ, from :func:`track_width_model`. The two are
    applied as a product (each is a few %, their cross term second order)."""

    spread_over_width: np.ndarray
    spread_ratio: np.ndarray
    floor_over_width: np.ndarray
    floor_ratio: np.ndarray

    def ratio_at(self, spread_over_width, floor_over_width=0.0) -> np.ndarray:
        s = np.clip(np.asarray(spread_over_width, dtype=np.float64), 0.0, float(self.spread_over_width[-1]))
        f = np.clip(np.asarray(floor_over_width, dtype=np.float64), 0.0, float(self.floor_over_width[-1]))
        return (np.interp(s, self.spread_over_width, self.spread_ratio)
                * np.interp(f, self.floor_over_width, self.floor_ratio))

    def correct(self, width_um, spread_um=0.0, floor_um=0.0, n_iter: int = 5) -> np.ndarray:
        """δ of the local curves from a width read with ``spread_um`` of foci along the edge and a blur floor
        ``floor_um``: the fixed point of ``δ = width / ratio(spread / δ, floor / δ)`` (the ratio varies slowly:
        a few steps converge). NaN spread or floor (unknown) counts as none."""
        w = np.asarray(width_um, dtype=np.float64)
        sp = np.nan_to_num(np.asarray(spread_um, dtype=np.float64), nan=0.0)
        fl = np.nan_to_num(np.asarray(floor_um, dtype=np.float64), nan=0.0)
        d = w.copy()
        for _ in range(n_iter):
            inv = 1.0 / np.where(d > 0, d, np.inf)
            d = w / self.ratio_at(sp * inv, fl * inv)
        return d


IDENTITY_WIDTHS = TrackWidthModel(np.array([0.0, 1.0]), np.array([1.0, 1.0]), np.array([0.0, 1.0]),
                                  np.array([1.0, 1.0]))


def track_width_model(step_um: float, width_um: float, q: float, spread_grid: tuple[float, ...] = SPREAD_GRID,
                      floor_grid: tuple[float, ...] = FLOOR_GRID) -> TrackWidthModel:
    """Forward model of what widens or narrows an edge track, as the measurement sees it.

    The local through-focus curve is the defocus disc's, MTF(fs, z) = ``|D(x_q e(z) / δ)|``, ``D = 2 J1(x)/x``,
    ``|D(x_q)| = 1 - q`` (the shape :mod:`fieldcal.fit.tolerance` assumes), ``e`` the blur's extent across the
    edge in units of defocus. Two effects of the field, not of δ, change the track:

    * **spread**: the e-SFR averages the curves along the edge, whose foci a focus gradient spreads uniformly
      over ``s δ`` (:func:`along_edge_spread_um`); the mean curve is wider;
    * **floor**: an edge whose normal makes an angle phi with the radius projects the astigmatic (elliptical)
      defocus disc to an extent ``sqrt((z - z*)^2 + f^2)`` with ``f = |sin 2 phi| |T - S| / 2``: the blur across
      it never vanishes, the peak is lower, and the disc's curve falls off it faster (narrower).

    Each curve, sampled at the stack's step, is analysed by the very estimator of the real tracks
    (:func:`.esfr_focus.analyse_track`: a defocus law fitted over the whole peak); its width over the width
    read without either (same sampling: the law's own sampling error cancels) is the ratio. Two sampling
    phases (peak on a sample, half a step off) are averaged.
    """
    from ..optics.defocus import disc_otf, disc_x_at_contrast

    delta = float(width_um)
    step = float(step_um)
    if not (math.isfinite(delta) and delta > 0 and math.isfinite(step) and step > 0):
        return IDENTITY_WIDTHS
    xq = disc_x_at_contrast(1.0 - float(q))
    u = (np.arange(48) + 0.5) / 48 - 0.5

    def read(spread: float, floor: float) -> float:
        half = 0.5 * spread * delta + 6.0 * delta
        out = []
        for phase in (0.0, 0.5):
            z = np.arange(-half, half + step, step) + phase * step
            e = np.hypot(z[:, None] - spread * delta * u[None, :], floor * delta)
            v = np.mean(np.abs(disc_otf(xq * e / delta)), axis=1)
            tk = analyse_track(z, 0.5 * v, q)
            out.append(0.5 * (tk.tol_left_um + tk.tol_right_um) if tk.ok else math.nan)
        return float(np.mean(out))

    w0 = read(0.0, 0.0)
    if not (math.isfinite(w0) and w0 > 0):
        return IDENTITY_WIDTHS

    def table(grid, which):
        g = np.asarray(grid, dtype=np.float64)
        w = np.array([w0 if v == 0 else (read(v, 0.0) if which == "spread" else read(0.0, v)) for v in g])
        good = np.isfinite(w) & (w > 0)
        last = int(np.flatnonzero(~good)[0]) if (~good).any() else g.size  # the valid run from 0
        if last < 2:
            return np.array([0.0, 1.0]), np.array([1.0, 1.0])
        return g[:last], w[:last] / w0

    s, sr = table(spread_grid, "spread")
    f, fr = table(floor_grid, "floor")
    return TrackWidthModel(s, sr, f, fr)


def pair_width_um(w_tan: float, w_sag: float) -> float:
    """The focus tolerance of a T/S pair from its two tracks' widths (each freed of its along-edge spread).

    Defocus blurs an edge at the rate set by the pupil whatever the edge's orientation: astigmatism moves the
    tangential and sagittal foci apart, it does not change how fast each curve falls off its own peak (an
    elliptical defocus disc projects on the normal of a T edge with a half-width set by the T defocus alone).
    So both tracks estimate one δ; the smaller of the two (the rule before session 8) is biased low by 0.56 of a
    track's scatter (the expected minimum of two normal draws). They are averaged where their error is
    symmetric: each width is the defocus law's ``x_q / (pi fs k)`` and the samples fix the peak's curvature
    ``a k^2`` (:func:`fieldcal.fit.tolerance.fit_tolerance`, ``residuals="curvature"``), so the estimate is
    ``mean(w^-2)^(-1/2)``. The plain mean in µm took the skewed tail of one flat track into the pair: on the
    random lenses 4 and 7 of bench_edge_calibration (7-9 frames, step ≈ δ) it read δ 2.7 and 5.0 % wide.
    """
    v = np.array([w_tan, w_sag], dtype=np.float64)
    v = v[np.isfinite(v) & (v > 0)]
    return float(np.mean(v ** -2.0) ** -0.5) if v.size else math.nan


def _gradient(fn, x: float, y: float, h_px: float = 2.0) -> tuple[float, float]:
    """(dz/dx, dz/dy) in µm/px of a smooth surface callable at one point (central differences)."""
    return ((fn(x + h_px, y) - fn(x - h_px, y)) / (2.0 * h_px), (fn(x, y + h_px) - fn(x, y - h_px)) / (2.0 * h_px))


def _ts_from_pair(z_t: float, z_s: float, sd_t: float, sd_s: float, c_t: float, c_s: float):
    """(z_mean, its sd, z_tan, z_sag) from a tangential-ish and a sagittal-ish edge focus at one point.

    An edge whose normal makes an angle phi with the radius is sharpest where the wavefront's curvature along
    its normal vanishes, ``z(phi) = z_mean + (A / 2) cos 2 phi`` (defocus + astigmatism, the ray aberration
    along the normal). Edges are classified T for phi < 30 and S for phi > 60 degrees, so taking them as pure T
    and S would read about 0.7-0.8 of A (measured 0.68 on the wave-optics astigmatic triplet): solve the two
    equations for z_mean and A instead. Without angles (``c`` NaN): phi = 0 and 90.
    """
    c_t = 1.0 if not math.isfinite(c_t) else c_t
    c_s = -1.0 if not math.isfinite(c_s) else c_s
    d = c_t - c_s  # >= 1 for edges classified clearly (cos 60 - cos 120)
    if d < 0.5:
        c_t, c_s, d = 1.0, -1.0, 2.0
    a = 2.0 * (z_t - z_s) / d
    zm = (z_s * c_t - z_t * c_s) / d
    sd = math.hypot(c_t * sd_s, c_s * sd_t) / d
    return zm, sd, zm + 0.5 * a, zm - 0.5 * a


def _pairs(xt, yt, xs, ys, max_px: float) -> list[tuple[int, int]]:
    """Optimal one-to-one T-S pairs within ``max_px`` (Hungarian assignment on distance)."""
    from scipy.optimize import linear_sum_assignment

    if xt.size == 0 or xs.size == 0:
        return []
    d = np.hypot(xt[:, None] - xs[None, :], yt[:, None] - ys[None, :])
    cost = np.where(d <= max_px, d, 1e9)
    ri, ci = linear_sum_assignment(cost)
    return [(int(a), int(b)) for a, b in zip(ri, ci) if cost[a, b] < 1e9]


def _local_surface(x, y, z, image_size_px, degree: int = 4):
    """A least-squares polynomial of ``degree`` in normalised x, y through the tracks' best foci (a callable
    ``(x_px, y_px) -> z_um``), or None with fewer than 3x its terms."""
    w, h = (float(v) for v in image_size_px)
    r = 0.5 * math.hypot(w, h)

    def design(xp, yp):
        u, v = (np.asarray(xp, float) - 0.5 * w) / r, (np.asarray(yp, float) - 0.5 * h) / r
        return np.stack([u ** i * v ** (k - i) for k in range(degree + 1) for i in range(k + 1)], axis=-1)

    n_terms = (degree + 1) * (degree + 2) // 2
    if np.size(z) < 3 * n_terms:
        return None
    coef, *_ = np.linalg.lstsq(design(x, y), np.asarray(z, float), rcond=None)
    return lambda xp, yp: float(design(xp, yp) @ coef)


def along_edge_spreads_um(tf: dict, ok: np.ndarray, channels, image_size_px) -> np.ndarray:
    """Each track's along-edge spread of foci (µm, :func:`along_edge_spread_um`; NaN where unknown). The gradient
    is that of a smooth surface through the channel's tracks of the track's own orientation (a sagittal
    edge's foci along it follow the sagittal surface), or of all its tracks."""
    spread = np.full(tf["width_um"].shape, np.nan)
    x, y, z, orient = tf["x_px"], tf["y_px"], tf["z_best_um"], tf["orientation"]
    for ch in channels:
        m = (tf["channel"] == ch) & ok
        base = _robust_surface(x[m], y[m], z[m], image_size_px)
        surf = {o: _robust_surface(x[m & (orient == o)], y[m & (orient == o)], z[m & (orient == o)], image_size_px)
                for o in ("tangential", "sagittal")}
        for i in np.flatnonzero(m):
            fn = surf.get(str(orient[i])) or base
            if fn is None or not (math.isfinite(tf["edge_angle_deg"][i]) and math.isfinite(tf["length_px"][i])):
                continue
            gx, gy = _gradient(fn, float(x[i]), float(y[i]))
            spread[i] = along_edge_spread_um(gx, gy, tf["edge_angle_deg"][i], tf["length_px"][i])
    return spread


def astigmatic_floor_um(cos2phi, astig_um) -> np.ndarray:
    """The blur floor across an edge at angle phi from the radius, in defocus µm: ``|sin 2 phi| |T - S| / 2``.

    The elliptical defocus disc's semi-axes grow as ``|z - z_T|`` along the radius and ``|z - z_S|`` across
    it; projected on a normal at phi its extent is ``sqrt(c^2 (z - z_T)^2 + s^2 (z - z_S)^2)`` =
    ``sqrt((z - z*)^2 + (c s (z_T - z_S))^2)`` (c, s = cos, sin phi). NaN angle (unknown): none."""
    c2 = np.clip(np.nan_to_num(np.asarray(cos2phi, dtype=np.float64), nan=1.0), -1.0, 1.0)
    return 0.5 * np.sqrt(1.0 - c2 * c2) * np.abs(np.asarray(astig_um, dtype=np.float64))


def _robust_surface(x, y, z, image_size_px, degree: int = 4, clip: float = 3.5, n_iter: int = 3):
    """:func:`_local_surface` refitted without the points beyond ``clip`` robust sds (1.4826 MAD) of it: a track
    that locked onto a false peak is off by hundreds of µm (on the 1920x1080 triplet two such pairs' T - S swung
    a plain quartic of the astigmatism to 20 δ at the corners)."""
    x, y, z = (np.asarray(v, dtype=np.float64) for v in (x, y, z))
    keep = np.isfinite(z)
    fn = None
    for _ in range(n_iter):
        fn = _local_surface(x[keep], y[keep], z[keep], image_size_px, degree)
        if fn is None:
            return None
        r = z - np.array([fn(a, b) for a, b in zip(x, y)])
        sd = 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.isfinite(z) & (np.abs(r) <= clip * max(sd, 1e-9))
        if np.array_equal(new, keep):
            break
        keep = new
    return fn


def edge_window_px(mtf) -> int:
    """The side of the square tile whose window correction equals an edge row's (``TileTable.tile_px``).

    An edge's e-SFR bins every scan line of its region alike, so its MTF(fs) through focus is the mean of the
    local curves *along the edge*: for a symmetric peak its maximum is the mean best focus along the edge,
    ``z(p) + z_ss L^2 / 24`` (L the edge's length in the rows used, ``rows / cos(slant)``; z_ss the curvature
    along it) — across the edge only the blur's own width is seen. A square tile of side s is off by
    ``(z_xx + z_yy) s^2 / 24`` (fit.tiles.tile_average_correction_um). A T/S pair averages two perpendicular
    edges, ``(z_uu + z_vv) L^2 / 48`` = the Laplacian's, and an edge 45 degrees from the radius sees half the
    Laplacian of a rotationally symmetric surface: both are a square of side ``L / sqrt 2``. (The region's
    area, 18 x 32 px at 480x270, had given a 24 px tile: 7x the correction, +0.3 µm on the triplet.)
    """
    lengths = [v for v in (_edge_length_px(e["quality"]) for e in mtf.edges if _usable(e)) if math.isfinite(v)]
    return int(max(1, round(float(np.median(lengths)) / math.sqrt(2.0)))) if lengths else 1


def edge_table(mtf, *, fs_cyc_per_mm: float, q: float, pixel_pitch_um: float, z_um, image_size_px,
               z_ref_um: float, channels: tuple[str, ...], pair_px: float | None = None,
               min_pairs_per_channel: int = 12, geometry=None) -> tuple[TileTable, dict]:
    """A :class:`TileTable` of slanted-edge measurements (one row per T/S pair, or per track) and a summary.

    Parameters
    ----------
    mtf : MtfResult
        :func:`fieldcal.measure.measure_mtf` of the stack (records with ``track`` and ``z_um``).
    fs_cyc_per_mm, q : the calibration's criterion; fs is converted to cycles/px with ``pixel_pitch_um``.
    z_um : the stack's positions (µm); the median step sets the sd floor.
    image_size_px : (W, H).
    z_ref_um : positions are taken in the frame nearest this z (the reference geometry of the table).
    pair_px : largest T-S distance of a pair (default 1.5x the median distance between neighbouring tracks).
    min_pairs_per_channel : fewer pairs than this in a channel and its unpaired tracks are kept too.
    geometry : GeometryMeasurements, optional
        The stack's breathing (magnification, shift vs z about the reference frame): each track's position is
        then where its peak was measured (:func:`peak_position_px`), else its record nearest ``z_ref_um``.

    Returns
    -------
    (TileTable, dict)
        ``measure = "esfr"``; ``tile_px`` the square window equivalent to an edge row's (:func:`edge_window_px`);
        the dict records counts, the sd floor, the window and the pairing distance.
    """
    if not (math.isfinite(pixel_pitch_um) and pixel_pitch_um > 0):
        raise ParameterError(f"pixel pitch {pixel_pitch_um!r} µm", field="pixel_pitch_um",
                             fix="give the sensor's pixel pitch in µm")
    fs_px = float(fs_cyc_per_mm) * float(pixel_pitch_um) / 1000.0
    z = np.sort(np.asarray(z_um, dtype=np.float64))
    step = float(np.median(np.diff(z))) if z.size > 1 else 1.0
    shapes: dict = {}
    common: dict = {}
    tf = track_foci(mtf, fs_px, q, z_ref_um, shapes_out=shapes, fs_cyc_per_um=float(fs_cyc_per_mm) * 1e-3,
                    common_out=common, geometry=geometry)
    sig = np.maximum(np.nan_to_num(tf["z_sigma_um"], nan=0.0), SIGMA_FLOOR_STEP * step)
    ok = tf["status"] == "ok"
    if pair_px is None:
        xy = np.column_stack([tf["x_px"], tf["y_px"]])[ok & (tf["channel"] == tf["channel"][0])] \
            if tf["channel"].size else np.zeros((0, 2))
        if len(xy) >= 2:
            d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
            np.fill_diagonal(d, np.inf)
            pair_px = 1.5 * float(np.median(d.min(axis=1)))
        else:
            pair_px = 0.0
    spread = along_edge_spreads_um(tf, ok, channels, image_size_px)
    w_read = np.asarray(tf["width_um"], dtype=np.float64)
    good_w = ok & np.isfinite(w_read) & (w_read > 0)
    widths_model = track_width_model(step, float(np.median(w_read[good_w])) if good_w.any() else math.nan, q)
    width = w_read.copy()  # each track's δ freed of its along-edge spread and astigmatic floor (below)
    floor = np.full(w_read.shape, np.nan)
    rows = {k: [] for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um", "width_um", "peak", "status",
                            "z_tan_um", "z_sag_um", "stage_gain")}

    def add(ch, x, y, zb, s, w, pk, st, zt=math.nan, zs=math.nan, gain=math.nan):
        for k, v in zip(rows, (ch, x, y, zb, s, w, pk, st, zt, zs, gain)):
            rows[k].append(v)

    summary = {"tracks": {}, "pairs": {}, "unpaired_kept": {}, "status": {}, "ts_transfer": {}}
    for ch in channels:
        m = tf["channel"] == ch
        t = np.flatnonzero(m & ok & (tf["orientation"] == "tangential"))
        s = np.flatnonzero(m & ok & (tf["orientation"] == "sagittal"))
        pairs = _pairs(tf["x_px"][t], tf["y_px"][t], tf["x_px"][s], tf["y_px"][s], pair_px)
        local = _local_surface(tf["x_px"][m & ok], tf["y_px"][m & ok], tf["z_best_um"][m & ok], image_size_px)
        summary["ts_transfer"][ch] = "quartic in x, y of the channel's tracks" if local else "none (too few tracks)"
        pair_rows = []
        for a, b in pairs:
            i, j = t[a], s[b]
            xm, ym = 0.5 * (tf["x_px"][i] + tf["x_px"][j]), 0.5 * (tf["y_px"][i] + tf["y_px"][j])
            zt = zs = math.nan
            zi, zj = tf["z_best_um"][i], tf["z_best_um"][j]
            if local is not None:
                # T and S sit on different sides of a chart square: the field curvature between them (up to
                # ~1 µm/px at the corners) would enter T - S, so each is moved to the midpoint along a smooth
                # surface of all the channel's tracks first
                zi = zi + local(xm, ym) - local(tf["x_px"][i], tf["y_px"][i])
                zj = zj + local(xm, ym) - local(tf["x_px"][j], tf["y_px"][j])
            zb, sb, zt_, zs_ = _ts_from_pair(zi, zj, sig[i], sig[j], tf["cos2phi"][i], tf["cos2phi"][j])
            if local is not None:
                zt, zs = zt_, zs_
            else:  # the mean of two points about the midpoint: the gradient cancels in the plain mean
                zb = 0.5 * (tf["z_best_um"][i] + tf["z_best_um"][j])
            pair_rows.append((i, j, xm, ym, zb, sb, zt, zs))
        # T - S over the field (a smooth surface through the pairs' astigmatism) sets each track's blur floor
        pa = np.array([(r[2], r[3], r[6] - r[7]) for r in pair_rows if math.isfinite(r[6] - r[7])]).reshape(-1, 3)
        astig = (_robust_surface(pa[:, 0], pa[:, 1], pa[:, 2], image_size_px)
                 or _robust_surface(pa[:, 0], pa[:, 1], pa[:, 2], image_size_px, degree=2))
        for i in np.flatnonzero(m & ok):
            if astig is not None:
                floor[i] = float(astigmatic_floor_um(tf["cos2phi"][i], astig(tf["x_px"][i], tf["y_px"][i])))
            if math.isfinite(w_read[i]):
                width[i] = float(widths_model.correct(w_read[i], spread[i], floor[i]))
        for i, j, xm, ym, zb, sb, zt, zs in pair_rows:
            add(ch, xm, ym, zb, sb, pair_width_um(width[i], width[j]),
                0.5 * (tf["peak"][i] + tf["peak"][j]), "ok", zt, zs,
                # both tracks saw the same frames: their stage errors add (an upper bound on the mean's)
                0.5 * (tf["stage_gain"][i] + tf["stage_gain"][j]))
        keep_lone = len(pairs) < min_pairs_per_channel
        used = {int(t[a]) for a, _ in pairs} | {int(s[b]) for _, b in pairs}
        n_lone = 0
        for i in np.flatnonzero(m):
            if int(i) in used:
                continue
            st = str(tf["status"][i])
            if st == "ok" and not keep_lone and tf["orientation"][i] != "unclear":
                st = "unpaired"
            n_lone += st == "ok"
            add(ch, tf["x_px"][i], tf["y_px"][i], tf["z_best_um"][i] if st == "ok" else math.nan,
                sig[i] if st == "ok" else math.nan, width[i], tf["peak"][i], st,
                gain=tf["stage_gain"][i] if st == "ok" else math.nan)
        summary["tracks"][ch] = int(m.sum())
        summary["pairs"][ch] = len(pairs)
        summary["unpaired_kept"][ch] = n_lone
    st, n = np.unique(tf["status"], return_counts=True)
    summary["status"] = {str(a): int(b) for a, b in zip(st, n)}
    summary.update({"fs_cy_per_px": fs_px, "sigma_floor_um": SIGMA_FLOOR_STEP * step,
                    "pair_px": float(pair_px)})
    # what each orientation's widths were freed of: median spread / width, floor / width, width read / δ
    summary["track_widths"] = {
        str(o): {"spread_over_width": _finite_median(spread[sel] / w_read[sel]),
                 "floor_over_width": _finite_median(floor[sel] / w_read[sel]),
                 "width_ratio": _finite_median(w_read[sel] / width[sel])}
        for o in ("tangential", "sagittal", "unclear")
        for sel in [good_w & (tf["orientation"] == o)] if sel.any()}
    summary["track_widths"]["model"] = {k: getattr(widths_model, k).tolist() for k in (
        "spread_over_width", "spread_ratio", "floor_over_width", "floor_ratio")}
    table_tile_px = edge_window_px(mtf)
    summary["window_px"] = table_tile_px
    # the spherical-aberration asymmetry of each channel's MTF(fs) curves, pooled over its tracks
    summary["sa_shape"] = {str(c): v.to_dict() for c, v in shapes.items()}
    # the error every peak of a channel shares (its law's), measured on its tracks: the band's field-wide term
    # (calibration.pipeline: Discrepancy.set_common_mode)
    summary["common_mode"] = {str(c): v.to_dict() for c, v in pool_frame_term(common).items()}
    cols = {k: np.asarray(v, dtype=np.float64) if k not in ("channel", "status") else np.asarray(v, dtype=str)
            for k, v in rows.items()}
    # stage_gain is a column: the band's stage-repeatability term (fit.tiles.stage_sd_um) reads it
    table = TileTable(**cols, z_um=z, tile_px=table_tile_px, fs_cyc_per_mm=float(fs_cyc_per_mm), q=float(q),
                      measure="esfr", image_size_px=tuple(int(v) for v in image_size_px),
                      pixel_pitch_um=float(pixel_pitch_um))
    return table, summary
