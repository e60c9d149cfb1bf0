"""The interval cover behind stack plans: valid, minimal (against brute force), certified, anchored variant."""

import itertools

import numpy as np
import pytest
from hypothesis import example, given, settings, strategies as st

from fieldcal.plan.cover import anchored_cover, is_cover, min_cover, nearest_index


def brute_force_min(lo, hi):
    """Smallest k such that some k right endpoints pierce all intervals (an optimal cover uses right ends)."""
    cand = np.unique(hi)
    for k in range(1, len(lo) + 1):
        for pts in itertools.combinations(cand, k):
            if is_cover(pts, lo, hi):
                return k
    return 0


intervals = st.lists(st.tuples(st.floats(-50, 50, allow_nan=False), st.floats(0, 10, allow_nan=False)),
                     min_size=1, max_size=7)


@settings(max_examples=60, deadline=None)
@given(intervals)
def test_greedy_is_minimal_and_certified(iv):
    lo = np.array([a for a, _ in iv])
    hi = lo + np.array([w for _, w in iv])
    c = min_cover(lo, hi)
    assert is_cover(c.points_um, lo, hi)
    assert c.n == brute_force_min(lo, hi)
    # the witnesses are pairwise disjoint: no cover can be smaller
    w = c.witnesses
    assert len(set(w.tolist())) == c.n == c.lower_bound
    order = np.argsort(lo[w])
    assert np.all(lo[w][order][1:] > hi[w][order][:-1])


@settings(max_examples=60, deadline=None)
@given(intervals, st.floats(-50, 60))
@example(iv=[(0.0, 0.0), (1.1515657359150931e-138, 0.0)], anchor=2.5402085802883755e-158)  # float-noise anchor
@example(iv=[(0.0, 0.0), (0.0, 5.0)], anchor=4.21621589438089e-09)  # anchor within the touching tolerance
@example(iv=[(0.0, 0.0), (4.21621589438089e-09, 0.0), (-5.0, 0.0)], anchor=-1.0)
@example(iv=[(0.0, 0.0), (5.0, 5.0)], anchor=1.409510979260042e-08)
def test_anchored_cover_contains_anchor_and_costs_at_most_one_more(iv, anchor):
    lo = np.array([a for a, _ in iv])
    hi = lo + np.array([w for _, w in iv])
    c = anchored_cover(lo, hi, anchor)
    assert is_cover(c.points_um, lo, hi)
    assert np.any(np.isclose(c.points_um, anchor))
    assert c.n <= min_cover(lo, hi).n + 1


def test_uniform_bands_need_ceil_D_over_2d():
    # every best-focus value in [0, D] with half-width d: the greedy places frames d, 3d, 5d, ...
    z = np.linspace(0, 100.0, 5001)
    c = min_cover(z - 4.0, z + 4.0)
    assert c.n == 13  # ceil(100 / 8)
    np.testing.assert_allclose(np.diff(c.points_um), 8.0, atol=0.05)
    assert abs(c.points_um[0] - 4.0) < 1e-9


def test_nearest_index_is_the_voronoi_rule():
    p = np.array([0.0, 10.0, 30.0])
    z = np.array([-5, 4.9, 5.0, 19.9, 20.0, 100])
    assert nearest_index(p, z).tolist() == [0, 0, 1, 1, 2, 2]


def test_bad_intervals_are_rejected():
    with pytest.raises(ValueError):
        min_cover([0.0, 1.0], [1.0, 0.5])
    with pytest.raises(ValueError):
        min_cover([np.nan], [1.0])
    assert min_cover([], []).n == 0


from fieldcal.plan.cover import anchored_cover_values, min_cover_values  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-30, 30), st.floats(0, 15), st.floats(0.2, 5)), min_size=1, max_size=6))
def test_cover_of_a_continuum_serves_every_value_and_is_minimal(bins):
    b0 = np.array([b[0] for b in bins])
    b1 = b0 + np.array([b[1] for b in bins])
    d = np.array([b[2] for b in bins])
    c = min_cover_values(b0, b1, d)
    # dense samples of each bin, each with its bin's tolerance
    z = np.concatenate([np.linspace(a, b, 400) for a, b in zip(b0, b1)])
    dz = np.concatenate([np.full(400, t) for t in d])
    assert is_cover(c.points_um, z - dz, z + dz, atol=1e-7)
    # the samples are a subset of the continuum (a lower bound); samples with tolerances shrunk by the spacing
    # serve the continuum (an upper bound, since the greedy over the continuum is optimal)
    h = max((b - a) / 399 for a, b in zip(b0, b1))
    assert min_cover(z - dz, z + dz).n <= c.n <= min_cover(z - dz + h, z + dz - h).n
    a = anchored_cover_values(b0, b1, d, float(b0[0]))
    assert is_cover(a.points_um, z - dz, z + dz, atol=1e-7) and a.n <= c.n + 1


def test_continuum_closed_form():
    assert min_cover_values([0.0], [332.0], [4.0]).n == 42       # ceil(332 / 8)
    assert min_cover_values([0.0], [336.0], [4.0]).n == 42       # exact multiple: no extra frame
    assert anchored_cover_values([0.0], [336.0], [4.0], 336.0).n == 43  # the paper's on-axis start
    np.testing.assert_allclose(min_cover_values([0.0], [16.0], [4.0]).points_um, [4.0, 12.0])
