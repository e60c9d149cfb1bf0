"""Calibration fitting on tile data: best-focus surfaces (MAP + posterior + model selection), geometry vs z,
and the focus-tolerance model. See docs/fitting.md for the models and the statistics.

Typical use (by ``fieldcal.calibrate``)::

    from fieldcal.fit import TileData, ImageGeometry, fit_surfaces
    tiles = TileData.from_table(tile_table)          # accepted rows only
    surf = fit_surfaces(tiles, ImageGeometry(w, h, pitch_um), effort="standard")
    surf.predict(x, y, "G"); surf.interval(x, y, "G", level=0.9)
"""

from .data import FitError, ImageGeometry, TileData
from .geometry import GeometryData, GeometryFit, fit_geometry
from .result import SurfaceFit
from .select import fit_surfaces
from .tolerance import ToleranceFit, fit_tolerance

__all__ = ["FitError", "ImageGeometry", "TileData", "SurfaceFit", "fit_surfaces", "GeometryData", "GeometryFit",
           "fit_geometry", "ToleranceFit", "fit_tolerance"]
