"""Compositing uses calibration's physics: one focus measure, one (unbiased) registration.

The registration test pins the shared Gauss-Newton routine on a stack with a known magnification rate and
shift; the plain ECC it replaced measured ~+5 % too much breathing on the end-to-end stack
(tests/test_composite_e2e.py pins that stack's numbers).
"""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from fieldcal.composite import dff
from fieldcal.composite.register import estimate_geometry
from fieldcal.formats.frames import ArrayStack
from fieldcal.measure import focus


def test_dff_focus_measure_is_calibrations():
    rng = np.random.default_rng(1)
    img = rng.random((40, 50)).astype(np.float32)
    g = cv2.GaussianBlur(img, (3, 3), 0.7, borderType=cv2.BORDER_REFLECT_101)
    np.testing.assert_array_equal(dff.modified_laplacian(img), focus.sml(g))
    # closed form of the modified Laplacian away from the border
    ref = (np.abs(2 * g[1:-1, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:])
           + np.abs(2 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1]))
    np.testing.assert_allclose(dff.modified_laplacian(img)[1:-1, 1:-1], ref, rtol=1e-5, atol=1e-6)


def _scene(size=192, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)


def _warped(scene, m, sx, sy):
    """The scene magnified by m about the image centre and shifted by (sx, sy): frame(c + m (p - c) + s) = scene(p)."""
    h, w = scene.shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # inverse map: p = c + (q - c - s) / m
    px = c[0] + (xx - c[0] - sx) / m
    py = c[1] + (yy - c[1] - sy) / m
    return ndimage.map_coordinates(scene.astype(np.float64), [py, px], order=3, mode="reflect").astype(np.float32)


@pytest.mark.parametrize("rate, shift_rate", [(2e-4, (0.02, -0.01)), (-5e-4, (0.0, 0.03))])
def test_registration_recovers_known_breathing_and_shift(rate, shift_rate):
    scene = _scene()
    z = np.arange(-40.0, 40.1, 10.0)
    z_ref = 0.0
    frames = [_warped(scene, 1.0 + rate * (zz - z_ref), shift_rate[0] * (zz - z_ref), shift_rate[1] * (zz - z_ref))
              for zz in z]
    geo = estimate_geometry(ArrayStack(frames, z, ["Y"]), z_ref_um=z_ref, quiet=True)
    assert geo.n_pairs == len(z) - 1
    # ln(1 + a dz) per µm over 10 µm steps is a (1 - a dz / 2): well inside 1 % here
    assert geo.scale_rate_per_um == pytest.approx(rate, rel=0.01)
    assert geo.shift_rate_px_per_um[0] == pytest.approx(shift_rate[0], abs=5e-4)
    assert geo.shift_rate_px_per_um[1] == pytest.approx(shift_rate[1], abs=5e-4)
    np.testing.assert_allclose(geo.magnification(40.0), 1.0 + rate * 40.0, rtol=5e-5)
