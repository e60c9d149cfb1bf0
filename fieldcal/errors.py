"""Errors a user can cause, and how the CLI reports them.

Every user-facing failure is a :class:`FieldcalError` that names *where* (a file and, when known, the field
inside it), *what* went wrong and *how to fix it*. The CLI prints ``str(err)`` and exits non-zero, never a
traceback; library callers can catch the specific subclass.
"""

from __future__ import annotations

from pathlib import Path

#: Exit statuses of the ``fieldcal`` command (docs/safety.md). Every failure class maps to one of them.
EXIT_OK = 0
EXIT_CHECK_FAILED = 1      # reserved for `fieldcal validate`: a check failed (the report says which)
EXIT_BAD_INPUT = 2         # a user mistake: bad argument, malformed file, refused output path
EXIT_DEVICE = 3            # a device error or a lost link
EXIT_ENVIRONMENT = 4       # the machine: disk full, read-only, permissions, memory, a missing optional extra
EXIT_INTERNAL = 5          # a bug in fieldcal (an unexpected exception; --debug shows the traceback)
EXIT_INTERRUPTED = 130     # Ctrl-C / SIGINT


class FieldcalError(Exception):
    """A problem the user can fix. ``str()`` gives a one-paragraph message: where, what, fix."""

    exit_code = EXIT_BAD_INPUT

    def __init__(self, what: str, *, path: str | Path | None = None, field: str | None = None,
                 fix: str | None = None):
        self.what = what
        self.path = None if path is None else str(path)
        self.field = field
        self.fix = fix
        super().__init__(self._format())

    def _format(self) -> str:
        where = ""
        if self.path and self.field:
            where = f"{self.path}: field '{self.field}': "
        elif self.path:
            where = f"{self.path}: "
        elif self.field:
            where = f"field '{self.field}': "
        msg = where + self.what
        if self.fix:
            msg += f"\n  fix: {self.fix}"
        return msg


class StackError(FieldcalError):
    """A stack folder that does not follow ``fieldcal-stack/1``."""


class SpecError(FieldcalError):
    """A lens spec, profile or plan file that is malformed or of an unknown version."""


class ParameterError(FieldcalError):
    """An invalid argument value (q outside (0, 1), negative frequency, empty ROI, ...)."""


class OutputError(FieldcalError):
    """An output path fieldcal refuses: an existing file without --overwrite, one of the command's inputs, a
    symbolic link, a folder where a file is wanted (or the reverse), a case-only name collision."""


class DeviceError(FieldcalError):
    """A stage or camera reported an error (the device's state is known)."""

    exit_code = EXIT_DEVICE


class LinkError(FieldcalError):
    """The link to a device failed (timeout, garbled reply, disconnect): its state is unknown."""

    exit_code = EXIT_DEVICE


class ResourceError(FieldcalError, OSError):
    """The machine refused: disk full, read-only file system, permission denied, out of memory.

    Also an ``OSError`` (with the original ``errno``), so code that handled the bare error still does.
    """

    exit_code = EXIT_ENVIRONMENT


class PathError(OutputError, OSError):
    """An ``OSError`` caused by the path the user gave (no such folder, a file where a folder is needed)."""


class NotYetImplemented(FieldcalError):
    """A pipeline stage whose issue has not landed yet."""

    exit_code = EXIT_ENVIRONMENT


# errno -> (exit status, fix) for an OSError that reached the top level or a write helper
_ERRNO_FIXES = {
    "ENOSPC": (EXIT_ENVIRONMENT, "free some disk space (or write to another disk) and run the command again"),
    "EDQUOT": (EXIT_ENVIRONMENT, "free some space within your disk quota and run the command again"),
    "EROFS": (EXIT_ENVIRONMENT, "write to a writable location (the file system is mounted read-only)"),
    "EACCES": (EXIT_ENVIRONMENT, "check the permissions of the file and its folder, or write elsewhere"),
    "EPERM": (EXIT_ENVIRONMENT, "check the permissions of the file and its folder, or write elsewhere"),
    "EMFILE": (EXIT_ENVIRONMENT, "raise the open-file limit (ulimit -n) or close other programs"),
    "ENFILE": (EXIT_ENVIRONMENT, "the system ran out of file handles; close other programs and retry"),
    "ENOMEM": (EXIT_ENVIRONMENT, "free memory or work on smaller images"),
    "EIO": (EXIT_ENVIRONMENT, "the disk reported an I/O error: check the disk and its connection"),
    "EFBIG": (EXIT_ENVIRONMENT, "the file is too large for this file system; write to another disk"),
    "ENOENT": (EXIT_BAD_INPUT, "check the path (a file or folder in it does not exist)"),
    "ENOTDIR": (EXIT_BAD_INPUT, "a part of the path is a file, not a folder: choose another path"),
    "EISDIR": (EXIT_BAD_INPUT, "the path is a folder: give a file name"),
    "EEXIST": (EXIT_BAD_INPUT, "the path exists: choose another name (or add --overwrite)"),
    "ELOOP": (EXIT_BAD_INPUT, "the path is a symbolic link (or a loop of links): give a plain file or folder"),
    "ENAMETOOLONG": (EXIT_BAD_INPUT, "use a shorter path"),
    "ENOTEMPTY": (EXIT_BAD_INPUT, "the folder is not empty: choose another path"),
}


def from_oserror(exc: OSError, *, path: str | Path | None = None, action: str | None = None) -> FieldcalError:
    """The :class:`FieldcalError` to show for an ``OSError`` (exit 4 for the machine, 2 for a bad path)."""
    import errno as _errno

    name = _errno.errorcode.get(exc.errno or 0, "")
    code, fix = _ERRNO_FIXES.get(name, (EXIT_ENVIRONMENT, "check the disk, the path and its permissions"))
    where = path if path is not None else (exc.filename if exc.filename is not None else None)
    what = exc.strerror or str(exc) or type(exc).__name__
    if action:
        what = f"cannot {action}: {what}"
    cls = ResourceError if code == EXIT_ENVIRONMENT else PathError
    err = cls(what, path=where, fix=fix)
    err.errno = exc.errno
    return err
