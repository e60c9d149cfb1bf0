"""A sweep plan's per-pixel exposure windows in files an exposure device loads (``fieldcal-masks/1``).

The plan's ``.npz`` sidecar holds float windows and packed masks for fieldcal; a device wants images. One folder:

* ``lcos``: one 1-bit greyscale PNG per slot and plane, ``<plane>-slot-<k>.png`` (k = 0000, 0001, ...),
  full frame, 1 = open (the pixel integrates during slot k), 0 = closed. The device shows slot k for
  ``slot_ms`` while the camera integrates, then its complement for ``slot_ms`` with the camera closed (the
  complement is not stored: it is ``1 - mask``). A Bayer plan has one plane (``CFA-RGGB``), each pixel following
  its own colour's surface.
* ``pixelwise``: two 16-bit TIFFs per plane, ``<plane>-start.tif`` and ``<plane>-stop.tif``: the register
  values (ticks of the device clock ``clock_ms``) at which each pixel starts and stops integrating; a pixel
  never exposed has start = stop = 0. Deflate-compressed with horizontal differencing (the maps are smooth).

``masks.json`` lists every file with its size and sha256, the channel order, the slot time or clock, and is
written last: the folder is staged under a hidden name and renamed into place, so ``DIR`` is the old export
or the new one, never a mix. :func:`load_device_masks` checks every hash and returns exactly the arrays of
the plan's sidecar (``mask_bits`` or ``start_tick``/``stop_tick``).
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fieldcal.errors import OutputError, ParameterError, SpecError
from fieldcal.formats import documents
from fieldcal.formats.atomic import (atomic_write_bytes, check_output, check_replaceable_folder, replace_folder,
                                     make_staging, report_stale_staging, staging_lock)

from . import masks as mk

MANIFEST = "masks.json"
MASKS_FORMAT = documents.format_id("masks")
FORMATS = ("lcos", "pixelwise")
#: The plan's device name for each export format.
PLAN_DEVICE = {"lcos": "lcos", "pixelwise": "pixel"}
#: Largest register value a 16-bit map holds.
MAX_TICK_16 = 2**16 - 1
_FIX = "export the masks again with `fieldcal plan export-masks PLAN --out DIR` (docs/planning.md)"


@dataclass(frozen=True)
class DeviceMasks:
    """What a device folder holds, loaded back: the manifest and the plan-sidecar arrays it encodes."""

    manifest: dict
    arrays: dict[str, np.ndarray]


def plane_file_stem(plane: str) -> str:
    """File-name form of a plane (``CFA:RGGB`` -> ``CFA-RGGB``)."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", plane)


def _files_for(fmt: str, planes: list[str], n_slots: int | None) -> list[tuple[str, str, str, int | None]]:
    """(name, plane, role, slot) of every file of an export, in manifest order."""
    out = []
    for plane in planes:
        s = plane_file_stem(plane)
        if fmt == "lcos":
            out += [(f"{s}-slot-{k:04d}.png", plane, "slot", k) for k in range(int(n_slots))]
        else:
            out += [(f"{s}-start.tif", plane, "start", None), (f"{s}-stop.tif", plane, "stop", None)]
    return out


def export_format(doc: dict, fmt: str | None) -> str:
    """The export format for a sweep plan document: its device's, and ``fmt`` must agree when given."""
    if doc.get("kind") != "sweep":
        raise ParameterError("only sweep plans have exposure masks", field="plan",
                             fix="give a plan written by `fieldcal plan sweep`")
    dev = doc["device"]["name"]
    native = "lcos" if dev == "lcos" else "pixelwise"
    if fmt is None:
        return native
    if fmt not in FORMATS:
        raise ParameterError(f"mask format {fmt!r} unknown", field="format", fix="use lcos or pixelwise")
    if fmt != native:
        raise ParameterError(f"the plan is for the {dev!r} device, so its masks are {native!r}, not {fmt!r}",
                             field="format", fix=f"use --format {native}, or plan again with --device "
                                                 f"{PLAN_DEVICE[fmt]}")
    return fmt


def file_names(doc: dict, fmt: str | None = None) -> list[str]:
    """Every file an export of the sweep plan ``doc`` writes (for the output check before any work)."""
    fmt = export_format(doc, fmt)
    return [MANIFEST] + [n for n, *_ in _files_for(fmt, list(doc["masks"]["planes"]), doc["device"].get("n_slots"))]


# ------------------------------------------------------------------------------------------------ encoding


