"""Bring a camera's own files into a ``fieldcal-stack/1`` folder: TIFF, PNG, JPEG, DNG and camera raw.

What :func:`import_stack` does, in order, before anything is written:

1. takes the frames in natural-sort order of their names (``f2`` before ``f10``), or in the order and with the
   stage positions of a CSV of ``file,z_um`` rows;
2. reads what each file says about the camera: size, channels, sample type, make and model, f-number, focal
   length, exposure, pixel pitch (EXIF ``FocalPlaneXResolution``) and, for raw files, the CFA pattern and
   the black and white levels (LibRaw through rawpy);
3. decodes every TIFF, PNG and JPEG file once (a whole header over truncated data is refused here);
4. refuses a set that mixes sizes, cameras, sample types or CFA patterns, and a pixel pitch that is neither in
   the files nor given.

Then it builds the stack in a hidden folder beside ``out`` and renames it into place, so ``out`` either does
not exist or is a complete stack. TIFF, PNG and JPEG frames are copied byte for byte (or hard-linked /
symlinked with ``link=``), keeping their metadata; raw files become 16-bit TIFF Bayer mosaics (the sensor's
visible area, no demosaicing, so calibration can measure each CFA plane on its own), and the raw file's
SHA-256 is kept beside the frame's. Every frame's SHA-256 is recorded.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import re
import shutil
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np

from fieldcal.errors import ParameterError, StackError
from fieldcal.formats.atomic import (atomic_write_bytes, atomic_write_text, check_output,
                                     check_replaceable_folder, replace_folder, report_stale_staging,
                                     make_staging, staging_lock)
from fieldcal.formats.imageio import ImageFileError, check_finite, encode, probe, read_image

#: File name endings read through LibRaw (rawpy). Many raw formats are TIFF inside, so the ending decides.
RAW_SUFFIXES = frozenset({".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf",
                          ".rw2", ".rwl", ".pef", ".srw", ".3fr", ".iiq", ".erf", ".mef", ".mos", ".kdc", ".dcr",
                          ".x3f", ".raw"})
IMAGE_SUFFIXES = frozenset({".tif", ".tiff", ".png", ".jpg", ".jpeg"})
LINK_MODES = ("hard", "symlink")

# EXIF FocalPlaneResolutionUnit -> millimetres per unit (1 = none, 2 = inch, 3 = cm; 4 mm and 5 µm are
# used by some makers although EXIF 2.3 lists only 2 and 3).
_FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass(frozen=True)
class SourceFrame:
    """One input file and what it says about itself.

    Attributes
    ----------
    path : Path
        The file given.
    kind : {"tiff", "png", "jpeg", "raw"}
    width, height : int
        Size of the image fieldcal stores (for raw: the visible area).
    n_channels : int
        1 (mono or a Bayer mosaic) or 3.
    dtype : str
        Sample type of the stored frame.
    make, model : str or None
        Camera, from EXIF.
    f_number, focal_length_mm, exposure_ms, pixel_pitch_um : float or None
        From EXIF where present.
    cfa : str or None
        Bayer pattern of the top-left 2x2 pixels (raw only), e.g. ``"RGGB"``.
    black_level, white_level : float or None
        Raw levels (raw only).
    time : str or None
        EXIF DateTimeOriginal.
    """

    path: Path
    kind: str
    width: int
    height: int
    n_channels: int
    dtype: str
    make: str | None = None
    model: str | None = None
    f_number: float | None = None
    focal_length_mm: float | None = None
    exposure_ms: float | None = None
    pixel_pitch_um: float | None = None
    cfa: str | None = None
    black_level: float | None = None
    white_level: float | None = None
    time: str | None = None
    extra: dict = field(default_factory=dict)


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value: ``f2 < f10`` (case-insensitive otherwise)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _ratio(value) -> float | None:
    """An exifread value (Ratio, int, list of one) as a finite positive float, else None."""
    try:
        v = value.values[0] if hasattr(value, "values") else value
        if isinstance(v, (list, tuple)):
            v = v[0]
        if hasattr(v, "numerator") and hasattr(v, "denominator"):
            if v.denominator == 0:
                return None
            f = float(Fraction(int(v.numerator), int(v.denominator)))
        else:
            f = float(v)
    except (TypeError, ValueError, IndexError, ZeroDivisionError, OverflowError):
        return None
    return f if math.isfinite(f) and f > 0 else None


def _exif(path: Path) -> dict:
    """EXIF tags as exifread reads them (any TIFF-based raw, JPEG, TIFF, PNG eXIf); {} when there are none.

    exifread logs a file without EXIF as a warning, which Python's last-resort handler printed on stderr once per
    frame ("PNG file does not have exif data.", also under ``--quiet``): a frame without EXIF is normal here (the
    importer asks for what it needs, e.g. ``--pixel-pitch-um``), so its warnings are held back while it reads."""
    import logging

    import exifread

    log = logging.getLogger("exifread")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with open(path, "rb") as f:
            return exifread.process_file(f, details=False, strict=False)
    except Exception:  # exifread raises many types on odd files; metadata is optional
        return {}
    finally:
        log.setLevel(level)


def _exif_fields(tags: dict) -> dict:
    def text(key):
        v = tags.get(key)
        s = str(v).strip() if v is not None else ""
        return s or None

    out = {"make": text("Image Make"), "model": text("Image Model"), "time": text("EXIF DateTimeOriginal")}
    out["f_number"] = _ratio(tags.get("EXIF FNumber") or tags.get("Image FNumber"))
    out["focal_length_mm"] = _ratio(tags.get("EXIF FocalLength") or tags.get("Image FocalLength"))
    t = _ratio(tags.get("EXIF ExposureTime") or tags.get("Image ExposureTime"))
    out["exposure_ms"] = None if t is None else 1000.0 * t
    res = _ratio(tags.get("EXIF FocalPlaneXResolution") or tags.get("Image FocalPlaneXResolution"))
    unit_tag = tags.get("EXIF FocalPlaneResolutionUnit") or tags.get("Image FocalPlaneResolutionUnit")
    unit = None
    if unit_tag is not None:
        try:
            unit = int(unit_tag.values[0])
        except (AttributeError, TypeError, ValueError, IndexError):
            unit = None
    out["pixel_pitch_um"] = (1000.0 * _FOCAL_PLANE_UNIT_MM[unit] / res) if (res and unit in _FOCAL_PLANE_UNIT_MM) \
        else None
    # FocalPlaneXResolution refers to the camera's full-resolution image; a resized file keeps the tag but not
    # the pitch, so the width it refers to is kept to check against (EXIF PixelXDimension).
    out["exif_width"] = _ratio(tags.get("EXIF ExifImageWidth"))
    return out


def _cfa_from_rawpy(raw) -> str | None:
    """The 2x2 pattern of the visible area as e.g. "RGGB", or None for a sensor that is not a Bayer RGB mosaic."""
    pattern = getattr(raw, "raw_pattern", None)
    if pattern is None:
        return None
    pattern = np.asarray(pattern)
    desc = raw.color_desc.decode("ascii", "replace") if isinstance(raw.color_desc, bytes) else str(raw.color_desc)
    if pattern.shape != (2, 2) or len(desc) < 3:
        return None
    try:
        letters = "".join(desc[int(k)] for k in pattern.ravel())
    except IndexError:
        return None
    letters = letters.replace("g", "G")
    return letters if sorted(letters) == ["B", "G", "G", "R"] else None


def _read_raw(path: Path) -> tuple[np.ndarray, dict]:
    """The visible Bayer mosaic (uint16) and LibRaw's levels and pattern."""
    try:
        import rawpy
    except ImportError:  # pragma: no cover - rawpy is a dependency; a broken install still gets a clear message
        raise ParameterError("reading raw files needs rawpy (LibRaw)", path=path, field="images",
                             fix="pip install rawpy") from None
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            cfa = _cfa_from_rawpy(raw)
            blacks = [float(b) for b in raw.black_level_per_channel]
            white = float(raw.white_level)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise StackError(f"cannot be read as a camera raw file ({type(exc).__name__}: {exc})", path=path,
                         field="images", fix="check the file is a complete raw/DNG file from the camera") from None
    return mosaic, {"cfa": cfa, "blacks": blacks, "white": white}


