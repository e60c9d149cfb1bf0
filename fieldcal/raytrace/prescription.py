"""Lens prescription tables: parsing and validation (no ray-tracing library needed).

A prescription is a table of surfaces in order from the object side, one row per surface (CSV or JSON)::

    surface, type, radius, thickness, nd, vd, glass, k, a4, a6, a8

* ``surface``: a label (``1``, ``2``, ...); the aperture stop row has ``stop`` here (exactly one).
* ``type``: ``standard`` (sphere/plane) or ``even asphere`` (``k`` conic and ``a4, a6, a8`` coefficients of
  r⁴, r⁶, r⁸ in mm units, Zemax's convention ``z = c r²/(1 + sqrt(1 - (1+k) c² r²)) + a4 r⁴ + ...``).
* ``radius``: mm; ``inf``/``∞``/empty for a plane. ``thickness``: mm to the next surface; the last row's
  thickness is the distance to the (stated) image plane.
* The medium *after* a surface: ``nd`` and ``vd`` (refractive index at 587.56 nm, Abbe number), or a catalogue
  ``glass`` name from :data:`GLASS_CATALOGUE`; both empty for air. Glasses are modelled from (nd, vd) with a
  model-glass dispersion formula (see :func:`model_glass_index`).

CSV files may hold ``#`` comment lines; a comment ``# key: value`` with a key of :data:`META_KEYS` states a
design value (e.g. ``# efl_mm: 17.6``). A JSON file is ``{"surfaces": [{...row...}, ...], "efl_mm": 17.6, ...}``
(or a bare list of rows).
Every mistake raises :class:`~fieldcal.errors.SpecError` naming the file, the row and the column.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import SpecError

COLUMNS = ("surface", "type", "radius", "thickness", "nd", "vd", "glass", "k", "a4", "a6", "a8")
REQUIRED_COLUMNS = ("surface", "type", "radius", "thickness")
# Design values a table may state (CSV "# key: value" comments or JSON keys); the CLI's options override them.
META_KEYS = ("name", "description", "f_number", "image_height_mm", "efl_mm", "bfl_mm")
SURFACE_TYPES = {"standard": "standard", "sphere": "standard", "plane": "standard",
                 "even asphere": "even_asphere", "evenasph": "even_asphere", "even_asphere": "even_asphere",
                 "asphere": "even_asphere"}

# Catalogue glasses (nd, vd) that may be named in the ``glass`` column (Schott / Ohara datasheets).
GLASS_CATALOGUE: dict[str, tuple[float, float]] = {
    "N-BK7": (1.51680, 64.17),
    "N-BAK4": (1.56883, 55.98),
    "N-SK16": (1.62041, 60.32),
    "N-SF5": (1.67271, 32.25),
    "N-SF11": (1.78472, 25.68),
    "N-LAK9": (1.69100, 54.71),
    "F2": (1.62004, 36.37),
    "N-F2": (1.62005, 36.43),
    "N-FK51A": (1.48656, 84.47),
    "N-PK52A": (1.49700, 81.61),
    "S-FPL51": (1.49700, 81.54),
    "S-LAH79": (2.00330, 28.27),
    "FUSED SILICA": (1.45846, 67.82),
}

# Physical bounds for optical glasses and crystals in the visible (catalogue span with margin).
ND_RANGE = (1.2, 2.6)
VD_RANGE = (10.0, 120.0)

LINE_D_NM = 587.56
LINE_F_NM = 486.13
LINE_C_NM = 656.27


@dataclass(frozen=True)
class Surface:
    """One surface and the medium after it (``nd = 1`` for air)."""

    label: str
    kind: str  # "standard" | "even_asphere"
    radius_mm: float  # math.inf for a plane
    thickness_mm: float
    nd: float = 1.0
    vd: float = math.inf
    glass: str = ""
    conic: float = 0.0
    aspheric: tuple[float, float, float] = (0.0, 0.0, 0.0)  # a4, a6, a8 (mm^-3, mm^-5, mm^-7)
    is_stop: bool = False

    @property
    def curvature_per_mm(self) -> float:
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm

    @property
    def is_glass(self) -> bool:
        return self.nd != 1.0


@dataclass(frozen=True)
class Prescription:
    """An ordered list of surfaces from the object side; the last thickness reaches the image plane."""

    surfaces: tuple[Surface, ...]
    name: str = "lens"
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.is_stop)

    @property
    def image_distance_mm(self) -> float:
        """Distance from the last surface to the stated image plane."""
        return self.surfaces[-1].thickness_mm

    def index(self, i: int, wavelength_nm: float) -> float:
        """Refractive index of the medium after surface ``i`` at a wavelength (1 for air)."""
        s = self.surfaces[i]
        if not s.is_glass:
            return 1.0
        return model_glass_index(s.nd, s.vd, wavelength_nm)


def model_glass_index(nd: float, vd: float, wavelength_nm):
    """Refractive index of a model glass given only (nd, vd), at ``wavelength_nm`` (scalar or array).

    Buchdahl's chromatic coordinate ``w = dl / (1 + 2.5 dl)`` (``dl`` in µm from the d line) with the
    quadratic ``n = nd + v1 w + v2 w²``. The two coefficients follow from the Abbe number (``nF - nC =
    (nd - 1) / vd`` exactly) and the "normal line" of the partial dispersion ``P_gF = 0.6438 - 0.001682 vd``
    (Schott's reference line; fixes ``n_g``). For catalogue glasses this reproduces the indices at the
    C, e, F lines to ~1e-4 and at g to a few 1e-4 (they deviate from the normal line by their own dPgF).
    """
    import numpy as np

    def omega(lam_nm):
        dl = (np.asarray(lam_nm, dtype=np.float64) - LINE_D_NM) / 1000.0
        return dl / (1.0 + 2.5 * dl)

    if not math.isfinite(vd):  # dispersion-free medium
        return np.full(np.shape(wavelength_nm), float(nd)) if np.ndim(wavelength_nm) else float(nd)
    dn_fc = (nd - 1.0) / vd
    p_gf = 0.6438 - 0.001682 * vd
    dn_gf = p_gf * dn_fc  # n_g - n_F
    wf, wc, wg = omega(LINE_F_NM), omega(LINE_C_NM), omega(435.83)
    # Solve v1 (wF - wC) + v2 (wF² - wC²) = dn_fc and v1 (wg - wF) + v2 (wg² - wF²) = dn_gf.
    a = np.array([[wf - wc, wf * wf - wc * wc], [wg - wf, wg * wg - wf * wf]])
    v1, v2 = np.linalg.solve(a, np.array([dn_fc, dn_gf]))
    w = omega(wavelength_nm)
    n = nd + v1 * w + v2 * w * w
    return float(n) if np.ndim(n) == 0 else n


# ------------------------------------------------------------------------------------------------ parsing
def load_prescription(path: str | Path) -> Prescription:
    """Read and validate a prescription table (``.csv`` or ``.json``)."""
    path = Path(path)
    if not path.exists():
        raise SpecError("prescription table not found", path=path,
                        fix="give the path to a CSV or JSON table, e.g. models/triplet-uncorrected.prescription.csv")
    if not path.is_file():  # a folder, or a pipe that would block the read
        raise SpecError("is not a regular file", path=path,
                        fix="give the path to a CSV or JSON table, e.g. models/triplet-uncorrected.prescription.csv")
    try:
        text = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as e:
        raise SpecError(f"cannot read the table ({e})", path=path, fix="save it as UTF-8 text") from None
    suffix = path.suffix.lower()
    if suffix == ".json":
        rows, meta = _rows_from_json(text, path)
    elif suffix in (".csv", ".txt"):
        rows, meta = _rows_from_csv(text, path), _meta_from_csv(text)
    else:
        raise SpecError(f"unknown table type {path.suffix!r}", path=path, fix="use a .csv or .json file")
    return parse_rows(rows, path=path, name=str(meta.get("name", path.name.split(".")[0])), meta=meta)


def meta_number(rx: "Prescription", key: str) -> float | None:
    """A design value stated in the table (None when absent); SpecError naming the key when not a number."""
    v = rx.meta.get(key)
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise SpecError(f"design value {key} = {v!r} is not a number", path=rx.source or None, field=key,
                        fix=f"write e.g. '# {key}: 17.6' (CSV) or \"{key}\": 17.6 (JSON)") from None
    if not math.isfinite(x) or x <= 0:
        raise SpecError(f"design value {key} = {v!r} must be a positive number", path=rx.source or None,
                        field=key, fix="correct the value")
    return x


def _rows_from_csv(text: str, path) -> list[dict]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise SpecError("the table is empty", path=path, fix=f"write a header row ({', '.join(COLUMNS)}) and one row per surface")
    reader = csv.DictReader(io.StringIO("\n".join(lines)), skipinitialspace=True)
    header = [(h or "").strip().lower() for h in (reader.fieldnames or [])]
    unknown = [h for h in header if h not in COLUMNS]
    if unknown:
        raise SpecError(f"unknown column(s) {unknown}", path=path, field=unknown[0],
                        fix=f"use only the columns {', '.join(COLUMNS)}")
    for c in REQUIRED_COLUMNS:
        if c not in header:
            raise SpecError("required column missing from the header", path=path, field=c,
                            fix=f"add a '{c}' column (columns: {', '.join(COLUMNS)})")
    rows = []
    for raw in reader:
        if None in raw:
            raise SpecError(f"row {len(rows) + 1} has more values than the header has columns", path=path,
                            field=f"row {len(rows) + 1}", fix="quote values that contain commas, or drop the extra values")
        rows.append({(k or "").strip().lower(): (v or "").strip() for k, v in raw.items()})
    return rows


def _meta_from_csv(text: str) -> dict:
    meta = {}
    for ln in text.splitlines():
        m = re.match(r"^\s*#\s*([a-z_]+)\s*:\s*(.+?)\s*$", ln)
        if m and m.group(1) in META_KEYS:
            meta[m.group(1)] = m.group(2)
    return meta


def _rows_from_json(text: str, path) -> tuple[list[dict], dict]:
    from fieldcal.formats.documents import loads
    data = loads(text, path)  # safe parse: huge/deep/non-finite numbers and nesting refused with the field named
    meta = {}
    if isinstance(data, dict):
        meta = {k: v for k, v in data.items() if k in META_KEYS}
        unknown = [k for k in data if k not in META_KEYS and k != "surfaces"]
        if unknown:
            raise SpecError(f"unknown key(s) {unknown}", path=path, field=unknown[0],
                            fix=f"use 'surfaces' and the design values {', '.join(META_KEYS)}")
        data = data.get("surfaces")
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        raise SpecError("expected a list of surface objects", path=path, field="surfaces",
                        fix='write {"surfaces": [{"surface": "1", "type": "standard", "radius": 13.0, ...}, ...]}')
    rows = []
    for i, r in enumerate(data, 1):
        unknown = [k for k in r if k.lower() not in COLUMNS]
        if unknown:
            raise SpecError(f"row {i}: unknown key(s) {unknown}", path=path, field=unknown[0],
                            fix=f"use only the keys {', '.join(COLUMNS)}")
        rows.append({k.lower(): ("" if v is None else v) for k, v in r.items()})
    return rows, meta


def parse_rows(rows: list[dict], *, path=None, name: str = "lens", meta: dict | None = None) -> Prescription:
    """Validate table rows (dicts keyed by :data:`COLUMNS`; values str or numbers) into a Prescription."""
    if len(rows) < 2:
        raise SpecError(f"a lens needs at least two surfaces, the table has {len(rows)}", path=path,
                        field="surface", fix="write one row per surface, object side first")
    surfaces = []
    for i, r in enumerate(rows, 1):
        surfaces.append(_parse_row(i, r, path))
    stops = [s for s in surfaces if s.is_stop]
    if len(stops) != 1:
        raise SpecError(f"the table has {len(stops)} aperture stop rows; exactly one is needed", path=path,
                        field="surface", fix="label the aperture stop's row 'stop' in the surface column")
    if surfaces[-1].is_glass:
        raise SpecError(f"row {len(rows)} (surface {surfaces[-1].label}): the last surface is followed by glass "
                        f"(nd = {surfaces[-1].nd})", path=path, field="nd",
                        fix="the image side must be air: leave nd/vd/glass empty on the last row")
    if not any(s.is_glass for s in surfaces):
        raise SpecError("no surface is followed by glass: the table has no lens element", path=path, field="nd",
                        fix="give nd and vd (or a glass name) on the first surface of each element")
    if surfaces[-1].thickness_mm <= 0:
        raise SpecError(f"row {len(rows)}: the last thickness (distance to the image plane) must be > 0, got "
                        f"{surfaces[-1].thickness_mm}", path=path, field="thickness",
                        fix="give the back focal distance to the stated image plane")
    return Prescription(tuple(surfaces), name=name, source=str(path) if path else "", meta=dict(meta or {}))


def _parse_row(i: int, r: dict, path) -> Surface:
    label = str(r.get("surface", "")).strip()
    where = f"row {i} (surface {label or '?'})"

    def err(col, what, fix):
        return SpecError(f"{where}: {what}", path=path, field=col, fix=fix)

    def number(col, default=None, allow_inf=False):
        v = r.get(col, "")
        if isinstance(v, str):
            s = v.strip().replace("\u2212", "-")  # a typographic minus pasted from a document
            if s == "":
                if default is None:
                    raise err(col, "missing", f"write a number in the '{col}' column")
                return default
            if allow_inf and s.lower().lstrip("+-") in ("inf", "infinity", "\u221e"):
                return math.inf
            try:
                x = float(s)
            except ValueError:
                raise err(col, f"not a number: {v!r}", f"write a plain number in the '{col}' column") from None
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            raise err(col, f"not a number: {v!r}", f"write a number in the '{col}' column")
        else:
            x = float(v)
        if math.isnan(x) or (math.isinf(x) and not allow_inf):
            raise err(col, f"must be finite, got {v!r}", f"write a finite number in the '{col}' column")
        return x

    if not label:
        raise err("surface", "no surface label", "number the surfaces 1, 2, ... and label the aperture stop 'stop'")
    kind_raw = str(r.get("type", "")).strip().lower() or "standard"
    kind = SURFACE_TYPES.get(kind_raw)
    if kind is None:
        raise err("type", f"unknown surface type {kind_raw!r}", "use 'standard' or 'even asphere'")
    radius = number("radius", default=math.inf, allow_inf=True)
    if radius == 0:
        raise err("radius", "a radius of 0 is not a surface", "use inf (or leave it empty) for a plane")
    thickness = number("thickness")
    if thickness < 0:
        raise err("thickness", f"negative thickness {thickness}", "thicknesses are distances to the next surface (>= 0)")
    conic = number("k", default=0.0)
    asph = tuple(number(c, default=0.0) for c in ("a4", "a6", "a8"))
    if kind == "standard" and (conic != 0.0 or any(asph)):
        col = "k" if conic != 0.0 else ("a4", "a6", "a8")[[a != 0 for a in asph].index(True)]
        raise err(col, "aspheric coefficients on a 'standard' surface", "set type to 'even asphere' or clear the coefficients")
    glass = str(r.get("glass", "")).strip()
    has_nd = str(r.get("nd", "")).strip() != "" if isinstance(r.get("nd", ""), str) else True
    has_vd = str(r.get("vd", "")).strip() != "" if isinstance(r.get("vd", ""), str) else True
    nd, vd = 1.0, math.inf
    if glass and glass.upper() not in ("AIR", ""):
        key = glass.upper()
        if key not in GLASS_CATALOGUE:
            raise err("glass", f"unknown glass {glass!r}",
                      f"give nd and vd instead (columns nd, vd), or one of {', '.join(sorted(GLASS_CATALOGUE))}")
        if has_nd or has_vd:
            raise err("glass", f"both a glass name ({glass!r}) and nd/vd given", "give either the glass name or nd and vd")
        nd, vd = GLASS_CATALOGUE[key]
    elif has_nd or has_vd:
        if not has_vd:
            raise err("vd", f"nd = {r.get('nd')} given without an Abbe number", "add vd (e.g. 64.17 for N-BK7)")
        if not has_nd:
            raise err("nd", f"vd = {r.get('vd')} given without a refractive index", "add nd (e.g. 1.5168 for N-BK7)")
        nd, vd = number("nd"), number("vd")
        if not (ND_RANGE[0] <= nd <= ND_RANGE[1]):
            raise err("nd", f"refractive index {nd} is not that of an optical glass",
                      f"nd of glasses lies in [{ND_RANGE[0]}, {ND_RANGE[1]}]; check the column order (nd before vd)")
        if not (VD_RANGE[0] <= vd <= VD_RANGE[1]):
            raise err("vd", f"Abbe number {vd} is not that of an optical glass",
                      f"vd of glasses lies in [{VD_RANGE[0]:g}, {VD_RANGE[1]:g}]; check the column order (nd before vd)")
    is_stop = label.lower() == "stop"
    if is_stop and nd != 1.0:
        raise err("nd", "the stop row is followed by glass", "put the aperture stop in air (leave nd/vd/glass empty)")
    return Surface(label=label, kind=kind, radius_mm=radius, thickness_mm=thickness, nd=nd, vd=vd, glass=glass,
                   conic=conic, aspheric=asph, is_stop=is_stop)
