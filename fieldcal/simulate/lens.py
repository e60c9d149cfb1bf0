"""Simulated lens + camera spec (``fieldcal-lens/1``) and the optical model behind it.

One spec serves the simulator (what frames look like) and validation (the truth, through
:class:`fieldcal.simulate.truth.TruthProfile`). Everything in a spec is in physical units
(mm on the sensor, µm along the axis), never pixels, so one spec renders at any image size.

Coordinates
-----------
* Stage position ``z_um``: along the optical axis, +z moves the sensor *away* from the lens.
* Sensor position ``(x_mm, y_mm)``: relative to the sensor centre, x right, y down.
* The optical centre sits at ``decentre_mm`` from the sensor centre; image height
  ``h = |(x, y) - decentre|`` and normalised radius ``rho = h / image_height_max_mm``.

Best-focus surface of channel c (µm, stage coordinates)::

    z_c(x, y) = focus_offset_um[c] + sum_k curvature_um[c][k] * rho**(2k+2)
                + tilt_um_per_mm[0] * x_mm + tilt_um_per_mm[1] * y_mm

Astigmatism splits it: tangential focus ``z_c + A/2``, sagittal ``z_c - A/2`` with the field polynomial
``A(rho) = sum_k a_k rho**(2k+2)``; ``astigmatism_um`` is a number (``a_0``, the rho^2 term, as before) or a list
``[a_0, a_1, ...]`` (rho^2, rho^4, rho^6, ...), so that A can follow a traced T - S that peaks inside the field.
Both renderers draw it anisotropic and radially oriented: the geometric path as the elliptical defocus PSF
(diameters ``|z - z_T| / N`` radially, ``|z - z_S| / N`` azimuthally; ``simulate.astigmatism``), the wave path
from the pupil (``simulate.wave.terms_at``). :meth:`LensSpec.effective_defocus_um` is the isotropic equivalent
``sqrt((dt**2 + ds**2) / 2)`` (the geometric renderer's ``astigmatism="isotropic"``).

Through-focus optics: :func:`fieldcal.optics.through_focus_otf` (geometric defocus disc x diffraction x a
Gaussian of RMS ``residual_blur_um``), with this spec's F-number and channel wavelengths; the focus tolerance
is :func:`fieldcal.optics.focus_tolerance_um`. docs/simulator.md states the model's accuracy.

Geometry vs z (DESIGN.md): a point at pixel p of the frame at z_ref appears at ``c + m(z) (p - c) + s(z)``
with ``m(z) = 1 + (z - z_ref) / exit_pupil_um`` (non-telecentric image space: focus breathing) and
``s(z) = (z - z_ref) * tan(stage_axis_tilt) / pixel_pitch`` (stage axis not parallel to the optical axis).
Lateral colour is a constant per-channel scale about the optical centre, ``1 + lateral_colour[c]``.

Distortion (optional block ``distortion``, all terms 0 by default): Brown-Conrady radial (k1, k2) and tangential
(p1, p2) terms in the normalised coordinates ``w = (p - c) / image_height_max`` (sensor mm) about the optical
centre, each changing linearly with z (``k1(z) = k1 + dk1_dz_per_um (z - z_ref)``)::

    D_z(w) = w (1 + k1 r^2 + k2 r^4) + (2 p1 wx wy + p2 (r^2 + 2 wx^2), p1 (r^2 + 2 wy^2) + 2 p2 wx wy)

The full map of channel c from the (undistorted) scene to the sensor at z (:meth:`LensSpec.sensor_px`) is
``c + m(z) (1 + lateral_colour[c]) D_z(p - c) + s(z)``: the image is distorted and then scaled by breathing
and lateral colour, so a distortion that does not change with z cancels out of frame-to-frame maps.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from fieldcal.errors import SpecError
from fieldcal.optics import MTFCriterion, default_wavelength_nm, focus_tolerance_um, through_focus_otf
from fieldcal.formats import documents
from fieldcal.simulate.aberrations import Aberrations, parse_aberrations

LENS_FORMAT = documents.format_id("lens")


@dataclass(frozen=True)
class ChannelSpec:
    """Best-focus surface and colour properties of one channel."""

    name: str
    wavelength_nm: float
    focus_offset_um: float = 0.0
    curvature_um: tuple[float, ...] = ()
    astigmatism_um: float = 0.0
    lateral_colour: float = 0.0
    astigmatism_higher_um: tuple[float, ...] = ()  # rho^4, rho^6, ... terms of A (astigmatism_um is rho^2's)

    def astigmatism_at(self, rho) -> np.ndarray:
        """Tangential - sagittal focus ``A(rho)`` (µm) at normalised field height(s) rho."""
        r2 = np.asarray(rho, dtype=np.float64) ** 2
        p = r2
        a = self.astigmatism_um * p
        for c in self.astigmatism_higher_um:
            p = p * r2
            a = a + c * p
        return a

    @property
    def has_astigmatism(self) -> bool:
        return self.astigmatism_um != 0.0 or any(self.astigmatism_higher_um)

    def astigmatism_json(self) -> float | list[float]:
        """The document's ``astigmatism_um``: a number for a pure rho^2 term (old documents unchanged), else a list."""
        if not any(self.astigmatism_higher_um):
            return float(self.astigmatism_um)
        return [float(self.astigmatism_um), *(float(v) for v in self.astigmatism_higher_um)]


