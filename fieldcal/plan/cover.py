"""Fewest stage positions that put every pixel within its tolerance: a minimum piercing set of intervals.

Each pixel (or bin of best-focus values) gives an interval ``[lo, hi]`` of stage positions that keep it within
its focus tolerance; a frame at ``z`` serves every interval that contains ``z``. The fewest frames serving all
intervals is the classic interval-piercing problem, solved exactly by the greedy rule "sort by right end, put a
frame at the first unserved right end" (its chosen intervals are pairwise disjoint, which is a certificate
that no smaller set exists). The paper's placement (first frame at a given anchor, e.g. the on-axis best
focus) is the same greedy run outward from the anchor on each side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Cover:
    """A piercing set: ``points_um`` (ascending) and the indices of the disjoint intervals that certify it."""

    points_um: np.ndarray
    witnesses: np.ndarray  # indices into the input intervals, pairwise disjoint (a lower bound on any cover)

    @property
    def n(self) -> int:
        return int(self.points_um.size)

    @property
    def lower_bound(self) -> int:
        """Any cover needs at least this many points (number of pairwise disjoint input intervals found)."""
        return int(self.witnesses.size)


def _check(lo, hi):
    lo = np.asarray(lo, dtype=np.float64).ravel()
    hi = np.asarray(hi, dtype=np.float64).ravel()
    if lo.shape != hi.shape:
        raise ValueError("lo and hi must have the same length")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("interval ends must be finite")
    if np.any(hi < lo):
        raise ValueError("empty interval (hi < lo): a tolerance is negative")
    return lo, hi


def _touch_tol(values: np.ndarray) -> float:
    """Distance below which two interval ends count as touching: float noise in bin edges never costs a frame."""
    return 1e-9 * max(1.0, float(np.max(np.abs(values))) if np.size(values) else 1.0)


def _greedy_sorted(lo: np.ndarray, hi: np.ndarray, start_after: float = -np.inf, atol: float | None = None):
    """Greedy on intervals already sorted by ``hi``; skips intervals containing ``start_after``.

    Ends closer than ``atol`` (default ``1e-9 * scale``) count as touching, so float noise in bin edges never
    costs a frame.
    """
    points, wit = [], []
    atol = _touch_tol(hi) if atol is None else atol
    last = start_after
    i, n = 0, lo.size
    while i < n:
        rest = lo[i:] > last + atol
        if not rest.any():
            break
        i += int(np.argmax(rest))
        last = hi[i]
        points.append(last)
        wit.append(i)
        i += 1
    return points, wit


def min_cover(lo, hi, atol: float | None = None) -> Cover:
    """Minimum set of points such that every interval ``[lo_i, hi_i]`` contains one (exact, O(n log n + N n)).

    Ends closer than ``atol`` touch (default: 1e-9 of the largest magnitude, at least 1e-9).
    """
    lo, hi = _check(lo, hi)
    if lo.size == 0:
        return Cover(np.zeros(0), np.zeros(0, dtype=np.int64))
    order = np.argsort(hi, kind="stable")
    pts, wit = _greedy_sorted(lo[order], hi[order], atol=atol)
    return Cover(np.asarray(pts, dtype=np.float64), order[np.asarray(wit, dtype=np.int64)])


def anchored_cover(lo, hi, anchor_um: float) -> Cover:
    """The paper's placement: a point at ``anchor_um``, then the fewest points outward on each side.

    Optimal among covers that contain the anchor; can need one point more than :func:`min_cover`.
    The witnesses are those of each side (a lower bound for covers containing the anchor, minus one).
    """
    lo, hi = _check(lo, hi)
    a = float(anchor_um)
    # the anchor serves the intervals it touches within the greedy's own tolerance (ends closer than
    # 1e-9 * scale touch): strict comparisons here gave a point more than min_cover + 1 on float noise
    atol = _touch_tol(np.concatenate([lo, hi, [a]]))
    above = lo > a + atol
    below = hi < a - atol
    pts = [a]
    wit = []
    if above.any():
        idx = np.flatnonzero(above)
        c = min_cover(lo[idx], hi[idx], atol=atol)
        pts += list(c.points_um)
        wit += list(idx[c.witnesses])
    if below.any():
        idx = np.flatnonzero(below)
        c = min_cover(-hi[idx], -lo[idx], atol=atol)  # mirror: greedy from the anchor downward
        pts += list(-c.points_um)
        wit += list(idx[c.witnesses])
    return Cover(np.sort(np.asarray(pts, dtype=np.float64)), np.asarray(wit, dtype=np.int64))


def is_cover(points, lo, hi, atol: float | None = None) -> bool:
    """True if every interval contains at least one of ``points`` (within ``atol``: by default the covers'
    own touching tolerance, 1e-9 of the largest magnitude and at least 1e-9)."""
    lo, hi = _check(lo, hi)
    p = np.sort(np.asarray(points, dtype=np.float64))
    if atol is None:
        atol = _touch_tol(np.concatenate([lo, hi, p]))
    if p.size == 0:
        return lo.size == 0
    # the first point >= lo must also be <= hi
    j = np.searchsorted(p, lo - atol, side="left")
    ok = j < p.size
    jj = np.minimum(j, p.size - 1)
    return bool(np.all(ok & (p[jj] <= hi + atol)))


def nearest_index(points_sorted, z):
    """Index of the nearest point for each value of ``z`` (ties go to the higher point): the compositing rule.

    Point k serves ``mid[k-1] <= z < mid[k]`` with ``mid`` the midpoints between consecutive points.
    """
    p = np.asarray(points_sorted, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if p.size == 1:
        return np.zeros(z.shape, dtype=np.int64)
    mids = 0.5 * (p[1:] + p[:-1])
    return np.searchsorted(mids, z, side="right").astype(np.int64)


# --------------------------------------------------------------------- a continuum of best-focus values
def _greedy_values(b0, b1, d, start: float, limit: int | None = None):
    """Greedy over every value z in each bin ``[b0, b1]`` (tolerance ``d`` per bin), frames above ``start``.

    After a frame at f, the values of bin b still unserved are those above ``f + d_b`` (lower ones were served
    earlier: the greedy keeps that invariant), so the next frame is ``min_b(max(b0_b, f + d_b) + d_b)`` over
    the bins with such values. Exact for the continuum (no loss to the bin width); O(N * bins). With ``limit``
    it stops after ``limit + 1`` points (enough to know that more than ``limit`` are needed).
    """
    pts, wit = [], []
    f = start
    atol = 1e-9 * max(1.0, float(np.max(np.abs(b1))) if b1.size else 1.0)
    while True:
        u = np.maximum(b0, f + d) if np.isfinite(f) else b0.copy()
        open_ = u <= b1 if not np.isfinite(f) else (u <= b1) & (b1 > f + d + atol)
        if not open_.any():
            break
        right = np.where(open_, u + d, np.inf)
        k = int(np.argmin(right))
        f = float(right[k])
        pts.append(f)
        wit.append(k)
        if limit is not None and len(pts) > limit:
            break
    return pts, wit


def min_cover_values(b0, b1, d, limit: int | None = None) -> Cover:
    """Fewest points such that every value z in every bin ``[b0_i, b1_i]`` has a point within ``d_i``.

    ``limit``: stop after ``limit + 1`` points (the result then only says "more than ``limit``")."""
    b0, b1, d = (np.asarray(v, dtype=np.float64).ravel() for v in (b0, b1, d))
    if np.any(b1 < b0) or np.any(d < 0) or not np.all(np.isfinite(np.concatenate([b0, b1, d]))):
        raise ValueError("bins need finite b0 <= b1 and d >= 0")
    pts, wit = _greedy_values(b0, b1, d, -np.inf, limit)
    return Cover(np.asarray(pts, dtype=np.float64), np.asarray(wit, dtype=np.int64))


def anchored_cover_values(b0, b1, d, anchor_um: float, limit: int | None = None) -> Cover:
    """The paper's placement over a continuum of values: a point at the anchor, then greedy outward
    (``limit``: as :func:`min_cover_values`, per side)."""
    b0, b1, d = (np.asarray(v, dtype=np.float64).ravel() for v in (b0, b1, d))
    a = float(anchor_um)
    up, wu = _greedy_values(b0, b1, d, a, limit)
    down, wd = _greedy_values(-b1, -b0, d, -a, limit)
    pts = np.sort(np.asarray([a] + up + [-p for p in down], dtype=np.float64))
    return Cover(pts, np.asarray(wu + wd, dtype=np.int64))
