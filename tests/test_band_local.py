"""The band-local benchmark's statistics (benchmarks/bench_band_local.py), checked against closed forms."""

import itertools
import math

import numpy as np
import pytest
from scipy.special import ndtr, ndtri

from bench_util import import_bench

bench = import_bench("bench_band_local")


def test_in_window_counts_is_the_poisson_binomial():
    p = np.array([0.9, 0.2, 0.55, 0.7, 0.05])
    dist = bench.in_window_counts(p)
    brute = np.zeros(p.size + 1)
    for hits in itertools.product((0, 1), repeat=p.size):
        h = np.array(hits)
        brute[h.sum()] += float(np.prod(np.where(h == 1, p, 1.0 - p)))
    np.testing.assert_allclose(dist, brute, atol=1e-12)
    # 20 lenses each inside the window with probability 0.6 (an honest band with a field-wide share ~0.7):
    # >= 18 of 20 is the binomial tail
    tail = bench.in_window_counts(np.full(20, 0.6))[18:].sum()
    exact = sum(math.comb(20, k) * 0.6 ** k * 0.4 ** (20 - k) for k in range(18, 21))
    assert tail == pytest.approx(exact, rel=1e-10) and tail < 0.004


def test_honest_window_probability_counts_draws():
    c = np.array([0.5, 0.75, 0.9, 0.99, 1.0, 1.0, 0.8, 0.74])
    r = bench.honest_window_probability(c, (0.75, 0.99))
    assert (r["p_in"], r["p_below"], r["p_above"]) == (4 / 8, 2 / 8, 2 / 8)
    assert r["abs_dev"] == pytest.approx(np.mean(np.abs(c - c.mean())))


def test_local_what_ifs_recover_a_known_overstatement():
    """Independent errors of sd r about the band's centre, a band whose local variance is (2 r)^2 (twice too wide)
    on top of a field-wide variance f: stated coverage is P(|Z| <= z sqrt(f + 4 r^2) / r); the oracle rescales the
    local part to r^2 and gives P(|Z| <= z sqrt(f + r^2) / r); without it P(|Z| <= z sqrt(f) / r)."""
    rng = np.random.default_rng(3)
    n = 40000
    x, y = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    plane = np.column_stack([np.ones(n), x, y])
    r, f = 0.1, 0.05 ** 2
    e = r * rng.standard_normal(n)
    local = np.full(n, (2 * r) ** 2)
    w = bench.local_what_ifs(e, f + local, local, plane)
    z = float(ndtri(0.95))
    p = lambda v: float(2 * ndtr(z * math.sqrt(v) / r) - 1)
    assert w["stated"] == pytest.approx(p(f + 4 * r * r), abs=0.005)
    assert w["oracle"] == pytest.approx(p(f + r * r), abs=0.005)
    assert w["oracle_narrow"] == w["oracle"]
    assert w["none"] == pytest.approx(p(f), abs=0.01)
    assert w["rest_um"] == pytest.approx(r, rel=0.02) and w["local_sd_um"] == pytest.approx(2 * r)
    # a band already too narrow: the narrowing-only oracle keeps it as stated
    tight = np.full(n, (0.5 * r) ** 2)
    w2 = bench.local_what_ifs(e, f + tight, tight, plane)
    assert w2["oracle_narrow"] == w2["stated"] < w2["oracle"]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the minimal rows leave other columns empty
def test_band_coverage_summary_sums_the_own_model_probabilities():
    """bench_band_coverage's summary: the expected number of lenses in the window under each profile's own error
    model is the sum of the rows' probabilities (older rows without the key print a dash)."""
    cov = import_bench("bench_band_coverage")
    rows = [{"lens": k, "effort": "quick", "optics": "geometric", "cov_after": c, "cov_before": c, "rms_um": 0.1,
             "step_um": 10.0, "hw_um": 0.2, "p_in_range": 0.5, "field_share": 0.7, "p_in_model": p}
            for k, (c, p) in enumerate([(0.9, 0.8), (1.0, 0.3), (0.6, 0.45)])]
    (s,) = cov.summarise(rows, ["quick"])
    assert s["expected_in_model"] == "1.6" and s["expected_in"] == "1.5" and s["in_075_099"] == "1/3"
    (old,) = cov.summarise([{k: v for k, v in r.items() if k != "p_in_model"} for r in rows], ["quick"])
    assert old["expected_in_model"] == "—"