@dataclass(frozen=True)
class Distortion:
    """Radial (k1, k2) and tangential (p1, p2) distortion about the optical centre, each linear in z.

    Coefficients are dimensionless, in coordinates normalised by ``image_height_max_mm``; ``d*_dz_per_um`` are
    their changes per µm of stage travel from ``z_ref_um``. All zero: no distortion.
    """

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    dk1_dz_per_um: float = 0.0
    dk2_dz_per_um: float = 0.0
    dp1_dz_per_um: float = 0.0
    dp2_dz_per_um: float = 0.0

    @property
    def is_zero(self) -> bool:
        return not any(getattr(self, f) for f in self.__dataclass_fields__)

    def at(self, dz_um: float) -> tuple[float, float, float, float]:
        """(k1, k2, p1, p2) at ``dz_um`` from z_ref."""
        return (self.k1 + self.dk1_dz_per_um * dz_um, self.k2 + self.dk2_dz_per_um * dz_um,
                self.p1 + self.dp1_dz_per_um * dz_um, self.p2 + self.dp2_dz_per_um * dz_um)


def brown_conrady(wx, wy, k1: float, k2: float, p1: float, p2: float):
    """Distorted normalised coordinates of undistorted ones (radial k1, k2; tangential p1, p2)."""
    r2 = wx * wx + wy * wy
    radial = 1.0 + r2 * (k1 + k2 * r2)
    return (wx * radial + 2.0 * p1 * wx * wy + p2 * (r2 + 2.0 * wx * wx),
            wy * radial + p1 * (r2 + 2.0 * wy * wy) + 2.0 * p2 * wx * wy)


def brown_conrady_inverse(ux, uy, k1: float, k2: float, p1: float, p2: float, iterations: int = 50):
    """Undistorted normalised coordinates of distorted ones (fixed-point iteration, to 1e-13).

    Raises :class:`SpecError` where there is none: a strong barrel distortion folds the image (the radial
    factor turns back before the sensor's edge).
    """
    ux = np.asarray(ux, dtype=np.float64)
    uy = np.asarray(uy, dtype=np.float64)
    wx, wy = ux.copy(), uy.copy()
    err = np.inf
    with np.errstate(over="ignore", invalid="ignore"):
        for _ in range(iterations):
            dx, dy = brown_conrady(wx, wy, k1, k2, p1, p2)
            ex, ey = dx - ux, dy - uy
            wx, wy = wx - ex, wy - ey
            err = max(np.max(np.abs(ex), initial=0.0), np.max(np.abs(ey), initial=0.0))
            if not err >= 1e-13:  # converged (or NaN: caught below)
                break
    if not (np.isfinite(err) and err < 1e-9):
        raise SpecError(f"the distortion (k1 {k1:.4g}, k2 {k2:.4g}, p1 {p1:.4g}, p2 {p2:.4g}) folds the image: "
                        "some sensor points see no scene point", field="distortion",
                        fix="use smaller distortion terms (|k1| below ~0.1 over the sensor), or a smaller change "
                            "with z (d*_dz_per_um) over the scan")
    return wx, wy


