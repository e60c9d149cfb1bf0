"""Inputs of the calibration fits: the image geometry and per-tile focus measurements (validated arrays).

The fits never see images. ``measure.tiles`` produces a ``TileTable`` (docs/architecture.md); its accepted
rows become a :class:`TileData`. Coordinates are normalised here, once, for every model downstream:

* ``x_hat = (x_px - (W - 1) / 2) / R``, ``y_hat`` likewise, with ``R = hypot(W, H) / 2`` px (half-diagonal),
  so the sensor corner sits at radius ~1 and powers of the radius stay O(1);
* z is centred and scaled by the data (``z_centre_um``, ``z_scale_um``) by the model code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..errors import ParameterError


class FitError(ParameterError):
    """Fit input that cannot support the requested fit (too few tiles, degenerate layout, bad values)."""


# Fewer accepted tiles than this in a channel and no surface model is meaningful.
MIN_TILES_PER_CHANNEL = 6


@dataclass(frozen=True)
class ImageGeometry:
    """Size and pixel pitch of the calibrated images (the frame of every tile coordinate)."""

    width_px: int
    height_px: int
    pixel_pitch_um: float

    def __post_init__(self):
        if not (int(self.width_px) >= 2 and int(self.height_px) >= 2):
            raise FitError(f"image size {self.width_px}x{self.height_px} px is too small", field="width_px",
                           fix="give the calibration images' width and height in pixels (>= 2)")
        if not (math.isfinite(self.pixel_pitch_um) and self.pixel_pitch_um > 0):
            raise FitError(f"pixel pitch must be a positive number, got {self.pixel_pitch_um}",
                           field="pixel_pitch_um", fix="give the sensor pixel pitch in µm, e.g. 3.45")

    @property
    def centre_px(self) -> tuple[float, float]:
        """Sensor centre (origin at the centre of the top-left pixel)."""
        return ((self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0)

    @property
    def half_diagonal_px(self) -> float:
        """The radius unit R of the normalised coordinates."""
        return 0.5 * math.hypot(self.width_px, self.height_px)

    def normalise(self, x_px, y_px) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates to (x_hat, y_hat): about the sensor centre, in units of the half-diagonal."""
        cx, cy = self.centre_px
        r = self.half_diagonal_px
        return ((np.asarray(x_px, dtype=np.float64) - cx) / r, (np.asarray(y_px, dtype=np.float64) - cy) / r)

    def to_dict(self) -> dict[str, Any]:
        return {"width_px": int(self.width_px), "height_px": int(self.height_px),
                "pixel_pitch_um": float(self.pixel_pitch_um)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ImageGeometry":
        return cls(int(d["width_px"]), int(d["height_px"]), float(d["pixel_pitch_um"]))


def _column(table: Any, name: str):
    if isinstance(table, Mapping):
        return table.get(name)
    return getattr(table, name, None)


@dataclass(frozen=True)
class TileData:
    """Accepted per-tile, per-channel measurements (one row each; all arrays of equal length).

    ``z_tan_um``/``z_sag_um`` are the best foci of directional focus measures (NaN where absent) and feed
    the astigmatism term; ``width_um`` is the through-focus half-width at the calibration's (fs, q) and feeds
    the tolerance model (NaN where absent).
    """

    channel: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    z_best_um: np.ndarray
    z_sigma_um: np.ndarray
    z_tan_um: np.ndarray
    z_sag_um: np.ndarray
    width_um: np.ndarray

    @classmethod
    def from_arrays(cls, channel, x_px, y_px, z_best_um, z_sigma_um, z_tan_um=None, z_sag_um=None,
                    width_um=None, source: str | None = None) -> "TileData":
        """Build and validate; ``source`` (a file name) goes into error messages."""
        ch = np.asarray(channel).astype(str).ravel()
        n = ch.size

        def arr(name, v, allow_nan):
            if v is None:
                return np.full(n, np.nan)
            a = np.asarray(v, dtype=np.float64).ravel()
            if a.size != n:
                raise FitError(f"column '{name}' has {a.size} rows but 'channel' has {n}", path=source,
                               field=name, fix="give every tile column the same number of rows")
            bad = ~np.isfinite(a) if not allow_nan else np.isinf(a)
            if bad.any():
                raise FitError(f"column '{name}' has {int(bad.sum())} non-finite values (first at row "
                               f"{int(np.flatnonzero(bad)[0])})", path=source, field=name,
                               fix="drop rejected tiles (status != 'ok') before fitting")
            return a

        x = arr("x_px", x_px, False)
        y = arr("y_px", y_px, False)
        z = arr("z_best_um", z_best_um, False)
        s = arr("z_sigma_um", z_sigma_um, False)
        if (s <= 0).any():
            raise FitError(f"{int((s <= 0).sum())} tiles have z_sigma_um <= 0", path=source, field="z_sigma_um",
                           fix="per-tile uncertainties must be positive (µm)")
        zt = arr("z_tan_um", z_tan_um, True)
        zs = arr("z_sag_um", z_sag_um, True)
        w = arr("width_um", width_um, True)
        if (w[np.isfinite(w)] <= 0).any():
            raise FitError("some tiles have width_um <= 0", path=source, field="width_um",
                           fix="through-focus half-widths must be positive (µm); use NaN when not measured")
        return cls(ch, x, y, z, s, zt, zs, w)

    @classmethod
    def from_table(cls, table: Any, source: str | None = None) -> "TileData":
        """From a ``TileTable``-like object (attributes or a mapping of columns); keeps ``status == "ok"`` rows."""
        cols = {k: _column(table, k) for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um",
                                                "z_tan_um", "z_sag_um", "width_um", "status")}
        for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um"):
            if cols[k] is None:
                raise FitError(f"tile table has no column '{k}'", path=source, field=k,
                               fix="pass the TileTable from fieldcal.measure (columns channel, x_px, y_px, "
                                   "z_best_um, z_sigma_um)")
        keep = None
        if cols["status"] is not None:
            keep = np.asarray(cols["status"]).astype(str) == "ok"
        args = {}
        for k, v in cols.items():
            if k == "status":
                continue
            if v is not None:
                v = np.asarray(v)
                if keep is not None:
                    v = v[keep]
            args[k] = v
        return cls.from_arrays(**args, source=source)

    def __len__(self) -> int:
        return int(self.channel.size)

    @property
    def channels(self) -> tuple[str, ...]:
        """Channel names in order of first appearance."""
        seen: dict[str, None] = {}
        for c in self.channel:
            seen.setdefault(str(c), None)
        return tuple(seen)

    def subset(self, mask) -> "TileData":
        m = np.asarray(mask)
        return TileData(*(getattr(self, f)[m] for f in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um",
                                                         "z_tan_um", "z_sag_um", "width_um")))
