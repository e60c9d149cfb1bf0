"""The chart check's faster paths give the same answers as the slow ones they replace: the polygon clean-up of
the edge finder against the rescan-from-the-start rule it implements, and the chart check's edge count against
the full e-SFR records of measure_frame, on a texture frame and on slanted-edge frames at 2-20 degrees."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldcal.charts.targets import random_texture, slanted_edge_image, slanted_edge_spec
from fieldcal.measure.edge_tiles import MIN_CHART_EDGES, _count_ok_edges, chart_kind
from fieldcal.measure.esfr_detect import _merge_collinear
from fieldcal.measure.mtf import measure_frame


def _merge_rescan(poly: np.ndarray, tol_px: float) -> np.ndarray:
    """The rule as first written: delete the first vertex within tol of its neighbours' line, rescan from 0."""
    pts = [p for p in poly]
    changed = True
    while changed and len(pts) > 3:
        changed = False
        for i in range(len(pts)):
            a, b, c = pts[i - 1], pts[i], pts[(i + 1) % len(pts)]
            ac = c - a
            n = float(np.hypot(*ac))
            if n == 0 or abs(float(ac[0] * (b - a)[1] - ac[1] * (b - a)[0])) / n <= tol_px:
                del pts[i]
                changed = True
                break
    return np.asarray(pts)


def test_merge_collinear_matches_the_rescan_rule():
    rng = np.random.default_rng(3)
    polys = [rng.normal(size=(n, 2)) * 10 for n in (3, 4, 5, 9, 30, 80)]
    polys += [np.round(rng.normal(size=(60, 2)) * 3)]  # integer vertices: ties and repeated points
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)  # a circle: many vertices near their neighbours' line
    polys += [np.stack([40 * np.cos(t), 40 * np.sin(t)], axis=1)]
    for p in polys:
        for tol in (0.05, 0.5, 1.0, 5.0):
            assert np.array_equal(_merge_collinear(p, tol), _merge_rescan(p, tol))


def _edges_frame(angle_deg: float, rng) -> np.ndarray:
    # 3 cells on the short side (45 px squares): at 2 degrees an edge needs >= 1 / tan(2 deg) = 29 rows for one
    # phase cycle, which the default 4 cells (34 px squares, ~22 rows clear of the corners) do not give
    spec = slanted_edge_spec(480, 270, angle_deg=angle_deg, cells_short=3)
    im = np.asarray(slanted_edge_image(spec), np.float32)
    im = cv2.GaussianBlur(im, (0, 0), 1.2) + rng.normal(0, 0.005, im.shape).astype(np.float32)
    return np.clip(np.repeat(im[:, :, None], 3, axis=2) * np.float32([0.9, 1.0, 0.8]), 0, 1)


def _count_from_records(frame, channels, cfa=None):
    records, dets = measure_frame(frame, channels=channels, cfa=cfa)
    ok_all: dict[int, bool] = {}
    for r in records:
        ok_all[r["edge"]] = ok_all.get(r["edge"], True) and bool(r["quality"]["ok"])
    return len(dets), int(sum(ok_all.values()))


@pytest.mark.parametrize("angle_deg", [2.0, 5.0, 11.0, 19.0])
def test_edge_count_matches_measure_frame_and_finds_the_chart(angle_deg):
    frame = _edges_frame(angle_deg, np.random.default_rng(0))
    found, ok = _count_ok_edges(frame, ("R", "G", "B"), None)
    assert (found, ok) == _count_from_records(frame, ("R", "G", "B"))
    assert ok >= MIN_CHART_EDGES
    assert chart_kind(frame, ("R", "G", "B")).kind == "esfr"


def test_texture_frame_is_refused_with_the_same_count():
    tex = np.asarray(random_texture(480, 270, seed=2), np.float32)
    tex = cv2.GaussianBlur(tex, (0, 0), 0.8)
    frame = np.repeat(tex[:, :, None], 3, axis=2)
    assert _count_ok_edges(frame, ("R", "G", "B"), None) == _count_from_records(frame, ("R", "G", "B"))
    k = chart_kind(frame, ("R", "G", "B"))
    assert k.kind == "focus-measure" and k.edges_ok < MIN_CHART_EDGES


def test_raw_mosaic_count_matches_measure_frame():
    """A Bayer mosaic (one plane per colour site, e-SFR at 8 bins per plane pixel) counts the same way."""
    rgb = _edges_frame(5.0, np.random.default_rng(4))
    mosaic = np.empty(rgb.shape[:2], np.float32)
    mosaic[0::2, 0::2], mosaic[0::2, 1::2] = rgb[0::2, 0::2, 0], rgb[0::2, 1::2, 1]  # RGGB
    mosaic[1::2, 0::2], mosaic[1::2, 1::2] = rgb[1::2, 0::2, 1], rgb[1::2, 1::2, 2]
    counts = _count_ok_edges(mosaic, ("R", "G", "B"), "RGGB")
    assert counts == _count_from_records(mosaic, ("R", "G", "B"), "RGGB") and counts[0] > 0