def describe(path: str | os.PathLike) -> SourceFrame:
    """What one camera file holds (header and metadata; raw files are decoded by LibRaw).

    Raises
    ------
    StackError
        The file is missing, not an image fieldcal reads, or damaged.
    """
    path = Path(path)
    if not path.is_file():
        raise StackError("does not exist or is not a file", path=path, field="images",
                         fix="give image files (TIFF, PNG, JPEG, DNG or camera raw)")
    meta = _exif_fields(_exif(path))
    exif_width = meta.pop("exif_width")
    if path.suffix.lower() in RAW_SUFFIXES:
        mosaic, raw = _read_raw(path)
        if raw["cfa"] is None:
            raise StackError("is a raw file whose sensor is not an RGB Bayer mosaic (no 2x2 R/G/G/B pattern)",
                             path=path, field="images", fix="convert the frames to TIFF first")
        blacks = raw["blacks"]
        black = float(np.mean(blacks)) if blacks else 0.0
        h, w = mosaic.shape
        return SourceFrame(path, "raw", w, h, 1, "uint16", cfa=raw["cfa"], black_level=black,
                           white_level=raw["white"], extra={"black_levels": blacks}, **meta)
    try:
        header = probe(path)
        # decoded once, as calibrate will: a file whose header is whole but whose data is truncated or damaged
        # (a copy interrupted, a card pulled) is refused now, not after it was copied into a "valid" stack
        check_finite(read_image(path, header=header))
    except ImageFileError as exc:
        raise StackError(exc.what, path=path, field="images", fix=exc.fix) from None
    if exif_width and header.width != int(exif_width) and meta.get("pixel_pitch_um"):
        # The tag describes the full-resolution image; scale to this file's width.
        meta["pixel_pitch_um"] *= exif_width / header.width
    return SourceFrame(path, header.kind, header.width, header.height, header.n_channels, header.dtype.name,
                       **meta)


