"""The lens profile (``fieldcal-profile/1``): what a calibration produces and what labs deploy.

A profile is a JSON file plus a sidecar ``.npz`` (posterior samples, the tile table, the per-frame geometry
measurements). The JSON records the sidecar's name and sha256, so a profile never silently pairs with the
wrong samples. Loading validates the format version: an unknown or newer version is refused with a clear
message. See docs/profile-format.md.

The public API (DESIGN.md)::

    profile = LensProfile.load("lens.json")
    profile.channels; profile.z_ref_um
    profile.best_focus_um(x, y, "G")                          # MAP surface (µm)
    profile.best_focus_interval_um(x, y, "G", level=0.9)      # credible band (µm)
    profile.magnification(z_um, "G"); profile.shift_px(z_um, "G")
    profile.warp_px(x, y, z_um, "G"); profile.warp_sd_px(x, y, z_um, "G")   # dense geometry (docs/geometry.md)
    profile.distortion_px(x_u, y_u, z_um, "G"); profile.undistort_px(x, y, z_um, "G")  # absolute (ChArUco)

:class:`LensProfile` implements :class:`fieldcal.optics.LensModel`; its defocus physics is
:mod:`fieldcal.optics` (the same model the simulator and planner use).
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import re
import zipfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from fieldcal import __version__
from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes, atomic_write_text, jsonable
from fieldcal.errors import ParameterError, SpecError
from fieldcal.optics import MTFCriterion, default_wavelength_nm, defocus_otf, diffraction_mtf, focus_tolerance_um

if TYPE_CHECKING:  # the fits import the fitting stack; a profile loads them only when it reads one
    from fieldcal.fit import SurfaceFit
    from fieldcal.fit.geometry import GeometryFit
    from fieldcal.fit.geometry_map import GeometryMap
    from fieldcal.fit.distortion import AbsoluteDistortion
    from fieldcal.fit.tolerance import ToleranceFit

PROFILE_FORMAT = documents.format_id("profile")


def _check_points(x, y):
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    try:
        np.broadcast(x, y)
    except ValueError:
        raise ParameterError(f"x and y do not broadcast ({x.shape} vs {y.shape})", field="x, y",
                             fix="pass arrays of the same shape") from None
    return x, y


class ImageBlock(TypedDict, total=False):
    """The profile's ``image`` block (docs/profile-format.md)."""

    width_px: int
    height_px: int
    pixel_pitch_um: float
    channels: list[str]
    cfa: str | None


class OpticsBlock(TypedDict, total=False):
    """The profile's ``optics`` block: None where the stack did not record the value."""

    f_number: float | None
    focal_length_mm: float | None
    object_distance_mm: float | None
    wavelength_nm: dict[str, float]


