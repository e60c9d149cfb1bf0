"""Run a capture plan on a stage and a camera into a crash-safe, resumable ``fieldcal-stack/1`` folder.

The plan is data (:class:`CapturePlan`): positions in capture order, exposure, approach side. The executor
(:func:`capture`) checks the whole motion range against the stage's travel *before anything moves*, then for
each frame: approach the position from the same side (backlash), wait on target, read the measured position,
snap, read it again, write the frame, commit.

Commit protocol (per frame)
---------------------------
1. :meth:`fieldcal.formats.stack.StackWriter.add_frame` writes the frame to a temporary file, fsyncs, renames it to
   ``frames/NNNN.tiff`` (NNNN = plan index) and then rewrites ``stack.json`` atomically (temp + fsync +
   rename). ``stack.json`` therefore parses and lists only complete frames at every moment.
2. A line is appended to ``capture.journal`` and fsynced: **the commit point**.

On resume the journal is the truth: a frame whose journal line is missing (crash between 1 and 2), whose file
is missing, or whose sha256 no longer matches is *torn*; it is dropped from ``stack.json`` (atomic rewrite),
its file deleted, and it is taken again. Committed, intact frames are skipped. A journal started by a
different plan (its sha256 differs) or with a different camera geometry is refused.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_text, fsync_dir
from fieldcal.errors import DeviceError, FieldcalError, LinkError, ParameterError, SpecError, StackError
from fieldcal.progress import progress, status

JOURNAL = "capture.journal"
JOURNAL_FORMAT = documents.format_id("capture-journal")
# camera keys that fix the stack's geometry: a resume with other values would mix two cameras
CAMERA_STACK_KEYS = ("pixel_pitch_um", "channels", "bit_depth", "size_px", "roi", "lens")


@dataclass(frozen=True)
class PlannedFrame:
    index: int
    z_um: float
    exposure_ms: float | None = None


@dataclass(frozen=True)
class CapturePlan:
    """What to capture: positions (µm) in capture order and how to approach them.

    Attributes
    ----------
    frames : PlannedFrame per position, in capture order.
    approach : ``"+z"`` (every position is reached moving +z, i.e. from below) or ``"-z"``.
    overshoot_um : how far past a position the stage backs off before approaching it (must exceed the backlash).
    source : where the plan came from (plan-file parameters or the ``--z`` range), stored in the stack.
    """

    frames: tuple[PlannedFrame, ...]
    approach: str = "+z"
    overshoot_um: float = 20.0
    source: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.frames:
            raise ParameterError("the plan has no frames", field="frames", fix="give at least one position")
        z = [f.z_um for f in self.frames]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in z):
            raise ParameterError("plan positions must be finite numbers", field="frames[].z_um",
                                 fix="check the plan file or --z arguments")
        if len(set(z)) != len(z):
            raise ParameterError("plan positions repeat; a stack needs distinct z", field="frames[].z_um",
                                 fix="remove repeated positions")
        if self.approach not in ("+z", "-z"):
            raise ParameterError(f"approach must be '+z' or '-z', got {self.approach!r}", field="approach",
                                 fix="use --approach +z or -z")
        if not (math.isfinite(self.overshoot_um) and self.overshoot_um >= 0):
            raise ParameterError(f"overshoot {self.overshoot_um} um must be >= 0", field="overshoot_um",
                                 fix="use e.g. --overshoot-um 20 (more than the stage's backlash)")
        for f in self.frames:
            if f.exposure_ms is not None and not (math.isfinite(f.exposure_ms) and f.exposure_ms > 0):
                raise ParameterError(f"exposure {f.exposure_ms} ms of frame {f.index} must be > 0",
                                     field=f"frames[{f.index}].exposure_ms", fix="use a positive exposure")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_range(cls, start_um: float, stop_um: float, step_um: float, *, exposure_ms: float | None = None,
                   approach: str | None = None, overshoot_um: float = 20.0) -> "CapturePlan":
        """``start, start+step, ...`` up to and including ``stop`` when it falls on the grid."""
        if not all(math.isfinite(v) for v in (start_um, stop_um, step_um)) or step_um == 0:
            raise ParameterError(f"--z {start_um} {stop_um} {step_um}: step must be non-zero and all finite",
                                 field="--z", fix="e.g. --z -100 100 10")
        if (stop_um - start_um) * step_um < 0:
            raise ParameterError(f"--z {start_um} {stop_um} {step_um}: the step goes away from STOP", field="--z",
                                 fix="use a negative STEP to go down, e.g. --z 100 -100 -10")
        n = int(math.floor((stop_um - start_um) / step_um + 1e-9)) + 1
        if n > 100000:
            raise ParameterError(f"--z gives {n} frames", field="--z", fix="use a larger step")
        z = start_um + step_um * np.arange(n)
        frames = tuple(PlannedFrame(i, round(float(v), 6), exposure_ms) for i, v in enumerate(z))
        approach = approach or ("+z" if step_um > 0 else "-z")
        return cls(frames, approach, overshoot_um,
                   {"kind": "range", "z_um": [start_um, stop_um, step_um], "exposure_ms": exposure_ms})

    @classmethod
    def from_file(cls, path: str | Path, *, exposure_ms: float | None = None, approach: str | None = None,
                  overshoot_um: float = 20.0) -> "CapturePlan":
        """A ``fieldcal-plan/1`` stack plan (frames in capture order), read by :func:`fieldcal.plan.read_plan`."""
        from fieldcal.plan.planfile import read_plan
        path = Path(path)
        d = read_plan(path, check_files=False)
        if d["kind"] != "stack":
            raise SpecError(f"kind {d['kind']!r} cannot be captured frame by frame", path=path, field="kind",
                            fix="capture runs stack plans (kind 'stack'); sweeps need a camera that exposes "
                                "during motion and are not supported yet")
        frames = []
        for k, e in enumerate(d["frames"]):
            exp = exposure_ms if exposure_ms is not None else e.get("exposure_ms")
            frames.append(PlannedFrame(k, float(e["z_um"]), None if exp is None else float(exp)))
        if approach is None:
            approach = d.get("direction", "+z")
        try:
            return cls(tuple(frames), approach, overshoot_um,
                       {"kind": "plan", "file": str(path), "plan_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                        "parameters": d.get("parameters", {})})
        except ParameterError as exc:
            raise SpecError(exc.what, path=path, field=exc.field, fix=exc.fix) from None

    # ------------------------------------------------------------------ inspection
    @property
    def z_um(self) -> np.ndarray:
        return np.array([f.z_um for f in self.frames], dtype=np.float64)

    def fingerprint(self) -> str:
        """sha256 of what decides the frames (positions, order, exposures, approach); resume refuses a change."""
        doc = {"z_um": [f.z_um for f in self.frames], "exposure_ms": [f.exposure_ms for f in self.frames],
               "approach": self.approach, "overshoot_um": self.overshoot_um}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def motion_range_um(self) -> tuple[float, float]:
        """Every position the stage will be sent to, approach moves included."""
        z = self.z_um
        if self.approach == "+z":
            return float(z.min() - self.overshoot_um), float(z.max())
        return float(z.min()), float(z.max() + self.overshoot_um)

    def moves(self, start_um: float | None = None) -> list[tuple[float, bool]]:
        """The motion sequence ``[(z_um, is_frame)]``: a backing-off move wherever the next position would be
        reached from the wrong side (always before the first frame, as the start position is unknown)."""
        out, last = [], start_um
        sgn = 1.0 if self.approach == "+z" else -1.0
        for f in self.frames:
            if last is None or sgn * (f.z_um - last) <= 0:
                out.append((f.z_um - sgn * self.overshoot_um, False))
            out.append((f.z_um, True))
            last = f.z_um
        return out

    def summary(self, *, velocity_um_per_s: float, frame_bytes: int, settle_ms: float = 20.0,
                readout_ms: float = 30.0, exposure_ms: float | None = None) -> dict[str, Any]:
        """Dry-run numbers: positions, estimated time and disk."""
        if not (velocity_um_per_s > 0):
            raise ParameterError("stage velocity must be > 0", field="velocity", fix="check the stage")
        t_ms, last = 0.0, None
        for z, is_frame in self.moves():
            t_ms += (0.0 if last is None else abs(z - last) / velocity_um_per_s * 1000.0) + settle_ms
            last = z
        exp = [f.exposure_ms if f.exposure_ms is not None else (exposure_ms or 0.0) for f in self.frames]
        t_ms += float(np.sum(exp)) + readout_ms * len(self.frames)
        return {"n_frames": len(self.frames), "z_um": [f.z_um for f in self.frames], "approach": self.approach,
                "motion_range_um": list(self.motion_range_um()), "n_moves": len(self.moves()),
                "time_s": round(t_ms / 1000.0, 3), "disk_bytes": int(frame_bytes) * len(self.frames)}


@dataclass
class CaptureResult:
    path: Path
    n_frames: int
    taken: int
    skipped: int
    retaken: int
    link_retries: int = 0


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _sha256_file(path: Path) -> str | None:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError:
        return None
    return h.hexdigest()


class Journal:
    """``capture.journal``: a header line, then one JSON line per committed frame (append + fsync)."""

    def __init__(self, path: Path):
        self.path = path

    def create(self, header: dict) -> None:
        atomic_write_text(self.path, documents.dumps(header, "capture-journal", self.path, indent=None,
                                                     sort_keys=True, error=StackError) + "\n")

    def read(self) -> tuple[dict, list[dict]]:
        """Header and frame lines; a torn last line (no LF: a crash mid-append) is cut off the file."""
        data = self.path.read_bytes()
        cut = data.rfind(b"\n") + 1
        if cut < len(data):
            with open(self.path, "r+b") as f:
                f.truncate(cut)
                f.flush()
                os.fsync(f.fileno())
            data = data[:cut]
        lines = data.decode("utf-8", errors="replace").splitlines()
        if not lines:
            raise StackError("the capture journal is empty", path=self.path, fix="delete the folder and capture again")
        fix = "move the folder away and capture again (the journal was not written by fieldcal capture)"
        header = documents.validate(documents.loads(lines[0], self.path, where="line 1", error=StackError, fix=fix),
                                    "capture-journal", self.path, where="line 1", error=StackError)
        entries = [documents.validate(documents.loads(line, self.path, where=f"line {n}", error=StackError, fix=fix),
                                      "capture-journal", self.path, pointer="/$defs/entry", where=f"line {n}",
                                      error=StackError)
                   for n, line in enumerate(lines[1:], start=2) if line.strip()]
        return header, entries

    def append(self, entry: dict) -> None:
        text = documents.dumps(entry, path=self.path, indent=None, sort_keys=True, error=StackError)
        line = text.encode("utf-8") + b"\n"
        with open(self.path, "ab") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())


def _stack_header(cam: dict, stage: dict, plan: CapturePlan) -> dict:
    keys = {"bit_depth": cam.get("bit_depth"), "black_level": cam.get("black_level"),
            "white_level": cam.get("white_level"), "f_number": cam.get("f_number"),
            "object_distance_mm": cam.get("object_distance_mm"), "lens": cam.get("lens")}
    exps = {f.exposure_ms for f in plan.frames}
    if len(exps) == 1 and None not in exps:
        keys["exposure_ms"] = exps.pop()
    keys = {k: v for k, v in keys.items() if v is not None}
    keys["capture"] = {"stage": stage, "camera": cam, "plan": plan.source, "approach": plan.approach,
                       "overshoot_um": plan.overshoot_um, "z_um": "commanded position; z_measured_um = mean of "
                                                                   "the stage's readings before and after the exposure"}
    return keys


def _prepare(out: Path, plan: CapturePlan, cam: dict, stage: dict):
    """Create or resume the folder; returns (writer, journal, committed {index: entry}, n_torn)."""
    from fieldcal.formats.stack import STACK_JSON, StackWriter

    journal = Journal(out / JOURNAL)
    header = {"journal": JOURNAL_FORMAT, "plan_sha256": plan.fingerprint(), "n_frames": len(plan.frames),
              "camera": {k: cam.get(k) for k in CAMERA_STACK_KEYS}, "created": _now_iso()}
    json_path = out / STACK_JSON
    fresh = not out.exists() or (out.is_dir() and not any(out.iterdir()))
    if not fresh and not journal.path.is_file():
        # a crash right after StackWriter.create leaves an empty stack and no journal: safe to adopt
        try:
            meta = documents.read_json(json_path, error=StackError)
            adoptable = meta.get("frames") == [] and not any((out / "frames").glob("*.tif*"))
        except (FieldcalError, OSError, AttributeError):
            adoptable = False
        if not adoptable:
            raise StackError("exists and is not a capture folder (no capture.journal)", path=out,
                             fix="choose a new --out folder")
        fresh = True
        import shutil
        shutil.rmtree(out)
    if fresh:
        writer = StackWriter.create(out, pixel_pitch_um=cam["pixel_pitch_um"], channels=cam["channels"],
                                    **_stack_header(cam, stage, plan))
        journal.create(header)
        return writer, journal, {}, 0

    old, entries = journal.read()
    if old.get("plan_sha256") != header["plan_sha256"]:
        raise StackError("the plan changed since this capture started (plan sha256 differs)", path=journal.path,
                         field="plan_sha256", fix="re-run with the original plan/--z/--exposure-ms/--approach, "
                                                  "or capture into a new --out folder")
    if old.get("camera") != header["camera"]:
        raise StackError(f"the camera changed since this capture started ({old.get('camera')} vs "
                         f"{header['camera']})", path=journal.path, field="camera",
                         fix="use the same camera and settings, or capture into a new --out folder")
    latest: dict[int, dict] = {}
    for e in entries:  # validated by Journal.read: "i" and a frame "entry" inside frames/
        latest[e["i"]] = e["entry"]
    committed, torn_files = {}, set()
    for i, entry in latest.items():
        if 0 <= i < len(plan.frames) and _sha256_file(out / entry["file"]) == entry.get("sha256"):
            committed[i] = entry
        else:
            torn_files.add(entry["file"])
    # stack.json := the committed, intact frames (drops frames written but never committed)
    meta = documents.read_json(json_path, error=StackError, fix="move the folder away and capture again")
    if not isinstance(meta, dict):
        raise StackError("stack.json is unreadable", path=json_path, fix="move the folder away and capture again")
    keep = [committed[i] for i in sorted(committed, key=lambda k: committed[k].get("time", ""))]
    listed = {e.get("file") for e in meta.get("frames", []) if isinstance(e, dict)}
    torn = len(torn_files | (listed - {e["file"] for e in keep}))
    if meta.get("frames") != keep:
        meta["frames"] = keep
        documents.write(json_path, meta, "stack", error=StackError)
    keep_files = {(out / e["file"]).resolve() for e in keep}
    for p in (out / "frames").iterdir() if (out / "frames").is_dir() else ():
        if p.resolve() not in keep_files:  # uncommitted frame files and temporary files of an interrupted write
            p.unlink()
    fsync_dir(out / "frames")
    return StackWriter.open_existing(out), journal, committed, torn


def capture(plan: CapturePlan, stage, camera, out: str | Path, *, retries: int = 2,
            on_target_timeout_ms: float = 30000.0, settle_ms: float = 0.0, quiet: bool = False) -> CaptureResult:
    """Run ``plan`` on connected devices into the stack folder ``out`` (created, or resumed).

    Raises
    ------
    ParameterError
        The plan leaves the stage's travel (checked before any motion).
    StackError
        ``out`` holds a different plan or camera, or is not a capture folder.
    DeviceError / LinkError
        A device failed (after ``retries`` resyncs for link errors). The stage is stopped; the folder is
        resumable.
    KeyboardInterrupt
        After stopping the stage; the folder is resumable.
    """
    out = Path(out)
    lo, hi = stage.limits_um()
    m_lo, m_hi = plan.motion_range_um()
    if m_lo < lo or m_hi > hi:
        raise ParameterError(f"the plan needs the stage at {m_lo:g}..{m_hi:g} um (approach moves included) but its "
                             f"travel is {lo:g}..{hi:g} um; nothing was moved", field="z_um",
                             fix="shift or shorten the plan, or move the stage's zero (e.g. gcs:...,zero_mm=...)")
    cam = camera.describe()
    writer, journal, committed, torn = _prepare(out, plan, cam, stage.describe())
    todo = [f for f in plan.frames if f.index not in committed]
    result = CaptureResult(out, len(plan.frames), 0, len(committed), torn)
    if not todo:
        status(f"capture: all {len(plan.frames)} frames of {out} are committed and intact; nothing to do", quiet)
        return result
    if committed:
        status(f"capture: resuming {out}: {len(committed)} frames kept, {len(todo)} to take"
               + (f" ({torn} torn)" if torn else ""), quiet)
    try:
        if not stage.is_referenced():
            stage.reference()
        trigger_set = False
        last_cmd: list[float | None] = [None]
        sgn = 1.0 if plan.approach == "+z" else -1.0
        for f in progress(todo, total=len(todo), desc="capture", quiet=quiet, unit="frame"):
            for attempt in range(retries + 1):
                try:
                    if not trigger_set:
                        camera.configure(trigger="software")
                        trigger_set = True
                    if f.exposure_ms is not None:
                        camera.configure(exposure_ms=f.exposure_ms)
                    if last_cmd[0] is None or sgn * (f.z_um - last_cmd[0]) <= 0:
                        back = f.z_um - sgn * plan.overshoot_um
                        last_cmd[0] = None
                        stage.move_to_um(back)
                        stage.wait_on_target(on_target_timeout_ms)
                    last_cmd[0] = None
                    stage.move_to_um(f.z_um)
                    stage.wait_on_target(on_target_timeout_ms)
                    last_cmd[0] = f.z_um
                    if settle_ms > 0:
                        time.sleep(settle_ms / 1000.0)
                    z_before = stage.position_um()
                    t = _now_iso()
                    frame = camera.snap()
                    z_after = stage.position_um()
                    break
                except LinkError as exc:
                    last_cmd[0] = None  # the state is unknown: approach again from the backing-off position
                    if attempt >= retries:
                        raise
                    status(f"capture: link error ({exc.what}); resyncing and retrying frame {f.index}", quiet)
                    result.link_retries += 1
                    stage.resync()
                    if hasattr(camera, "resync"):
                        camera.resync()
            info = writer.add_frame(
                frame.image, f.z_um, file=f"frames/{f.index:04d}.tiff",
                z_measured_um=round(0.5 * (z_before + z_after), 6), z_measured_before_um=round(z_before, 6),
                z_measured_after_um=round(z_after, 6), z_commanded_um=f.z_um, exposure_ms=frame.exposure_ms,
                time=t, camera_frame_id=int(frame.frame_id), plan_index=f.index)
            journal.append({"i": f.index, "entry": info.meta})  # the commit point
            result.taken += 1
    except (DeviceError, LinkError) as exc:
        stage.stop()
        exc.fix = ((exc.fix + "; ") if exc.fix else "") + \
            f"{len(committed) + result.taken} of {len(plan.frames)} frames are committed in {out}: re-run the same command to resume"
        exc.args = (exc._format(),)
        raise
    except BaseException:
        stage.stop()  # Ctrl-C (or a bug): stop the motion first; the folder stays resumable
        raise
    return result
