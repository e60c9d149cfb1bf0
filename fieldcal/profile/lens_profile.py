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
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from fieldcal import __version__
from fieldcal.formats.atomic import atomic_write_bytes, atomic_write_text, jsonable
from fieldcal.errors import ParameterError, SpecError

PROFILE_FORMAT = "fieldcal-profile/1"
PROFILE_VERSION = 1


def _check_points(x, y):
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    try:
        np.broadcast(x, y)
    except ValueError:
        raise ParameterError(f"x and y do not broadcast ({x.shape} vs {y.shape})", field="x, y",
                             fix="pass arrays of the same shape") from None
    return x, y


@dataclass
class LensProfile:
    """A calibrated lens: per-channel best-focus surfaces with uncertainty, geometry vs z, tolerance model.

    Build with :func:`fieldcal.calibrate`; read with :meth:`load`; write with :meth:`save`.
    """

    surfaces: Any                       # fieldcal.fit.SurfaceFit
    geometry_fit: Any                   # fieldcal.fit.geometry.GeometryFit
    tolerance_fit: Any | None           # fieldcal.fit.tolerance.ToleranceFit (None: use the defocus model)
    image: dict                         # width_px, height_px, pixel_pitch_um, channels, cfa
    optics: dict                        # f_number, focal_length_mm, object_distance_mm (None when unknown)
    calibration: dict                   # fs_cyc_per_mm, q, effort, tile_px, z_range_um, z_step_um, ...
    z_ref_um: float
    diagnostics: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    tiles: dict | None = None           # tile table columns (for reports)
    geometry_measurements: dict | None = None
    source_path: str | None = None

    # ------------------------------------------------------------------------------ the DESIGN.md API
    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(self.image["channels"])

    def _channel(self, channel: str) -> str:
        if channel not in self.channels:
            raise ParameterError(f"no channel {channel!r} in this profile (it has {', '.join(self.channels)})",
                                 field="channel", fix=f"use one of {', '.join(self.channels)}")
        return channel

    def best_focus_um(self, x, y, channel: str):
        """MAP best-focus stage position (µm) at pixel(s) (x, y) of the z_ref geometry."""
        x, y = _check_points(x, y)
        return self.surfaces.predict(x, y, self._channel(channel))

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
        sys_sd = math.hypot(sys_sd, float(breathing))
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
        fn = getattr(self.geometry_fit, "lateral_colour_scale", None)
        return float(fn(self._channel(channel))) if fn else 1.0

    def wavelength_nm(self, channel: str) -> float:
        from fieldcal.simulate.lens import DEFAULT_WAVELENGTH_NM
        wl = self.optics.get("wavelength_nm", {}) or {}
        return float(wl.get(channel, DEFAULT_WAVELENGTH_NM.get(channel, 550.0)))

    def best_focus_sd_um(self, x, y, channel: str):
        x, y = _check_points(x, y)
        return self.surfaces.sd(x, y, self._channel(channel))

    def focus_tolerance_um(self, x, y, channel: str, fs_cyc_per_mm: float, q: float):
        """Half-width (µm) of the defocus range in which MTF(fs) stays within q of its peak.

        From the measured through-focus widths when the profile has them, else from the geometric defocus
        model with the stack's F-number (``has_measured_tolerance`` says which).
        """
        x, y = _check_points(x, y)
        ch = self._channel(channel)
        if self.tolerance_fit is not None:
            return np.asarray(self.tolerance_fit.tolerance_um(x, y, ch, fs_cyc_per_mm, q), dtype=np.float64)
        if not self.f_number:
            raise SpecError("the profile has neither measured widths nor an F-number for the defocus model",
                            path=self.source_path, field="optics.f_number",
                            fix="recalibrate from a stack whose stack.json gives f_number")
        from fieldcal.simulate.lens import focus_tolerance_um
        t = focus_tolerance_um(fs_cyc_per_mm, q, float(self.f_number), self.wavelength_nm(ch))
        return np.full(np.broadcast(x, y).shape, t)

    def defocus_mtf(self, f_cyc_per_mm, defocus_um, channel: str):
        """MTF of the geometric defocus + diffraction model (needs the F-number)."""
        from fieldcal.simulate.lens import defocus_otf, diffraction_mtf
        n = float(self.f_number or 0.0)
        if n <= 0:
            raise SpecError("the profile has no F-number", path=self.source_path, field="optics.f_number",
                            fix="recalibrate from a stack whose stack.json gives f_number")
        return np.abs(defocus_otf(f_cyc_per_mm, defocus_um, n)) * diffraction_mtf(
            f_cyc_per_mm, self.wavelength_nm(channel), n)

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
            raise ParameterError(f"a profile is a .json file, got {path.name!r}", path=path, field="--out",
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
        atomic_write_bytes(sidecar, data)
        d = self.to_dict(sidecar.name, digest)
        atomic_write_text(path, json.dumps(d, indent=1, allow_nan=False) + "\n")
        _remove_unreferenced_sidecars(path, keep=sidecar.name, old=old)
        self.source_path = str(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "LensProfile":
        """Read and validate a profile (and its samples sidecar)."""
        path = Path(path)
        if not path.is_file():
            raise SpecError("profile not found", path=path, fix="give the .json written by `fieldcal calibrate`")
        try:
            d = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise SpecError(f"not valid JSON ({e})", path=path, fix="regenerate it with `fieldcal calibrate`") from None
        if not isinstance(d, dict):
            raise SpecError("a profile must be a JSON object", path=path, fix="regenerate it with `fieldcal calibrate`")
        _check_format(d.get("format"), path)
        for key in ("image", "optics", "calibration", "z_ref_um", "surfaces", "geometry"):
            if key not in d:
                raise SpecError("missing", path=path, field=key, fix="regenerate the profile with `fieldcal calibrate`")
        img = d["image"]
        for key in ("width_px", "height_px", "pixel_pitch_um", "channels"):
            if not isinstance(img, dict) or key not in img:
                raise SpecError("missing", path=path, field=f"image.{key}", fix="regenerate the profile")
        samples = None
        arrays: dict[str, np.ndarray] = {}
        side = d.get("sidecar")
        if not isinstance(side, dict) or not isinstance(side.get("file"), str):
            raise SpecError("names no samples sidecar", path=path, field="sidecar",
                            fix="regenerate the profile with `fieldcal calibrate` (it writes the JSON and its "
                                ".npz together)")
        if not _SHA256.fullmatch(str(side.get("sha256", ""))):
            # without the hash any .npz beside the JSON would be taken as this profile's samples
            raise SpecError("the sidecar's sha256 is missing or not 64 hex digits, so its samples cannot be "
                            "trusted", path=path, field="sidecar.sha256",
                            fix="restore the profile as `fieldcal calibrate` wrote it, or recalibrate")
        name = side["file"]
        if not name or name != Path(name).name or name in (".", ".."):
            raise SpecError(f"the sidecar must be a file name beside the profile, got {name!r}", path=path,
                            field="sidecar.file", fix="restore the profile as `fieldcal calibrate` wrote it")
        sp = path.with_name(name)
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
                arrays = {k: z[k] for k in z.files}
        except (ValueError, OSError, EOFError) as e:  # hash matched, so the writer made a bad file
            raise SpecError(f"the sidecar {sp.name} cannot be read as .npz ({e})", path=sp, field="sidecar.file",
                            fix="recalibrate") from None
        samples = arrays.get("surface_samples")
        from fieldcal.fit import SurfaceFit
        from fieldcal.fit.geometry import GeometryFit
        surfaces = SurfaceFit.from_dict(d["surfaces"], samples=samples, path=path)
        geometry = GeometryFit.from_dict(d["geometry"])
        tolerance = None
        if d.get("tolerance"):
            from fieldcal.fit.tolerance import ToleranceFit
            tolerance = ToleranceFit.from_dict(d["tolerance"])
        tiles = {k[len("tiles__"):]: v for k, v in arrays.items() if k.startswith("tiles__")} or None
        geom = {k[len("geom__"):]: v for k, v in arrays.items() if k.startswith("geom__")} or None
        prov = dict(d.get("provenance", {}))
        prov.setdefault("created_utc", d.get("created_utc"))
        prov.setdefault("tool", d.get("tool"))
        return cls(surfaces=surfaces, geometry_fit=geometry, tolerance_fit=tolerance, image=dict(img),
                   optics=dict(d["optics"]), calibration=dict(d["calibration"]), z_ref_um=float(d["z_ref_um"]),
                   diagnostics=dict(d.get("diagnostics", {})), provenance=prov, tiles=tiles,
                   geometry_measurements=geom, source_path=str(path))


_SHA256 = re.compile(r"[0-9a-fA-F]{64}")
_SIDECAR_RE = r"{stem}\.[0-9a-f]{{16}}\.samples\.npz"


def sidecar_name(path: str | Path, sha256_hex: str) -> str:
    """The content-addressed sidecar name of profile ``path``: ``<stem>.<sha256[:16]>.samples.npz``."""
    return f"{Path(path).stem}.{sha256_hex[:16]}.samples.npz"


def _sidecar_of(json_path: Path) -> str | None:
    """The plain file name an existing profile JSON gives as its sidecar (None if unreadable or not plain)."""
    try:
        if not json_path.is_file() or json_path.is_symlink() or json_path.stat().st_size > (64 << 20):
            return None
        d = json.loads(json_path.read_text())
        name = d.get("sidecar", {}).get("file") if isinstance(d, dict) and isinstance(d.get("sidecar"), dict) else None
    except (OSError, ValueError, RecursionError):
        return None
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


def _check_format(fmt, path):
    if fmt == PROFILE_FORMAT:
        return
    m = re.fullmatch(r"fieldcal-profile/(\d+)", str(fmt))
    if m and int(m.group(1)) > PROFILE_VERSION:
        raise SpecError(f"profile format {fmt} is newer than this fieldcal understands ({PROFILE_FORMAT})",
                        path=path, field="format", fix="upgrade fieldcal (pip install -U fieldcal)")
    raise SpecError(f"unknown profile format {fmt!r} (expected {PROFILE_FORMAT!r})", path=path, field="format",
                    fix="give a lens profile written by `fieldcal calibrate`")


def load_profile_or_truth(path: str | Path, size_px: tuple[int, int] | None = None):
    """A lens profile, or the exact answers of a simulated lens — whichever the file holds.

    Returns ``(profile, info)``. A ``fieldcal-lens/1`` spec gives its :class:`fieldcal.simulate.truth.TruthProfile` at
    ``size_px`` (design studies and simulated data); a ``fieldcal-profile/1`` file gives a :class:`LensProfile`
    (``size_px`` does not apply to it). ``info`` says which, for plans, composites and reports.
    """
    path = Path(path)
    if not path.is_file():
        raise SpecError("profile not found", path=path,
                        fix="give a profile from `fieldcal calibrate` or a lens spec such as models/triplet-uncorrected.json")
    try:
        head = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"not valid JSON ({e})", path=path, fix="repair the JSON syntax") from None
    fmt = head.get("format") if isinstance(head, dict) else None
    if isinstance(fmt, str) and fmt.startswith("fieldcal-lens/"):
        from fieldcal.simulate.lens import LensSpec
        from fieldcal.simulate.truth import TruthProfile
        spec = LensSpec.from_dict(head, path=path)
        prof = TruthProfile(spec, *(size_px or (None, None)))
        return prof, {"path": str(path), "format": fmt, "name": spec.name,
                      "source": "lens spec: the simulated lens's true surfaces",
                      "image_size_px": list(prof.image_size_px)}
    prof = LensProfile.load(path)
    return prof, {"path": str(path), "format": fmt, "name": path.stem, "source": "lens profile (calibrated)",
                  "image_size_px": list(prof.image_size_px)}
