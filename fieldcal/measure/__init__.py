"""Calibration measurement: per-tile through-focus curves and per-frame geometry from chart stacks.

Entry points: :func:`measure_stack` (both, one pass over the frames), :func:`measure_tiles`,
:func:`measure_geometry`. See docs/measurement.md for the method, thresholds and measured accuracy.
"""

from .geometry import GeometryMeasurements
from .source import ArrayStack
from .throughfocus import CurveFit, CurveRules, analyse_curve, analyse_curves
from .tiles import TileRules, TileTable, measure_geometry, measure_stack, measure_tiles

__all__ = ["ArrayStack", "CurveFit", "CurveRules", "GeometryMeasurements", "TileRules", "TileTable",
           "analyse_curve", "analyse_curves", "measure_geometry", "measure_stack", "measure_tiles"]
