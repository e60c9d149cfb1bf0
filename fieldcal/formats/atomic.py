"""The one way fieldcal writes a file, and the checks every output path passes first (docs/safety.md).

:func:`write_bytes` creates a temporary file with an unpredictable name in the target folder
(``O_CREAT|O_EXCL|O_NOFOLLOW``: it cannot be a planted file or a symbolic link), writes and fsyncs it, gives it
the file mode of the file it replaces, and renames it over the final name; the folder is fsynced after. A
reader therefore sees the old file or the new one, never a mix; a symbolic link at the final name is refused,
never followed; a crash leaves at most a hidden ``.NAME.<random>.tmp`` beside the output.

:func:`check_output` is called by every command before any work: it refuses an output that is, or lies
inside, one of the command's inputs (even with ``--overwrite``), an existing output without ``--overwrite``,
a folder where a file is wanted (or the reverse), a path through a file, and a name that differs from an
existing one only in case (the same file on macOS and Windows). The inputs it is given stay protected for the
rest of the command: :func:`write_bytes` refuses to write to them or inside them.
"""

from __future__ import annotations

import contextlib
import contextvars
import io
import math
import os
import re
import secrets
import stat
from pathlib import Path
from typing import Iterable

import numpy as np

from fieldcal.errors import OutputError, from_oserror

# Inputs of the running command (resolved paths): nothing may be written to them or inside them.
_PROTECTED: contextvars.ContextVar[tuple[Path, ...]] = contextvars.ContextVar("fieldcal_protected", default=())

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_FIX_ELSEWHERE = "write the output somewhere else: fieldcal never writes over or into its own inputs"


# ------------------------------------------------------------------------------------------- input guard


def _resolved(path: str | os.PathLike) -> Path:
    """Absolute path with every existing symbolic link resolved (so a link to an input is that input).

    Raises
    ------
    PathError
        The path is a loop of symbolic links (Python raises RuntimeError or OSError ELOOP for it).
    """
    import errno

    p = Path(os.path.abspath(os.path.expanduser(os.fspath(path))))
    try:
        return p.resolve(strict=False)
    except (RuntimeError, OSError) as e:
        if isinstance(e, OSError) and e.errno != errno.ELOOP:
            raise
        raise from_oserror(OSError(errno.ELOOP, "is a loop of symbolic links", str(path)), path=path) from None


def _within(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


@contextlib.contextmanager
def command_scope():
    """Protected inputs last for one command (the CLI wraps each command, nested ``main`` calls included)."""
    token = _PROTECTED.set(())
    try:
        yield
    finally:
        _PROTECTED.reset(token)


def protect(*paths: str | os.PathLike | None) -> None:
    """Add ``paths`` (files or folders) to the inputs no write of this command may touch."""
    new = tuple(_resolved(p) for p in paths if p is not None and str(p) != "")
    _PROTECTED.set(_PROTECTED.get() + new)


def protected_inputs() -> tuple[Path, ...]:
    return _PROTECTED.get()


def _refuse_if_input(path: Path, inputs: Iterable[Path | str], field: str | None, given: dict) -> None:
    target = _resolved(path)
    for inp in inputs:
        root = _resolved(inp)
        if _within(target, root):
            rel = "is" if target == root else "lies inside"
            raise OutputError(f"the output {rel} the input {given.get(root, root)}", path=path, field=field,
                              fix=_FIX_ELSEWHERE)


#: Most entries of a folder input looked at for links out of it (a stack holds frames, not a disk).
_LINK_SCAN_LIMIT = 20000


def _file_id(path: str | os.PathLike) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino) if stat.S_ISREG(st.st_mode) else None