def _png_1bit(mask: np.ndarray) -> bytes:
    import cv2
    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * np.uint8(255),
                           [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:  # pragma: no cover - OpenCV encodes any 2-D uint8 image
        raise OutputError("OpenCV could not encode a 1-bit PNG", fix="check the OpenCV installation")
    return buf.tobytes()


def _tiff_u16(ticks: np.ndarray) -> bytes:
    import tifffile
    buf = io.BytesIO()
    # horizontal differencing turns the smooth tick maps into near-constant rows that deflate to almost nothing
    tifffile.imwrite(buf, np.ascontiguousarray(ticks, dtype=np.uint16), compression="zlib",
                     compressionargs={"level": 9}, predictor=True, photometric="minisblack", rowsperstrip=64)
    return buf.getvalue()


def _encode(fmt: str, arrays: dict, planes: list[str], n_slots: int | None) -> dict[str, bytes]:
    """Every file's bytes, by name (slot masks are unpacked one at a time: a 4K slot is 8 MB as bool)."""
    data: dict[str, bytes] = {}
    if fmt == "lcos":
        p, h, w = (int(v) for v in arrays["mask_shape"][1:])
        bits = arrays["mask_bits"]
        for name, plane, _role, k in _files_for(fmt, planes, n_slots):
            data[name] = _png_1bit(mk.unpack(bits[k, planes.index(plane)], w))
    else:
        for name, plane, role, _k in _files_for(fmt, planes, n_slots):
            data[name] = _tiff_u16(arrays[f"{role}_tick"][planes.index(plane)])
    return data


def _check_ticks(arrays: dict, clock_ms: float) -> None:
    top = int(max(arrays["start_tick"].max(initial=0), arrays["stop_tick"].max(initial=0)))
    if top > MAX_TICK_16:
        k = math.ceil(top / MAX_TICK_16)
        raise ParameterError(f"the sweep lasts {top} ticks of {clock_ms * 1000:g} µs, more than a 16-bit map holds "
                             f"({MAX_TICK_16})", field="clock_us",
                             fix=f"plan again with a slower register clock: --clock-us {clock_ms * 1000 * k:g}")


# ------------------------------------------------------------------------------------------------- export


def export_device_masks(doc: dict, arrays: dict, out: str | Path, *, fmt: str | None = None,
                        overwrite: bool = False, plan_file: str | None = None) -> dict:
    """Write a sweep plan's masks as device files into the folder ``out``; returns the manifest.

    Parameters
    ----------
    doc : dict
        The ``fieldcal-plan/1`` sweep document (``SweepPlan.to_dict()`` or ``read_plan``).
    arrays : dict
        Its mask arrays (``SweepPlan.mask_arrays()`` or ``masks.load_npz`` of the sidecar).
    out : path
        Output folder; replaced as a whole (staged, then renamed) when ``overwrite``.
    fmt : {"lcos", "pixelwise"}, optional
        Must be the plan device's format (default: that format).
    plan_file : str, optional
        The plan's file name, recorded in the manifest.
    """
    fmt = export_format(doc, fmt)
    out = Path(os.path.abspath(out))  # "." has no name to stage beside; its absolute path has
    planes = [str(p) for p in doc["masks"]["planes"]]
    dev = doc["device"]
    n_slots = dev.get("n_slots")
    if fmt == "lcos":
        n, p, h, w = (int(v) for v in arrays["mask_shape"])
        if n != n_slots or p != len(planes):
            raise SpecError(f"the mask file holds {n} slots x {p} planes, the plan {n_slots} x {len(planes)}",
                            field="masks.file", fix="make the plan again")
    else:
        p, h, w = arrays["start_tick"].shape
        _check_ticks(arrays, float(dev["clock_ms"]))
    check_replaceable_folder(out, MANIFEST, overwrite, "exported masks")
    files = _files_for(fmt, planes, n_slots)
    out.parent.mkdir(parents=True, exist_ok=True)
    report_stale_staging(out, MANIFEST)  # what a killed export left beside out
    staging = make_staging(out, "fieldcal-partial")
    try:
        with staging_lock(staging):  # a later run sees the folder is in use, not a leftover
            data = _encode(fmt, arrays, planes, n_slots)
            records = []
            for name, plane, role, k in files:
                atomic_write_bytes(staging / name, data[name])
                records.append({"name": name, "plane": plane, "role": role, "slot": k, "bytes": len(data[name]),
                                "sha256": hashlib.sha256(data[name]).hexdigest()})
            manifest = {
                "format": MASKS_FORMAT,
                "device": fmt,
                "image_size_px": [int(w), int(h)],
                "planes": planes,
                "cfa": doc["parameters"].get("cfa"),
                "direction": doc["direction"],
                "pixel_exposure_ms": float(doc["pixel_exposure_ms"]),
                "total_time_ms": float(doc["total_time_ms"]),
                "plan": {"file": plan_file, "masks_sha256": doc["masks"].get("sha256")},
                "files": records,
                "total_bytes": int(sum(r["bytes"] for r in records)),
            }
            if fmt == "lcos":
                manifest["lcos"] = {"slot_ms": float(dev["slot_ms"]), "n_slots": int(n_slots),
                                    "max_hold_ms": float(dev["max_hold_ms"]), "complement": bool(dev["complement"]),
                                    "encoding": "PNG greyscale, bit depth 1; 1 = open (the pixel integrates in "
                                                "the slot)"}
            else:
                manifest["pixelwise"] = {"clock_ms": float(dev["clock_ms"]),
                                         "exposure_ticks": int(round(float(doc["pixel_exposure_ms"])
                                                                     / dev["clock_ms"])),
                                         "encoding": "TIFF uint16 register ticks, deflate + horizontal predictor; a "
                                                     "pixel never exposed has start = stop = 0"}
            documents.write(staging / MANIFEST, manifest, "masks")
            replace_folder(staging, out, marker=MANIFEST, overwrite=overwrite, what="exported masks")
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return manifest


def export_plan_file(plan: str | Path, out: str | Path, *, fmt: str | None = None, overwrite: bool = False) -> dict:
    """Export the masks of the sweep plan file ``plan`` (its ``.npz`` sidecar, hash checked) into ``out``."""
    from .planfile import masks_path, read_plan
    doc = read_plan(plan)
    fmt = export_format(doc, fmt)
    npz = masks_path(plan, doc)
    check_output(out, inputs=[plan, npz], overwrite=overwrite, kind="dir", replaces_folder=True,
                 files=file_names(doc, fmt))
    want = doc["masks"].get("sha256")
    if want and hashlib.sha256(npz.read_bytes()).hexdigest() != want:
        raise SpecError("the mask file does not match the plan's sha256", path=npz, field="masks.sha256",
                        fix="make the plan again (plan and .npz belong together)")
    return export_device_masks(doc, mk.load_npz(npz), out, fmt=fmt, overwrite=overwrite,
                               plan_file=Path(plan).name)


# --------------------------------------------------------------------------------------------------- load


def _file(folder: Path, rec: dict) -> bytes:
    name = rec["name"]
    if os.sep in name or "/" in name or name in (".", ".."):  # the schema's pattern already refuses these
        raise SpecError(f"file name {name!r} is not a plain name", path=folder / MANIFEST, field="files", fix=_FIX)
    p = folder / name
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise SpecError("a mask file listed in masks.json is missing", path=p, fix=_FIX) from None
    if hashlib.sha256(data).hexdigest() != rec["sha256"]:
        raise SpecError("the file does not match its sha256 in masks.json (changed or damaged)", path=p,
                        field="sha256", fix=_FIX)
    return data


def _decode_png(data: bytes, path: Path, shape: tuple[int, int]) -> np.ndarray:
    import cv2
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.shape != shape:
        raise SpecError(f"is not a {shape[1]}x{shape[0]} greyscale mask image", path=path, fix=_FIX)
    if not np.isin(img, (0, 255)).all():
        raise SpecError("holds values other than 0 and 1: not a binary mask", path=path, fix=_FIX)
    return img > 0


def _decode_tiff(data: bytes, path: Path, shape: tuple[int, int]) -> np.ndarray:
    import tifffile
    try:
        img = tifffile.imread(io.BytesIO(data))
    except Exception as e:  # tifffile raises several types on a bad file
        raise SpecError(f"cannot read the TIFF ({e})", path=path, fix=_FIX) from None
    if img.dtype != np.uint16 or img.shape != shape:
        raise SpecError(f"is {img.dtype} {img.shape}, expected a uint16 {shape[1]}x{shape[0]} tick map", path=path,
                        fix=_FIX)
    return img


def load_device_masks(folder: str | Path) -> DeviceMasks:
    """Read an exported folder back: manifest checked against its schema, every file against its sha256.

    Returns the arrays of the plan's sidecar that the files encode: ``mask_bits`` (n_slots, P, H, ceil(W/8))
    packed as :func:`fieldcal.plan.masks.pack` and ``mask_shape`` for ``lcos``; ``start_tick``/``stop_tick``
    (P, H, W) uint32 for ``pixelwise``.
    """
    folder = Path(folder)
    man = documents.read(folder / MANIFEST, "masks", not_found="masks.json not found in the folder",
                         not_found_fix=_FIX)
    fmt, planes = man["device"], man["planes"]
    w, h = man["image_size_px"]
    if fmt not in man:  # the schema requires it too
        raise SpecError(f"the {fmt} section is missing", path=folder / MANIFEST, field=fmt, fix=_FIX)
    n_slots = man["lcos"]["n_slots"] if fmt == "lcos" else None
    expect = _files_for(fmt, planes, n_slots)
    got = [(r["name"], r["plane"], r["role"], r["slot"]) for r in man["files"]]
    if got != expect:
        raise SpecError("the file list does not match the planes and slots", path=folder / MANIFEST,
                        field="files", fix=_FIX)
    if fmt == "lcos":
        bits = np.zeros((n_slots, len(planes), h, (w + 7) // 8), dtype=np.uint8)
        for rec in man["files"]:
            m = _decode_png(_file(folder, rec), folder / rec["name"], (h, w))
            bits[rec["slot"], planes.index(rec["plane"])] = mk.pack(m)
        arrays = {"mask_bits": bits, "mask_shape": np.asarray([n_slots, len(planes), h, w], dtype=np.int64)}
    else:
        ticks = {r: np.zeros((len(planes), h, w), dtype=np.uint32) for r in ("start", "stop")}
        for rec in man["files"]:
            ticks[rec["role"]][planes.index(rec["plane"])] = _decode_tiff(_file(folder, rec), folder / rec["name"],
                                                                          (h, w))
        arrays = {"start_tick": ticks["start"], "stop_tick": ticks["stop"]}
    return DeviceMasks(man, arrays)
