"""Shared helpers of the Pareto benchmarks: Pareto fronts, markdown tables, docs/benchmarks.md sections, figures.

Each benchmark owns one section of docs/benchmarks.md between ``<!-- bench_<name>:start -->`` and
``<!-- bench_<name>:end -->``; :func:`write_docs_section` replaces only that section (other benchmarks write
theirs), creating the file or appending the section when it is missing. Files are written atomically.
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