def _linked_inputs(inputs: dict[Path, object]) -> tuple[dict[Path, str], set[tuple[int, int]]]:
    """What the inputs hold through links, which an output must not replace either.

    Returns the real files that symbolic links inside folder inputs lead to (a stack made by ``fieldcal import
    --link symlink`` keeps its frames' data outside its folder), each named for messages as the link that leads
    there, and the (device, inode) of input files that have other hard links (``--link hard``: the camera file
    and the frame are one file under two names)."""
    targets: dict[Path, str] = {}
    ids: set[tuple[int, int]] = set()
    for root, name in inputs.items():
        if not root.is_dir():
            fid = _file_id(root)
            if fid is not None:
                ids.add(fid)
            continue
        seen = 0  # each input its own budget: one large input does not leave the next unprotected
        for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
            if seen > _LINK_SCAN_LIMIT:
                break
            for n in dirnames + filenames:
                seen += 1
                if seen > _LINK_SCAN_LIMIT:
                    break
                p = Path(dirpath) / n
                try:
                    st = os.lstat(p)
                except OSError:
                    continue
                if stat.S_ISLNK(st.st_mode):
                    try:
                        real = _resolved(p)
                    except OutputError:  # a loop of links leads nowhere; the input's reader refuses it
                        continue
                    fid = _file_id(real)  # files only: a link to a folder (e.g. "up -> ..") holds no frame data
                    if fid is not None and not _within(real, root):
                        targets.setdefault(real, f"{real} (the file {name}/{p.relative_to(root)} links to)")
                        ids.add(fid)
                elif stat.S_ISREG(st.st_mode) and st.st_nlink > 1:
                    ids.add((st.st_dev, st.st_ino))
    return targets, ids


def _refuse_if_same_file(path: Path, ids: set[tuple[int, int]], field: str | None) -> None:
    fid = _file_id(path) if ids else None
    if fid is not None and fid in ids:
        raise OutputError("is the same file as one of the inputs (a hard or symbolic link to it)", path=path,
                          field=field, fix=_FIX_ELSEWHERE)


# -------------------------------------------------------------------------------------------- path checks


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _check_parent(path: Path, field: str | None) -> None:
    anc = _nearest_existing(path.parent if str(path.parent) else Path("."))
    if os.path.lexists(anc) and not anc.is_dir():
        raise OutputError(f"{anc} is a file, so {path} cannot be created inside it", path=path, field=field,
                          fix="choose an output path whose folders are folders")


#: Room a profile needs below the file system's longest name for its ``NAME.<16 hex>.samples.npz`` sidecar.
SIDECAR_NAME_ROOM = 32


