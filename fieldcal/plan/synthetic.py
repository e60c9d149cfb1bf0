"""An analytic lens profile with chosen surfaces, tolerances and credible bands (design studies and tests).

Best focus of every channel: ``z0 + offset[c] + a * rho**2`` with rho = distance from the optical centre over
the half-diagonal, so the range over the full image is exactly ``|a|``; tolerance δ is uniform or a function of
rho, with sd ``tolerance_sd_um``; the credible band is ``±band_um`` about the surface (Gaussian posterior); its OTF is the geometric blur
disc alone (no diffraction). It implements :class:`fieldcal.optics.LensModel`.
"""

from __future__ import annotations

import math

import numpy as np

from fieldcal.optics import default_wavelength_nm, defocus_otf


class SyntheticProfile:
    def __init__(self, width_px=96, height_px=64, a_um=-332.0, z0_um=0.0, tolerance_um=4.0, band_um=0.0,
                 channels=("G",), offsets_um=None, centre_px=None, pixel_pitch_um=20.0, f_number=2.0,
                 focal_length_mm=17.6, object_distance_mm=1000.0, tolerance_fn=None, cfa=None,
                 tolerance_sd_um=0.0):
        self.image_size_px = (int(width_px), int(height_px))
        self.channels = tuple(channels)
        self.a_um, self.z0_um = float(a_um), float(z0_um)
        self.offsets_um = dict(offsets_um or {})
        self.tol_um, self.band_um, self.tolerance_fn = float(tolerance_um), float(band_um), tolerance_fn
        self.tol_sd_um = float(tolerance_sd_um)
        self.centre = centre_px or ((width_px - 1) / 2.0, (height_px - 1) / 2.0)
        self.pixel_pitch_um, self.f_number = float(pixel_pitch_um), float(f_number)
        self.focal_length_mm, self.object_distance_mm = focal_length_mm, object_distance_mm
        self.z_ref_um = 0.0
        self.has_measured_tolerance = True
        self.cfa = cfa
        self.source_path = None
        cx, cy = self.centre
        self.r_max_px = max(math.hypot(x - cx, y - cy) for x in (0, width_px - 1) for y in (0, height_px - 1))

    def rho(self, x, y):
        return np.hypot(np.asarray(x, dtype=np.float64) - self.centre[0],
                        np.asarray(y, dtype=np.float64) - self.centre[1]) / self.r_max_px

    def best_focus_um(self, x, y, channel):
        return self.z0_um + self.offsets_um.get(channel, 0.0) + self.a_um * self.rho(x, y) ** 2

    def best_focus_interval_um(self, x, y, channel, level=0.9):
        z = self.best_focus_um(x, y, channel)
        return z - self.band_um, z + self.band_um

    def focus_tolerance_um(self, x, y, channel, fs_cyc_per_mm, q):
        r = self.rho(x, y)
        if self.tolerance_fn is not None:
            return self.tolerance_fn(r, fs_cyc_per_mm, q)
        return np.full(r.shape, self.tol_um)

    def focus_tolerance_sd_um(self, x, y, channel, fs_cyc_per_mm, q):
        return np.full(self.rho(x, y).shape, self.tol_sd_um)

    def optical_centre_px(self):
        return self.centre

    def magnification(self, z_um, channel=None):
        return np.ones_like(np.asarray(z_um, dtype=np.float64))

    def shift_px(self, z_um, channel=None):
        z = np.asarray(z_um, dtype=np.float64)
        return np.zeros_like(z), np.zeros_like(z)

    def lateral_colour_scale(self, channel):
        return 1.0

    def wavelength_nm(self, channel):
        return default_wavelength_nm(channel)

    def defocus_otf(self, f_cyc_per_mm, defocus_um, channel):
        return defocus_otf(f_cyc_per_mm, defocus_um, self.f_number)

    def defocus_mtf(self, f_cyc_per_mm, defocus_um, channel):
        return np.abs(self.defocus_otf(f_cyc_per_mm, defocus_um, channel))
