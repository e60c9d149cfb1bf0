"""The ``fieldcal`` command: a thin dispatcher over fieldcal.commands.<name> modules.

Each command module defines ``register(subparsers)`` that adds its parser and sets ``func=run``; ``run(args)``
returns an exit code. :func:`main` is the one place failures end: every failure class maps to a documented exit
status (docs/safety.md) and a what/where/fix message on stderr, never a traceback (``--debug`` shows one).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys

from . import __version__
from .errors import (EXIT_BAD_INPUT, EXIT_ENVIRONMENT, EXIT_INTERNAL, EXIT_INTERRUPTED, FieldcalError,
                     from_oserror)

COMMANDS = ["demo", "targets", "simulate", "import_stack", "calibrate", "mtf", "plan", "capture", "composite",
            "report", "validate", "lens", "batch", "profile"]


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: exit 2 with usage, as usual
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="fieldcal", description="Field-curvature calibration and curved-sensor emulation.",
                formatter_class=argparse.RawDescriptionHelpFormatter,
                epilog="example:\n  fieldcal demo --out demo-out\n\nRun 'fieldcal COMMAND --help' for each command. "
                       "Exit status: 0 done, 1 validate found a failed check, 2 bad input, 3 device, "
                       "4 disk/permissions/memory, 5 internal error, 130 interrupted (docs/safety.md).")
    p.add_argument("--version", action="version", version=f"fieldcal {__version__}")
    p.add_argument("--debug", action="store_true",
                   help="show the Python traceback of a failure (also FIELDCAL_DEBUG=1); may go anywhere")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        mod = importlib.import_module(f"fieldcal.commands.{name}")
        mod.register(sub)
    return p


def _say(command: str, text: str) -> None:
    try:
        print(f"fieldcal {command}: {text}", file=sys.stderr, flush=True)
    except (OSError, ValueError):  # stderr itself is gone (closed pipe): nothing left to tell
        pass


def _command_name(args) -> str:
    name = getattr(args, "command", None) or ""
    kind = (getattr(args, "plan_kind", None) or getattr(args, "lens_command", None)
            or getattr(args, "batch_command", None)
            or getattr(args, "profile_command", None))
    return f"{name} {kind}" if kind and isinstance(kind, str) else name


def _name_flags(err: FieldcalError, parser: argparse.ArgumentParser, args) -> None:
    """Library errors name API fields; show the CLI user the flag instead (fieldcal.commands.name_flags)."""
    from .commands import name_flags
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
    module = {"import": "import_stack"}.get(args.command, args.command)  # `import` is a Python keyword
    extra = getattr(importlib.import_module(f"fieldcal.commands.{module}"), "FIELD_FLAGS", None)
    name_flags(err, sub, args, extra)


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit status (see :mod:`fieldcal.errors` ``EXIT_*``)."""
    from .formats.atomic import command_scope
    from .measure.esfr_pool import allow_processes

    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("FIELDCAL_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    name = _command_name(args)
    try:
        # the command owns the process: its e-SFR may run in worker processes (fieldcal/measure/esfr_pool.py)
        with command_scope(), allow_processes(True):
            return int(args.func(args) or 0)
    except FieldcalError as e:
        if debug:
            raise
        _name_flags(e, parser, args)
        _say(name, f"error: {e}")
        return e.exit_code
    except KeyboardInterrupt:
        _say(name, "interrupted")
        return EXIT_INTERRUPTED
    except MemoryError:
        if debug:
            raise
        _say(name, "error: not enough memory\n  fix: work on smaller images or a smaller region, or free memory")
        return EXIT_ENVIRONMENT
    except OSError as e:
        if debug:
            raise
        if e.errno == errno.EPIPE:  # the reader of our output went away (e.g. `| head`): nothing to say
            return EXIT_ENVIRONMENT
        err = from_oserror(e)
        _say(name, f"error: {err}")
        return err.exit_code
    except RecursionError:
        if debug:
            raise
        _say(name, "error: an input is nested too deeply to read\n  fix: check the input files (JSON nested "
                   "thousands of levels deep is not a fieldcal file)")
        return EXIT_BAD_INPUT
    except RuntimeError as e:
        if debug:
            raise
        if str(e).startswith("Symlink loop from "):  # Path.resolve() before Python 3.13 (then OSError ELOOP)
            loop = str(e)[len("Symlink loop from "):].strip("'\"")
            err = from_oserror(OSError(errno.ELOOP, "is a loop of symbolic links", loop))
            _say(name, f"error: {err}")
            return err.exit_code
        _say(name, f"internal error ({type(e).__name__}: {str(e)[:300]})\n  this is a bug in fieldcal: run the "
                   f"same command again with --debug to see the traceback, and report it (exit {EXIT_INTERNAL})")
        return EXIT_INTERNAL
    except Exception as e:  # a bug: short message, the traceback only with --debug
        if debug:
            raise
        _say(name, f"internal error ({type(e).__name__}: {str(e)[:300]})\n  this is a bug in fieldcal: run the "
                   f"same command again with --debug to see the traceback, and report it (exit {EXIT_INTERNAL})")
        return EXIT_INTERNAL


def entry() -> None:
    """The ``fieldcal`` program (its console script and ``python -m fieldcal``): :func:`main`, then the process
    ends at once with its status, its output flushed.

    By then the command's work is done and its files are written (atomically, :mod:`fieldcal.formats.atomic`);
    fieldcal registers nothing to run at exit. The interpreter's own teardown (freeing the modules of NumPy,
    SciPy and OpenCV one by one, joining finished worker threads) took ~0.1 s of wall and CPU after a composite
    (docs/benchmarks.md ``bench_composite_speed_s18``) and is skipped. A program calling :func:`main` (the tests)
    keeps its process.

    Before :func:`main`, NumPy's f2py and testing are made to load on first use
    (:func:`fieldcal._startup.defer_unused_numpy_modules`): no command uses them, and SciPy's array-API layer
    would load them with SciPy (~70 ms of every command's start-up)."""
    from ._startup import defer_unused_numpy_modules

    defer_unused_numpy_modules()
    status = main()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader that went away, a closed stream: the status stands
            pass
    os._exit(status)


if __name__ == "__main__":  # pragma: no cover
    entry()
