"""Calibration measurement: per-tile through-focus curves and per-frame geometry from chart stacks.

Entry points: :func:`measure_stack` (both, one pass over the frames), :func:`measure_tiles`,
:func:`measure_geometry`. See docs/measurement.md for the method, thresholds and measured accuracy.
"""

from .._lazy import lazy_names

# The names below are imported on first use (PEP 562): compositing imports ``fieldcal.measure.focus`` and
# ``.geometry`` only, and the through-focus fits pull in scipy.optimize (~0.3 s of a composite's start-up).
_WHERE = {"ArrayStack": "..formats.frames", "FrameSource": "..formats.frames", "GeometryMeasurements": ".geometry",
          "CurveFit": ".throughfocus", "CurveRules": ".throughfocus", "analyse_curve": ".throughfocus",
          "analyse_curves": ".throughfocus", "TileRules": ".tiles", "TileTable": ".tiles",
          "measure_geometry": ".tiles", "measure_stack": ".tiles", "measure_tiles": ".tiles"}

__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())


__all__ = ["ArrayStack", "FrameSource", "CurveFit", "CurveRules", "GeometryMeasurements", "TileRules", "TileTable",
           "analyse_curve", "analyse_curves", "measure_geometry", "measure_stack", "measure_tiles"]