_Z_CSV_FIX = "give a UTF-8 CSV file of file,z_um rows"
_DECIMAL_FIX = ("write z with a decimal point (12.5, not 12,5), or quote the field (\"file name, with commas\")")


def read_z_csv(path: str | os.PathLike) -> list[tuple[str, float]]:
    """Rows ``file,z_um`` of a CSV (a header row naming the columns is optional), in file order.

    Every row must have as many columns as the header (two without one): a z written with a decimal comma
    (``a.jpg,12,5`` for 12.5 µm) has one more and would otherwise be read as 12, so it is refused, naming the line.

    Raises
    ------
    ParameterError
        Naming the file and the line: a row of another column count, a z that is not a finite number (a quoted
        ``"12,5"`` included), no rows.
    """
    import io

    path = Path(path)
    if path.exists() and not path.is_file():  # a pipe would block the read
        raise ParameterError("is not a regular file", path=path, field="z_csv", fix=_Z_CSV_FIX)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterError(f"cannot be read ({exc})", path=path, field="z_csv", fix=_Z_CSV_FIX) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[tuple[int, list[str]]] = []  # (line number where the row ends, cells)
    try:
        for r in reader:
            if r and any(c.strip() for c in r):
                rows.append((reader.line_num, r))
    except csv.Error as exc:
        raise ParameterError(f"is not a well-formed CSV file ({exc})", path=path, field=f"line {reader.line_num}",
                             fix=_Z_CSV_FIX + ", with any quoted field closed") from None
    n_columns = 2
    if rows and rows[0][1][0].strip().lower() in ("file", "filename", "name"):
        n_columns = max(2, len(rows[0][1]))
        rows = rows[1:]
    out = []
    for line, r in rows:
        where = f"line {line}"
        if len(r) != n_columns:
            cells = ",".join(r)
            if len(r) > n_columns and not any(c.strip() for c in r[n_columns:]):
                what = f"has {len(r)} columns ({cells!r}) where the file has {n_columns}: it ends in an empty column"
                fix = "remove the trailing comma(s), or name the extra column in a header row (file,z_um,...)"
            elif len(r) > n_columns:
                what = (f"has {len(r)} columns ({cells!r}) where the file has {n_columns} (file,z_um): a z written "
                        "with a decimal comma (12,5) splits into two columns and would be read as 12")
                fix = _DECIMAL_FIX
            else:
                what = f"has {len(r)} column(s) ({cells!r}) where the file has {n_columns} (file,z_um)"
                fix = "write one 'file,z_um' pair per row"
            raise ParameterError(what, path=path, field=where, fix=fix)
        cell = r[1].strip()
        try:
            z = float(cell)
        except ValueError:
            if "," in cell:
                raise ParameterError(f"z_um {r[1]!r} is not a number (a decimal comma)", path=path, field=where,
                                     fix="write z with a decimal point (12.5, not 12,5)") from None
            raise ParameterError(f"z_um {r[1]!r} is not a number", path=path, field=where,
                                 fix="give the stage position in µm") from None
        if not math.isfinite(z) or abs(z) > 1e9:
            raise ParameterError(f"z_um {r[1]!r} is not a finite position", path=path, field=where,
                                 fix="give the stage position in µm")
        out.append((r[0].strip(), z))
    if not out:
        raise ParameterError("holds no file,z_um rows", path=path, field="z_csv", fix="list every frame")
    return out


