"""Read, validate and write ``fieldcal-plan/1`` files (schema: fieldcal/formats/schemas/fieldcal-plan-1.schema.json,
described in docs/planning.md).

Types, ranges and required keys are the schema's, checked by :mod:`fieldcal.formats.documents`; the checks a
schema cannot express (one direction of travel, bands ordered, the sweep's kinematics agreeing, the masks file
beside the plan) are here, once.
"""

from __future__ import annotations

import math
import numbers
from pathlib import Path, PurePosixPath
from typing import Any

from fieldcal.formats import documents
from ..errors import SpecError

PLAN_FORMAT = documents.format_id("plan")
_FIX = "make the plan again with `fieldcal plan`"


def validate_plan(doc: Any, path: str | Path | None = None, check_files: bool = True) -> dict:
    """Check a plan document; raise :class:`SpecError` naming the field and the fix. Returns the document."""
    documents.validate(doc, "plan", path)
    plan_image_size_px(doc, path)
    if doc["kind"] == "stack":
        _validate_stack(doc, path, doc.get("direction"))
    else:
        _validate_sweep(doc, path, doc["direction"], check_files)
    return doc


def _validate_stack(doc, path, direction):
    zs = [float(f["z_um"]) for f in doc["frames"]]
    for i, f in enumerate(doc["frames"]):
        for c, b in (f.get("bands") or {}).items():
            if b is not None and b[0] > b[1]:
                raise SpecError(f"band must be [lo, hi] with lo <= hi or null, got {b!r}", path=path,
                                field=f"frames[{i}].bands.{c}", fix=_FIX)
    steps = [b - a for a, b in zip(zs, zs[1:])]
    if direction is None:  # a hand-written plan: capture order as listed, positions distinct
        if len(set(zs)) != len(zs):
            raise SpecError("frames repeat a z; a stack needs distinct positions", path=path, field="frames",
                            fix="remove repeated positions")
        return
    if any((s <= 0) if direction == "+z" else (s >= 0) for s in steps):
        raise SpecError(f"frames are not in one direction of travel ({direction}) with distinct z", path=path,
                        field="frames", fix="list frames in capture order, all increasing (+z) or decreasing (-z)")


def _validate_sweep(doc, path, direction, check_files):
    D, a, ts = float(doc["range_um"]), float(doc["alpha_um"]), float(doc["pixel_exposure_ms"])
    v, T = float(doc["velocity_um_per_ms"]), float(doc["total_time_ms"])
    start, stop = float(doc["start_um"]), float(doc["stop_um"])
    if not math.isclose(v, 2 * a / ts, rel_tol=1e-6):
        raise SpecError(f"velocity {v} is not 2α/t_s = {2 * a / ts}", path=path, field="velocity_um_per_ms", fix=_FIX)
    if not math.isclose(T, (D / (2 * a) + 1) * ts, rel_tol=1e-6):
        raise SpecError(f"total time {T} is not (D/2α + 1) t_s", path=path, field="total_time_ms", fix=_FIX)
    if (stop - start > 0) != (direction == "+z"):
        raise SpecError("start/stop disagree with the direction", path=path, field="stop_um", fix=_FIX)
    if check_files and path is not None:
        p = masks_path(path, doc)
        if not p.is_file():
            raise SpecError(f"mask file {doc['masks']['file']} is missing beside the plan", path=path,
                            field="masks.file", fix="copy the .npz together with the plan, or make the plan again")


def plan_image_size_px(doc: dict, path: str | Path | None = None) -> tuple[int, int] | None:
    """The image size ``(width, height)`` in px the plan was made for: its ``profile.image_size_px``, which
    ``fieldcal plan`` writes from the profile or lens spec it planned from. None when the plan does not say
    (a hand-written plan); a malformed value is a :class:`SpecError` naming the field."""
    prof = doc.get("profile")
    size = prof.get("image_size_px") if isinstance(prof, dict) else None
    if size is None:
        return None
    ok = (isinstance(size, (list, tuple)) and len(size) == 2
          and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and 1 <= v <= 1_000_000 for v in size))
    if not ok:
        raise SpecError(f"image size {size!r} is not [width, height] in whole pixels", path=path,
                        field="profile.image_size_px", fix=_FIX + ", or remove the key from a hand-written plan")
    return int(size[0]), int(size[1])


def write_plan(path: str | Path, doc: dict) -> None:
    validate_plan(doc, path, check_files=False)
    documents.write(path, doc, "plan")


def read_plan(path: str | Path, check_files: bool = True) -> dict:
    doc = documents.read(path, "plan", not_found="plan file not found",
                         not_found_fix="give the path written by `fieldcal plan ... --out`")
    return validate_plan(doc, path, check_files=check_files)


def masks_path(plan_path: str | Path, doc: dict) -> Path:
    """The sweep's mask file: relative to the plan's folder (schema) and inside it, links included."""
    folder = Path(plan_path).parent
    p = folder.joinpath(*PurePosixPath(doc["masks"]["file"].replace("\\", "/")).parts)
    try:
        p.resolve().relative_to(folder.resolve())
    except ValueError:
        raise SpecError(f"mask path {doc['masks']['file']!r} resolves outside the plan's folder", path=plan_path,
                        field="masks.file", fix="keep the .npz beside the plan") from None
    return p
