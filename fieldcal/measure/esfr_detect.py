"""Find slanted edges in a frame: dark squares or half-planes at a few degrees from the pixel axes.

OpenCV does the detection: Otsu threshold of a lightly smoothed copy, ``findContours`` (every dark/light
boundary once), ``approxPolyDP`` to split each boundary into straight sides, ``fitLine`` (Huber) on the
contour points of each side's middle. A side is kept when it is long enough and 2-20 degrees from the nearest
pixel axis. Long sides (a half-plane across the field) are cut into segments of at most ``max_length_px``.

Each edge gets a region of interest: the rows (or columns) of its middle part, clear of the corners, and a
half-width across the edge that stops halfway to the next boundary in the thresholded image, so that one
region holds one edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class EdgeCandidate:
    """A detected edge segment and the region the e-SFR will analyse (full-image pixel coordinates).

    ``vertical``: the edge is near-vertical (scan lines are rows); else near-horizontal (scan lines are columns).
    ``roi``: ``(y0, y1, x0, x1)`` half-open; ``line_init``: the edge's position along each scan line of the ROI,
    in ROI coordinates; ``half_width_px``: usable distance from the edge across it.
    """

    x_px: float
    y_px: float
    angle_deg: float  # direction from +x, [0, 180), y down
    length_px: float
    vertical: bool
    roi: tuple[int, int, int, int]
    line_init: np.ndarray
    half_width_px: float


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """0.5-99.5 percentile stretch to uint8 (percentiles from a sparse sample; OpenCV saturating convert)."""
    sample = img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)]
    lo, hi = np.percentile(sample, (0.5, 99.5))
    if not hi > lo:
        return np.zeros(img.shape, np.uint8)
    alpha = 255.0 / (hi - lo)
    return cv2.convertScaleAbs(np.asarray(img, dtype=np.float32), alpha=alpha, beta=-lo * alpha)


def dark_mask(img: np.ndarray) -> np.ndarray:
    """Otsu threshold of a lightly smoothed copy: 1 where dark (uint8), small specks removed."""
    u8 = cv2.GaussianBlur(_to_uint8(np.asarray(img, dtype=np.float32)), (5, 5), 1.0)
    _, mask = cv2.threshold(u8, 0, 1, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    k = np.ones((3, 3), np.uint8)
    return cv2.morphologyEx(cv2.morphologyEx(mask, cv2.MORPH_OPEN, k), cv2.MORPH_CLOSE, k)


def _row_changes(mask: np.ndarray, transposed: bool = False) -> np.ndarray:
    """Where the scan lines of ``mask`` (its rows, or its columns when ``transposed``: the rows of ``mask.T``)
    change: the sorted flat indices ``r * W + c`` in that row-major frame (c in 1 .. W-1) of every pixel that
    differs from its predecessor on the line (a few per line on a chart: the boundaries, not the pixels).
    Both from a contiguous difference of ``mask`` (a difference along the transposed view cost ~8x)."""
    H, W = mask.shape
    if not transposed:
        f = np.flatnonzero(mask[:, 1:] != mask[:, :-1])  # flat index in the H x (W-1) difference
        return f + f // (W - 1) + 1
    f = np.flatnonzero(mask[1:] != mask[:-1])  # change between rows r and r+1 at column c: f = r * W + c
    r, c = np.divmod(f, W)
    return np.sort(c * H + (r + 1))


def _free_distance(changes: np.ndarray, W: int, rows: np.ndarray, xs: np.ndarray, reach: int) -> float:
    """Smallest distance (px) from the edge, over ``rows``, to the next change of the mask on either side
    (``changes`` of :func:`_row_changes`, ``W`` its row length), looked for at 2 .. ``reach`` px from the edge's
    pixel and against the mask 2 px from it: the first boundary past that pixel (to the right: the first change
    after it; to the left: the pixel before the last change at or before it), found by bisection in the row's
    boundaries instead of reading every pixel on the way."""
    best = float(reach)
    if changes.size == 0:
        return best
    xi = np.rint(xs).astype(np.int64)
    key0 = rows.astype(np.int64) * W  # the row's first flat index
    # np.minimum/np.maximum: np.clip's per-call overhead was a third of this function on a texture frame
    j = np.searchsorted(changes, key0 + np.minimum(np.maximum(xi + 2, 0), W - 1), side="right")
    c = changes[np.minimum(j, changes.size - 1)] - key0  # within the row when 1 <= c <= W - 1
    off = c - xi
    hit = (j < changes.size) & (c <= W - 1) & (off <= reach)
    if hit.any():
        best = min(best, float(off[hit].min()))
    j = np.searchsorted(changes, key0 + np.minimum(np.maximum(xi - 2, 0), W - 1), side="right") - 1
    c = changes[np.maximum(j, 0)] - key0
    off = xi - (c - 1)
    hit = (j >= 0) & (c >= 1) & (off <= reach)
    if hit.any():
        best = min(best, float(off[hit].min()))
    return best


def _merge_collinear(poly: np.ndarray, tol_px: float) -> np.ndarray:
    """Drop polygon vertices lying within ``tol_px`` of the line through their neighbours (approxPolyDP
    sometimes splits one straight side into two at a spurious vertex).

    The first such vertex in order goes, then the test resumes one vertex back: only the deleted vertex's two
    neighbours see a new line, so the vertices before them would test as before (the wrap-around: deleting the
    last vertex gives the first a new neighbour, and the test restarts at the first). The same result as
    rescanning from the first vertex after every deletion, in linear rather than quadratic time, on Python
    floats (the same IEEE operations as NumPy's scalars)."""
    pts = [(float(x), float(y)) for x, y in poly]
    i = 0
    while len(pts) > 3 and i < len(pts):
        n_pts = len(pts)
        (ax, ay), (bx, by), (cx, cy) = pts[i - 1], pts[i], pts[(i + 1) % n_pts]
        acx, acy = cx - ax, cy - ay
        n = float(np.hypot(acx, acy))
        if n == 0 or abs(acx * (by - ay) - acy * (bx - ax)) / n <= tol_px:
            del pts[i]
            i = 0 if i == n_pts - 1 else max(i - 1, 0)
        else:
            i += 1
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2) if pts else np.asarray(poly, dtype=np.float64)


