"""Shared helpers of the Pareto benchmarks: Pareto fronts, markdown tables, docs/benchmarks.md sections, figures.

Each benchmark owns one section of docs/benchmarks.md between ``<!-- bench_<name>:start -->`` and
``<!-- bench_<name>:end -->``; :func:`write_docs_section` replaces only that section (other benchmarks write
theirs), creating the file or appending the section when it is missing. Files are written atomically.
:func:`flag_slowdowns` compares a run's timings with the table it is about to replace (2x slower is flagged).
"""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs" / "benchmarks.md"
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
os.environ.setdefault("MPLBACKEND", "Agg")

from fieldcal.formats.atomic import atomic_write_bytes, atomic_write_text  # noqa: E402


def pareto_front(rows: list[dict], objectives: list[tuple[str, str]]) -> list[bool]:
    """True for rows no other row dominates (no worse in every objective, better in one).

    ``objectives``: ``(key, "min" | "max")``; rows with a missing/NaN objective are never on the front.
    """
    def vec(r):
        v = []
        for k, sense in objectives:
            x = r.get(k)
            if x is None or x != x:
                return None
            v.append(float(x) if sense == "min" else -float(x))
        return v

    vs = [vec(r) for r in rows]
    out = []
    for i, a in enumerate(vs):
        if a is None:
            out.append(False)
            continue
        dominated = any(b is not None and j != i and all(bb <= aa for aa, bb in zip(a, b))
                        and any(bb < aa for aa, bb in zip(a, b)) for j, b in enumerate(vs))
        out.append(not dominated)
    return out


def md_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> list[str]:
    """Markdown table: ``columns`` = (header, key, format spec); None/NaN print as "—"."""
    lines = ["| " + " | ".join(h for h, _, _ in columns) + " |", "|" + " --- |" * len(columns)]
    for r in rows:
        cells = []
        for _, k, f in columns:
            v = r.get(k)
            if v is None or (isinstance(v, float) and v != v):
                cells.append("—")
            elif f:
                cells.append(format(v, f))
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_docs_section(name: str, text: str, path: Path = DOCS) -> None:
    """Replace this benchmark's section of docs/benchmarks.md (or add it)."""
    start, end = f"<!-- bench_{name}:start -->", f"<!-- bench_{name}:end -->"
    block = f"{start}\n{text.rstrip()}\n{end}"
    old = path.read_text() if path.exists() else "# Benchmarks\n\nEach section is written by its benchmark script.\n"
    if start in old and end in old:
        a = old.index(start)
        b = old.index(end) + len(end)
        new = old[:a] + block + old[b:]
    else:
        new = old.rstrip() + "\n\n" + block + "\n"
    atomic_write_text(path, new)


def save_fig(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def triplet(size: tuple[int, int]):
    from fieldcal.simulate.lens import LensSpec
    return LensSpec.load(REPO / "models" / "triplet-uncorrected.json").with_sensor_size(*size)


# ------------------------------------------------------------------------------------ regression flags
#: A figure this many times the stored table's is flagged.
SLOWDOWN_FACTOR = 2.0


def _section(name: str, text: str) -> str | None:
    """The text of benchmark ``name``'s section (markers ``:start``/``:begin`` ... ``:end``), or None."""
    for start in (f"<!-- bench_{name}:start -->", f"<!-- bench_{name}:begin -->"):
        end = f"<!-- bench_{name}:end -->"
        if start in text and end in text[text.index(start):]:
            a = text.index(start) + len(start)
            return text[a:text.index(end, a)]
    return None


def stored_rows(name: str, path: Path = DOCS) -> list[dict[str, str]]:
    """Rows of every markdown table in benchmark ``name``'s section of docs/benchmarks.md, as header -> cell."""
    return table_rows(_section(name, path.read_text(encoding="utf-8")) if path.exists() else None)


def table_rows(text: str | None) -> list[dict[str, str]]:
    """Rows of every markdown table in ``text``, as header -> cell."""
    rows: list[dict[str, str]] = []
    header: list[str] | None = None
    for line in (text or "").splitlines():
        line = line.strip()
        if not (line.startswith("|") and line.endswith("|")):
            header = None
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if header is None:
            header = cells
        elif all(set(c) <= set("-: ") for c in cells):
            continue  # the separator row
        else:
            rows.append(dict(zip(header, cells)))
    return rows


def _number(cell) -> float | None:
    try:
        return float(str(cell).replace("x", "").replace("×", "").strip())
    except ValueError:
        return None


def flag_slowdowns(name: str, rows: list[dict] | str, key: tuple[str, ...], columns: tuple[str, ...],
                   factor: float = SLOWDOWN_FACTOR, path: Path = DOCS) -> list[str]:
    """Compare this run's timings with the table stored in docs/benchmarks.md (read before it is rewritten).

    ``rows``: this run's table rows (header -> value), or its markdown (its tables are read); a row is matched to the stored row with the same
    ``key`` cells; every ``columns`` figure (seconds: lower is better) at ``factor`` times the stored one or more
    is flagged. The flags are printed (stderr) and returned, for the benchmark to write beside its table.
    """
    if isinstance(rows, str):
        rows = table_rows(rows)
    old = {tuple(r.get(k, "") for k in key): r for r in stored_rows(name, path)}
    flags = []
    for r in rows:
        k = tuple(str(r.get(c, "")) for c in key)
        prev = old.get(k)
        if prev is None:
            continue
        for col in columns:
            a, b = _number(r.get(col)), _number(prev.get(col))
            if a is not None and b is not None and b > 0 and a >= factor * b:
                flags.append(f"{' / '.join(k)}: {col} {a:g} against {b:g} in the stored table "
                             f"({a / b:.1f}x slower)")
    for f in flags:
        print(f"SLOWER: {f}", file=sys.stderr)
    return flags


def slowdown_note(flags: list[str], factor: float = SLOWDOWN_FACTOR) -> str:
    """The line a benchmark writes under its table when :func:`flag_slowdowns` found something ('' if not)."""
    if not flags:
        return ""
    return (f"**Slower than the previous table (≥ {factor:g}x):** " + "; ".join(flags)
            + ". Check the load, then the change.")
