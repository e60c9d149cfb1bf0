"""One module per CLI subcommand: ``register(subparsers)`` + ``run(args) -> int``.

Commands only parse flags, call the package's public functions and print. Library errors name API fields
(``fs_cyc_per_mm``, ``sweep_alpha_um``, ``out``); :func:`name_flags` turns them into the flags that set them
(``--fs``, ``--sweep-alpha-um``, ``--out``) so a CLI user reads the flag they typed. The mapping comes from the
parsers themselves (an option's ``dest`` is the API field it fills), plus a command module's optional
``FIELD_FLAGS`` table for the fields whose names differ.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub, name: str, help: str, example: str, description: str | None = None) -> argparse.ArgumentParser:
    """Every subcommand's --help ends with an example."""
    return sub.add_parser(name, help=help, description=description or help,
                          formatter_class=argparse.RawDescriptionHelpFormatter,
                          epilog=f"example:\n  {example}")


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for p in a.choices.values():
                yield from _parsers(p)


def field_flags(parser: argparse.ArgumentParser, extra: dict[str, str] | None = None) -> dict[str, str]:
    """API field -> CLI flag for a (sub)command's parser: ``dest`` -> the longest option string
    (the metavar for positionals), then ``extra`` on top."""
    out: dict[str, str] = {}
    for p in _parsers(parser):
        for a in p._actions:
            if a.dest in (argparse.SUPPRESS, "help") or isinstance(a, argparse._SubParsersAction):
                continue
            if a.option_strings:
                out.setdefault(a.dest, max(a.option_strings, key=len))
            else:
                mv = a.metavar if isinstance(a.metavar, str) else a.dest.upper()
                out.setdefault(a.dest, mv)
    out.update(extra or {})
    return out


def name_flags(err, parser: argparse.ArgumentParser, args: argparse.Namespace, extra: dict[str, str] | None = None):
    """Rename ``err.field`` from an API field to the CLI flag that set it (in place; returns ``err``).

    Only an error about an argument is renamed: one without a file, one whose file is the argument's value
    (``--out x.png``), or a field the command's ``extra`` table names. A field inside a file
    (``stack.json: field 'channels'``) keeps its name.
    """
    field = getattr(err, "field", None)
    if not field:
        return err
    table = field_flags(parser, extra)
    base = field.split(" ", 1)[0]
    flag = table.get(base)
    if flag is None:
        return err
    if err.path is not None and base not in (extra or {}):
        value = getattr(args, base, None)
        values = value if isinstance(value, (list, tuple)) else [value]
        if not any(v is not None and Path(str(v)) == Path(err.path) for v in values):
            return err
    err.field = flag + field[len(base):]
    err.args = (err._format(),)
    return err


def parse_size(text: str | None, minimum: int = 8) -> tuple[int, int] | None:
    """``"640x360"`` -> (640, 360) for every command's ``--size`` (None stays None); a clear error otherwise."""
    import re

    from ..errors import ParameterError

    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", str(text))
    if not m or int(m.group(1)) < minimum or int(m.group(2)) < minimum:
        raise ParameterError(f"bad size {text!r}", field="size",
                             fix=f"give WIDTHxHEIGHT in pixels, each at least {minimum}, e.g. 320x180")
    return int(m.group(1)), int(m.group(2))