def _segments(p0: np.ndarray, p1: np.ndarray, max_len: float) -> list[tuple[np.ndarray, np.ndarray]]:
    L = float(np.hypot(*(p1 - p0)))
    n = max(1, int(math.ceil(L / max_len)))
    return [(p0 + (p1 - p0) * k / n, p0 + (p1 - p0) * (k + 1) / n) for k in range(n)]


def find_edges(img: np.ndarray, *, min_length_px: float = 12.0, max_length_px: float = 128.0,
               slant_range_deg: tuple[float, float] = (1.5, 22.0), max_half_width_px: float = 32.0,
               min_half_width_px: float = 4.0, corner_margin: float = 0.12) -> list[EdgeCandidate]:
    """Slanted edges in a 2-D image (any units; dark squares on light, light on dark, or half-planes).

    Parameters
    ----------
    img : (H, W) array
    min_length_px : shortest straight side kept (after the corner margins are removed: 70 % of the side).
    max_length_px : longer sides are split into segments of at most this length.
    slant_range_deg : angles from the nearest pixel axis kept (a little wider than the e-SFR's own "ok" range,
        so that edges just outside it are reported with a reason rather than silently missed).
    max_half_width_px, min_half_width_px : the analysis half-width across each edge is the room to the next
        boundary (half of it), clipped to this range; edges with less room are dropped.
    corner_margin : fraction of each side left out at either end (corners are rounded by the blur).
    """
    img = np.asarray(img)
    H, W = img.shape
    mask = dark_mask(img)
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out: list[EdgeCandidate] = []
    changes: dict[bool, np.ndarray] = {}  # boundaries along the scan lines, per orientation, made when first needed
    for cnt in contours:
        per = cv2.arcLength(cnt, True)
        if per < 4 * min_length_px:
            continue
        eps = float(np.clip(0.01 * per, 1.5, 4.0))
        poly = _merge_collinear(cv2.approxPolyDP(cnt, eps, True)[:, 0, :].astype(np.float64), eps + 1.0)
        pts = cnt[:, 0, :].astype(np.float64)
        for i in range(len(poly)):
            a, b = poly[i], poly[(i + 1) % len(poly)]
            v = b - a
            L = float(np.hypot(*v))
            if L * (1 - 2 * corner_margin) < min_length_px:
                continue
            ang = math.degrees(math.atan2(v[1], v[0])) % 180.0
            slant = min(ang % 90.0, 90.0 - ang % 90.0)
            if not slant_range_deg[0] <= slant <= slant_range_deg[1]:
                continue
            t = v / L
            rel = pts - a
            along = rel @ t
            perp = rel @ np.array([-t[1], t[0]])
            sel = (np.abs(perp) <= eps + 1.0) & (along >= corner_margin * L) & (along <= (1 - corner_margin) * L)
            if sel.sum() < 8:
                continue
            vx, vy, x0, y0 = cv2.fitLine(pts[sel].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
            # the contour runs along the pixel centres just inside the dark side: half a pixel off the boundary
            nrm = np.array([-vy, vx], dtype=np.float64)
            inside_dark = mask[min(max(int(round(y0 + 2 * nrm[1])), 0), H - 1),
                               min(max(int(round(x0 + 2 * nrm[0])), 0), W - 1)]
            shift = 0.5 if inside_dark else -0.5
            x0, y0 = x0 - shift * nrm[0], y0 - shift * nrm[1]
            d = np.array([vx, vy], dtype=np.float64)
            s_lo, s_hi = (np.array([along[sel].min(), along[sel].max()]) + (a - (x0, y0)) @ t) * np.sign(d @ t)
            p_lo = np.array([x0, y0]) + d * min(s_lo, s_hi)
            p_hi = np.array([x0, y0]) + d * max(s_lo, s_hi)
            vertical = abs(d[1]) > abs(d[0])
            if vertical not in changes:
                changes[vertical] = _row_changes(mask, transposed=not vertical)
            for q0, q1 in _segments(p_lo, p_hi, max_length_px):
                c = _candidate(q0, q1, vertical, changes[vertical], (H, W), max_half_width_px)
                if c is not None and c.half_width_px >= min_half_width_px and c.length_px >= min_length_px:
                    out.append(c)
    return out


def _candidate(q0, q1, vertical: bool, changes: np.ndarray, shape: tuple[int, int],
               max_half_width_px: float) -> EdgeCandidate | None:
    """Region of one segment, computed in the 'vertical frame' (scan lines = rows of the mask, transposed for a
    near-horizontal edge; ``changes``: its boundaries, :func:`_row_changes`)."""
    if vertical:
        (xa, ya), (xb, yb) = q0, q1
    else:
        (ya, xa), (yb, xb) = q0, q1  # transpose: rows are image columns
    if ya > yb:
        xa, ya, xb, yb = xb, yb, xa, ya
    Hv, Wv = shape if vertical else shape[::-1]
    r0, r1 = int(math.ceil(ya)), int(math.floor(yb)) + 1
    r0, r1 = max(r0, 0), min(r1, Hv)
    if r1 - r0 < 4:
        return None
    rows = np.arange(r0, r1)
    slope = (xb - xa) / (yb - ya)
    xs = xa + (rows - ya) * slope
    reach = int(2 * max_half_width_px + 2)
    free = _free_distance(changes, Wv, rows, xs, reach)
    # half the room to the next boundary, and no further than the image border allows
    border = math.floor(min(xs.min(), Wv - 1 - xs.max()))
    hw = float(min(max_half_width_px, math.floor(free / 2.0), border))
    inside = (xs - hw >= 0) & (xs + hw <= Wv - 1)
    if not inside.all():
        keep = np.flatnonzero(inside)
        if keep.size < 4:
            return None
        rows, xs = rows[keep[0]:keep[-1] + 1], xs[keep[0]:keep[-1] + 1]
    c0 = int(max(0, math.floor(xs.min() - hw - 1)))
    c1 = int(min(Wv, math.ceil(xs.max() + hw + 2)))
    xm, ym = float(xs[len(xs) // 2]), float(rows[len(rows) // 2])
    length = float(len(rows) * math.sqrt(1 + slope * slope))
    ang_v = math.degrees(math.atan2(1.0, slope)) % 180.0
    line_init = xs - c0
    if vertical:
        return EdgeCandidate(xm, ym, ang_v, length, True, (int(rows[0]), int(rows[-1]) + 1, c0, c1), line_init, hw)
    return EdgeCandidate(ym, xm, (90.0 - ang_v) % 180.0, length, False, (c0, c1, int(rows[0]), int(rows[-1]) + 1),
                         line_init, hw)