def _match_csv(images: list[Path], rows: list[tuple[str, float]], csv_path: Path) -> list[tuple[Path, float]]:
    by_name: dict[str, Path] = {}
    for p in images:
        for key in (str(p), p.name):
            by_name.setdefault(key, p)
    out, used = [], set()
    for name, z in rows:
        p = by_name.get(name) or by_name.get(Path(name).name)
        if p is None:
            raise ParameterError(f"names {name!r}, which is not among the images given", path=csv_path,
                                 field="z_csv", fix="give every file the CSV lists (or remove its row)")
        if p in used:
            raise ParameterError(f"lists {name!r} twice", path=csv_path, field="z_csv", fix="one row per frame")
        used.add(p)
        out.append((p, z))
    missing = [p.name for p in images if p not in used]
    if missing:
        raise ParameterError(f"has no row for {missing[:3]}{' ...' if len(missing) > 3 else ''}", path=csv_path,
                             field="z_csv", fix="give a z_um for every image")
    return out


def _expand(images: Sequence[str | os.PathLike]) -> list[Path]:
    """Files as given; a folder stands for the image and raw files directly inside it."""
    out: list[Path] = []
    for item in images:
        p = Path(item)
        if p.is_dir():
            found = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in (IMAGE_SUFFIXES | RAW_SUFFIXES)]
            if not found:
                raise ParameterError("holds no TIFF, PNG, JPEG or raw files", path=p, field="images",
                                     fix="give the image files or the folder that holds them")
            out.extend(found)
        else:
            out.append(p)
    if not out:
        raise ParameterError("no images given", field="images", fix="give at least two image files")
    seen: set[Path] = set()
    for p in out:
        r = p.resolve()
        if r in seen:
            raise ParameterError("is given twice", path=p, field="images", fix="give each frame once")
        seen.add(r)
    return out


def _agree(frames: list[SourceFrame], attr: str, what: str, fix: str) -> None:
    first = frames[0]
    for f in frames[1:]:
        if getattr(f, attr) != getattr(first, attr):
            raise StackError(f"has {what} {getattr(f, attr)!r}, but {first.path.name} has {getattr(first, attr)!r}",
                             path=f.path, field="images", fix=fix)


