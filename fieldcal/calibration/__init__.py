"""Calibration: a chart stack in, a lens profile out. It only orchestrates measure → fit → profile.

Named ``calibration`` (not ``calibrate``) so that ``fieldcal.calibrate`` stays the public function.
"""

from fieldcal.calibration.pipeline import calibrate

__all__ = ["calibrate"]
