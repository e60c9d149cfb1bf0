"""Simulated lens + camera spec (``fieldcal-lens/1``) and the optical model behind it.

One model serves the simulator (what frames look like), the planner (depth-of-focus tolerance when a
profile has no measured width) and validation (the truth). Everything in a spec is in physical units
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

Astigmatism splits it: tangential focus ``z_c + A/2``, sagittal ``z_c - A/2`` with ``A = astigmatism_um[c]
* rho**2``. The renderer uses the isotropic equivalent defocus ``sqrt((dt**2 + ds**2) / 2)``.

Through-focus optics: the OTF at spatial frequency f (cycles/mm) and defocus dz (µm) is the product of

* geometric defocus: a uniform disc of diameter ``b = |dz| / N`` (image-side F-number N) whose OTF is
  ``2 J1(pi b f) / (pi b f)`` (can go negative: contrast reversal);
* diffraction: the incoherent MTF of a circular pupil, cut-off ``1 / (lambda N)``;
* residual aberrations at best focus: a Gaussian of RMS ``residual_blur_um``.

The product is exact at focus and at large defocus and a few-percent approximation between (Stokseth
1969 gives the full defocused-diffraction OTF); docs/simulator.md states this.

Geometry vs z (DESIGN.md): a point at pixel p of the frame at z_ref appears at ``c + m(z) (p - c) + s(z)``
with ``m(z) = 1 + (z - z_ref) / exit_pupil_um`` (non-telecentric image space: focus breathing) and
``s(z) = (z - z_ref) * tan(stage_axis_tilt) / pixel_pitch`` (stage axis not parallel to the optical axis).
Lateral colour is a constant per-channel scale about the optical centre, ``1 + lateral_colour[c]``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import special

from fieldcal.errors import SpecError
from fieldcal.simulate.aberrations import Aberrations, parse_aberrations

LENS_FORMAT = "fieldcal-lens/1"

# Default wavelengths (nm) of the usual channels: the paper's C, e and F lines.
DEFAULT_WAVELENGTH_NM = {"R": 656.3, "G": 546.1, "B": 486.1, "Y": 546.1}


@dataclass(frozen=True)
class ChannelSpec:
    """Best-focus surface and colour properties of one channel."""

    name: str
    wavelength_nm: float
    focus_offset_um: float = 0.0
    curvature_um: tuple[float, ...] = ()
    astigmatism_um: float = 0.0
    lateral_colour: float = 0.0


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
        half = 0.5 * c.astigmatism_um * r2
        if which == "tangential":
            return z + half
        if which == "sagittal":
            return z - half
        raise ValueError(f"which must be 'mean', 'tangential' or 'sagittal', not {which!r}")

    def effective_defocus_um(self, z_um, x_mm, y_mm, channel: str):
        """Isotropic-equivalent defocus (µm, >= 0) at stage position z for a sensor point."""
        c = self.channel(channel)
        dz = np.asarray(z_um, dtype=np.float64) - self.best_focus_um(x_mm, y_mm, channel)
        if c.astigmatism_um == 0.0:
            return np.abs(dz)
        half = 0.5 * c.astigmatism_um * self.rho(x_mm, y_mm) ** 2
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

    def relative_illumination(self, x_mm, y_mm):
        """Vignetting: 1 on axis falling quadratically in rho to ``relative_illumination_edge`` at rho=1."""
        r2 = self.rho(x_mm, y_mm) ** 2
        return np.clip(1.0 - (1.0 - self.relative_illumination_edge) * r2, 0.05, 1.0)

    # ------------------------------------------------------------------ optics
    def otf(self, f_cyc_per_mm, defocus_um, channel: str):
        """Real OTF (may be negative: contrast reversal) at frequency f and isotropic defocus."""
        c = self.channel(channel)
        return otf(f_cyc_per_mm, defocus_um, self.f_number, c.wavelength_nm, self.residual_blur_um)

    def mtf(self, f_cyc_per_mm, defocus_um, channel: str):
        return np.abs(self.otf(f_cyc_per_mm, defocus_um, channel))

    def focus_tolerance_um(self, fs_cyc_per_mm: float, q: float, channel: str) -> float:
        """Half-width of the defocus range over which MTF(fs) stays within a fraction q of its peak."""
        return focus_tolerance_um(fs_cyc_per_mm, q, self.f_number, self.channel(channel).wavelength_nm,
                                  self.residual_blur_um)

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
        if self.aberrations is not None:
            d["aberrations"] = self.aberrations.to_dict()
        d.update(extra)
        return d

    def save(self, path: str | Path) -> None:
        from fieldcal.formats.atomic import atomic_write_text
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "LensSpec":
        path = Path(path)
        if not path.exists():
            raise SpecError("lens spec not found", path=path,
                            fix="give the path to a fieldcal-lens/1 JSON file, e.g. models/triplet-uncorrected.json")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise SpecError(f"not valid JSON ({e})", path=path, fix="repair the JSON syntax") from None
        return cls.from_dict(data, path=path)

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: str | Path | None = None) -> "LensSpec":
        return _lens_from_dict(d, path)


# ---------------------------------------------------------------------------------------------- optics
def defocus_otf(f_cyc_per_mm, defocus_um, f_number: float):
    """Geometric-optics OTF of a uniform blur disc of diameter |dz|/N: 2 J1(x)/x, x = pi b f."""
    b_mm = np.abs(np.asarray(defocus_um, dtype=np.float64)) / f_number / 1000.0
    x = np.pi * b_mm * np.asarray(f_cyc_per_mm, dtype=np.float64)
    small = x < 1e-6
    xs = np.where(small, 1.0, x)  # guard the 0/0 at focus
    return np.where(small, 1.0 - x * x / 8.0, 2.0 * special.j1(xs) / xs)


def diffraction_mtf(f_cyc_per_mm, wavelength_nm: float, f_number: float):
    """Incoherent MTF of an aberration-free circular pupil."""
    fc = 1.0 / (wavelength_nm * 1e-6 * f_number)  # cycles/mm
    v = np.clip(np.abs(np.asarray(f_cyc_per_mm, dtype=np.float64)) / fc, 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(v) - v * np.sqrt(1.0 - v * v))


def gaussian_mtf(f_cyc_per_mm, sigma_um: float):
    s_mm = sigma_um / 1000.0
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    return np.exp(-2.0 * (np.pi * s_mm * f) ** 2)


def otf(f_cyc_per_mm, defocus_um, f_number: float, wavelength_nm: float, residual_blur_um: float):
    """Through-focus OTF of the model (see module docstring)."""
    return (defocus_otf(f_cyc_per_mm, defocus_um, f_number)
            * diffraction_mtf(f_cyc_per_mm, wavelength_nm, f_number)
            * gaussian_mtf(f_cyc_per_mm, residual_blur_um))


def focus_tolerance_um(fs_cyc_per_mm: float, q: float, f_number: float, wavelength_nm: float = 546.1,
                       residual_blur_um: float = 0.0) -> float:
    """Defocus |dz| at which MTF(fs) has fallen to (1 - q) of its in-focus value.

    Only the defocus factor depends on dz, so this solves 2 J1(x)/x = 1 - q with x = pi (dz/N) fs.
    Check: fs = 80 cycles/mm, q = 0.05, F/2 gives 5.08 µm; ray tracing the paper's triplet gives
    -5.4/+6.1 µm on axis (shared/lenses/paper-triplet-uncorrected.md).
    """
    if not (0.0 < q < 1.0) or not math.isfinite(q):
        raise ValueError("q must be in (0, 1)")
    if not (fs_cyc_per_mm > 0.0) or not math.isfinite(fs_cyc_per_mm):
        raise ValueError("fs must be > 0")
    from scipy.optimize import brentq
    # 2 J1(x)/x decreases monotonically from 1 to 0 on [0, j1] (j1 = 3.8317..., the first zero of J1).
    # As q -> 1 the target 1 - q drops below the rounding floor of 2 J1(x)/x near j1, where brentq would find
    # no sign change: the tolerance is then the first zero itself (the contrast is lost entirely there).
    j1 = float(special.jn_zeros(1, 1)[0])
    target = 1.0 - q

    def d(t):
        return (2.0 * special.j1(t) / t if t > 1e-12 else 1.0) - target

    x = j1 if d(j1) >= 0.0 else brentq(d, 1e-12, j1)
    b_mm = x / (math.pi * fs_cyc_per_mm)
    return float(b_mm * f_number * 1000.0)


# ------------------------------------------------------------------------------------------ validation
def _lens_from_dict(d: Any, path) -> LensSpec:
    def err(field, what, fix):
        return SpecError(what, path=path, field=field, fix=fix)

    if not isinstance(d, dict):
        raise err(None, "a lens spec must be a JSON object", "see docs/lens-spec.md")
    fmt = d.get("format")
    if fmt != LENS_FORMAT:
        raise err("format", f"unknown lens spec format {fmt!r}; this fieldcal reads {LENS_FORMAT!r}",
                  f"set \"format\": \"{LENS_FORMAT}\" (or upgrade fieldcal if the file is newer)")

    def num(key, src=d, prefix="", positive=False, nonneg=False, default=None, allow_none=False):
        full = prefix + key
        if key not in src:
            if default is not None or allow_none:
                return default
            raise err(full, "missing", f"add \"{key}\" (see docs/lens-spec.md)")
        v = src[key]
        if v is None and allow_none:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise err(full, f"must be a finite number, got {v!r}", "write a number")
        if positive and v <= 0:
            raise err(full, f"must be > 0, got {v}", "use a positive value")
        if nonneg and v < 0:
            raise err(full, f"must be >= 0, got {v}", "use a non-negative value")
        return float(v)

    def pair(key, default=(0.0, 0.0)):
        v = d.get(key, list(default))
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or not all(isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in v)):
            raise err(key, f"must be a list of two finite numbers, got {v!r}", "e.g. [0.0, 0.0]")
        return (float(v[0]), float(v[1]))

    name = d.get("name", Path(path).stem if path else "lens")
    sens = d.get("sensor")
    if not isinstance(sens, dict):
        raise err("sensor", "missing or not an object", "add a sensor block (width_px, height_px, pixel_pitch_um, ...)")
    try:
        w = int(sens["width_px"]); h = int(sens["height_px"])
    except (KeyError, TypeError, ValueError):
        raise err("sensor.width_px", "sensor width_px and height_px must be integers", "e.g. 2592 and 1944") from None
    if w < 8 or h < 8:
        raise err("sensor.width_px", f"sensor of {w}x{h} px is too small", "use at least 8x8 pixels")
    bit_depth = int(sens.get("bit_depth", 12))
    if bit_depth not in (8, 10, 12, 14, 16, 32):
        raise err("sensor.bit_depth", f"unsupported bit depth {bit_depth}", "use 8, 10, 12, 14, 16 or 32 (float)")
    cfa = sens.get("cfa")
    if cfa is not None and cfa not in ("RGGB", "BGGR", "GRBG", "GBRG"):
        raise err("sensor.cfa", f"unknown CFA pattern {cfa!r}", "use RGGB, BGGR, GRBG, GBRG or null")
    sensor = SensorSpec(
        width_px=w, height_px=h,
        pixel_pitch_um=num("pixel_pitch_um", sens, "sensor.", positive=True),
        bit_depth=bit_depth,
        black_level_dn=num("black_level_dn", sens, "sensor.", nonneg=True, default=0.0),
        full_well_e=num("full_well_e", sens, "sensor.", positive=True, default=10000.0),
        read_noise_e=num("read_noise_e", sens, "sensor.", nonneg=True, default=2.0),
        cfa=cfa,
        exposure_ms=num("exposure_ms", sens, "sensor.", positive=True, default=10.0),
        signal_fraction=num("signal_fraction", sens, "sensor.", positive=True, default=0.7),
    )
    chans = d.get("channels")
    if not isinstance(chans, list) or not chans:
        raise err("channels", "must be a non-empty list of channel objects", "e.g. [{\"name\": \"G\", ...}]")
    channels = []
    for i, c in enumerate(chans):
        pre = f"channels[{i}]."
        if not isinstance(c, dict) or "name" not in c:
            raise err(f"channels[{i}]", "each channel needs a name", "add \"name\": \"R\" (R, G, B or Y)")
        cname = str(c["name"])
        curv = c.get("curvature_um", [])
        if not isinstance(curv, (list, tuple)) or not all(isinstance(a, (int, float)) and math.isfinite(a) for a in curv):
            raise err(pre + "curvature_um", "must be a list of finite numbers (µm at rho^2, rho^4, ...)", "e.g. [-294.3, -19.5]")
        channels.append(ChannelSpec(
            name=cname,
            wavelength_nm=num("wavelength_nm", c, pre, positive=True, default=DEFAULT_WAVELENGTH_NM.get(cname, 550.0)),
            focus_offset_um=num("focus_offset_um", c, pre, default=0.0),
            curvature_um=tuple(float(a) for a in curv),
            astigmatism_um=num("astigmatism_um", c, pre, default=0.0),
            lateral_colour=num("lateral_colour", c, pre, default=0.0),
        ))
    names = [c.name for c in channels]
    if len(set(names)) != len(names):
        raise err("channels", f"duplicate channel names {names}", "give each channel a distinct name")
    if cfa is not None and sorted(set(names)) != ["B", "G", "R"]:
        raise err("sensor.cfa", "a Bayer sensor needs exactly channels R, G, B", "set channels to R, G, B or cfa to null")
    exit_pupil = d.get("exit_pupil_mm")
    if exit_pupil is None:
        exit_pupil = math.inf
    else:
        exit_pupil = num("exit_pupil_mm")
        if exit_pupil == 0:
            raise err("exit_pupil_mm", "cannot be 0", "use null for a telecentric image space")
    known = {"format", "name", "focal_length_mm", "f_number", "image_height_max_mm", "channels", "sensor",
             "object_distance_mm", "decentre_mm", "tilt_um_per_mm", "exit_pupil_mm", "stage_axis_tilt_mrad",
             "z_ref_um", "residual_blur_um", "relative_illumination_edge", "description", "sources", "aberrations"}
    ri = num("relative_illumination_edge", default=1.0)
    if not (0.05 <= ri <= 1.0):
        raise err("relative_illumination_edge", f"must be in [0.05, 1], got {ri}", "e.g. 0.8 for 20% corner fall-off")
    return LensSpec(
        name=str(name),
        focal_length_mm=num("focal_length_mm", positive=True),
        f_number=num("f_number", positive=True),
        image_height_max_mm=num("image_height_max_mm", positive=True),
        channels=tuple(channels),
        sensor=sensor,
        object_distance_mm=num("object_distance_mm", positive=True, default=1000.0),
        decentre_mm=pair("decentre_mm"),
        tilt_um_per_mm=pair("tilt_um_per_mm"),
        exit_pupil_mm=exit_pupil,
        stage_axis_tilt_mrad=pair("stage_axis_tilt_mrad"),
        z_ref_um=num("z_ref_um", default=0.0),
        residual_blur_um=num("residual_blur_um", nonneg=True, default=0.5),
        relative_illumination_edge=ri,
        description=str(d.get("description", "")),
        sources=dict(d.get("sources", {})) if isinstance(d.get("sources", {}), dict) else {},
        extra={k: v for k, v in d.items() if k not in known},
        aberrations=(parse_aberrations(d["aberrations"], path, tuple(names))
                     if d.get("aberrations") is not None else None),
    )
