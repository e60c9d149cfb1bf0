"""Progress display for long work: tqdm on stderr, silenced with FIELDCAL_PROGRESS=0 or quiet=True.

Warnings (:func:`warn`) are not progress: they always reach stderr, so ``-q`` and ``FIELDCAL_PROGRESS=0``
(which silence bars and status lines) never hide that a result is doubtful."""

from __future__ import annotations

import os
import sys
from typing import Iterable, TypeVar

T = TypeVar("T")


def enabled(quiet: bool = False) -> bool:
    if quiet or os.environ.get("FIELDCAL_PROGRESS", "1") == "0":
        return False
    return True


def progress(iterable: Iterable[T], *, total: int | None = None, desc: str = "", quiet: bool = False,
             unit: str = "it") -> Iterable[T]:
    """Wrap an iterable with a progress bar on stderr (a no-op when disabled)."""
    if not enabled(quiet):
        return iterable
    from tqdm import tqdm
    return tqdm(iterable, total=total, desc=desc, unit=unit, file=sys.stderr, leave=False,
                dynamic_ncols=True, mininterval=0.5)


def status(msg: str, quiet: bool = False) -> None:
    """One line of status on stderr."""
    if enabled(quiet):
        print(msg, file=sys.stderr, flush=True)


def warn(msg: str) -> None:
    """A warning line on stderr (``warning: msg``), printed whatever the progress setting."""
    print("warning: " + msg, file=sys.stderr, flush=True)
