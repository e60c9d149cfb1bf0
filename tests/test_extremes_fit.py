"""Extremes of the surface fit and of calibration: degenerate posteriors (tiles at one radius, a channel with 3
tiles), a flat field, huge offsets, near-zero uncertainties, every tile rejected, too few frames.

A fit either recovers the known surface (closed form: the tiles are generated from it) with a finite band
that covers it, or raises a FitError/StackError naming the field and the fix. RuntimeWarnings are errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import FieldcalError
from fieldcal.fit import FitError, ImageGeometry, TileData, fit_surfaces

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

GEO = ImageGeometry(128, 96, 4.0)
GX, GY = (a.ravel() for a in np.meshgrid(np.linspace(4, 123, 7), np.linspace(4, 91, 5)))


def tiles(z, sigma=0.5, x=GX, y=GY, channel="Y"):
    n = x.size
    return TileData.from_arrays([channel] * n, x, y, np.broadcast_to(z, (n,)), np.full(n, sigma))


def rho2(x, y):
    xh, yh = GEO.normalise(x, y)
    return xh ** 2 + yh ** 2


def test_tiles_all_at_one_radius_are_refused_with_a_fix():
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    cx, cy = GEO.centre_px
    x, y = cx + 30 * np.cos(ang), cy + 30 * np.sin(ang)
    with pytest.raises(FitError) as e:
        fit_surfaces(tiles(np.zeros(12), x=x, y=y), GEO, effort="quick", quiet=True)
    assert "one radius" in str(e.value) and e.value.fix


def test_one_channel_with_three_tiles_is_refused_naming_the_channel():
    n = GX.size
    t = TileData.from_arrays(["R"] * n + ["G"] * n + ["B"] * 3, np.r_[GX, GX, GX[:3]], np.r_[GY, GY, GY[:3]],
                             np.zeros(2 * n + 3), np.ones(2 * n + 3))
    with pytest.raises(FitError) as e:
        fit_surfaces(t, GEO, effort="quick", quiet=True)
    assert "channel B has only 3" in str(e.value) and e.value.field == "tiles"


def test_no_tiles_is_refused():
    with pytest.raises(FitError):
        fit_surfaces(tiles(np.zeros(0), x=np.zeros(0), y=np.zeros(0)), GEO, effort="quick", quiet=True)


@pytest.mark.parametrize("offset_um", [0.0, 5.0, -3e4, 1e7])
def test_flat_field_fits_a_flat_surface_at_any_offset(offset_um):
    """A lens without field curvature (a one-frame plan later): the surface is the constant, exactly."""
    fit = fit_surfaces(tiles(np.full(GX.size, offset_um), sigma=0.5), GEO, effort="quick", quiet=True)
    x, y = np.array([0.0, 63.5, 127.0]), np.array([0.0, 47.5, 95.0])
    z = fit.predict(x, y, "Y")
    np.testing.assert_allclose(z, offset_um, atol=1e-6 * max(1.0, abs(offset_um)))
    lo, hi = fit.interval(x, y, "Y", level=0.9)
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= z) and np.all(z <= hi)


def test_near_zero_tile_uncertainties_stay_finite():
    z = 5.0 - 30.0 * rho2(GX, GY)
    fit = fit_surfaces(tiles(z, sigma=1e-9), GEO, effort="quick", quiet=True)
    np.testing.assert_allclose(fit.predict(GX, GY, "Y"), z, atol=1e-3)
    lo, hi = fit.interval(GX, GY, "Y")
    assert np.all(np.isfinite(hi - lo))


@settings(max_examples=6, deadline=None)
@given(a_um=st.floats(-400.0, 400.0), z0_um=st.floats(-1e4, 1e4), seed=st.integers(0, 100))
def test_curvature_of_any_sign_and_size_is_recovered(a_um, z0_um, seed):
    rng = np.random.default_rng(seed)
    z = z0_um + a_um * rho2(GX, GY)
    fit = fit_surfaces(tiles(z + rng.normal(0, 0.3, z.size), sigma=0.3), GEO, effort="quick", quiet=True)
    pred = fit.predict(GX, GY, "Y")
    assert np.all(np.isfinite(pred))
    assert np.sqrt(np.mean((pred - z) ** 2)) < 0.5


def _tiny_colour_lens(w=128, h=96):
    from fieldcal.simulate.lens import ChannelSpec, LensSpec, SensorSpec
    hmax = 0.5 * math.hypot(w, h) * 4.0 / 1000.0
    return LensSpec(name="tiny", focal_length_mm=10.0, f_number=4.0, image_height_max_mm=hmax,
                    channels=(ChannelSpec("Y", 546.1, 0.0, (-40.0,)),),
                    sensor=SensorSpec(w, h, 4.0, bit_depth=12, full_well_e=20000.0, read_noise_e=2.0))


def _write(tmp_path, frames, z):
    from fieldcal.formats.stack import StackWriter
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=4.0, channels=["Y"], bit_depth=12)
    for f, zi in zip(frames, z):
        w.add_frame(f, zi)
    return w.stack()


def test_calibrating_a_textureless_stack_says_every_tile_was_rejected(tmp_path):
    from fieldcal.calibration.pipeline import calibrate
    z = np.arange(-40.0, 40.1, 8.0)
    stack = _write(tmp_path, [np.full((96, 128), 2000, np.uint16) for _ in z], z)
    with pytest.raises(FieldcalError) as e:
        calibrate(stack, fs_cyc_per_mm=40.0, effort="quick", quiet=True)
    assert "every tile was rejected" in str(e.value) and "low_texture" in str(e.value)


@pytest.mark.parametrize("n", [1, 2])
def test_calibrating_one_or_two_frames_is_a_clear_error(tmp_path, n):
    from fieldcal.calibration.pipeline import calibrate
    z = [0.0, 8.0][:n]
    stack = _write(tmp_path, [np.full((96, 128), 2000, np.uint16) for _ in z], z)
    with pytest.raises(FieldcalError) as e:
        calibrate(stack, fs_cyc_per_mm=40.0, effort="quick", quiet=True)
    assert "too few frames" in str(e.value)


def test_calibrate_a_tiny_simulated_stack_recovers_the_surface(tmp_path):
    """A working end-to-end reference for the cases above: the quick calibration of a 128x96 stack."""
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.simulate import simulate_stack
    from fieldcal.simulate.truth import TruthProfile
    spec = _tiny_colour_lens()
    stack = simulate_stack(spec, tmp_path / "s", np.arange(-100.0, 61.0, 5.0), seed=1, progress=False)
    prof = calibrate(stack, fs_cyc_per_mm=40.0, effort="quick", tile_px=16, quiet=True)
    truth = TruthProfile(spec)
    x, y = np.meshgrid(np.linspace(10, 117, 6), np.linspace(10, 85, 5))
    err = prof.best_focus_um(x, y, "Y") - truth.best_focus_um(x, y, "Y")
    assert np.sqrt(np.mean(err ** 2)) < 3.0


def test_public_calibrate_stays_callable_after_the_submodule_is_imported():
    import importlib
    import fieldcal
    importlib.import_module("fieldcal.calibration.pipeline")
    assert callable(fieldcal.calibrate)
