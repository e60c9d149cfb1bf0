"""Read, validate and write ``fieldcal-plan/1`` files (the schema is in docs/planning.md)."""

from __future__ import annotations

import json
import math
from pathlib import Path, PurePosixPath
from typing import Any

from fieldcal.formats.atomic import atomic_write_text
from ..errors import SpecError

PLAN_FORMAT = "fieldcal-plan/1"


def _num(d, key, path, where="", positive=False):
    v = d.get(key) if isinstance(d, dict) else None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SpecError(f"must be a finite number, got {v!r}", path=path, field=where + key,
                        fix="make the plan again with `fieldcal plan`")
    if positive and v <= 0:
        raise SpecError(f"must be > 0, got {v}", path=path, field=where + key, fix="make the plan again")
    return float(v)


def validate_plan(doc: Any, path: str | Path | None = None, check_files: bool = True) -> dict:
    """Check a plan document; raise :class:`SpecError` naming the field and the fix. Returns the document."""
    if not isinstance(doc, dict):
        raise SpecError("a plan must be a JSON object", path=path, fix="make the plan with `fieldcal plan`")
    if doc.get("format") != PLAN_FORMAT:
        raise SpecError(f"unknown plan format {doc.get('format')!r}; this fieldcal reads {PLAN_FORMAT!r}", path=path,
                        field="format", fix=f"set \"format\": \"{PLAN_FORMAT}\" or make the plan again")
    kind = doc.get("kind")
    if kind not in ("stack", "sweep"):
        raise SpecError(f"kind must be \"stack\" or \"sweep\", got {kind!r}", path=path, field="kind",
                        fix="make the plan again with `fieldcal plan stack|sweep`")
    if not isinstance(doc.get("parameters"), dict):
        raise SpecError("missing or not an object", path=path, field="parameters", fix="make the plan again")
    direction = doc.get("direction")
    if direction not in ("+z", "-z"):
        raise SpecError(f"direction must be \"+z\" or \"-z\", got {direction!r}", path=path, field="direction",
                        fix="make the plan again")
    if kind == "stack":
        _validate_stack(doc, path, direction)
    else:
        _validate_sweep(doc, path, direction, check_files)
    return doc


def _validate_stack(doc, path, direction):
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SpecError("a stack plan needs a non-empty list of frames", path=path, field="frames",
                        fix="make the plan again")
    zs = []
    for i, f in enumerate(frames):
        if not isinstance(f, dict):
            raise SpecError("each frame must be an object", path=path, field=f"frames[{i}]", fix="make the plan again")
        zs.append(_num(f, "z_um", path, f"frames[{i}]."))
        if "exposure_ms" in f:
            _num(f, "exposure_ms", path, f"frames[{i}].", positive=True)
        bands = f.get("bands", {})
        if not isinstance(bands, dict):
            raise SpecError("bands must map channel names to [lo, hi] or null", path=path,
                            field=f"frames[{i}].bands", fix="make the plan again")
        for c, b in bands.items():
            if b is None:
                continue
            if (not isinstance(b, list) or len(b) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                                  and math.isfinite(v) for v in b) or b[0] > b[1]):
                raise SpecError(f"band must be [lo, hi] with lo <= hi or null, got {b!r}", path=path,
                                field=f"frames[{i}].bands.{c}", fix="make the plan again")
    steps = [b - a for a, b in zip(zs, zs[1:])]
    if any((s <= 0) if direction == "+z" else (s >= 0) for s in steps):
        raise SpecError(f"frames are not in one direction of travel ({direction}) with distinct z", path=path,
                        field="frames", fix="list frames in capture order, all increasing (+z) or decreasing (-z)")


def _validate_sweep(doc, path, direction, check_files):
    D = _num(doc, "range_um", path)
    a = _num(doc, "alpha_um", path, positive=True)
    ts = _num(doc, "pixel_exposure_ms", path, positive=True)
    v = _num(doc, "velocity_um_per_ms", path, positive=True)
    T = _num(doc, "total_time_ms", path, positive=True)
    start, stop = _num(doc, "start_um", path), _num(doc, "stop_um", path)
    if D < 0:
        raise SpecError("must be >= 0", path=path, field="range_um", fix="make the plan again")
    if not math.isclose(v, 2 * a / ts, rel_tol=1e-6):
        raise SpecError(f"velocity {v} is not 2α/t_s = {2 * a / ts}", path=path, field="velocity_um_per_ms",
                        fix="make the plan again")
    if not math.isclose(T, (D / (2 * a) + 1) * ts, rel_tol=1e-6):
        raise SpecError(f"total time {T} is not (D/2α + 1) t_s", path=path, field="total_time_ms", fix="make the plan again")
    if (stop - start > 0) != (direction == "+z"):
        raise SpecError("start/stop disagree with the direction", path=path, field="stop_um", fix="make the plan again")
    m = doc.get("masks")
    if not isinstance(m, dict) or not isinstance(m.get("file"), str):
        raise SpecError("a sweep plan must say where its masks are", path=path, field="masks.file",
                        fix="make the plan again (it writes PLAN.masks.npz beside PLAN.json)")
    p = PurePosixPath(m["file"])
    if p.is_absolute() or ".." in p.parts:
        raise SpecError(f"mask path {m['file']!r} must be relative to the plan's folder", path=path,
                        field="masks.file", fix="keep the .npz beside the plan")
    if check_files and path is not None and not (Path(path).parent / p).exists():
        raise SpecError(f"mask file {m['file']} is missing beside the plan", path=path, field="masks.file",
                        fix="copy the .npz together with the plan, or make the plan again")


def write_plan(path: str | Path, doc: dict) -> None:
    validate_plan(doc, path, check_files=False)
    atomic_write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n")


def read_plan(path: str | Path, check_files: bool = True) -> dict:
    path = Path(path)
    if not path.exists():
        raise SpecError("plan file not found", path=path, fix="give the path written by `fieldcal plan ... --out`")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"not valid JSON ({e})", path=path, fix="make the plan again") from None
    return validate_plan(doc, path, check_files=check_files)


def masks_path(plan_path: str | Path, doc: dict) -> Path:
    return Path(plan_path).parent / doc["masks"]["file"]