def _refuse_turned(frames: list[SourceFrame]) -> None:
    """A frame stored turned by 90° against the first (its width and height swapped): software that applied
    the EXIF orientation to some frames and not to others. Said plainly, as a size mismatch would not."""
    first = frames[0]
    for f in frames[1:]:
        if (f.width, f.height) != (first.width, first.height) and (f.height, f.width) == (first.width, first.height):
            raise StackError(f"is stored turned by 90° against {first.path.name} ({f.width}x{f.height} px against "
                             f"{first.width}x{first.height})", path=f.path, field="images",
                             fix="import the files as the camera wrote them, or turn every frame the same way "
                                 "(e.g. all upright); fieldcal keeps the EXIF orientation tag and does not need "
                                 "the frames turned")


def _common(frames: list[SourceFrame], attr: str):
    vals = {getattr(f, attr) for f in frames if getattr(f, attr) is not None}
    return vals.pop() if len(vals) == 1 else None


def _positive(value, name: str) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"must be a number, got {value!r}", field=name, fix=f"give {name} as a positive number")
    if not math.isfinite(v) or v <= 0 or v > 1e6:
        raise ParameterError(f"must be a finite positive number, got {value!r}", field=name,
                             fix=f"give {name} as a positive number")
    return v


def _check_out(out: Path, sources: list[Path], overwrite: bool, z_csv=None) -> None:
    """The shared output checks (never over or into an input or through a file; the inputs stay protected),
    then the stack folder's own: new, empty, or a stack replaced only with ``overwrite``."""
    check_output(out, inputs=[*sources, z_csv], overwrite=overwrite, kind="dir", replaces_folder=True,
                 field="out")
    check_replaceable_folder(out, "stack.json", overwrite, "a stack", error=ParameterError)


