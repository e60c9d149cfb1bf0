"""The capture folder: a ``fieldcal-stack/1`` folder plus ``capture.journal``, locked, checked, resumable.

Rules (issue #12):

* **Lock.** :meth:`CaptureFolder.lock` takes ``fcntl.flock(LOCK_EX | LOCK_NB)`` on the folder itself for the
  whole run; a second capture into the same folder is refused (:class:`~fieldcal.errors.ResourceError`, exit 4).
* **Check every path before touching anything.** ``--out`` must not be a symbolic link; ``stack.json`` and
  ``capture.journal`` must be regular files, ``frames/`` a real folder, and ``frames/`` may hold only regular
  files with the names capture writes. Every journal line is validated (header and entries: the file of frame
  ``i`` must be ``frames/NNNN.tiff``, its z the plan's). Anything else is refused with nothing changed.
* **Never delete what the journal did not create.** A folder without a journal is never adopted, emptied or
  removed — except the one state a crash inside :meth:`_create` leaves: exactly an empty ``frames/`` and a
  ``stack.json`` with no frames whose ``capture.plan_sha256`` is this plan's; it is adopted in place (nothing is
  deleted). On resume only files under capture's own names are removed: uncommitted ``frames/NNNN.tiff`` of
  this plan, and the temporary files of an interrupted atomic write.

Commit protocol per frame: :meth:`fieldcal.formats.stack.StackWriter.add_frame` writes the frame (temporary
file, fsync, rename) and rewrites ``stack.json`` atomically; then one line is appended to the journal and
fsynced — **the commit point**. On resume the journal is the truth: a frame without a journal line, with its file
missing or its sha256 changed is taken again.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import math
import os
import re
import stat
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from ..errors import ResourceError, StackError
from ..formats.atomic import atomic_write_text, fsync_dir

JOURNAL = "capture.journal"
JOURNAL_FORMAT = "fieldcal-capture-journal/1"
# camera keys that fix the stack's geometry: a resume with other values would mix two cameras
CAMERA_STACK_KEYS = ("pixel_pitch_um", "channels", "bit_depth", "size_px", "roi", "lens")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_FRAME_NAME = re.compile(r"^(\d{4,})\.tiff$")
_FRAME_TMP = re.compile(r"^\.\d{4,}\.tiff\.[A-Za-z0-9_]+\.tmp$")        # formats.atomic's temporary names
_TOP_TMP = re.compile(r"^\.(stack\.json|capture\.journal)\.[A-Za-z0-9_]+\.tmp$")
MAX_JOURNAL_BYTES = 64 << 20


def _is_num(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def _is_int(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, int)


# Every key a committed frame's entry may have (what CaptureFolder.save writes), and its check: a journal line
# with anything else was not written by capture, and nothing from it may reach stack.json.
ENTRY_KEYS = {"file": lambda v: isinstance(v, str), "sha256": lambda v: isinstance(v, str) and bool(_HEX64.match(v)),
              "z_um": _is_num, "z_commanded_um": _is_num, "z_measured_um": _is_num, "z_measured_before_um": _is_num,
              "z_measured_after_um": _is_num, "exposure_ms": lambda v: _is_num(v) and v > 0,
              "time": lambda v: isinstance(v, str) and len(v) <= 64, "camera_frame_id": _is_int,
              "plan_index": _is_int, "sweep": lambda v: _sweep_ok(v)}


def _sweep_ok(v) -> bool:
    """A sweep record (the runner's measured open/close positions and times): flat JSON of numbers, strings
    and lists of numbers."""
    if not isinstance(v, dict) or len(v) > 32:
        return False
    for k, x in v.items():
        if not isinstance(k, str) or len(k) > 64:
            return False
        if isinstance(x, str):
            if len(x) > 4096:
                return False
        elif isinstance(x, list):
            if len(x) > 8 or not all(_is_num(e) for e in x):
                return False
        elif not (_is_num(x) or x is None):
            return False
    return True


def parse_journal_lines(lines: list[bytes], path: Path, fix: str) -> tuple[dict, list[dict]]:
    """Header and entry lines of a journal, each parsed safely and validated against the journal's JSON Schema
    (``fieldcal-capture-journal/1``: line 1 is the header, later lines ``$defs/entry``)."""
    from ..formats import documents

    if not lines:
        raise StackError("the capture journal has no complete header line", path=path, fix=fix)
    docs = []
    for k, raw in enumerate(lines, start=1):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise StackError(f"line {k} is not UTF-8 text", path=path, field=f"line {k}", fix=fix) from None
        doc = documents.loads(text, path, where=f"line {k}", error=StackError, fix=fix)
        docs.append(documents.validate(doc, "capture-journal", path, where=f"line {k}", error=StackError,
                                       pointer="" if k == 1 else "/$defs/entry"))
    return docs[0], docs[1:]


def read_journal(path: str | Path) -> tuple[dict, list[dict]]:
    """A journal file's header and complete entry lines, validated (a torn last line is ignored)."""
    path = Path(path)
    data = path.read_bytes()[: MAX_JOURNAL_BYTES + 1]
    if len(data) > MAX_JOURNAL_BYTES:
        raise StackError(f"the capture journal is larger than {MAX_JOURNAL_BYTES >> 20} MiB", path=path,
                         fix="this is not a journal capture wrote; capture into a new --out folder")
    complete = data.rfind(b"\n") + 1
    return parse_journal_lines(data[:complete].split(b"\n")[:-1], path,
                               "this journal was not written by fieldcal capture (or was edited); capture into a "
                               "new --out folder")


def frame_file(index: int) -> str:
    """The one file name frame ``index`` of a capture may have."""
    return f"frames/{index:04d}.tiff"


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _sha256_file(path: Path) -> str | None:
    h = hashlib.sha256()
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def environment_error(exc: OSError, path: Path, action: str) -> ResourceError:
    """An OSError of the machine (disk full, read-only, permissions) as a clear exit-4 error."""
    return ResourceError(f"cannot {action}: {exc.strerror or exc}", path=path,
                         fix="check free disk space and the folder's permissions, then re-run the same command "
                             "(the capture resumes)")


def _kind(path: Path) -> str | None:
    """``"file"``, ``"dir"``, ``"link"``, ``"other"`` or None (missing), without following a link."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return "link"
    if stat.S_ISDIR(st.st_mode):
        return "dir"
    return "file" if stat.S_ISREG(st.st_mode) else "other"


@dataclass(frozen=True)
class Resume:
    """What :meth:`CaptureFolder.prepare` found: committed frames ``{index: stack entry}`` and how many torn."""

    committed: dict
    torn: int
    fresh: bool


class CaptureFolder:
    """A locked capture folder. Use as a context manager around :meth:`prepare` and :meth:`save`."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.journal_path = self.path / JOURNAL
        self._fd: int | None = None
        self._writer = None

    # ------------------------------------------------------------------ lock
    def lock(self) -> None:
        """Create the folder if missing, then hold an exclusive ``flock`` on it (refused if another run has it)."""
        kind = _kind(self.path)
        if kind == "link":
            raise StackError("is a symbolic link; capture writes only into a real folder", path=self.path,
                             fix="give the real folder as --out (or a new folder name)")
        if kind not in (None, "dir"):
            raise StackError("exists and is not a folder", path=self.path, fix="choose a new --out folder")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError as exc:
            if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                raise StackError("is not a real folder (a link or a file)", path=self.path,
                                 fix="give a real folder as --out") from None
            raise environment_error(exc, self.path, "create or open the output folder") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise ResourceError("another capture is writing into this folder (it holds the folder's lock)",
                                    path=self.path, fix="wait for that capture to end (or stop it), then re-run "
                                                        "to resume; or capture into another --out") from None
            raise environment_error(exc, self.path, "lock the output folder") from None
        self._fd = fd

    def unlock(self) -> None:
        if self._fd is not None:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> "CaptureFolder":
        self.lock()
        return self

    def __exit__(self, *exc) -> None:
        self.unlock()

    # ------------------------------------------------------------------ create / adopt / resume
    def prepare(self, *, plan_sha256: str, n_frames: int, frame_z_um: list[float], camera: dict,
                stack_header: dict) -> Resume:
        """Create the folder's stack and journal, or resume them; checks everything before changing anything."""
        if self._fd is None:
            raise RuntimeError("CaptureFolder.prepare() needs the lock: use `with CaptureFolder(...)`")
        header = {"journal": JOURNAL_FORMAT, "plan_sha256": plan_sha256, "n_frames": n_frames,
                  "camera": {k: camera.get(k) for k in CAMERA_STACK_KEYS}, "created": _now_iso()}
        try:
            names = set(os.listdir(self.path))
        except OSError as exc:
            raise environment_error(exc, self.path, "list the output folder") from None
        if not names:
            return self._create(header, camera, stack_header)
        if JOURNAL not in names:
            if self._adoptable(names, plan_sha256):
                self._write_journal_header(header)
                return self._resume(header, frame_z_um)
            raise StackError("exists and is not a capture folder (no capture.journal); nothing was changed",
                             path=self.path, fix="choose a new --out folder (capture never writes into, or "
                                                 "deletes, a folder it did not create)")
        return self._resume(header, frame_z_um)

    def _create(self, header: dict, camera: dict, stack_header: dict) -> Resume:
        from ..formats.stack import StackWriter
        try:
            stack_header = dict(stack_header)
            stack_header.setdefault("capture", {})["plan_sha256"] = header["plan_sha256"]
            self._writer = StackWriter.create(self.path, pixel_pitch_um=camera["pixel_pitch_um"],
                                              channels=camera["channels"], **stack_header)
            self._write_journal_header(header)  # a crash before this line leaves an adoptable folder
        except OSError as exc:
            raise environment_error(exc, self.path, "create the stack") from None
        return Resume({}, 0, True)

    def _write_journal_header(self, header: dict) -> None:
        atomic_write_text(self.journal_path, json.dumps(header, sort_keys=True) + "\n")

    def _adoptable(self, names: set[str], plan_sha256: str) -> bool:
        """The exact state a crash inside :meth:`_create` leaves: an empty real frames/ and an empty stack.json
        of this plan, and nothing else."""
        if names != {"stack.json", "frames"}:
            return False
        if _kind(self.path / "frames") != "dir" or _kind(self.path / "stack.json") != "file":
            return False
        if os.listdir(self.path / "frames"):
            return False
        from ..errors import FieldcalError
        from ..formats import documents
        try:
            meta = documents.read_json(self.path / "stack.json", error=StackError)
        except (FieldcalError, OSError):
            return False
        return (isinstance(meta, dict) and meta.get("frames") == [] and isinstance(meta.get("capture"), dict)
                and meta["capture"].get("plan_sha256") == plan_sha256)

    # ------------------------------------------------------------------ journal
    def _read_journal(self, n_frames: int, frame_z_um: list[float]) -> tuple[dict, list[dict], int]:
        """Header, validated entries and the byte length of the complete lines (a torn last line is ignored)."""
        jp = self.journal_path
        if _kind(jp) != "file":
            raise StackError("capture.journal is not a regular file (a link or a folder?); nothing was changed",
                             path=jp, fix="capture into a new --out folder")
        try:
            fd = os.open(jp, os.O_RDONLY | os.O_NOFOLLOW)
            with os.fdopen(fd, "rb") as f:
                data = f.read(MAX_JOURNAL_BYTES + 1)
        except OSError as exc:
            raise environment_error(exc, jp, "read the capture journal") from None
        if len(data) > MAX_JOURNAL_BYTES:
            raise StackError(f"the capture journal is larger than {MAX_JOURNAL_BYTES >> 20} MiB", path=jp,
                             fix="this is not a journal capture wrote; capture into a new --out folder")
        complete = data.rfind(b"\n") + 1
        lines = data[:complete].split(b"\n")[:-1]
        fix = "this journal was not written by fieldcal capture (or was edited); capture into a new --out folder"
        if not lines:
            raise StackError("the capture journal has no complete header line", path=jp, fix=fix)
        header, parsed = parse_journal_lines(lines, jp, fix)
        if not (isinstance(header.get("plan_sha256"), str) and _HEX64.match(header["plan_sha256"])):
            raise StackError("plan_sha256 is not a sha256 hex digest", path=jp, field="plan_sha256", fix=fix)
        if not isinstance(header.get("camera"), dict):
            raise StackError("camera is not an object", path=jp, field="camera", fix=fix)
        entries = []
        for k, e in enumerate(parsed, start=2):
            where = f"line {k}"
            if not (isinstance(e, dict) and isinstance(e.get("i"), int) and not isinstance(e.get("i"), bool)
                    and 0 <= e["i"] < n_frames and isinstance(e.get("entry"), dict)):
                raise StackError(f"{where} is not a frame record {{'i': 0..{n_frames - 1}, 'entry': {{...}}}}",
                                 path=jp, field=where, fix=fix)
            i, entry = e["i"], e["entry"]
            if entry.get("file") != frame_file(i):
                raise StackError(f"{where}: frame {i} must be {frame_file(i)!r}, the journal says "
                                 f"{entry.get('file')!r}", path=jp, field=f"{where}.entry.file", fix=fix)
            if not (isinstance(entry.get("sha256"), str) and _HEX64.match(entry["sha256"])):
                raise StackError(f"{where}: sha256 is not a hex digest", path=jp, field=f"{where}.entry.sha256",
                                 fix=fix)
            bad = sorted(k for k in entry if k not in ENTRY_KEYS or not ENTRY_KEYS[k](entry[k]))
            if bad:
                raise StackError(f"{where}: field {bad[0]!r} is unknown or has a wrong value "
                                 f"{entry.get(bad[0])!r:.60}", path=jp, field=f"{where}.entry.{bad[0]}", fix=fix)
            if entry.get("plan_index", i) != i:
                raise StackError(f"{where}: plan_index {entry['plan_index']} is not {i}", path=jp,
                                 field=f"{where}.entry.plan_index", fix=fix)
            z = entry.get("z_um")
            if isinstance(z, bool) or not isinstance(z, (int, float)) or not math.isfinite(z) \
                    or float(z) != frame_z_um[i]:
                raise StackError(f"{where}: z_um {z!r} is not the plan's {frame_z_um[i]:g} for frame {i}", path=jp,
                                 field=f"{where}.entry.z_um", fix=fix)
            entries.append(e)
        return header, entries, complete

    # ------------------------------------------------------------------ resume
    def _check_layout(self, n_frames: int) -> list[Path]:
        """Refuse links and foreign entries; return the removable leftovers (capture's own names only)."""
        jp = self.path / "stack.json"
        if _kind(jp) != "file":
            raise StackError("stack.json is missing or not a regular file (a link?); nothing was changed", path=jp,
                             fix="capture into a new --out folder")
        frames = self.path / "frames"
        fk = _kind(frames)
        if fk not in ("dir", None):
            raise StackError("frames/ is not a real folder (a symbolic link or a file); nothing was changed",
                             path=frames, fix="replace it by a real folder or capture into a new --out folder")
        leftovers: list[Path] = []
        for name in (os.listdir(frames) if fk == "dir" else ()):
            p = frames / name
            k = _kind(p)
            m = _FRAME_NAME.match(name)
            if k != "file":
                raise StackError(f"frames/{name} is a {'symbolic link' if k == 'link' else 'folder' if k == 'dir' else 'special file'}"
                                 "; frames/ may hold only the frame files capture writes; nothing was changed",
                                 path=p, fix="move it out of frames/, then re-run")
            if not ((m and int(m.group(1)) < n_frames) or _FRAME_TMP.match(name)):
                raise StackError(f"frames/{name} was not written by this capture; nothing was changed", path=p,
                                 fix="move it out of frames/, then re-run")
            if _FRAME_TMP.match(name):
                leftovers.append(p)
        for name in os.listdir(self.path):
            if _TOP_TMP.match(name) and _kind(self.path / name) == "file":
                leftovers.append(self.path / name)
        return leftovers

    def _resume(self, header: dict, frame_z_um: list[float]) -> Resume:
        from ..formats.stack import StackWriter
        n_frames = header["n_frames"]
        old, entries, complete = self._read_journal(n_frames, frame_z_um)
        jp = self.journal_path
        if old.get("plan_sha256") != header["plan_sha256"]:
            raise StackError("the plan changed since this capture started (plan sha256 differs)", path=jp,
                             field="plan_sha256", fix="re-run with the original plan/--z/--exposure-ms/--approach, "
                                                      "or capture into a new --out folder")
        if old.get("camera") != header["camera"]:
            raise StackError(f"the camera changed since this capture started ({old.get('camera')} vs "
                             f"{header['camera']})", path=jp, field="camera",
                             fix="use the same camera and settings, or capture into a new --out folder")
        leftovers = self._check_layout(n_frames)
        json_path = self.path / "stack.json"
        from ..errors import FieldcalError
        from ..formats import documents
        try:
            meta = documents.read_json(json_path, error=StackError)
        except (FieldcalError, OSError):
            meta = None
        if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
            raise StackError("stack.json is unreadable; nothing was changed", path=json_path,
                             fix="move the folder away and capture again")
        latest = {e["i"]: e["entry"] for e in entries}  # a re-taken frame's later line wins
        committed = {i: entry for i, entry in latest.items()
                     if _sha256_file(self.path / entry["file"]) == entry["sha256"]}
        keep = [committed[i] for i in sorted(committed, key=lambda k: (str(committed[k].get("time", "")), k))]
        listed = {e.get("file") for e in meta["frames"] if isinstance(e, dict)}
        kept_files = {e["file"] for e in keep}
        torn = len({latest[i]["file"] for i in latest if i not in committed} | (listed - kept_files))
        # everything checked: now change the folder (each step is idempotent if killed here)
        try:
            if complete < os.path.getsize(jp):  # a torn half-line: a crash mid-append
                with open(jp, "r+b") as f:
                    f.truncate(complete)
                    f.flush()
                    os.fsync(f.fileno())
            if meta["frames"] != keep:
                meta["frames"] = keep
                atomic_write_text(json_path, json.dumps(meta, indent=2, allow_nan=False) + "\n")
            frames = self.path / "frames"
            frames.mkdir(exist_ok=True)
            keep_names = {Path(e["file"]).name for e in keep}
            for name in os.listdir(frames):
                if _FRAME_NAME.match(name) and name not in keep_names:
                    leftovers.append(frames / name)  # written, never committed (or altered): taken again
            for p in leftovers:
                p.unlink()
            fsync_dir(frames)
            fsync_dir(self.path)
            self._writer = StackWriter.open_existing(self.path)
        except OSError as exc:
            raise environment_error(exc, self.path, "resume the capture") from None
        return Resume(committed, torn, False)

    # ------------------------------------------------------------------ commit
    def save(self, index: int, z_um: float, image, **frame_meta) -> dict:
        """Write frame ``index`` and append its journal line (the commit point); returns the stack entry."""
        size = [int(image.shape[1]), int(image.shape[0])] if getattr(image, "ndim", 0) >= 2 else None
        if size is not None and self._writer.meta.get("image_size_px") not in (None, size):
            # the camera stated another size than it delivers (pylon's emulator does): the frames are authoritative
            self._writer.meta["image_size_px"] = size
        try:
            info = self._writer.add_frame(image, z_um, file=frame_file(index), **frame_meta)
            self._append_journal(json.dumps({"i": index, "entry": info.meta}, sort_keys=True, allow_nan=False))
        except OSError as exc:
            raise environment_error(exc, self.path, f"write frame {index}") from None
        return info.meta

    def _append_journal(self, line: str) -> None:
        """Append one line and fsync it (never through a link)."""
        fd = os.open(self.journal_path, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
        with os.fdopen(fd, "ab") as f:
            f.write((line + "\n").encode("utf-8"))
            f.flush()
            os.fsync(f.fileno())
