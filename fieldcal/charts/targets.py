"""Calibration charts: random texture (focus), ChArUco (geometry) and slanted edges (MTF).

Every chart is a pure function of its size in pixels (and a seed), returning a float32 ``H x W`` image in
[0, 1]. The simulator renders these as scenes; :func:`write_targets` writes the same images as printable
files at a stated physical size. Pixel coordinates follow DESIGN.md: origin at the centre of the top-left
pixel, x right, y down.

* ``texture`` — dead leaves (Lee, Mumford & Huang 2001; Cao, Guichard & Hornung 2010, the basis of
  ISO 19567-2): occluding discs with radii drawn from ``p(r) ~ r**-3``. The model is scale invariant, so its
  power spectrum falls as ``1/f**2`` from ``1/r_max`` up to the chart's Nyquist frequency, and it has sharp
  edges in every direction: a focus measure finds energy at whichever frequency it looks.
* ``charuco`` — an OpenCV ChArUco board; :class:`CharucoSpec` maps each corner id to its pixel and physical
  position, :func:`detect_charuco` finds corners in a frame.
* ``slanted-edge`` — a grid of dark squares rotated by ~5 degrees (ISO 12233 e-SFR style, ~4:1 contrast,
  never clipped); :class:`SlantedEdgeSpec` lists every edge with its angle and a region of interest.
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes
from fieldcal.errors import FieldcalError, ParameterError
from fieldcal.progress import progress

KINDS = ("texture", "charuco", "slanted-edge")
TARGETS_FORMAT = documents.format_id("targets")
MM_PER_INCH = 25.4

# Sub-pixel precision of OpenCV's drawing functions: coordinates are fixed point with 4 fractional bits.
_SHIFT_BITS = 4
_SHIFT = 1 << _SHIFT_BITS

# Limits for printable charts: below 50 dpi nothing useful prints; above 1200 dpi no printer resolves it.
DPI_MIN, DPI_MAX = 50.0, 1200.0
MAX_CHART_PIXELS = 120_000_000  # ~ A2 at 600 dpi: keeps one uint8 chart (plus float32 copy) in memory


def _check_size(width_px: int, height_px: int, min_px: int = 8) -> tuple[int, int]:
    try:
        w, h = int(width_px), int(height_px)
    except (TypeError, ValueError):
        raise ParameterError(f"chart size must be integers, got {width_px!r} x {height_px!r}",
                             field="width_px/height_px", fix="pass whole numbers of pixels") from None
    if w != width_px or h != height_px or w < min_px or h < min_px:
        raise ParameterError(f"chart size {width_px} x {height_px} px is not usable",
                             field="width_px/height_px", fix=f"use whole numbers >= {min_px}")
    if w * h > MAX_CHART_PIXELS:
        raise ParameterError(f"chart of {w} x {h} px is too large ({w * h / 1e6:.0f} MP)",
                             field="width_px/height_px",
                             fix=f"stay below {MAX_CHART_PIXELS / 1e6:.0f} MP (lower the dpi or the size)")
    return w, h


# ----------------------------------------------------------------------------------------- texture
@dataclass(frozen=True)
class TextureParams:
    """Dead-leaves parameters (all lengths in chart pixels)."""

    r_min_px: float = 0.5
    r_max_px: float | None = None  # default: 10 % of the short side
    grey_min: float = 0.1
    grey_max: float = 0.9
    coverage: float = 5.0  # mean number of discs over a pixel: uncovered fraction exp(-coverage)


def random_texture(width_px: int, height_px: int, seed: int = 0, *, r_min_px: float = 0.5,
                   r_max_px: float | None = None, grey_min: float = 0.1, grey_max: float = 0.9,
                   coverage: float = 5.0, quiet: bool = True) -> np.ndarray:
    """Dead-leaves texture: scale-invariant, ``1/f**2`` power up to Nyquist, sharp edges, mean ~0.5.

    Parameters
    ----------
    width_px, height_px : int
        Image size.
    seed : int
        The image is a deterministic function of the seed and the other arguments.
    r_min_px, r_max_px : float
        Disc radius range in pixels; ``r_max_px`` defaults to 10 % of the short side. Radii follow
        ``p(r) ~ r**-3``, the scale-invariant law. ``r_min_px`` below one pixel keeps the ``1/f**2``
        spectrum up to the Nyquist frequency (sub-pixel discs are drawn antialiased).
    grey_min, grey_max : float
        Disc grey levels are uniform in this range (defaults give mean 0.5 and no clipping).
    coverage : float
        Mean number of discs drawn over each pixel; more removes the last uncovered pixels.
    quiet : bool
        Hide the progress bar (big printable charts draw millions of discs).

    Returns
    -------
    numpy.ndarray
        float32 ``H x W`` in [grey_min, grey_max] (within 1/255 from 8-bit antialiased drawing).
    """
    w, h = _check_size(width_px, height_px)
    if not (0.0 <= grey_min < grey_max <= 1.0):
        raise ParameterError(f"grey range [{grey_min}, {grey_max}] is not inside [0, 1]",
                             field="grey_min/grey_max", fix="use 0 <= grey_min < grey_max <= 1")
    r_max = 0.1 * min(w, h) if r_max_px is None else float(r_max_px)
    if not (0.1 <= r_min_px < r_max) or not math.isfinite(r_max):
        raise ParameterError(f"disc radius range [{r_min_px}, {r_max}] px is not usable",
                             field="r_min_px/r_max_px", fix="use 0.1 <= r_min_px < r_max_px")
    if not (0.5 <= coverage <= 20.0):
        raise ParameterError(f"coverage {coverage} out of range", field="coverage", fix="use 1..20 (default 5)")
    rng = np.random.default_rng(seed)
    margin = r_max  # centres beyond the border so the edges are covered like the middle
    area = (w + 2 * margin) * (h + 2 * margin)
    a, b = r_min_px ** -2, r_max ** -2
    mean_r2 = math.log(r_max / r_min_px) / ((a - b) / 2.0)  # E[r^2] for p(r) ~ r^-3 on [r_min, r_max]
    n = int(math.ceil(coverage * area / (math.pi * mean_r2)))
    # Inverse CDF of p(r) ~ r^-3: r^-2 is uniform between r_max^-2 and r_min^-2.
    r = (a - rng.random(n) * (a - b)) ** -0.5
    x = rng.uniform(-margin, w - 1 + margin, n)
    y = rng.uniform(-margin, h - 1 + margin, n)
    g = rng.uniform(grey_min, grey_max, n)
    # Drawn back to front (painter's algorithm): the visible discs are the last ones, as in the model.
    xs = np.round(x * _SHIFT).astype(np.int64).tolist()
    ys = np.round(y * _SHIFT).astype(np.int64).tolist()
    rs = np.maximum(np.round(r * _SHIFT), 1).astype(np.int64).tolist()
    gs = np.round(g * 255.0).astype(np.int64).tolist()
    img = np.full((h, w), int(round(127.5 * (grey_min + grey_max))), np.uint8)
    circle, aa = cv2.circle, cv2.LINE_AA
    batch = 200_000
    for start in progress(range(0, n, batch), total=(n + batch - 1) // batch, desc="dead leaves",
                          quiet=quiet, unit="batch"):
        for k in range(start, min(n, start + batch)):
            circle(img, (xs[k], ys[k]), rs[k], gs[k], -1, aa, _SHIFT_BITS)
    return img.astype(np.float32) / np.float32(255.0)


# ----------------------------------------------------------------------------------------- ChArUco
_ARUCO_DICTS = ("DICT_5X5_250", "DICT_5X5_1000")


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board placed in a chart image.

    ``squares_x`` x ``squares_y`` chessboard squares of ``square_px`` pixels; ArUco markers of
    ``marker_px`` pixels in the white squares; the board's top-left outer corner sits at pixel edge
    ``(origin_x_px, origin_y_px)`` (i.e. at ``origin - 0.5`` in pixel-centre coordinates).
    ``square_mm`` is the printed square size (None for a chart that only exists in pixels).
    """

    squares_x: int
    squares_y: int
    square_px: int
    marker_px: int
    dictionary: str
    origin_x_px: int
    origin_y_px: int
    width_px: int
    height_px: int
    square_mm: float | None = None

    @property
    def marker_mm(self) -> float | None:
        return None if self.square_mm is None else self.square_mm * self.marker_px / self.square_px

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def board(self):
        """The OpenCV board (lengths in pixels of the chart image)."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), float(self.square_px),
                                      float(self.marker_px), d)

    def _corner_board(self, ids) -> np.ndarray:
        """Corner positions on the board (x right, y down) in units of squares, from the board's definition."""
        obj = np.asarray(self.board().getChessboardCorners(), dtype=np.float64)[:, :2] / self.square_px
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= len(obj)):
            raise ParameterError(f"corner id out of range 0..{len(obj) - 1}", field="ids",
                                 fix="pass ids returned by detect_charuco for this board")
        return obj[ids]

    def corner_px(self, ids) -> np.ndarray:
        """N x 2 pixel coordinates (pixel-centre origin) of corners in the chart image."""
        sq = self._corner_board(ids)
        return np.column_stack([self.origin_x_px - 0.5 + sq[:, 0] * self.square_px,
                                self.origin_y_px - 0.5 + sq[:, 1] * self.square_px])

    def corner_mm(self, ids) -> np.ndarray:
        """N x 2 physical positions (mm from the board's top-left corner, x right, y down) of corners."""
        if self.square_mm is None:
            raise ParameterError("this board has no physical size", field="square_mm",
                                 fix="make the board with write_targets/charuco_spec(..., dpi=) to know its mm")
        return self._corner_board(ids) * self.square_mm

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: str | Path | None = None) -> "CharucoSpec":
        """Rebuild a board from :meth:`to_dict` (e.g. the ``params`` of a ``targets.json`` entry)."""
        names = [f for f in cls.__dataclass_fields__]
        try:
            kw = {k: d[k] for k in names if k != "square_mm"}
            kw = {k: (str(v) if k == "dictionary" else int(v)) for k, v in kw.items()}
            sq_mm = d.get("square_mm")
            kw["square_mm"] = None if sq_mm is None else float(sq_mm)
        except (KeyError, TypeError, ValueError) as e:
            raise ParameterError(f"not a ChArUco board description ({e!r})", path=path, field="params",
                                 fix="use the params of a charuco entry in targets.json") from None
        if kw["dictionary"] not in _ARUCO_DICTS:
            raise ParameterError(f"unsupported dictionary {kw['dictionary']!r}", path=path, field="dictionary",
                                 fix=f"use one of {', '.join(_ARUCO_DICTS)}")
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["marker_mm"] = self.marker_mm
        d["corner_id_order"] = "row-major over interior corners, id = row * (squares_x - 1) + column"
        return d


