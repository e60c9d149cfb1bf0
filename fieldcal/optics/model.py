"""The lens-model interface: what planning, compositing, validation and reports ask of a lens.

A calibrated :class:`fieldcal.profile.LensProfile`, the exact :class:`fieldcal.simulate.truth.TruthProfile` of a
simulated lens and the analytic :class:`fieldcal.plan.synthetic.SyntheticProfile` all implement
:class:`LensModel`, so callers use its attributes directly (no probing). Coordinates are pixels of the
``z_ref_um`` frame (origin at the centre of the top-left pixel), stage positions are µm (+z moves the sensor
away from the lens), frequencies are cycles/mm at the sensor. A :class:`fieldcal.simulate.lens.LensSpec`
works in sensor millimetres instead; :class:`~fieldcal.simulate.truth.TruthProfile` is its lens model.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np



@runtime_checkable
class FrameGeometry(Protocol):
    """Where a frame at stage position z puts the scene, relative to the ``z_ref_um`` frame: the part of a lens
    model that warping frames needs (a geometry measured from a stack alone, as compositing without a profile
    does, answers only this)."""

    #: stage position (µm) of the reference geometry: pixel coordinates are those of this frame
    z_ref_um: float

    def magnification(self, z_um, channel: str | None = None) -> np.ndarray:
        """Image scale at z relative to z_ref (1 at z_ref)."""

    def shift_px(self, z_um, channel: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(dx, dy) image shift (px) at z relative to z_ref."""

    def optical_centre_px(self) -> tuple[float, float]:
        """(cx, cy) of the optical axis in pixels."""

    def lateral_colour_scale(self, channel: str) -> float:
        """Channel scale about the optical centre relative to the reference channel."""


@runtime_checkable
class LensModel(FrameGeometry, Protocol):
    """Queries every lens model answers (docs/architecture.md, "Lens model interface")."""

    #: channel names, e.g. ("R", "G", "B")
    channels: tuple[str, ...]
    #: (width, height) in pixels
    image_size_px: tuple[int, int]
    pixel_pitch_um: float
    #: image-side F-number (None: unknown, so no defocus model)
    f_number: float | None
    focal_length_mm: float | None
    #: object distance (mm) the surfaces hold for (None: unknown)
    object_distance_mm: float | None
    #: Bayer pattern of raw frames ("RGGB", ...) or None for demosaiced/monochrome images
    cfa: str | None
    #: True when ``focus_tolerance_um`` comes from measured through-focus widths, not the defocus model
    has_measured_tolerance: bool
    #: the file the model was read from (for messages), or None
    source_path: str | None

    def best_focus_um(self, x, y, channel: str) -> np.ndarray:
        """Best-focus stage position (µm) of the scene point at pixel(s) (x, y)."""

    def best_focus_interval_um(self, x, y, channel: str, level: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) credible band of the best focus (µm); lo == hi for an exact model."""

    def wavelength_nm(self, channel: str) -> float:
        """Wavelength (nm) the channel stands for."""

    def focus_tolerance_um(self, x, y, channel: str, fs_cyc_per_mm: float, q: float) -> np.ndarray:
        """Half-width (µm) of the defocus range in which MTF(fs) stays within q of its peak, per point."""

    def defocus_otf(self, f_cyc_per_mm, defocus_um, channel: str) -> np.ndarray:
        """Signed OTF at frequency f and defocus dz (negative past the first zero: contrast reversal)."""

    def defocus_mtf(self, f_cyc_per_mm, defocus_um, channel: str) -> np.ndarray:
        """``|defocus_otf|``."""
