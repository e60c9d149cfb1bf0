"""Errors a user can cause, and how the CLI reports them.

Every user-facing failure is a :class:`FieldcalError` that names *where* (a file and, when known, the field
inside it), *what* went wrong and *how to fix it*. The CLI prints ``str(err)`` and exits non-zero, never a
traceback; library callers can catch the specific subclass.
"""

from __future__ import annotations

from pathlib import Path


class FieldcalError(Exception):
    """A problem the user can fix. ``str()`` gives a one-paragraph message: where, what, fix."""

    exit_code = 2

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


class DeviceError(FieldcalError):
    """A stage or camera reported an error (the device's state is known)."""

    exit_code = 3


class LinkError(FieldcalError):
    """The link to a device failed (timeout, garbled reply, disconnect): its state is unknown."""

    exit_code = 3


class NotYetImplemented(FieldcalError):
    """A pipeline stage whose issue has not landed yet."""

    exit_code = 4


class ResourceError(FieldcalError):
    """The machine refused: disk full, read-only file system, permission denied, a lock another run holds."""

    exit_code = 4