#: the keys of a stack's ``chart`` record for a ChArUco board (stack.json, docs/formats.md)
CHARUCO_RECORD_KEYS = ("kind", "dictionary", "squares_x", "squares_y", "square_mm", "marker_mm")
# a recorded board's OpenCV geometry in these units per mm: only the marker/square ratio matters to the detector
_RECORD_PX_PER_SQUARE = 1000


def charuco_record(spec: CharucoSpec, square_mm: float | None = None) -> dict[str, Any]:
    """The ``chart`` record of a stack showing the board ``spec`` (as targets.json describes it).

    ``square_mm``: the printed square (default ``spec.square_mm``; None when the board has no physical size).
    """
    sq = spec.square_mm if square_mm is None else float(square_mm)
    return {"kind": "charuco", "dictionary": spec.dictionary, "squares_x": int(spec.squares_x),
            "squares_y": int(spec.squares_y), "square_mm": sq,
            "marker_mm": None if sq is None else sq * spec.marker_px / spec.square_px,
            "marker_ratio": spec.marker_px / spec.square_px}


def board_from_record(chart: dict[str, Any], width_px: int, height_px: int,
                      path: str | Path | None = None) -> CharucoSpec:
    """A :class:`CharucoSpec` that detects the board a stack's ``chart`` record describes in W x H frames.

    Only the dictionary, the square counts and the marker-to-square ratio reach OpenCV's detector; the board's
    placement in the frame is unknown (``origin`` 0) and found by detection.
    """
    try:
        ratio = chart.get("marker_ratio")
        if ratio is None:
            ratio = float(chart["marker_mm"]) / float(chart["square_mm"])
        sq = _RECORD_PX_PER_SQUARE
        spec = {"squares_x": int(chart["squares_x"]), "squares_y": int(chart["squares_y"]), "square_px": sq,
                "marker_px": int(round(float(ratio) * sq)), "dictionary": str(chart["dictionary"]),
                "origin_x_px": 0, "origin_y_px": 0, "width_px": int(width_px), "height_px": int(height_px),
                "square_mm": chart.get("square_mm")}
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as e:
        raise ParameterError(f"the chart record is not a ChArUco board ({e!r})", path=path, field="chart",
                             fix="give kind, dictionary, squares_x, squares_y, square_mm and marker_mm (as "
                                 "targets.json's charuco entry)") from None
    if not (0.1 <= spec["marker_px"] / sq <= 0.95) or min(spec["squares_x"], spec["squares_y"]) < 2:
        raise ParameterError("the chart record's board is implausible (marker/square ratio or square counts)",
                             path=path, field="chart", fix="copy the charuco entry of targets.json")
    return CharucoSpec.from_dict(spec, path)