@dataclass(frozen=True)
class SensorSpec:
    """The simulated camera: geometry, radiometry and noise."""

    width_px: int
    height_px: int
    pixel_pitch_um: float
    bit_depth: int = 12
    black_level_dn: float = 0.0
    full_well_e: float = 10000.0
    read_noise_e: float = 2.0
    cfa: str | None = None  # e.g. "RGGB": write a raw Bayer mosaic instead of demosaiced channels
    exposure_ms: float = 10.0
    signal_fraction: float = 0.7  # mean scene brightness as a fraction of full well (exposure setting)

    @property
    def white_level_dn(self) -> int:
        return (1 << self.bit_depth) - 1 if self.bit_depth < 32 else 1

    @property
    def size_mm(self) -> tuple[float, float]:
        return (self.width_px * self.pixel_pitch_um / 1000.0, self.height_px * self.pixel_pitch_um / 1000.0)


@dataclass(frozen=True)
class LensSpec:
    """A simulated lens on a simulated camera. Load with :meth:`load`, save with :meth:`save`."""

    name: str
    focal_length_mm: float
    f_number: float
    image_height_max_mm: float
    channels: tuple[ChannelSpec, ...]
    sensor: SensorSpec
    object_distance_mm: float = 1000.0
    decentre_mm: tuple[float, float] = (0.0, 0.0)
    tilt_um_per_mm: tuple[float, float] = (0.0, 0.0)
    exit_pupil_mm: float = math.inf
    stage_axis_tilt_mrad: tuple[float, float] = (0.0, 0.0)
    z_ref_um: float = 0.0
    residual_blur_um: float = 0.5
    relative_illumination_edge: float = 1.0
    description: str = ""
    sources: dict[str, str] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    aberrations: Aberrations | None = None  # wave-optics terms (fieldcal.simulate.aberrations); None = none
    distortion: Distortion = field(default_factory=Distortion)

    # ------------------------------------------------------------------ access
    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    def channel(self, name: str) -> ChannelSpec:
        for c in self.channels:
            if c.name == name:
                return c
        raise SpecError(f"no channel '{name}' in lens '{self.name}' (it has {', '.join(self.channel_names)})",
                        field="channels", fix=f"use one of {', '.join(self.channel_names)}")

    def with_sensor_size(self, width_px: int, height_px: int) -> "LensSpec":
        """Same lens and sensor area sampled with fewer/more pixels (pitch rescaled to keep the field)."""
        s = self.sensor
        pitch = s.pixel_pitch_um * max(s.width_px / width_px, s.height_px / height_px)
        return replace(self, sensor=replace(s, width_px=int(width_px), height_px=int(height_px),
                                            pixel_pitch_um=float(pitch)))

    # --------------------------------------------------------------- geometry
    def pixel_to_mm(self, x_px, y_px, width_px: int | None = None, height_px: int | None = None,
                    pixel_pitch_um: float | None = None):
        """Pixel coordinates (origin at the centre of the top-left pixel) to sensor mm from the sensor centre."""
        w = self.sensor.width_px if width_px is None else width_px
        h = self.sensor.height_px if height_px is None else height_px
        p = self.sensor.pixel_pitch_um if pixel_pitch_um is None else pixel_pitch_um
        x = (np.asarray(x_px, dtype=np.float64) - (w - 1) / 2.0) * p / 1000.0
        y = (np.asarray(y_px, dtype=np.float64) - (h - 1) / 2.0) * p / 1000.0
        return x, y

    def optical_centre_px(self, width_px: int | None = None, height_px: int | None = None,
                          pixel_pitch_um: float | None = None) -> tuple[float, float]:
        w = self.sensor.width_px if width_px is None else width_px
        h = self.sensor.height_px if height_px is None else height_px
        p = self.sensor.pixel_pitch_um if pixel_pitch_um is None else pixel_pitch_um
        return ((w - 1) / 2.0 + self.decentre_mm[0] * 1000.0 / p,
                (h - 1) / 2.0 + self.decentre_mm[1] * 1000.0 / p)

    def rho(self, x_mm, y_mm):
        """Normalised image height about the optical centre."""
        dx = np.asarray(x_mm, dtype=np.float64) - self.decentre_mm[0]
        dy = np.asarray(y_mm, dtype=np.float64) - self.decentre_mm[1]
        return np.hypot(dx, dy) / self.image_height_max_mm

    def best_focus_um(self, x_mm, y_mm, channel: str, which: str = "mean"):
        """Best-focus stage position (µm) at sensor position (mm from the sensor centre).

        ``which``: "mean" (circle of least confusion), "tangential" or "sagittal".
        """
        c = self.channel(channel)
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        r2 = self.rho(x, y) ** 2
        z = np.full(np.broadcast(x, y).shape, c.focus_offset_um, dtype=np.float64)
        p = np.ones_like(z)
        for a in c.curvature_um:
            p = p * r2
            z = z + a * p
        z = z + self.tilt_um_per_mm[0] * x + self.tilt_um_per_mm[1] * y
        if which == "mean":
            return z
        half = 0.5 * c.astigmatism_at(np.sqrt(r2))
        if which == "tangential":
            return z + half
        if which == "sagittal":
            return z - half
        raise ValueError(f"which must be 'mean', 'tangential' or 'sagittal', not {which!r}")

    def effective_defocus_um(self, z_um, x_mm, y_mm, channel: str):
        """Isotropic-equivalent defocus (µm, >= 0) at stage position z for a sensor point."""
        c = self.channel(channel)
        dz = np.asarray(z_um, dtype=np.float64) - self.best_focus_um(x_mm, y_mm, channel)
        if not c.has_astigmatism:
            return np.abs(dz)
        half = 0.5 * c.astigmatism_at(self.rho(x_mm, y_mm))
        return np.sqrt(0.5 * ((dz - half) ** 2 + (dz + half) ** 2))

    def magnification(self, z_um, channel: str | None = None):
        """Image scale at z relative to z_ref, same channel (1.0 at z_ref); DESIGN.md's meaning."""
        dz = np.asarray(z_um, dtype=np.float64) - self.z_ref_um
        if not math.isfinite(self.exit_pupil_mm):
            return np.ones_like(dz)
        return 1.0 + dz / (self.exit_pupil_mm * 1000.0)

    def lateral_colour_scale(self, channel: str) -> float:
        """Constant scale of a channel about the optical centre relative to the nominal image."""
        return 1.0 + self.channel(channel).lateral_colour

    def shift_px(self, z_um, pixel_pitch_um: float | None = None):
        """(dx, dy) image shift in pixels at z relative to z_ref."""
        p = self.sensor.pixel_pitch_um if pixel_pitch_um is None else pixel_pitch_um
        dz = np.asarray(z_um, dtype=np.float64) - self.z_ref_um
        ax, ay = (math.tan(a * 1e-3) for a in self.stage_axis_tilt_mrad)
        return dz * ax / p, dz * ay / p

    def _norm_px(self, pixel_pitch_um: float | None) -> float:
        """Pixels per unit of normalised image height."""
        p = self.sensor.pixel_pitch_um if pixel_pitch_um is None else pixel_pitch_um
        return self.image_height_max_mm * 1000.0 / p

    def sensor_px(self, x_px, y_px, z_um, channel: str, pixel_pitch_um: float | None = None,
                  breathing: bool = True):
        """Where the scene point at pixel (x, y) of the undistorted scene lands on the sensor at z, channel c.

        ``c + m(z) (1 + lateral_colour) D_z(p - c) + s(z)`` (module docstring); ``breathing=False`` leaves
        out m(z) and s(z) (the truth image, in the geometry of z_ref). Pixel coordinates at the spec's sensor
        size (use :meth:`with_sensor_size` for another).
        """
        cx, cy = self.optical_centre_px(pixel_pitch_um=pixel_pitch_um)
        n = self._norm_px(pixel_pitch_um)
        wx = (np.asarray(x_px, dtype=np.float64) - cx) / n
        wy = (np.asarray(y_px, dtype=np.float64) - cy) / n
        # z may be one per point (the truth's focus solve lands each pixel at its own z)
        dz = np.asarray(z_um, dtype=np.float64) - self.z_ref_um if breathing else 0.0
        if not self.distortion.is_zero:
            wx, wy = brown_conrady(wx, wy, *self.distortion.at(dz))
        a = self.lateral_colour_scale(channel) * (np.asarray(self.magnification(z_um)) if breathing else 1.0)
        sx, sy = (self.shift_px(z_um, pixel_pitch_um) if breathing else (0.0, 0.0))
        return cx + a * n * wx + sx, cy + a * n * wy + sy

    def scene_px(self, x_px, y_px, z_um, channel: str, pixel_pitch_um: float | None = None,
                 breathing: bool = True):
        """Inverse of :meth:`sensor_px`: the scene pixel that lands at sensor pixel (x, y)."""
        cx, cy = self.optical_centre_px(pixel_pitch_um=pixel_pitch_um)
        n = self._norm_px(pixel_pitch_um)
        a = self.lateral_colour_scale(channel) * (float(self.magnification(z_um)) if breathing else 1.0)
        sx, sy = ((float(v) for v in self.shift_px(z_um, pixel_pitch_um)) if breathing else (0.0, 0.0))
        ux = (np.asarray(x_px, dtype=np.float64) - cx - sx) / (a * n)
        uy = (np.asarray(y_px, dtype=np.float64) - cy - sy) / (a * n)
        dz = float(z_um) - self.z_ref_um if breathing else 0.0
        if not self.distortion.is_zero:
            ux, uy = brown_conrady_inverse(ux, uy, *self.distortion.at(dz))
        return cx + n * ux, cy + n * uy

    def relative_illumination(self, x_mm, y_mm):
        """Vignetting: 1 on axis falling quadratically in rho to ``relative_illumination_edge`` at rho=1."""
        r2 = self.rho(x_mm, y_mm) ** 2
        return np.clip(1.0 - (1.0 - self.relative_illumination_edge) * r2, 0.05, 1.0)

    # ------------------------------------------------------------------ optics
    def otf(self, f_cyc_per_mm, defocus_um, channel: str):
        """Real OTF (may be negative: contrast reversal) at frequency f and isotropic defocus."""
        c = self.channel(channel)
        return through_focus_otf(f_cyc_per_mm, defocus_um, self.f_number, c.wavelength_nm, self.residual_blur_um)

    def mtf(self, f_cyc_per_mm, defocus_um, channel: str):
        return np.abs(self.otf(f_cyc_per_mm, defocus_um, channel))

    def focus_tolerance_um(self, fs_cyc_per_mm: float, q: float, channel: str) -> float:
        """Half-width of the defocus range over which MTF(fs) stays within a fraction q of its peak."""
        self.channel(channel)  # only the defocus factor depends on dz: δ is the same for every channel
        return focus_tolerance_um(MTFCriterion(fs_cyc_per_mm, q), self.f_number)

    def focus_range_um(self, channels=None) -> tuple[float, float]:
        """(min, max) best focus over the sensor and channels: the paper's D is max - min."""
        s = self.sensor
        xs, ys = np.meshgrid(np.linspace(0, s.width_px - 1, 65), np.linspace(0, s.height_px - 1, 49))
        x, y = self.pixel_to_mm(xs, ys)
        zs = []
        for name in channels or self.channel_names:
            for which in ("mean",):
                zs.append(self.best_focus_um(x, y, name, which))
        zz = np.concatenate([a.ravel() for a in zs])
        return float(zz.min()), float(zz.max())

    # --------------------------------------------------------------------- I/O
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (lists, not tuples), inverse of :meth:`from_dict`."""
        d = json.loads(json.dumps(asdict(self), default=list, allow_nan=True))
        d = {"format": LENS_FORMAT, **d}
        d["exit_pupil_mm"] = None if not math.isfinite(self.exit_pupil_mm) else self.exit_pupil_mm
        extra = d.pop("extra")
        d.pop("aberrations")
        for cd, c in zip(d["channels"], self.channels):
            cd.pop("astigmatism_higher_um", None)
            cd["astigmatism_um"] = c.astigmatism_json()
        if self.distortion.is_zero:  # documents of lenses without distortion stay as they were
            d.pop("distortion")
        if self.aberrations is not None:
            d["aberrations"] = self.aberrations.to_dict()
        d.update(extra)
        return d

    def save(self, path: str | Path) -> None:
        documents.write(path, self.to_dict(), "lens")

    @classmethod
    def load(cls, path: str | Path) -> "LensSpec":
        doc = documents.read(path, "lens", not_found="lens spec not found",
                             not_found_fix="give the path to a fieldcal-lens/1 JSON file, e.g. "
                                           "models/triplet-uncorrected.json")
        return cls.from_dict(doc, path=path)

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: str | Path | None = None, where: str = "") -> "LensSpec":
        """A spec from its ``fieldcal-lens/1`` document (validated against the schema; ``where`` prefixes field
        names when the spec sits inside another document, e.g. truth.json's ``lens``)."""
        return _lens_from_dict(d, path, where)


# ------------------------------------------------------------------------------------------ validation
_KNOWN_KEYS = {"format", "name", "focal_length_mm", "f_number", "image_height_max_mm", "channels", "sensor",
               "object_distance_mm", "decentre_mm", "tilt_um_per_mm", "exit_pupil_mm", "stage_axis_tilt_mrad",
               "z_ref_um", "residual_blur_um", "relative_illumination_edge", "description", "sources", "aberrations",
               "distortion"}


def _astigmatism_fields(a) -> dict[str, Any]:
    """ChannelSpec fields of a document's ``astigmatism_um``: a number is the rho^2 term, a list rho^2, rho^4, ..."""
    if isinstance(a, (list, tuple)):
        vals = [float(v) for v in a] or [0.0]
        return {"astigmatism_um": vals[0], "astigmatism_higher_um": tuple(vals[1:])}
    return {"astigmatism_um": float(a)}


def _lens_from_dict(d: Any, path, where: str = "") -> LensSpec:
    """Types, ranges and required keys are the schema's (fieldcal-lens-1.schema.json); the checks across
    fields a schema cannot express are here."""
    documents.validate(d, "lens", path, where=where)
    pre = f"{where}." if where else ""
    sens = d["sensor"]
    cfa = sens.get("cfa")
    sensor = SensorSpec(
        width_px=int(sens["width_px"]), height_px=int(sens["height_px"]),
        pixel_pitch_um=float(sens["pixel_pitch_um"]), bit_depth=int(sens.get("bit_depth", 12)),
        black_level_dn=float(sens.get("black_level_dn", 0.0)), full_well_e=float(sens.get("full_well_e", 10000.0)),
        read_noise_e=float(sens.get("read_noise_e", 2.0)), cfa=cfa, exposure_ms=float(sens.get("exposure_ms", 10.0)),
        signal_fraction=float(sens.get("signal_fraction", 0.7)))
    channels = tuple(ChannelSpec(
        name=c["name"],
        wavelength_nm=float(c.get("wavelength_nm", default_wavelength_nm(c["name"]))),
        focus_offset_um=float(c.get("focus_offset_um", 0.0)),
        curvature_um=tuple(float(a) for a in c.get("curvature_um", [])),
        **_astigmatism_fields(c.get("astigmatism_um", 0.0)),
        lateral_colour=float(c.get("lateral_colour", 0.0))) for c in d["channels"])
    names = [c.name for c in channels]
    if len(set(names)) != len(names):
        raise SpecError(f"duplicate channel names {names}", path=path, field=pre + "channels",
                        fix="give each channel a distinct name")
    if cfa is not None and sorted(names) != ["B", "G", "R"]:
        raise SpecError("a Bayer sensor needs exactly channels R, G, B", path=path, field=pre + "sensor.cfa",
                        fix="set channels to R, G, B or cfa to null")
    exit_pupil = d.get("exit_pupil_mm")
    pair = lambda key: tuple(float(v) for v in d.get(key, (0.0, 0.0)))  # noqa: E731
    return LensSpec(
        name=str(d.get("name", Path(path).stem if path else "lens")),
        focal_length_mm=float(d["focal_length_mm"]),
        f_number=float(d["f_number"]),
        image_height_max_mm=float(d["image_height_max_mm"]),
        channels=channels,
        sensor=sensor,
        object_distance_mm=float(d.get("object_distance_mm", 1000.0)),
        decentre_mm=pair("decentre_mm"),
        tilt_um_per_mm=pair("tilt_um_per_mm"),
        exit_pupil_mm=math.inf if exit_pupil is None else float(exit_pupil),
        stage_axis_tilt_mrad=pair("stage_axis_tilt_mrad"),
        z_ref_um=float(d.get("z_ref_um", 0.0)),
        residual_blur_um=float(d.get("residual_blur_um", 0.5)),
        relative_illumination_edge=float(d.get("relative_illumination_edge", 1.0)),
        description=str(d.get("description", "")),
        sources=dict(d.get("sources", {})),
        extra={k: v for k, v in d.items() if k not in _KNOWN_KEYS},
        aberrations=(parse_aberrations(d["aberrations"], path, tuple(c["name"] for c in d["channels"]))
                     if d.get("aberrations") is not None else None),
        distortion=Distortion(**{k: float(v) for k, v in (d.get("distortion") or {}).items()}),
    )
