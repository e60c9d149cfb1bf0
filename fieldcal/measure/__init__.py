"""Calibration measurement: per-tile through-focus curves and per-frame geometry from chart stacks.

Entry points: :func:`measure_stack` (both, one pass over the frames), :func:`measure_tiles`,
:func:`measure_geometry`. See docs/measurement.md for the method, thresholds and measured accuracy.
"""

from ..formats.frames import ArrayStack, FrameSource
from .geometry import GeometryMeasurements
from .throughfocus import CurveFit, CurveRules, analyse_curve, analyse_curves
from .tiles import TileRules, TileTable, measure_geometry, measure_stack, measure_tiles

__all__ = ["ArrayStack", "FrameSource", "CurveFit", "CurveRules", "GeometryMeasurements", "TileRules", "TileTable",
           "analyse_curve", "analyse_curves", "measure_geometry", "measure_stack", "measure_tiles"]
