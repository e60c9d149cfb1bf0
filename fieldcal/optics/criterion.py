"""The MTF criterion ``(fs, q)``: contrast at spatial frequency fs may fall by at most a fraction q.

One value type, validated once: every part of fieldcal that takes an (fs, q) pair (calibration, measurement,
planning, compositing, validation) builds an :class:`MTFCriterion`, so a bad value is reported the same way
everywhere, naming the API field (the CLI's ``--fs`` and ``--q`` set these fields).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fieldcal.errors import ParameterError


def _as_float(v) -> float:
    if isinstance(v, bool):
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def valid_fs_cyc_per_mm(value) -> float:
    """``value`` as a spatial frequency (cycles/mm, finite, > 0), else a ParameterError naming ``fs_cyc_per_mm``.

    For callers that take fs without q (sweep plans); everything with both builds an :class:`MTFCriterion`.
    """
    fs = _as_float(value)
    if not (math.isfinite(fs) and fs > 0.0):
        raise ParameterError(f"spatial frequency fs = {value!r} cycles/mm must be a finite number > 0",
                             field="fs_cyc_per_mm", fix="give e.g. fs_cyc_per_mm=80 (--fs 80 on the command line)")
    return fs


def valid_q(value) -> float:
    """``value`` as an allowed MTF loss in (0, 1), else a ParameterError naming ``q``."""
    q = _as_float(value)
    if not (math.isfinite(q) and 0.0 < q < 1.0):
        raise ParameterError(f"allowed MTF loss q = {value!r} must be in (0, 1)", field="q",
                             fix="give e.g. q=0.05, a 5% loss of MTF at fs (--q 0.05 on the command line)")
    return q


@dataclass(frozen=True)
class MTFCriterion:
    """MTF at ``fs_cyc_per_mm`` (cycles/mm at the sensor) may drop by at most ``q`` (0 < q < 1) of its peak.

    Raises
    ------
    ParameterError
        naming ``fs_cyc_per_mm`` or ``q`` when a value is not a finite number in range.
    """

    fs_cyc_per_mm: float
    q: float

    def __post_init__(self):
        object.__setattr__(self, "fs_cyc_per_mm", valid_fs_cyc_per_mm(self.fs_cyc_per_mm))
        object.__setattr__(self, "q", valid_q(self.q))

    def nyquist_fraction(self, pixel_pitch_um: float) -> float:
        """fs as a fraction of the sensor's Nyquist frequency ``1 / (2 pitch)``."""
        return self.fs_cyc_per_mm / (1000.0 / (2.0 * float(pixel_pitch_um)))

    def focus_tolerance_um(self, f_number: float) -> float:
        """δ of the geometric defocus disc at this F-number, without diffraction
        (:func:`fieldcal.optics.focus_tolerance_um`; with it: :func:`fieldcal.optics.pupil_tolerance_um`)."""
        from .defocus import focus_tolerance_um
        return focus_tolerance_um(self, f_number)
