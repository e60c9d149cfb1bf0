"""Optics shared by the simulator, calibration, planner and compositor (physics, not simulation).

* :mod:`.criterion` — :class:`MTFCriterion` ``(fs_cyc_per_mm, q)``, validated once.
* :mod:`.defocus` — geometric defocus / diffraction / residual-blur OTF, the geometric focus tolerance δ(fs, q)
  and the physical one from the exact pupil OTF (:mod:`.pupil`).
* :mod:`.sweep` — the integrated OTF/PSF of a focal sweep (paper eq. 2), one implementation.
* :mod:`.model` — :class:`LensModel`, the protocol every lens model (profile, truth, synthetic) implements,
  and its geometry part :class:`FrameGeometry`.
"""

from .criterion import MTFCriterion, valid_fs_cyc_per_mm, valid_q
from .defocus import (DEFAULT_WAVELENGTH_NM, default_wavelength_nm, defocus_otf, diffraction_mtf, disc_otf,
                      disc_x_at_contrast, focus_tolerance_um, gaussian_mtf, model_tolerance_um,
                      model_tolerance_ratio, pupil_tolerance_um, through_focus_otf, tolerance_band_nm,
                      tolerance_wavelength_nm, TOLERANCE_BAND_NM, TOLERANCE_WAVELENGTH_NM)
from .model import FrameGeometry, LensModel
from .sweep import disc_sweep_otf, integrated_otf, integrated_psf_radial, sweep_psf_kernel

__all__ = ["MTFCriterion", "valid_fs_cyc_per_mm", "valid_q", "DEFAULT_WAVELENGTH_NM", "default_wavelength_nm", "defocus_otf", "diffraction_mtf",
           "disc_otf", "disc_x_at_contrast", "focus_tolerance_um", "gaussian_mtf", "through_focus_otf",
           "model_tolerance_um", "model_tolerance_ratio", "pupil_tolerance_um", "tolerance_band_nm",
           "tolerance_wavelength_nm", "TOLERANCE_BAND_NM", "TOLERANCE_WAVELENGTH_NM",
           "FrameGeometry", "LensModel", "disc_sweep_otf", "integrated_otf", "integrated_psf_radial", "sweep_psf_kernel"]