@dataclass
class LensProfile:
    """A calibrated lens: per-channel best-focus surfaces with uncertainty, geometry vs z, tolerance model.

    Build with :func:`fieldcal.calibrate`; read with :meth:`load`; write with :meth:`save`.
    """

    surfaces: SurfaceFit
    geometry_fit: GeometryFit
    tolerance_fit: ToleranceFit | None  # None: the tolerance comes from the defocus model
    image: ImageBlock
    optics: OpticsBlock
    calibration: dict[str, Any]         # JSON block: fs_cyc_per_mm, q, effort, tile_px, z_range_um, ...
    z_ref_um: float
    diagnostics: dict[str, Any] = field(default_factory=dict)   # JSON block, free-form
    provenance: dict[str, Any] = field(default_factory=dict)    # JSON block, free-form
    tiles: dict[str, np.ndarray] | None = None                  # tile table columns (for reports)
    geometry_measurements: dict[str, np.ndarray] | None = None  # per-frame geometry columns
    source_path: str | None = None
    geometry_map: GeometryMap | None = None  # dense maps (x, y, z) with covariance; None: the scalar m(z), s(z)
    absolute_distortion: AbsoluteDistortion | None = None  # the z_ref geometry vs a board's ideal image (ChArUco)

    # ------------------------------------------------------------------------------ the DESIGN.md API
    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(self.image["channels"])

    def _channel(self, channel: str) -> str:
        if channel not in self.channels:
            raise ParameterError(f"no channel {channel!r} in this profile (it has {', '.join(self.channels)})",
                                 field="channel", fix=f"use one of {', '.join(self.channels)}")
        return channel

    def best_focus_um(self, x, y, channel: str, orientation: str | None = None):
        """MAP best-focus stage position (µm) at pixel(s) (x, y) of the z_ref geometry.

        ``orientation``: None for the mean surface (circle of least confusion), "tangential" or "sagittal" for
        the surface of edges seen across the radius / along it: the mean ± half the fitted astigmatism
        ``z_tan - z_sag`` (zero when the calibration saw no directional foci).
        """
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        z = self.surfaces.predict(x, y, ch)
        if orientation is None or orientation == "mean":
            return z
        if orientation not in ("tangential", "sagittal"):
            raise ParameterError(f"orientation must be None, 'tangential' or 'sagittal', not {orientation!r}",
                                 field="orientation", fix="use orientation='tangential' or 'sagittal' (None: the mean)")
        half = 0.5 * np.asarray(self.surfaces.astigmatism_um(x, y, ch), dtype=np.float64)
        return z + half if orientation == "tangential" else z - half

    def best_focus_interval_um(self, x, y, channel: str, level: float = 0.9):
        """(lo, hi) equal-tailed credible band of the best-focus surface (µm)."""
        if not (0.0 < float(level) < 1.0):
            raise ParameterError(f"level must be in (0, 1), got {level}", field="level", fix="e.g. level=0.9")
        x, y = _check_points(x, y)
        lo, hi = self.surfaces.interval(x, y, self._channel(channel), level=float(level))
        sys_sd = float(self.calibration.get("systematic_sd_um") or 0.0)
        # the breathing systematic (per channel, measured on the stack; docs/fitting.md) is common to every
        # tile of a channel, so no fit sees it either
        breathing = (self.calibration.get("breathing_systematic_sd_um") or {}).get(channel) or 0.0
        # so is the error of the sml@fs offset (one pooled number per channel; fit/tiles.measure_offset_sd_um)
        offset = (self.calibration.get("measure_offset_sd_um") or {}).get(channel) or 0.0
        sys_sd = math.hypot(sys_sd, float(breathing), float(offset))
        if sys_sd <= 0.0:
            return lo, hi
        # Profiles written before the systematic was estimated from the data (docs/fitting.md "Systematic")
        # carry a fixed systematic sd here: combine it in quadrature, so they keep the band they had. New
        # profiles record 0 and carry the estimated terms in the surface fit.
        from scipy.special import ndtri
        zq = float(ndtri(0.5 + 0.5 * float(level)))
        mid = 0.5 * (np.asarray(lo) + np.asarray(hi))
        half = np.sqrt((0.5 * (np.asarray(hi) - np.asarray(lo))) ** 2 + (zq * sys_sd) ** 2)
        return mid - half, mid + half

    def magnification(self, z_um, channel: str | None = None):
        """Image scale at z relative to the same channel at z_ref (1.0 at z_ref)."""
        ch = self.channels[0] if channel is None else self._channel(channel)
        return self.geometry_fit.magnification(np.asarray(z_um, dtype=np.float64), ch)

    def shift_px(self, z_um, channel: str | None = None):
        """(dx, dy) image shift (px) at z relative to z_ref."""
        ch = self.channels[0] if channel is None else self._channel(channel)
        return self.geometry_fit.shift_px(np.asarray(z_um, dtype=np.float64), ch)

    @property
    def has_geometry_map(self) -> bool:
        """Dense maps (the compositor warps with :meth:`warp_px`); False: the scalar model's affine maps."""
        return self.geometry_map is not None

    @property
    def reference_channel(self) -> str:
        """The channel whose frame at z_ref defines the pixel geometry of :meth:`warp_px`."""
        if self.geometry_map is not None:
            return self.geometry_map.reference_channel
        ref = getattr(self.geometry_fit, "reference_channel", None)
        return ref if ref in self.channels else ("G" if "G" in self.channels else self.channels[0])

    def warp_px(self, x, y, z_um, channel: str, lateral_colour: bool = True):
        """Where the point at pixel (x, y) of the z_ref geometry appears in ``channel`` of the frame at z (px).

        The z_ref geometry is the reference channel's frame at ``z_ref_um``; the map holds distortion (changing
        with z), breathing, shift and lateral colour (docs/geometry.md). ``lateral_colour=False`` maps from the
        channel's own frame at z_ref instead. Profiles without maps answer with the scalar model
        ``c + m(z) L (p - c) + s(z)`` (``L`` the lateral-colour scale).
        """
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        z = np.asarray(z_um, dtype=np.float64)
        if self.geometry_map is None:
            cx, cy = self.optical_centre_px()
            m = self.geometry_fit.magnification(z, ch) * (self.lateral_colour_scale(ch) if lateral_colour else 1.0)
            sx, sy = self.geometry_fit.shift_px(z, ch)
            return cx + m * (x - cx) + sx, cy + m * (y - cy) + sy
        if not lateral_colour:
            x, y = self._from_own_frame(x, y, ch)
        return self.geometry_map.warp_px(x, y, z, ch)

    def _from_own_frame(self, x, y, channel: str):
        """The z_ref-geometry point that channel ``channel``'s own z_ref frame shows at (x, y): the inverse of the
        map at z_ref (fixed point: the map is within ~1e-2 of the identity in its derivative)."""
        px, py = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
        for _ in range(20):
            qx, qy = self.geometry_map.warp_px(px, py, self.geometry_map.z_ref_um, channel)
            ex, ey = qx - x, qy - y
            px, py = px - ex, py - ey
            if max(np.max(np.abs(ex), initial=0.0), np.max(np.abs(ey), initial=0.0)) < 1e-9:
                break
        return px, py

    def warp_sd_px(self, x, y, z_um, channel: str):
        """1-sigma uncertainty (px, x and y) of :meth:`warp_px`: from the maps' covariance, or for profiles
        without maps from the scalar fits' (magnification and shift sd)."""
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        z = np.asarray(z_um, dtype=np.float64)
        if self.geometry_map is not None:
            return self.geometry_map.warp_sd_px(x, y, z, ch)
        cx, cy = self.optical_centre_px()
        msd = self.geometry_fit.magnification_sd(z, ch)
        ssx, ssy = self.geometry_fit.shift_sd_px(z, ch)
        return np.hypot(msd * (x - cx), ssx), np.hypot(msd * (y - cy), ssy)

    # -------------------------------------------------------- absolute distortion (docs/geometry.md)
    @property
    def has_absolute_distortion(self) -> bool:
        """A board measured the lens's absolute distortion (ChArUco); texture-only profiles have none."""
        return self.absolute_distortion is not None

    def _absolute(self) -> AbsoluteDistortion:
        if self.absolute_distortion is None:
            src = getattr(self.geometry_map, "source", None)
            why = ("its geometry maps come from texture, which shows no straight lines" if src == "texture" else
                   "it was calibrated without a ChArUco board's geometry")
            raise ParameterError(f"this profile has no absolute distortion: {why}", path=self.source_path,
                                 field="absolute_distortion",
                                 fix="calibrate a stack that shows the ChArUco board (--chart, docs/geometry.md)")
        return self.absolute_distortion

    def distortion_px(self, x_u, y_u, z_um=None, channel: str | None = None):
        """Where the undistorted pixel (x_u, y_u) appears in ``channel`` of the frame at ``z_um`` (px).

        Undistorted pixels are the board's ideal (pinhole) image scaled and placed so that the reference
        channel's distortion at z has no linear part at the centre (breathing and shift taken out); the other
        channels keep their lateral colour. Default z: the maps' z_ref; default channel: the reference one.
        Raises :class:`ParameterError` for profiles without absolute distortion (texture-only).
        """
        from fieldcal.fit.distortion import compose_distortion
        d = self._absolute()
        x, y = _check_points(x_u, y_u)
        ch = self._channel(channel or d.reference_channel)
        z = d.z_um if z_um is None else float(z_um)
        return compose_distortion(d, self.warp_px, x, y, z, ch)

    def distortion_sd_px(self, x_u, y_u, z_um=None, channel: str | None = None):
        """1-sigma (px, x and y) of :meth:`distortion_px`."""
        from fieldcal.fit.distortion import compose_distortion_sd
        d = self._absolute()
        x, y = _check_points(x_u, y_u)
        ch = self._channel(channel or d.reference_channel)
        z = d.z_um if z_um is None else float(z_um)
        return compose_distortion_sd(d, self.warp_sd_px, x, y, z, ch)

    def undistort_px(self, x_d, y_d, z_um=None, channel: str | None = None):
        """The undistorted pixel that ``channel`` of the frame at ``z_um`` shows at (x_d, y_d): the inverse of
        :meth:`distortion_px` (Newton's method)."""
        from fieldcal.fit.distortion import invert_map
        x, y = _check_points(x_d, y_d)
        return invert_map(lambda u, v: self.distortion_px(u, v, z_um, channel), x, y)

    # ------------------------------------------------------------------ what planning/compositing use
    @property
    def image_size_px(self) -> tuple[int, int]:
        return int(self.image["width_px"]), int(self.image["height_px"])

    @property
    def pixel_pitch_um(self) -> float:
        return float(self.image["pixel_pitch_um"])

    @property
    def f_number(self) -> float | None:
        return self.optics.get("f_number")

    @property
    def focal_length_mm(self) -> float | None:
        return self.optics.get("focal_length_mm")

    @property
    def object_distance_mm(self) -> float | None:
        return self.optics.get("object_distance_mm")

    @property
    def cfa(self) -> str | None:
        return self.image.get("cfa")

    @property
    def has_measured_tolerance(self) -> bool:
        return self.tolerance_fit is not None

    @property
    def z_range_um(self) -> tuple[float, float]:
        lo, hi = self.calibration.get("z_range_um", (self.z_ref_um, self.z_ref_um))
        return float(lo), float(hi)

    @property
    def model_selection(self) -> list[dict]:
        return list(self.surfaces.candidates)

    def optical_centre_px(self) -> tuple[float, float]:
        return tuple(float(v) for v in self.surfaces.optical_centre_px())

    def lateral_colour_scale(self, channel: str) -> float:
        return float(self.geometry_fit.lateral_colour_scale(self._channel(channel)))

    def wavelength_nm(self, channel: str) -> float:
        wl = self.optics.get("wavelength_nm", {}) or {}
        return float(wl.get(channel, default_wavelength_nm(channel)))

    def best_focus_sd_um(self, x, y, channel: str):
        x, y = _check_points(x, y)
        return self.surfaces.sd(x, y, self._channel(channel))

    def focus_tolerance_um(self, x, y, channel: str, fs_cyc_per_mm: float, q: float):
        """Half-width (µm) of the defocus range in which MTF(fs) stays within q of its peak.

        From the measured through-focus widths when the profile has them, else from the geometric defocus disc at
        the stack's F-number (``has_measured_tolerance`` says which): with nothing measured, the lower bound on any
        lens of that F-number (the pupil with diffraction, :func:`fieldcal.optics.model_tolerance_um`, is wider
        and is what a measured width is capped at; docs/planning.md).
        """
        crit = MTFCriterion(fs_cyc_per_mm, q)
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        if self.tolerance_fit is not None:
            return np.asarray(self.tolerance_fit.tolerance_um(x, y, ch, crit.fs_cyc_per_mm, crit.q),
                              dtype=np.float64)
        if not self.f_number:
            raise SpecError("the profile has neither measured widths nor an F-number for the defocus model",
                            path=self.source_path, field="optics.f_number",
                            fix="recalibrate from a stack whose stack.json gives f_number")
        t = focus_tolerance_um(crit, float(self.f_number))
        return np.full(np.broadcast(x, y).shape, t)

    def focus_tolerance_sd_um(self, x, y, channel: str, fs_cyc_per_mm: float, q: float):
        """Standard error (µm) of :meth:`focus_tolerance_um` from the width fit (its coefficients' HC3
        covariance from the tiles' residuals, tiles independent); 0 where the tolerance comes from the defocus model.

        Only the fit's own scatter: a bias common to every tile of the measurement (docs/planning.md "Measured
        tolerance") is not in it."""
        crit = MTFCriterion(fs_cyc_per_mm, q)
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        shape = np.broadcast(x, y).shape
        tol = self.tolerance_fit
        if tol is None or ch not in tol.coef_um:
            return np.zeros(shape)
        from fieldcal.profile.uncertainty import _tolerance_coef_cov
        order = len(tol.coef_um[ch])
        cov = _tolerance_coef_cov(self, ch, order)
        if cov is None:
            return np.zeros(shape)
        xb, yb = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        J = tol.design(xb, yb, order)
        ratio = (np.asarray(tol.tolerance_um(xb, yb, ch, crit.fs_cyc_per_mm, crit.q), dtype=np.float64)
                 / np.asarray(tol.width_cal_um(xb, yb, ch), dtype=np.float64))
        return ratio * np.sqrt(np.maximum(np.einsum("...i,ij,...j->...", J, cov, J), 0.0))

    def defocus_otf(self, f_cyc_per_mm, defocus_um, channel: str):
        """Signed OTF of the geometric defocus x diffraction model (needs the F-number)."""
        n = float(self.f_number or 0.0)
        if n <= 0:
            raise SpecError("the profile has no F-number", path=self.source_path, field="optics.f_number",
                            fix="recalibrate from a stack whose stack.json gives f_number")
        return defocus_otf(f_cyc_per_mm, defocus_um, n) * diffraction_mtf(
            f_cyc_per_mm, self.wavelength_nm(self._channel(channel)), n)

    def defocus_mtf(self, f_cyc_per_mm, defocus_um, channel: str):
        """MTF (``|defocus_otf|``) of the geometric defocus x diffraction model."""
        return np.abs(self.defocus_otf(f_cyc_per_mm, defocus_um, channel))

    # ---------------------------------------------------------------------------------------- I/O
    def to_dict(self, sidecar_name: str | None = None, sidecar_sha256: str | None = None) -> dict:
        return {
            "format": PROFILE_FORMAT,
            "tool": {"name": "fieldcal", "version": __version__},
            "created_utc": self.provenance.get("created_utc") or datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "image": self.image,
            "optics": self.optics,
            "calibration": self.calibration,
            "z_ref_um": float(self.z_ref_um),
            "surfaces": self.surfaces.to_dict(include_samples=False),
            "geometry": self.geometry_fit.to_dict(),
            **({"geometry_map": self.geometry_map.to_dict()} if self.geometry_map is not None else {}),
            **({"absolute_distortion": self.absolute_distortion.to_dict()}
               if self.absolute_distortion is not None else {}),
            "tolerance": None if self.tolerance_fit is None else self.tolerance_fit.to_dict(),
            "model_selection": jsonable(self.model_selection),
            "diagnostics": jsonable(self.diagnostics),
            "provenance": jsonable(self.provenance),
            "sidecar": None if sidecar_name is None else {"file": sidecar_name, "sha256": sidecar_sha256},
        }

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (JSON) and its samples sidecar beside it as one unit (docs/safety.md).

        The sidecar's name carries its content hash (``<stem>.<sha256[:16]>.samples.npz``), so a new sidecar
        never replaces the one the current JSON names; the JSON is renamed into place last, and only then is
        the previous sidecar removed. A crash at any point leaves the old profile or the new one, each with its
        own samples (at worst an unreferenced ``.npz`` that the next save removes).
        """
        path = Path(path)
        if path.suffix.lower() != ".json":
            raise ParameterError(f"a profile is a .json file, got {path.name!r}", path=path, field="path",
                                 fix="name it e.g. lens.json")
        buf = io.BytesIO()
        arrays = {"surface_samples": np.asarray(self.surfaces.samples, dtype=np.float64)}
        for prefix, cols in (("tiles__", self.tiles or {}), ("geom__", self.geometry_measurements or {})):
            for k, v in cols.items():
                a = np.asarray(v)
                if a.dtype == object:
                    a = np.asarray([np.nan if e is None else e for e in v]) if k not in ("channel", "status", "channels") else a.astype(str)
                arrays[prefix + k] = a
        np.savez_compressed(buf, **arrays)
        data = buf.getvalue()
        digest = hashlib.sha256(data).hexdigest()
        sidecar = path.with_name(sidecar_name(path, digest))
        old = _referenced_sidecar(path)
        d = self.to_dict(sidecar.name, digest)
        text = documents.dumps(d, "profile", path, indent=1)  # validated before anything is written
        atomic_write_bytes(sidecar, data)  # the sidecar first, under its own content-addressed name
        atomic_write_text(path, text)      # the JSON last: until this rename the old profile is whole
        _remove_unreferenced_sidecars(path, keep=sidecar.name, old=old)
        self.source_path = str(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "LensProfile":
        """Read and validate a profile (and its samples sidecar)."""
        doc = documents.read(path, "profile", not_found="profile not found",
                             not_found_fix="give the .json written by `fieldcal calibrate`")
        return cls.from_document(doc, path)

    @classmethod
    def from_document(cls, d: dict, path: str | Path) -> "LensProfile":
        """A profile from its parsed ``fieldcal-profile/1`` document (validated here) and the sidecar beside
        ``path``."""
        path = Path(path)
        documents.validate(d, "profile", path)
        img = d["image"]
        samples = None
        arrays = _read_sidecar(d.get("sidecar"), path)
        samples = arrays.get("surface_samples")
        from fieldcal.fit import SurfaceFit
        from fieldcal.fit.geometry import GeometryFit
        surfaces = SurfaceFit.from_dict(d["surfaces"], samples=samples, path=path)
        geometry = GeometryFit.from_dict(d["geometry"], path=path)
        gmap = None
        if d.get("geometry_map") is not None:  # profiles before the maps have none: the scalar model answers
            from fieldcal.fit.geometry_map import GeometryMap
            gmap = GeometryMap.from_dict(d["geometry_map"], path=path)
        absd = None
        if d.get("absolute_distortion") is not None:  # ChArUco profiles; texture-only ones have none
            from fieldcal.fit.distortion import AbsoluteDistortion
            absd = AbsoluteDistortion.from_dict(d["absolute_distortion"], path=path)
        tolerance = None
        if d.get("tolerance"):
            from fieldcal.fit.tolerance import ToleranceFit
            tolerance = ToleranceFit.from_dict(d["tolerance"], path=path)
        tiles = {k[len("tiles__"):]: v for k, v in arrays.items() if k.startswith("tiles__")} or None
        geom = {k[len("geom__"):]: v for k, v in arrays.items() if k.startswith("geom__")} or None
        prov = dict(d.get("provenance", {}))
        prov.setdefault("created_utc", d.get("created_utc"))
        prov.setdefault("tool", d.get("tool"))
        return cls(surfaces=surfaces, geometry_fit=geometry, tolerance_fit=tolerance, image=dict(img),
                   optics=dict(d["optics"]), calibration=dict(d["calibration"]), z_ref_um=float(d["z_ref_um"]),
                   diagnostics=dict(d.get("diagnostics", {})), provenance=prov, tiles=tiles,
                   geometry_measurements=geom, source_path=str(path), geometry_map=gmap,
                   absolute_distortion=absd)


_SHA256 = re.compile(r"[0-9a-fA-F]{64}")
_SIDECAR_RE = r"{stem}\.[0-9a-f]{{16}}\.samples\.npz"


def sidecar_name(path: str | Path, sha256_hex: str) -> str:
    """The content-addressed sidecar name of profile ``path``: ``<stem>.<sha256[:16]>.samples.npz``."""
    return f"{Path(path).stem}.{sha256_hex[:16]}.samples.npz"


def _sidecar_of(json_path: Path) -> str | None:
    """The plain file name an existing profile JSON gives as its sidecar (None if unreadable or not plain)."""
    from fieldcal.errors import FieldcalError
    try:
        if not json_path.is_file() or json_path.is_symlink():
            return None
        d = documents.read_json(json_path)
    except (FieldcalError, OSError):
        return None
    name = d.get("sidecar", {}).get("file") if isinstance(d, dict) and isinstance(d.get("sidecar"), dict) else None
    if not isinstance(name, str) or not name or name != Path(name).name or name in (".", ".."):
        return None
    return name


def _referenced_sidecar(path: Path) -> str | None:
    return _sidecar_of(path)


def _sidecars_in_use(folder: Path, skip: Path) -> set[str]:
    """Sidecar names named by the other profile JSONs of ``folder`` (any case of .json)."""
    used = set()
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return used
    for e in entries:
        if e.name.lower().endswith(".json") and e.name != skip.name:
            n = _sidecar_of(Path(e.path))
            if n:
                used.add(n)
    return used


def _remove_unreferenced_sidecars(path: Path, keep: str, old: str | None) -> None:
    """After the new JSON is in place: remove the old sidecar and orphans of killed saves of this profile.

    Only files this profile wrote (its old sidecar, or ``<stem>.<16 hex>.samples.npz``) and that no other
    profile JSON of the folder names are removed; failures leave an orphan, never a broken profile.
    """
    folder = path.parent if str(path.parent) else Path(".")
    pattern = re.compile(_SIDECAR_RE.format(stem=re.escape(path.stem)))
    candidates = set()
    if old and old != keep:
        candidates.add(old)
    try:
        candidates |= {n for n in os.listdir(folder) if pattern.fullmatch(n) and n != keep}
    except OSError:
        return
    if not candidates:
        return
    in_use = _sidecars_in_use(folder, skip=path) | {keep}
    for name in candidates - in_use:
        f = folder / name
        try:
            if f.is_file() and not f.is_symlink():
                f.unlink()
        except OSError:
            pass


def profile_files(path: str | Path) -> list[Path]:
    """A profile JSON and the sidecar it names (for protecting a command's inputs); a lens spec alone."""
    path = Path(path)
    files = [path]
    name = _sidecar_of(path)
    if name:
        files.append(path.with_name(name))
    return files


def _read_sidecar(side: dict | None, path: Path) -> dict[str, np.ndarray]:
    """The sidecar's arrays: a bare file name beside the profile (schema), inside its folder, matching its sha256.

    The sha256 is required: without it any .npz beside the JSON would be taken as this profile's samples.
    """
    if not isinstance(side, dict) or not isinstance(side.get("file"), str):
        raise SpecError("names no samples sidecar", path=path, field="sidecar",
                        fix="regenerate the profile with `fieldcal calibrate` (it writes the JSON and its .npz "
                            "together)")
    if not _SHA256.fullmatch(str(side.get("sha256", ""))):
        raise SpecError("the sidecar's sha256 is missing or not 64 hex digits, so its samples cannot be trusted",
                        path=path, field="sidecar.sha256",
                        fix="restore the profile as `fieldcal calibrate` wrote it, or recalibrate")
    name = side["file"]
    if not name or name != Path(name).name or name in (".", ".."):
        raise SpecError(f"the sidecar must be a file name beside the profile, got {name!r}", path=path,
                        field="sidecar.file", fix="restore the profile as `fieldcal calibrate` wrote it")
    sp = path.with_name(name)
    if sp.is_symlink() or (sp.exists() and sp.resolve().parent != path.resolve().parent):
        raise SpecError(f"the sidecar {name!r} is not a file in the profile's folder", path=path,
                        field="sidecar.file", fix="keep the sidecar itself next to the profile (not a link)")
    if not sp.is_file():
        raise SpecError(f"the posterior-samples sidecar {sp.name} is missing", path=path, field="sidecar.file",
                        fix=f"copy {sp.name} next to {path.name} (they are written together)")
    try:
        raw = sp.read_bytes()
    except OSError as e:
        raise SpecError(f"the sidecar {sp.name} cannot be read ({e.strerror or e})", path=sp,
                        field="sidecar.file", fix="check the file and its permissions") from None
    if hashlib.sha256(raw).hexdigest() != side["sha256"].lower():
        raise SpecError(f"the sidecar {sp.name} does not belong to this profile (sha256 differs)",
                        path=path, field="sidecar.sha256",
                        fix=f"copy the {sp.name} written with this profile, or recalibrate")
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise SpecError(f"the sidecar {sp.name} is not a readable .npz ({exc})", path=sp, field="sidecar.file",
                        fix="recalibrate: the sidecar is written with the profile") from None


def load_profile_or_truth(path: str | Path, size_px: tuple[int, int] | None = None):
    """A lens profile, or the exact answers of a simulated lens — whichever the file holds. The one loader.

    Returns ``(profile, info)``. A ``fieldcal-lens/1`` spec (or a simulated stack's ``fieldcal-truth/1``
    truth.json) gives its :class:`fieldcal.simulate.truth.TruthProfile` at ``size_px`` (design studies and
    simulated data; a truth.json defaults to the size it was rendered at); a ``fieldcal-profile/1`` file gives a
    :class:`LensProfile` (``size_px`` does not apply to it). ``info`` says which, for plans, composites and reports.
    The file is read once, through :mod:`fieldcal.formats.documents`.
    """
    path = Path(path)
    head = documents.read_json(path, not_found="profile not found",
                               not_found_fix="give a profile from `fieldcal calibrate` or a lens spec such as "
                                             "models/triplet-uncorrected.json")
    fmt = head.get("format") if isinstance(head, dict) else None
    if isinstance(fmt, str) and fmt.startswith(("fieldcal-lens/", "fieldcal-truth/")):
        from fieldcal.simulate.lens import LensSpec
        from fieldcal.simulate.truth import TruthProfile, truth_lens
        if fmt.startswith("fieldcal-truth/"):
            spec, rendered = truth_lens(head, path)
            size_px = size_px or rendered
        else:
            spec = LensSpec.from_dict(head, path=path)
        prof = TruthProfile(spec, *(size_px or (None, None)))
        return prof, {"path": str(path), "format": fmt, "name": spec.name,
                      "source": "lens spec: the simulated lens's true surfaces",
                      "image_size_px": list(prof.image_size_px)}
    prof = LensProfile.from_document(head, path)
    return prof, {"path": str(path), "format": fmt, "name": path.stem, "source": "lens profile (calibrated)",
                  "image_size_px": list(prof.image_size_px)}