def chart_record_from_targets(path: str | Path) -> dict[str, Any]:
    """The ``chart`` record of the (first) ChArUco board in a ``targets.json`` (``fieldcal targets``), or of a
    JSON file holding a record itself."""
    doc = documents.read_json(path, not_found="chart description not found",
                              not_found_fix="give the targets.json written by `fieldcal targets`")
    if isinstance(doc, dict) and doc.get("format") == TARGETS_FORMAT:
        for e in doc.get("charts", []):
            if isinstance(e, dict) and e.get("kind") == "charuco":
                return charuco_record(CharucoSpec.from_dict(e.get("params") or {}, path))
        raise ParameterError("targets.json describes no ChArUco board", path=path, field="charts",
                             fix="write one with `fieldcal targets OUT --kind charuco`")
    if isinstance(doc, dict) and doc.get("kind") == "charuco":
        board_from_record(doc, 1, 1, path)  # validates
        return {k: doc.get(k) for k in CHARUCO_RECORD_KEYS if k in doc} | (
            {"marker_ratio": doc["marker_ratio"]} if "marker_ratio" in doc else {})
    raise ParameterError("not a chart description", path=path, field="chart",
                         fix="give targets.json from `fieldcal targets`, or a JSON record with kind \"charuco\"")


def charuco_spec(width_px: int, height_px: int, *, squares_short: int | None = None,
                 marker_ratio: float = 0.7, dpi: float | None = None) -> CharucoSpec:
    """Lay out a ChArUco board centred in a ``width_px x height_px`` chart.

    Parameters
    ----------
    squares_short : int, optional
        Squares along the short side (default: one per 32 px, 3 to 10). At least half a square of white
        margin is kept all round.
    marker_ratio : float
        Marker size as a fraction of the square.
    dpi : float, optional
        Print resolution; sets ``square_mm``.
    """
    w, h = _check_size(width_px, height_px, min_px=80)
    short = min(w, h)
    n_short = int(np.clip(short // 32, 3, 10)) if squares_short is None else int(squares_short)
    if n_short < 3:
        raise ParameterError(f"{n_short} squares is too few", field="squares_short", fix="use at least 3")
    if not (0.3 <= marker_ratio <= 0.9):
        raise ParameterError(f"marker ratio {marker_ratio} out of range", field="marker_ratio", fix="use 0.3..0.9")
    square = int(short // (n_short + 1))  # +1: half a square of quiet margin on each side
    if square < 20:
        raise ParameterError(f"squares of {square} px are too small to detect", field="squares_short",
                             fix="use fewer squares or a larger chart (squares need >= 20 px: >= 80 px charts)")
    n_long = int((max(w, h) - square) // square)
    sx, sy = (n_long, n_short) if w >= h else (n_short, n_long)
    # The dictionary must hold one marker per white square.
    n_markers = (sx * sy) // 2
    dictionary = _ARUCO_DICTS[0] if n_markers <= 250 else _ARUCO_DICTS[1]
    if n_markers > 1000:
        raise ParameterError(f"a board of {sx} x {sy} squares needs {n_markers} markers (max 1000)",
                             field="squares_short", fix="use fewer squares")
    # Small markers need whole pixels per bit (5x5 data + 1-bit border = 7 cells) to decode reliably.
    marker = int(round(marker_ratio * square))
    if square < 70:
        marker = 7 * max(2, int(marker_ratio * square) // 7)
    # An odd square-minus-marker gap puts the marker half a pixel off-centre, which biases the sub-pixel
    # corners by ~0.2 px: make the gap even (shrink the square for small boards, the marker for big ones).
    if (square - marker) % 2:
        if square < 70:
            square -= 1
        else:
            marker -= 1
    return CharucoSpec(squares_x=sx, squares_y=sy, square_px=square, marker_px=marker, dictionary=dictionary,
                       origin_x_px=(w - sx * square) // 2, origin_y_px=(h - sy * square) // 2,
                       width_px=w, height_px=h,
                       square_mm=None if dpi is None else square * MM_PER_INCH / float(dpi))


def charuco_image(spec: CharucoSpec) -> np.ndarray:
    """Render the board of ``spec`` (white surround) as float32 in [0, 1]."""
    bw, bh = spec.squares_x * spec.square_px, spec.squares_y * spec.square_px
    board_img = spec.board().generateImage((bw, bh), marginSize=0, borderBits=1)
    img = np.full((spec.height_px, spec.width_px), 255, np.uint8)
    img[spec.origin_y_px:spec.origin_y_px + bh, spec.origin_x_px:spec.origin_x_px + bw] = board_img
    return img.astype(np.float32) / np.float32(255.0)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """Any grey or colour frame (uint8/uint16/float) to an 8-bit grey image stretched to its own range."""
    a = np.asarray(image)
    if a.ndim == 3:
        a = a.astype(np.float32).mean(axis=2) if a.shape[2] > 1 else a[:, :, 0]
    if a.ndim != 2:
        raise ParameterError(f"expected an H x W or H x W x C image, got shape {a.shape}", field="image",
                             fix="pass one frame")
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise ParameterError("image contains NaN or Inf", field="image", fix="pass finite pixel values")
    lo, hi = np.percentile(a, [0.5, 99.5])
    span = hi - lo
    if span <= 0:
        return np.zeros(a.shape, np.uint8)
    return np.clip((a - lo) * (255.0 / span), 0, 255).astype(np.uint8)


def detect_charuco(image: np.ndarray, spec: CharucoSpec | None = None, *,
                   min_corners: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Find ChArUco corners in a frame with OpenCV's ``CharucoDetector``.

    Parameters
    ----------
    image : numpy.ndarray
        ``H x W`` or ``H x W x C`` frame, any dtype (scaled to 8 bit by its own 0.5–99.5 % range).
    spec : CharucoSpec, optional
        The board; default :func:`charuco_spec` for the frame's size (the chart the simulator renders).
    min_corners : int
        Raise :class:`ParameterError` when fewer corners are found.

    Returns
    -------
    corners_px : numpy.ndarray
        N x 2 float64 sub-pixel corner positions (pixel-centre origin), sorted by id.
    ids : numpy.ndarray
        N int64 corner ids: map to the board with ``spec.corner_px(ids)`` / ``spec.corner_mm(ids)``.
    """
    grey = _to_uint8(image)
    if spec is None:
        spec = charuco_spec(grey.shape[1], grey.shape[0])
    # OpenCV's default minimum marker perimeter is 3 % of the image's long side, which drops the small markers
    # of a many-square board in a big frame; any marker >= 10 px across (~1.5 px per bit) is worth decoding.
    params = cv2.aruco.DetectorParameters()
    params.minMarkerPerimeterRate = min(params.minMarkerPerimeterRate, 40.0 / max(grey.shape))
    detector = cv2.aruco.CharucoDetector(spec.board(), cv2.aruco.CharucoParameters(), params)
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) == 0:
        corners_px, out_ids = np.zeros((0, 2)), np.zeros(0, np.int64)
    else:
        out_ids = np.asarray(ids, dtype=np.int64).ravel()
        corners_px = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        order = np.argsort(out_ids)
        out_ids, corners_px = out_ids[order], corners_px[order]
    if len(out_ids) < min_corners:
        raise ParameterError(f"found {len(out_ids)} ChArUco corners, need {min_corners}", field="image",
                             fix="check the chart fills the frame, is lit evenly and is near focus")
    return corners_px, out_ids


# ------------------------------------------------------------------------------------ slanted edge
@dataclass(frozen=True)
class SlantedEdgeSpec:
    """A grid of dark squares rotated by ``angle_deg`` on a light background.

    Each square gives four edges, two near-vertical (for horizontal MTF) and two near-horizontal
    (for vertical MTF), all ``angle_deg`` off the pixel axes.
    """

    width_px: int
    height_px: int
    nx: int
    ny: int
    cell_px: float
    side_px: float
    angle_deg: float
    dark: float
    light: float
    centres_px: tuple[tuple[float, float], ...] = field(repr=False)

    def edges(self) -> list[dict[str, Any]]:
        """Every edge: midpoint (px), direction angle from the x axis (deg), orientation and a square ROI.

        The ROI ``(x0, y0, x1, y1)`` (inclusive-exclusive pixel indices) is centred on the edge midpoint,
        spans 60 % of the edge length and stays inside the chart.
        """
        th = math.radians(self.angle_deg)
        c, s = math.cos(th), math.sin(th)
        half = self.side_px / 2.0
        roi_half = int(max(4, 0.3 * self.side_px))
        out = []
        for (cx, cy) in self.centres_px:
            # Outward normals of the four sides in the rotated frame: +u, -u, +v, -v.
            for nu, nv, orient in ((1, 0, "near-vertical"), (-1, 0, "near-vertical"),
                                   (0, 1, "near-horizontal"), (0, -1, "near-horizontal")):
                mx = cx + half * (nu * c - nv * s)
                my = cy + half * (nu * s + nv * c)
                direction = math.degrees(math.atan2(nu * s + nv * c, nu * c - nv * s)) + 90.0
                x0 = int(np.clip(round(mx) - roi_half, 0, self.width_px))
                y0 = int(np.clip(round(my) - roi_half, 0, self.height_px))
                x1 = int(np.clip(round(mx) + roi_half + 1, 0, self.width_px))
                y1 = int(np.clip(round(my) + roi_half + 1, 0, self.height_px))
                out.append({"mid_px": (mx, my), "direction_deg": direction % 180.0, "orientation": orient,
                            "roi": (x0, y0, x1, y1)})
        return out

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["centres_px"] = [list(p) for p in self.centres_px]
        return d


def slanted_edge_spec(width_px: int, height_px: int, *, angle_deg: float = 5.0, cells_short: int | None = None,
                      dark: float = 0.2, light: float = 0.8) -> SlantedEdgeSpec:
    """Lay out a grid of slanted squares covering the field (one square per cell, half the cell wide)."""
    w, h = _check_size(width_px, height_px, min_px=32)
    if not (1.0 <= abs(angle_deg) <= 20.0):
        raise ParameterError(f"edge angle {angle_deg} deg out of range", field="angle_deg",
                             fix="use 1..20 degrees (ISO 12233 suggests ~5)")
    if not (0.0 <= dark < light <= 1.0):
        raise ParameterError(f"dark {dark} / light {light} not ordered in [0, 1]", field="dark/light",
                             fix="use 0 <= dark < light <= 1 (e.g. 0.2 and 0.8, 4:1 contrast)")
    short = min(w, h)
    n_short = int(np.clip(short // 48, 1, 8)) if cells_short is None else int(cells_short)
    cell = short / n_short
    if n_short < 1 or cell < 24:
        raise ParameterError(f"cells of {cell:.0f} px are too small", field="cells_short",
                             fix="use fewer cells (each needs >= 24 px)")
    nx = max(1, int(w // cell)) if w >= h else n_short
    ny = n_short if w >= h else max(1, int(h // cell))
    cell_x, cell_y = w / nx, h / ny
    centres = tuple(((i + 0.5) * cell_x - 0.5, (j + 0.5) * cell_y - 0.5) for j in range(ny) for i in range(nx))
    return SlantedEdgeSpec(width_px=w, height_px=h, nx=nx, ny=ny, cell_px=float(min(cell_x, cell_y)),
                           side_px=float(0.5 * min(cell_x, cell_y)), angle_deg=float(angle_deg),
                           dark=float(dark), light=float(light), centres_px=centres)


def slanted_edge_image(spec: SlantedEdgeSpec) -> np.ndarray:
    """Render ``spec`` with box-filtered (area-coverage) edges: sharp, antialiased, never clipped."""
    h, w = spec.height_px, spec.width_px
    th = math.radians(spec.angle_deg)
    c, s = math.cos(th), math.sin(th)
    half = spec.side_px / 2.0
    img = np.full((h, w), spec.light, np.float32)
    reach = int(math.ceil(half * math.sqrt(2.0))) + 2
    for (cx, cy) in spec.centres_px:
        x0, x1 = max(0, int(cx) - reach), min(w, int(cx) + reach + 1)
        y0, y1 = max(0, int(cy) - reach), min(h, int(cy) + reach + 1)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        dx, dy = xx - cx, yy - cy
        u = c * dx + s * dy   # coordinates in the square's rotated frame
        v = -s * dx + c * dy
        # Fraction of a pixel inside each pair of sides (a unit box filter across a straight edge).
        cov = np.clip(half - np.abs(u) + 0.5, 0.0, 1.0) * np.clip(half - np.abs(v) + 0.5, 0.0, 1.0)
        patch = img[y0:y1, x0:x1]
        np.minimum(patch, (spec.light - (spec.light - spec.dark) * cov).astype(np.float32), out=patch)
    return img


# ------------------------------------------------------------------------------------------ public
def chart_image(kind: str = "texture", width_px: int = 256, height_px: int = 256, seed: int = 0) -> np.ndarray:
    """A calibration chart as a float32 ``H x W`` image in [0, 1].

    Parameters
    ----------
    kind : {"texture", "charuco", "slanted-edge"}
        Dead-leaves texture (focus), ChArUco board (geometry) or slanted-edge grid (MTF).
    width_px, height_px : int
        Size in pixels (the simulator passes the sensor size).
    seed : int
        Seed of the random texture (the other charts are deterministic and ignore it).
    """
    if kind == "texture":
        return random_texture(width_px, height_px, seed=seed)
    if kind == "charuco":
        return charuco_image(charuco_spec(width_px, height_px))
    if kind == "slanted-edge":
        return slanted_edge_image(slanted_edge_spec(width_px, height_px))
    raise ParameterError(f"unknown chart kind {kind!r}", field="kind", fix=f"use one of {', '.join(KINDS)}")


# ------------------------------------------------------------------------------------ printable files
PAPER_SIZES_MM = {"A5": (210.0, 148.0), "A4": (297.0, 210.0), "A3": (420.0, 297.0), "A2": (594.0, 420.0),
                  "letter": (279.4, 215.9), "legal": (355.6, 215.9)}


def print_requirements(pixel_pitch_um: float, sensor_size_mm: tuple[float, float], focal_length_mm: float,
                       object_distance_mm: float) -> dict[str, float]:
    """What a printed chart needs for a camera: minimum dpi and the field it must cover.

    Thin-lens magnification ``m = f / (d - f)`` (d from the lens to the chart). One printed pixel must image
    to at most one sensor pixel, so the texture keeps energy up to the *sensor's* Nyquist frequency:
    ``dpi >= 25.4 * m / pitch_mm``. The chart must cover the field of view ``sensor_size / m``.

    Returns
    -------
    dict
        ``magnification``, ``min_dpi``, ``field_width_mm``, ``field_height_mm``.
    """
    for name, v in (("pixel_pitch_um", pixel_pitch_um), ("focal_length_mm", focal_length_mm),
                    ("object_distance_mm", object_distance_mm), ("sensor width", sensor_size_mm[0]),
                    ("sensor height", sensor_size_mm[1])):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ParameterError(f"{name} = {v!r} must be a positive number", field=name, fix="pass a positive value")
    if object_distance_mm <= focal_length_mm:
        raise ParameterError(f"object distance {object_distance_mm} mm is inside the focal length {focal_length_mm} mm",
                             field="object_distance_mm", fix="the chart must be farther than one focal length")
    m = focal_length_mm / (object_distance_mm - focal_length_mm)
    return {"magnification": m, "min_dpi": MM_PER_INCH * m / (pixel_pitch_um / 1000.0),
            "field_width_mm": sensor_size_mm[0] / m, "field_height_mm": sensor_size_mm[1] / m}


def check_chart_for_lens(spec, width_mm: float, height_mm: float, dpi: float) -> tuple[dict[str, float], list[str]]:
    """:func:`print_requirements` for a simulated lens (``fieldcal-lens/1`` spec) and where a print falls short.

    Returns ``(requirements, warnings)``: the dict of :func:`print_requirements` and one sentence per shortfall
    (too few dpi for the sensor's Nyquist frequency; a chart smaller than the field of view).
    """
    req = print_requirements(spec.sensor.pixel_pitch_um, spec.sensor.size_mm, spec.focal_length_mm,
                             spec.object_distance_mm)
    warnings = []
    if dpi < req["min_dpi"]:
        warnings.append(f"{dpi:g} dpi is below {req['min_dpi']:.0f} dpi: the texture will not reach the sensor's "
                        "Nyquist frequency (print at a higher dpi or move the chart farther away)")
    if width_mm < req["field_width_mm"] or height_mm < req["field_height_mm"]:
        warnings.append("the chart does not fill the field of view (print it larger, tile several prints, "
                        "or move the chart farther away)")
    return req, warnings


def parse_size_mm(text: str) -> tuple[float, float]:
    """``"297x210"`` (width x height in mm) or a paper name (A5..A2, letter, legal; landscape) to mm."""
    t = str(text).strip()
    for name, size in PAPER_SIZES_MM.items():
        if t.lower() == name.lower():
            return size
    parts = t.lower().replace("×", "x").split("x")
    fix = "write WIDTHxHEIGHT in mm, e.g. 297x210, or a paper name (" + ", ".join(PAPER_SIZES_MM) + ")"
    if len(parts) != 2:
        raise ParameterError(f"cannot read the size {text!r}", field="size_mm", fix=fix)
    try:
        w, h = float(parts[0]), float(parts[1])
    except ValueError:
        raise ParameterError(f"cannot read the size {text!r}", field="size_mm", fix=fix) from None
    _check_physical(w, h)
    return w, h


def _check_physical(width_mm: float, height_mm: float, dpi: float | None = None) -> None:
    for name, v in (("width_mm", width_mm), ("height_mm", height_mm)):
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not (10.0 <= v <= 2000.0):
            raise ParameterError(f"chart {name} = {v!r} is not a usable size", field=name,
                                 fix="use a size between 10 and 2000 mm, e.g. --size-mm 297x210 (A4)")
    if dpi is not None and (not isinstance(dpi, (int, float)) or isinstance(dpi, bool) or not math.isfinite(dpi)
                            or not (DPI_MIN <= dpi <= DPI_MAX)):
        raise ParameterError(f"dpi = {dpi!r} is out of range", field="dpi",
                             fix=f"use {DPI_MIN:.0f}..{DPI_MAX:.0f} dots per inch (300 suits most printers)")


def _png_bytes(img01: np.ndarray, dpi: float, text: dict[str, str]) -> bytes:
    from PIL import Image, PngImagePlugin
    info = PngImagePlugin.PngInfo()
    for k, v in text.items():
        info.add_text(k, v)
    u8 = np.clip(np.round(img01 * 255.0), 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(u8, mode="L").save(buf, format="PNG", dpi=(dpi, dpi), pnginfo=info, optimize=True)
    return buf.getvalue()


def _pdf_bytes(img01: np.ndarray, width_mm: float, height_mm: float, dpi: float, title: str, subject: str) -> bytes:
    """One page of exactly width_mm x height_mm with the chart filling it, pixels embedded unresampled."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.imshow(np.clip(np.round(img01 * 255.0), 0, 255).astype(np.uint8), cmap="gray", vmin=0, vmax=255,
              interpolation="none", aspect="auto")
    ax.set_axis_off()
    buf = io.BytesIO()
    # CreationDate None: the same chart gives the same bytes (committed files do not churn).
    fig.savefig(buf, format="pdf", dpi=dpi,
                metadata={"Title": title, "Subject": subject, "Creator": "fieldcal targets", "CreationDate": None})
    return buf.getvalue()


def _chart_stem(kind: str, width_mm: float, height_mm: float, dpi: float, seed: int) -> str:
    tag = f"{_fmt_num(width_mm)}x{_fmt_num(height_mm)}mm_{_fmt_num(dpi)}dpi"
    return {"texture": f"texture_seed{seed}_{tag}", "charuco": f"charuco_{tag}"}.get(kind, f"slanted-edge_{tag}")


def target_files(width_mm: float, height_mm: float, dpi: float, *, kinds=KINDS, seed: int = 0,
                 formats=("png", "pdf")) -> list[str]:
    """The names :func:`write_targets` writes in its folder (``targets.json`` last), for checking them first."""
    return [f"{_chart_stem(k, width_mm, height_mm, dpi, seed)}.{f}" for k in kinds for f in formats] + \
        ["targets.json"]


def write_targets(out_dir: str | Path, width_mm: float = 297.0, height_mm: float = 210.0, dpi: float = 300.0, *,
                  kinds: tuple[str, ...] | list[str] = KINDS, seed: int = 0, formats: tuple[str, ...] = ("png", "pdf"),
                  quiet: bool = True) -> dict[str, Any]:
    """Write printable charts at a physical size, plus ``targets.json`` describing them.

    Parameters
    ----------
    out_dir : path
        Folder (created if needed). Existing entries of ``targets.json`` for other files are kept.
    width_mm, height_mm : float
        Printed size of each chart (the PDF page size; the PNG carries ``dpi``).
    dpi : float
        Print resolution: the chart has ``round(size_mm / 25.4 * dpi)`` pixels per side.
    kinds : sequence of str
        Any of ``"texture"``, ``"charuco"``, ``"slanted-edge"``.
    seed : int
        Texture seed.
    formats : sequence of str
        ``"png"`` and/or ``"pdf"``.

    Returns
    -------
    dict
        The manifest written to ``targets.json`` (``format`` ``fieldcal-targets/1``, ``charts`` list).
    """
    _check_physical(width_mm, height_mm, dpi)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ParameterError(f"seed {seed!r} is not a whole number >= 0", field="seed", fix="use a seed >= 0, e.g. 0")
    kinds = list(kinds)
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise ParameterError(f"unknown chart kind(s) {bad or kinds}", field="kind",
                             fix=f"use any of {', '.join(KINDS)} (or 'all' on the command line)")
    bad_f = [f for f in formats if f not in ("png", "pdf")]
    if bad_f or not formats:
        raise ParameterError(f"unknown format(s) {bad_f or list(formats)}", field="format", fix="use png and/or pdf")
    w_px = int(round(width_mm / MM_PER_INCH * dpi))
    h_px = int(round(height_mm / MM_PER_INCH * dpi))
    if w_px * h_px > MAX_CHART_PIXELS:
        raise ParameterError(f"{width_mm:g} x {height_mm:g} mm at {dpi:g} dpi is {w_px * h_px / 1e6:.0f} MP, too large",
                             field="dpi", fix=f"lower the dpi or the size (limit {MAX_CHART_PIXELS / 1e6:.0f} MP)")
    _check_size(w_px, h_px, min_px=64)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mm_per_px = MM_PER_INCH / dpi
    entries = []
    for kind in kinds:
        params: dict[str, Any]
        if kind == "texture":
            tp = TextureParams()
            img = random_texture(w_px, h_px, seed=seed, quiet=quiet)
            r_max = tp.r_max_px if tp.r_max_px is not None else 0.1 * min(w_px, h_px)
            params = {**asdict(tp), "r_max_px": r_max, "model": "dead leaves, p(r) ~ r^-3",
                      "r_min_mm": tp.r_min_px * mm_per_px, "r_max_mm": r_max * mm_per_px,
                      "nyquist_cyc_per_mm": 0.5 / mm_per_px}
            name = _chart_stem("texture", width_mm, height_mm, dpi, seed)
        elif kind == "charuco":
            spec = charuco_spec(w_px, h_px, dpi=dpi)
            img = charuco_image(spec)
            params = spec.to_dict()
            name = _chart_stem("charuco", width_mm, height_mm, dpi, seed)
        else:
            se = slanted_edge_spec(w_px, h_px)
            img = slanted_edge_image(se)
            params = {k: v for k, v in se.to_dict().items()}
            params.update(side_mm=se.side_px * mm_per_px, cell_mm=se.cell_px * mm_per_px)
            name = _chart_stem("slanted-edge", width_mm, height_mm, dpi, seed)
        subject = (f"fieldcal {kind} chart; print at 100 % (no fit-to-page): {width_mm:g} x {height_mm:g} mm, "
                   f"{dpi:g} dpi")
        files = []
        for fmt in formats:
            fname = f"{name}.{fmt}"
            if fmt == "png":
                data = _png_bytes(img, dpi, {"Title": f"fieldcal {kind}", "Description": subject})
            else:
                data = _pdf_bytes(img, width_mm, height_mm, dpi, f"fieldcal {kind}", subject)
            _write_shareable(out / fname, data)
            files.append(fname)
        entries.append({"kind": kind, "files": files, "width_mm": float(width_mm), "height_mm": float(height_mm),
                        "dpi": float(dpi), "width_px": w_px, "height_px": h_px,
                        "seed": seed if kind == "texture" else None, "params": params})
    manifest = _merge_manifest(out / "targets.json", entries)
    _write_shareable(out / "targets.json", documents.dumps(manifest, "targets", out / "targets.json").encode("utf-8"))
    return manifest


def _write_shareable(path: Path, data: bytes) -> None:
    """Atomic write, then the permissions of an ordinary new file (temp files are created owner-only)."""
    atomic_write_bytes(path, data)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def _fmt_num(v: float) -> str:
    return f"{v:g}".replace(".", "p")


def _merge_manifest(path: Path, entries: list[dict[str, Any]]) -> dict[str, Any]:
    """Keep earlier entries whose files still exist and are not rewritten now; a corrupt manifest is replaced."""
    old: list[dict[str, Any]] = []
    if path.is_file():
        try:
            old = documents.read(path, "targets")["charts"]
        except FieldcalError:
            pass  # not a manifest fieldcal can trust: replaced
    new_files = {f for e in entries for f in e["files"]}
    kept = [e for e in old if not (set(e["files"]) & new_files) and all((path.parent / f).exists() for f in e["files"])]
    return {"format": TARGETS_FORMAT,
            "note": "print at 100 % scale (disable fit-to-page); measure a printed square to confirm the scale",
            "charts": kept + entries}
