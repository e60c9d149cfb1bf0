"""The ``fieldcal`` command: a thin dispatcher over fieldcal.commands.<name> modules.

Each command module defines ``register(subparsers)`` that adds its parser and sets ``func=run``; ``run(args)``
returns an exit code. User mistakes raise :class:`fieldcal.errors.FieldcalError` and end here as a one-paragraph
message and a non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import FieldcalError

COMMANDS = ["demo", "targets", "simulate", "import_stack", "calibrate", "plan", "capture", "composite", "report", "validate", "lens"]


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: exit 2 with usage, as usual
        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="fieldcal", description="Field-curvature calibration and curved-sensor emulation.",
                formatter_class=argparse.RawDescriptionHelpFormatter,
                epilog="example:\n  fieldcal demo --out demo-out\n\nRun 'fieldcal COMMAND --help' for each command.")
    p.add_argument("--version", action="version", version=f"fieldcal {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        mod = importlib.import_module(f"fieldcal.commands.{name}")
        mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except FieldcalError as e:
        print(f"fieldcal {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"fieldcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
