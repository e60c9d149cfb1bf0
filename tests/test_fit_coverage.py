"""Calibrated uncertainty, small version of benchmarks/bench_fit_coverage.py (quick effort)."""

import numpy as np

from fieldcal.fit import fit_surfaces
from fieldcal.fit.synthetic import band_coverage, random_lens, synthetic_tiles


def test_band_coverage_is_calibrated_over_random_lenses():
    """Small version of benchmarks/bench_fit_coverage.py: quick effort, 8 random lenses with underestimated
    sigmas and outliers. A fit without the error scale or without the robust loss lands far below 0.8."""
    covs = []
    for k in range(8):
        rng = np.random.default_rng(1000 + k)
        spec = random_lens(rng, channels=("R", "G", "B") if k % 2 else ("Y",))
        tiles, geom, truth = synthetic_tiles(spec, rng, nx=7, ny=5, underestimate=float(rng.uniform(1.0, 2.0)),
                                             outlier_fraction=0.03 if k % 3 == 0 else 0.0, directional=k % 4 == 1)
        f = fit_surfaces(tiles, geom, effort="quick", quiet=True)
        covs.append(band_coverage(f, truth, n=9))
    assert 0.78 <= float(np.mean(covs)) <= 0.99, covs
