"""Tile widths corrected for the spread of best focus inside the tile (fit/width_window.py), against curves
built independently: the through-focus curve of a tile whose pixels' best foci spread uniformly over a known
range (a tilted surface), integrated finely, fitted by the measurement's own curve fit."""

import numpy as np
import pytest

from fieldcal.fit.data import TileData
from fieldcal.fit.width_window import correct_widths, window_bias
from fieldcal.measure.throughfocus import CurveRules, analyse_curves
from fieldcal.optics.defocus import disc_otf, disc_x_at_contrast

Q = 0.05
FS = 40.0  # cycles/mm: only the curve model's parametrisation, the widths are in µm
TILE_PX = 40.0


class Tilted:
    """z = g * (x - 100) µm: a tile of side s spans g * s of best focus along x."""

    def __init__(self, g_um_per_px: float):
        self.g = g_um_per_px

    def predict(self, x, y, channel):
        return self.g * (np.asarray(x, dtype=float) - 100.0) + 0.0 * np.asarray(y, dtype=float)


def measured_width(w_um: float, spread_um: float, z_um: np.ndarray) -> float:
    """Width the curve fit reads from the mean of D(x_q (z - u)/w)^2 over u uniform in ±spread/2 (2001 nodes)."""
    u = np.linspace(-0.5 * spread_um, 0.5 * spread_um, 2001)
    xq = disc_x_at_contrast(1.0 - Q)
    curve = np.mean(disc_otf(xq * (z_um[:, None] - u[None, :]) / w_um) ** 2, axis=1)
    fit = analyse_curves(z_um, curve[None, :], "otf", FS, Q, CurveRules(skew=False))[0]
    assert fit.status == "ok"
    return fit.width_um


def tiles(width_um, n=1):
    return TileData.from_arrays(channel=["G"] * n, x_px=[100.0] * n, y_px=[50.0] * n, z_best_um=[0.0] * n,
                                z_sigma_um=[0.1] * n, width_um=[width_um] * n)


@pytest.mark.parametrize("spread_over_w", [0.0, 2.0, 3.0])
def test_corrected_width_recovers_the_pixels_width(spread_over_w):
    w0 = 10.0
    z = np.arange(-40.0, 40.01, 2.5)
    spread = spread_over_w * w0
    w_meas = measured_width(w0, spread, z)
    if spread_over_w > 0:
        assert w_meas > 1.015 * w0  # the spread widens the tile's curve (the bias being removed): 2 % at 2 w, 5 % at 3 w
    t, note = correct_widths(Tilted(spread / TILE_PX), tiles(w_meas), z, TILE_PX, FS, Q)
    # the tile's own 8 x 8 sampling of the spread against the fine integral, and the fixed-point inversion
    assert t.width_um[0] == pytest.approx(w0, rel=0.01)
    assert note["max_factor"] >= 1.0


def test_no_spread_is_no_correction_and_bias_grows_with_the_gradient():
    z = np.arange(-40.0, 40.01, 2.5)
    b = [float(window_bias(Tilted(g), tiles(10.0), z, TILE_PX, FS, Q)[0]) for g in (0.0, 0.25, 0.5, 0.75)]
    assert b[0] == pytest.approx(1.0, abs=1e-9)
    assert all(b2 > b1 for b1, b2 in zip(b, b[1:]))


def test_missing_widths_keep_factor_one():
    z = np.arange(-40.0, 40.01, 2.5)
    t = TileData.from_arrays(channel=["G", "G"], x_px=[100.0, 120.0], y_px=[50.0, 50.0], z_best_um=[0.0, 0.0],
                             z_sigma_um=[0.1, 0.1], width_um=[np.nan, 10.0])
    b = window_bias(Tilted(0.5), t, z, TILE_PX, FS, Q)
    assert b[0] == 1.0 and b[1] > 1.0


def test_a_tile_that_measures_its_spread_is_left_out():
    """Spread 6 widths: the tile's width responds to its pixels' at ~0.25 of the rate (the fine integral), so it
    cannot tell δ and is dropped from the tolerance fit."""
    w0 = 10.0
    z = np.arange(-60.0, 60.01, 2.5)
    spread = 6.0 * w0
    up, down = measured_width(w0 * np.exp(0.05), spread, z), measured_width(w0 * np.exp(-0.05), spread, z)
    assert (np.log(up) - np.log(down)) / 0.1 < 0.5
    t, note = correct_widths(Tilted(spread / TILE_PX), tiles(measured_width(w0, spread, z)), z, TILE_PX, FS, Q)
    assert np.isnan(t.width_um[0]) and note["tiles_dropped"] == 1