def import_stack(images: Sequence[str | os.PathLike], out: str | os.PathLike, *,
                 z_start_um: float | None = None, z_step_um: float | None = None,
                 z_csv: str | os.PathLike | None = None, pixel_pitch_um: float | None = None,
                 f_number: float | None = None, focal_length_mm: float | None = None,
                 object_distance_mm: float | None = None, link: str | None = None, overwrite: bool = False):
    """Make a ``fieldcal-stack/1`` folder from a camera's image files.

    Parameters
    ----------
    images : sequence of path-like
        Frame files (TIFF, PNG, JPEG, DNG or camera raw), or folders holding them. Natural-sort order of the
        file names is the stage order unless ``z_csv`` is given.
    out : path-like
        The stack folder to create (must not exist, or be empty; an existing stack only with ``overwrite``).
    z_start_um, z_step_um : float
        Stage position of the first frame and the step between frames (µm): frame ``k`` is at
        ``z_start_um + k * z_step_um``.
    z_csv : path-like
        Instead of start/step: a CSV of ``file,z_um`` rows (file by name or path as given).
    pixel_pitch_um : float, optional
        Sensor pixel pitch (µm). Required when the files do not state it (EXIF FocalPlaneXResolution).
    f_number, focal_length_mm, object_distance_mm : float, optional
        Override or supply what the EXIF data say (or do not).
    link : {None, "hard", "symlink"}
        Copy frames (default), hard-link them, or symlink them. Raw files are always converted (a TIFF mosaic).
    overwrite : bool
        Replace an existing stack folder at ``out``.

    Returns
    -------
    fieldcal.Stack
        The new stack, opened (and so validated).

    Examples
    --------
    >>> stack = import_stack(["IMG_0001.JPG", "IMG_0002.JPG", "IMG_0003.JPG"], "STACK",
    ...                      z_start_um=0, z_step_um=20, pixel_pitch_um=1.4)   # doctest: +SKIP
    """
    from fieldcal.formats.stack import FORMAT, STACK_JSON, Stack, _sha256_file

    out = Path(os.path.abspath(out))  # "." or "x/.." has no name to stage beside; its absolute path has
    paths = _expand(images)
    if link is not None and link not in LINK_MODES:
        raise ParameterError(f"must be one of {LINK_MODES} or None, got {link!r}", field="link",
                             fix="use link='hard' or link='symlink' (CLI: --link hard|symlink)")
    if (z_csv is None) == (z_start_um is None or z_step_um is None):
        raise ParameterError("give either z_start_um and z_step_um, or z_csv", field="z_start_um",
                             fix="say where the stage was: --z START STEP or --z-csv FILE")
    if z_csv is not None:
        ordered = _match_csv(paths, read_z_csv(z_csv), Path(z_csv))
    else:
        start, step = float(z_start_um), float(z_step_um)
        if not (math.isfinite(start) and math.isfinite(step)) or step == 0 or abs(start) > 1e9 or abs(step) > 1e9:
            raise ParameterError(f"z start {z_start_um!r} / step {z_step_um!r} are not usable", field="z_step_um",
                                 fix="give a finite start and a non-zero step in µm")
        paths = sorted(paths, key=lambda p: natural_key(p.name))
        ordered = [(p, start + k * step) for k, p in enumerate(paths)]
    if len(ordered) < 2:
        raise ParameterError(f"{len(ordered)} image(s) given; a stack needs at least 2", field="images",
                             fix="give every frame of the through-focus series")
    zs = [z for _, z in ordered]
    if len(set(zs)) != len(zs):
        raise ParameterError("two frames have the same z_um", field="z_csv", fix="give every frame its own position")
    _check_out(out, [p for p, _ in ordered], overwrite, z_csv)

    frames = [describe(p) for p, _ in ordered]
    _agree(frames, "kind", "file type", "import frames of one kind (all raw, or all JPEG, ...)")
    _refuse_turned(frames)
    _agree(frames, "width", "width", "all frames must have the same size; re-export them at one size")
    _agree(frames, "height", "height", "all frames must have the same size; re-export them at one size")
    _agree(frames, "n_channels", "channel count", "all frames must be colour, or all mono")
    _agree(frames, "dtype", "sample type", "export every frame with the same bit depth")
    _agree(frames, "cfa", "CFA pattern", "import frames of one camera and one crop")
    # a raw frame's levels say where black and clipping are: one stack records one pair, so frames must agree
    _agree(frames, "black_level", "black level", "import frames taken with one camera setting (a black level "
           "changes with ISO and temperature on some sensors: take the series again at one setting)")
    _agree(frames, "white_level", "white level", "import frames taken with one camera setting")
    first = frames[0]
    if first.white_level is not None and first.black_level is not None and \
            not first.white_level > first.black_level:
        raise StackError(f"states a white level ({first.white_level:g}) not above its black level "
                         f"({first.black_level:g})", path=first.path, field="images",
                         fix="check the raw file (a damaged or hand-edited DNG), or convert the frames to TIFF")
    _agree(frames, "make", "camera make", "import frames from one camera")
    _agree(frames, "model", "camera model", "import frames from one camera")
    if link is not None and frames[0].kind == "raw":
        raise ParameterError("raw files are converted to TIFF mosaics, so they cannot be linked", field="link",
                             fix="drop --link for raw files")

    pitch = _positive(pixel_pitch_um, "pixel_pitch_um")
    pitch_source = "given"
    if pitch is None:
        pitch = _common(frames, "pixel_pitch_um")
        pitch_source = "EXIF FocalPlaneXResolution"
    if pitch is None:
        raise ParameterError("the pixel pitch is not in the files' metadata", path=frames[0].path,
                             field="pixel_pitch_um",
                             fix="give the sensor's pixel pitch in µm (CLI: --pixel-pitch-um), from the camera's "
                                 "data sheet: sensor width in mm x 1000 / width in pixels")
    fnum = _positive(f_number, "f_number") or _common(frames, "f_number")
    focal = _positive(focal_length_mm, "focal_length_mm") or _common(frames, "focal_length_mm")
    obj = _positive(object_distance_mm, "object_distance_mm")

    first = frames[0]
    meta: dict = {"format": FORMAT, "pixel_pitch_um": pitch}
    if first.kind == "raw":
        meta["channels"] = ["R", "G", "B"]
        meta["cfa"] = first.cfa
        meta["black_level"] = first.black_level
        meta["white_level"] = first.white_level
        meta["bit_depth"] = max(1, int(math.ceil(math.log2(first.white_level + 1)))) if first.white_level else 16
    else:
        names = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}  # RGBA: e.g. align_image_stack's TIFFs
        if first.n_channels not in names:
            raise StackError(f"has {first.n_channels} channels", path=first.path, field="images",
                             fix="save the frames as grayscale, RGB or RGBA")
        meta["channels"] = names[first.n_channels]
        if first.kind == "jpeg":
            meta["encoding"] = "sRGB JPEG (8-bit, gamma-encoded)"
    if fnum:
        meta["f_number"] = fnum
    # a camera's frames carry the pixel aperture and the pupil's diffraction, both fixed at the sensor: a breathing
    # stack's band-pass curves are corrected for their change (measure/breathing_mtf.py); diffraction needs f_number
    meta["sensor_mtf"] = {"pixel_aperture": True, "diffraction": bool(fnum)}
    if focal:
        meta["focal_length_mm"] = focal
    if obj:
        meta["object_distance_mm"] = obj
    camera = {k: v for k, v in (("make", first.make), ("model", first.model)) if v}
    if camera:
        meta["camera"] = camera
    meta["imported"] = {"pixel_pitch_source": pitch_source, "link": link or "copy"}
    if link == "symlink":
        meta["links"] = "symlink"  # the reader then accepts frames that are symlinks out of the folder

    parent = out.resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    report_stale_staging(parent / out.name, "stack.json")  # what a killed import or simulate left beside out
    staging = make_staging(parent / out.name, "fieldcal-import")
    try:
        with staging_lock(staging):  # a later run sees the folder is in use, not a leftover
            (staging / "frames").mkdir()
            entries = []
            width = max(4, len(str(len(ordered) - 1)))
            for k, ((src, z), info) in enumerate(zip(ordered, frames)):
                stem = re.sub(r"[^A-Za-z0-9._-]+", "_", src.stem)[:80] or "frame"
                entry: dict = {"z_um": z}
                if info.kind == "raw":
                    mosaic, _ = _read_raw(src)
                    rel = f"frames/{k:0{width}d}_{stem}.tiff"
                    data = encode(mosaic, "tiff")
                    atomic_write_bytes(staging / rel, data)
                    entry["sha256"] = hashlib.sha256(data).hexdigest()
                    entry["source"] = {"file": src.name, "sha256": _sha256_file(src)}
                else:
                    rel = f"frames/{k:0{width}d}_{stem}{src.suffix.lower()}"
                    dst = staging / rel
                    if link == "hard":
                        try:
                            os.link(src, dst)
                        except OSError as exc:
                            raise ParameterError(f"cannot be hard-linked into {out} ({exc.strerror})", path=src,
                                                 field="link", fix="copy instead (no --link), or put the output on "
                                                                   "the same file system") from None
                    elif link == "symlink":
                        os.symlink(src.resolve(), dst)
                    else:
                        shutil.copyfile(src, dst)
                    entry["sha256"] = _sha256_file(dst)
                    entry["source"] = {"file": src.name}
                entry = {"file": rel, **entry}
                if info.exposure_ms:
                    entry["exposure_ms"] = info.exposure_ms
                if info.time:
                    entry["time"] = info.time
                entries.append(entry)
            meta["frames"] = entries
            atomic_write_text(staging / STACK_JSON, json.dumps(meta, indent=2, allow_nan=False) + "\n")
            Stack.open(staging)  # validate what was built before it takes the final name
            replace_folder(staging, out, marker="stack.json", overwrite=overwrite, what="a stack",
                           error=ParameterError)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return Stack.open(out)