def _check_name_length(path: Path, field: str | None, room: int = 0) -> None:
    """A name the file system cannot hold fails now, not when the finished result is renamed into place;
    ``room``: bytes kept for a file written beside the output under a longer name."""
    anc = _nearest_existing(path.parent if str(path.parent) else Path("."))
    try:
        name_max = os.pathconf(anc if anc.is_dir() else anc.parent, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        name_max = 255
    for part in path.parts[len(anc.parts):] if path != anc else (path.name,):
        if len(os.fsencode(part)) > name_max - room:
            beside = f" and {room} are kept for the file written beside it" if room else ""
            raise OutputError(f"has a name of {len(os.fsencode(part))} bytes; this file system holds at most "
                              f"{name_max}{beside}", path=path, field=field, fix="use a shorter name")


def _case_twin(path: Path) -> str | None:
    """The name of an existing sibling that differs from ``path``'s name only in case, if any."""
    parent = path.parent if str(path.parent) else Path(".")
    try:
        names = os.listdir(parent)
    except OSError:
        return None
    key = path.name.casefold()
    for n in names:
        if n != path.name and n.casefold() == key:
            return n
    return None


def _check_file_target(path: Path, overwrite: bool, field: str | None) -> None:
    if os.path.islink(path):
        raise OutputError("is a symbolic link; fieldcal does not write through links", path=path, field=field,
                          fix="remove the link, or give the real file's path")
    if path.is_dir():
        raise OutputError("is a folder, not a file", path=path, field=field,
                          fix=f"give a file name, e.g. {path / 'out'}{path.suffix or ''}")
    twin = _case_twin(path)
    if twin is not None:
        raise OutputError(f"differs only in case from the existing {twin} (the same file on macOS and Windows)",
                          path=path, field=field, fix=f"choose another name, or write to {path.parent / twin} "
                                                      "with --overwrite")
    if os.path.lexists(path) and not overwrite:
        raise OutputError("exists", path=path, field=field,
                          fix="choose another name, or add --overwrite to replace it")


def check_output(path: str | os.PathLike, *, inputs: Iterable[str | os.PathLike | None] = (),
                 overwrite: bool = False, kind: str = "file", files: Iterable[str] = (),
                 suffixes: Iterable[str] | None = None, field: str | None = "--out",
                 replaces_folder: bool = False, name_room: int = 0) -> Path:
    """Refuse an output path before any work is done; returns it as a :class:`Path`.

    Parameters
    ----------
    path : path-like
        The output (a file when ``kind="file"``, a folder when ``kind="dir"``).
    inputs : paths
        The command's inputs (files or folders). The output may not be one of them or lie inside one, even
        with ``overwrite``; they stay protected from every write for the rest of the command.
    overwrite : bool
        Whether an existing output may be replaced (the command's ``--overwrite``).
    kind : {"file", "dir"}
    files : names
        For a folder output: the files the command writes in it (each is checked like a file output).
    suffixes : extensions, optional
        Accepted extensions (lower case, with the dot) of a file output.
    replaces_folder : bool
        A folder output that is replaced as a whole: an input inside it is refused too.
    name_room : int
        Bytes the output's name must leave free below the file system's longest name, for a file written beside
        it under a longer name (a profile's sidecar: :data:`SIDECAR_NAME_ROOM`).

    Raises
    ------
    OutputError
        Naming the path, the option and the fix.
    """
    p = Path(os.path.expanduser(os.fspath(path)))
    if not str(path).strip():
        raise OutputError("is empty", field=field, fix="give an output path")
    given = {_resolved(i): i for i in inputs if i is not None and str(i) != ""}
    linked, ids = _linked_inputs(given)
    for real, name in linked.items():
        given.setdefault(real, name)
    _refuse_if_input(p, given, field, given)
    _refuse_if_same_file(p, ids, field)
    if replaces_folder:
        for root, inp in given.items():
            if _within(root, _resolved(p)):
                raise OutputError(f"the output folder holds the input {inp}, which replacing it would delete",
                                  path=p, field=field, fix=_FIX_ELSEWHERE)
    protect(*given)
    _check_parent(p, field)
    _check_name_length(p, field, name_room)
    if kind == "file":
        if suffixes is not None:
            suffixes = tuple(suffixes)
            if p.suffix.lower() not in suffixes:
                raise OutputError(f"must end in {' or '.join(suffixes)}, got {p.name!r}", path=p, field=field,
                                  fix=f"e.g. {p.with_suffix(suffixes[0]).name}")
        _check_file_target(p, overwrite, field)
    elif kind == "dir":
        if os.path.islink(p) and not p.is_dir():
            raise OutputError("is a symbolic link that does not lead to a folder", path=p, field=field,
                              fix="remove the link or choose another folder")
        if os.path.lexists(p) and not p.is_dir():
            raise OutputError("is a file, not a folder", path=p, field=field, fix="give a folder name")
        for name in files:
            _refuse_if_input(p / name, given, field, given)
            _refuse_if_same_file(p / name, ids, field)
            _check_file_target(p / name, overwrite, field)
    else:  # pragma: no cover - programming error
        raise ValueError(kind)
    return p


# ----------------------------------------------------------------------------------------------- writing


def _umask() -> int:
    """The process umask, read without changing it where the OS allows (another thread may be creating files)."""
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mkdirs(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise OutputError(f"cannot create the folder {folder}: a part of its path is a file", path=folder,
                          fix="choose an output path whose folders are folders") from None
    except OSError as e:
        raise from_oserror(e, path=folder, action="create the folder") from None


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring); returns the path.

    Raises
    ------
    OutputError
        ``path`` is a symbolic link, a folder, or one of the command's protected inputs (exit 2).
    ResourceError
        The disk is full, read-only, or the folder not writable (exit 4); nothing is left behind.
    """
    path = Path(path)
    for root in _PROTECTED.get():
        if _within(_resolved(path), root):
            raise OutputError(f"refusing to write over the input {root}", path=path, fix=_FIX_ELSEWHERE)
    folder = path.parent if str(path.parent) else Path(".")
    _mkdirs(folder)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise from_oserror(e, path=path, action="write") from None
    if st is not None and stat.S_ISLNK(st.st_mode):
        raise OutputError("is a symbolic link; fieldcal does not write through links", path=path,
                          fix="remove the link, or give the real file's path")
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError("is a folder, not a file", path=path, fix="give a file name")
    mode = stat.S_IMODE(st.st_mode) & 0o777 if st is not None else 0o666 & ~_umask()
    stem = path.name[:180]
    tmp = None
    try:
        for _ in range(64):
            tmp = folder / f".{stem}.{secrets.token_hex(8)}.tmp"
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC, 0o600)
                break
            except FileExistsError:
                tmp = None
        else:  # pragma: no cover - 64 collisions of 64 random bits
            raise OutputError("cannot create a unique temporary file", path=path, fix="clean the folder")
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            os.fchmod(fd, mode)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        tmp = None
    except OSError as e:
        raise from_oserror(e, path=path, action="write") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    fsync_dir(folder)
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    """:func:`write_bytes` of UTF-8 text."""
    return write_bytes(path, text.encode("utf-8"))


def save_figure(fig, path: str | os.PathLike, **kwargs) -> Path:
    """Render a Matplotlib figure in memory (format from the suffix) and :func:`write_bytes` it."""
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=(path.suffix[1:] or "png").lower(), **kwargs)
    return write_bytes(path, buf.getvalue())


# The names the package has always used
atomic_write_bytes = write_bytes
atomic_write_text = write_text


def fsync_dir(path: str | Path) -> None:
    """Make a rename durable (POSIX); harmless no-op where directories cannot be opened."""
    try:
        fd = os.open(str(path), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def jsonable(v):
    """A JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None, tuples to lists."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        if v.dtype.kind == "f":  # whole arrays at once (a 46 000-record MTF file holds 4.6 M values)
            o = v.astype(np.float64).astype(object)
            o[~np.isfinite(v)] = None
            return o.tolist()
        if v.dtype.kind in "iub":
            return v.tolist()
        return jsonable(v.tolist())
    return v


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the kernel, the C library
    or the file system cannot, so the caller falls back to two renames."""
    import errno
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # glibc < 2.28 or another C library
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))  # both paths: either may be the one at fault


def replace_folder(staging: str | Path, out: str | Path, *, marker: str | None = None, overwrite: bool = False,
                   what: str = "a folder", error: type | None = None) -> None:
    """Rename a finished folder ``staging`` to ``out`` (same parent). An empty ``out`` is removed first; an
    existing one is swapped with ``staging`` in one step where the OS can (Linux ``renameat2``), else moved
    aside under an unpredictable name first; it is deleted only after the new folder took its name, so ``out``
    is always either the old or the new folder (after a crash in the fallback's two renames, the old one under
    its hidden name ``.NAME.fieldcal-old-XXXXXXXX``, which no later run deletes). With ``marker`` the checks of
    :func:`check_replaceable_folder` run again here, just before the swap: what the output holds now may not be
    what it held when the command started (a folder made or a file added meanwhile, a capture started)."""
    import shutil
    import tempfile

    staging, out = Path(staging), Path(out)
    if marker is not None:
        check_replaceable_folder(out, marker, overwrite, what, error=error)
    old = None
    if out.exists():
        if out.is_dir() and not out.is_symlink() and not any(out.iterdir()):
            out.rmdir()
        elif out.is_dir() and not out.is_symlink() and _exchange(staging, out):
            fsync_dir(out.resolve().parent)
            shutil.rmtree(staging, ignore_errors=True)  # the old folder, under the staging name now
            return
        else:
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.{OLD_TAG}-", dir=out.resolve().parent))
            old.rmdir()
            os.rename(out, old)
    try:
        os.rename(staging, out)
    except BaseException:
        if old is not None and not os.path.lexists(out):
            os.rename(old, out)  # the old folder back under its name: nothing lost
        raise
    fsync_dir(out.resolve().parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def check_replaceable_folder(out: str | Path, marker: str, overwrite: bool, what: str,
                             error: type | None = None) -> None:
    """An output folder that a command builds aside and renames into place (:func:`replace_folder`): it may be
    new or empty; an existing non-empty one is replaced only with ``overwrite`` and only when it holds
    ``marker`` (the file that says fieldcal made it, e.g. ``stack.json``): fieldcal never deletes a folder it
    did not create. ``what`` names the folder's kind in the messages ("a stack")."""
    from fieldcal.errors import OutputError

    err = error or OutputError
    out = Path(out)
    if out.is_symlink():
        raise err("is a symbolic link", path=out, field="out", fix="give a real folder path")
    if out.exists() and not out.is_dir():
        raise err("exists and is not a folder", path=out, field="out", fix="choose another output path")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise err("already exists and is not empty", path=out, field="out",
                      fix=f"choose a new folder, or pass overwrite=True (CLI: --overwrite) to replace {what}")
        if not (out / marker).is_file():
            raise err(f"is not empty and holds no {marker}: fieldcal will not delete a folder that is not {what}",
                      path=out, field="out", fix="choose a new or empty folder")
        if _folder_locked(out):
            raise err("is in use by a running fieldcal command (a capture writing into it): replacing it now "
                      "would delete its frames under it", path=out, field="out",
                      fix="wait for that command to finish, or choose another folder")
        foreign = foreign_files(out, marker)
        if foreign:
            more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
            raise err(f"holds files that are not part of {what} ({', '.join(foreign[:3])}{more}): replacing the "
                      "folder would delete them, and fieldcal never deletes what it did not write", path=out,
                      field="out", fix="move those files out of the folder, or choose a new folder")


def _open_folder(folder: str | Path) -> int:
    """A descriptor of the folder itself (not through a link), to lock it or to know it again."""
    return os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | _NOFOLLOW | _CLOEXEC)


def _try_lock(fd: int) -> bool | None:
    """Take an exclusive ``flock`` on ``fd`` without waiting: True when taken, False when a running process holds
    it, None where the system or the file system has no such locks."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return None
    return True


def _folder_locked(folder: Path) -> bool:
    """Whether a running command holds ``flock`` on the folder (capture holds its output folder's for the whole
    run; builds hold their staging folder's): False where the file system has no locks."""
    try:
        fd = _open_folder(folder)
    except OSError:
        return False
    try:
        return _try_lock(fd) is False
    finally:
        os.close(fd)  # closing drops the probe's own lock


#: Files a folder made by fieldcal may hold beside those its marker lists (simulate's truth, capture's journal).
_SIDE_FILES = {"stack.json": ("truth.json", "truth.tiff", "capture.journal")}


#: A frame capture wrote and never committed (killed between the frame's rename and its journal line): capture's
#: own name pattern, in a folder that has capture's journal (fieldcal.capture.folder).
_CAPTURE_FRAME = re.compile(r"^frames/\d{4,}\.tiff$")


def _listed_files(out: Path, marker: str) -> set[str]:
    """The files the marker document says the folder holds (relative POSIX paths); empty if it is unreadable."""
    import json

    try:
        doc = json.loads((out / marker).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return set()
    if not isinstance(doc, dict):
        return set()
    from pathlib import PurePosixPath

    names = set()
    for key, field in (("frames", "file"), ("files", "name")):  # stack.json frames; masks.json records
        records = doc.get(key)
        for rec in records if isinstance(records, list) else []:
            if isinstance(rec, dict) and isinstance(rec.get(field), str):
                names.add(PurePosixPath(rec[field].replace("\\", "/")).as_posix())  # "./frames/a" -> "frames/a"
    return names


def foreign_files(out: str | Path, marker: str) -> list[str]:
    """Files (and links) inside the folder ``out`` that neither its ``marker`` document lists nor fieldcal writes
    beside it, as relative paths: what replacing the folder would delete that fieldcal did not write. Hidden
    temporary files of fieldcal's own writes (``.NAME.<hex>.tmp``) are not counted."""
    out = Path(out)
    known = {marker, *_SIDE_FILES.get(marker, ()), *_listed_files(out, marker)}
    journal = marker == "stack.json" and (out / "capture.journal").is_file()
    found = []
    for dirpath, dirnames, filenames in os.walk(out, followlinks=False):
        for n in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
            rel = Path(os.path.relpath(os.path.join(dirpath, n), out)).as_posix()
            if rel in known or _TMP_NAME.match(n):
                continue
            if journal and _CAPTURE_FRAME.match(rel) and not os.path.islink(os.path.join(dirpath, n)):
                continue  # a frame a killed capture wrote and never committed (it takes it again on resume)
            found.append(rel)
            if len(found) > 100:
                return sorted(found)
    return sorted(found)


# ------------------------------------------------------------------------ staging folders of killed commands

#: The hidden folders fieldcal builds a folder output in, beside the output: ``.NAME.fieldcal-import-XXXXXXXX``
#: (import) and ``.NAME.fieldcal-partial-XXXXXXXX`` (simulate, plan export-masks; :func:`make_staging`);
#: ``XXXXXXXX`` is :func:`tempfile.mkdtemp`'s random part. The "fieldcal-" token keeps a user's own backup
#: (``.S.old-20261125``) out of the pattern.
STAGING_TAGS = ("fieldcal-import", "fieldcal-partial")
#: The old folder :func:`replace_folder`'s fallback moves aside: reported by the cleaner, never deleted (after a
#: crash between the two renames it is the only copy of the old output).
OLD_TAG = "fieldcal-old"


#: What fieldcal writes in such a folder besides its marker and the files the marker lists: stack frames
#: (``StackWriter``'s ``frames/NNNN.tiff``, import's ``frames/NNNN_stem.ext``), exported mask files, and the
#: hidden temporary files of :func:`write_bytes`.
_STAGING_FILES = {
    "stack.json": re.compile(r"^frames/\d{4,}(_[A-Za-z0-9._-]{1,80})?\.(tiff|tif|png|jpg|jpeg)$"),
    "masks.json": re.compile(r"^[A-Za-z0-9_-]+-(slot-\d{4,}\.png|start\.tif|stop\.tif)$"),
}
_STAGING_DIRS = {"stack.json": ("frames",), "masks.json": ()}
_TMP_NAME = re.compile(r"^\..*\.[0-9a-f]{16}\.tmp$")
_STAGING_SCAN_LIMIT = 100000


def make_staging(out: Path, tag: str) -> Path:
    """A fresh, unpredictable hidden folder beside ``out`` to build it in (``tag`` one of :data:`STAGING_TAGS`)."""
    import tempfile

    assert tag in STAGING_TAGS
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.{tag}-", dir=out.parent))


def _staging_pattern(out_name: str) -> re.Pattern:
    return re.compile(rf"^\.{re.escape(out_name)}\.(?:{'|'.join(STAGING_TAGS)})-[a-z0-9_]{{8}}$")


@contextlib.contextmanager
def staging_lock(folder: str | Path):
    """Hold an exclusive lock on a staging folder while a command builds in it (``flock`` on the folder): a
    later command that finds the folder locked knows a running fieldcal owns it and leaves it alone. The kernel
    drops the lock when the process ends, however it ends. A no-op where ``flock`` is not available."""
    fd = None
    try:
        fd = _open_folder(folder)
    except FileNotFoundError:  # removed between its making and this lock (another run's cleaner): stop here
        from fieldcal.errors import ResourceError
        raise ResourceError("the folder fieldcal had just made to build its output in was removed by another "
                            "process", path=folder, fix="run the command again (one at a time on an output)")
    except OSError:
        pass  # cannot be opened for a lock: the folder is still fieldcal's, only not marked as in use
    if fd is not None:
        _try_lock(fd)  # without locks the folder is still fieldcal's, only not marked as in use
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)


def _staging_foreign(folder: Path, marker: str) -> list[str] | None:
    """What in the staging folder ``folder`` fieldcal does not write there (relative paths), or None when the
    folder is too large to look through (then it is left alone)."""
    pattern = _STAGING_FILES.get(marker)
    dirs = _STAGING_DIRS.get(marker, ())
    listed = _listed_files(folder, marker) if (folder / marker).is_file() else set()
    known = {marker, *_SIDE_FILES.get(marker, ())}
    foreign, seen = [], 0
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for n in dirnames + filenames:
            seen += 1
            if seen > _STAGING_SCAN_LIMIT:
                return None
            p = os.path.join(dirpath, n)
            rel = Path(os.path.relpath(p, folder)).as_posix()
            try:
                st = os.lstat(p)
            except OSError:
                foreign.append(rel)
                continue
            if stat.S_ISDIR(st.st_mode):
                if rel not in dirs:
                    foreign.append(rel + "/")
                    dirnames.remove(n) if n in dirnames else None
                continue
            is_frame = rel in listed or bool(pattern and pattern.match(rel))
            if stat.S_ISLNK(st.st_mode):
                # import --link symlink makes its frames links to the camera files; removing a link leaves them
                if not is_frame:
                    foreign.append(rel)
            elif not stat.S_ISREG(st.st_mode) or not (rel in known or is_frame or _TMP_NAME.match(n)):
                foreign.append(rel)
    return sorted(foreign)


def clean_stale_staging(out: str | Path, marker: str) -> tuple[list[Path], list[tuple[Path, str]]]:
    """Remove the staging folders a killed fieldcal left beside the folder output ``out``; returns the removed
    folders and those left alone, each with the reason.

    A folder is removed only when fieldcal provably made it and no running command owns it: its name is
    fieldcal's exact staging name for this output (``.NAME.TAG-XXXXXXXX``, :data:`STAGING_TAGS`), it is a
    folder (not a link) owned by this user, it is not locked by a running command (:func:`staging_lock`), and it
    holds nothing but what fieldcal writes there (``marker``, the files it lists, fieldcal's frame or mask
    names, hidden temporary files; or nothing). Anything else is left, and reported.
    """
    import shutil

    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    pattern = _staging_pattern(out.name)
    old_pattern = re.compile(rf"^\.{re.escape(out.name)}\.{OLD_TAG}-[a-z0-9_]{{8}}$")
    try:
        listing = os.listdir(parent)
    except OSError:
        return [], []
    names = [n for n in listing if pattern.match(n)]
    removed, kept = [], []
    for n in sorted(listing):
        if old_pattern.match(n):  # the old output a crash left aside: perhaps the only copy; never deleted
            kept.append((parent / n, (f"it is the previous {out.name} that an interrupted replacement moved "
                                      f"aside (if {out.name} is missing or unfinished, rename it back to "
                                      f"{out.name})")))
    for n in sorted(names):
        folder = parent / n
        try:
            st = os.lstat(folder)
        except OSError:
            continue
        if not stat.S_ISDIR(st.st_mode):
            kept.append((folder, "not a folder"))
            continue
        if hasattr(os, "getuid") and st.st_uid != os.getuid():
            kept.append((folder, "owned by another user"))
            continue
        try:
            fd = _open_folder(folder)
        except OSError:
            kept.append((folder, "cannot be opened"))
            continue
        try:
            locked = _try_lock(fd)
            if locked is False:
                kept.append((folder, "in use by a running fieldcal command"))
                continue
            if locked is None and os.name == "posix":  # a build elsewhere (another host) could not be seen
                kept.append((folder, "on a file system without locks, so fieldcal cannot tell whether a command "
                                     "is still building in it"))
                continue
            foreign = _staging_foreign(folder, marker)
            if foreign is None:
                kept.append((folder, f"holds more than {_STAGING_SCAN_LIMIT} entries"))
                continue
            if foreign:
                more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
                kept.append((folder, f"holds {', '.join(foreign[:3])}{more}, which fieldcal does not write there"))
                continue
            try:  # the folder checked, not another renamed into its name meanwhile
                now, held = os.lstat(folder), os.fstat(fd)
            except OSError:
                continue
            if (now.st_dev, now.st_ino) != (held.st_dev, held.st_ino):
                kept.append((folder, "changed while it was being checked"))
                continue
            shutil.rmtree(folder, ignore_errors=True)
            if os.path.lexists(folder):
                kept.append((folder, "could not be removed entirely"))
            else:
                removed.append(folder)
        finally:
            os.close(fd)
    return removed, kept


def report_stale_staging(out: str | Path, marker: str) -> None:
    """:func:`clean_stale_staging`, saying on stderr what it removed and what it left."""
    from fieldcal.progress import warn

    removed, kept = clean_stale_staging(out, marker)
    for folder in removed:
        warn(f"removed {folder}, the unfinished work of an earlier fieldcal run on {out} that was stopped")
    for folder, why in kept:
        warn(f"left {folder} alone: it is named like fieldcal's unfinished work on {out}, but {why}; delete it "
             "yourself if it is not needed")
