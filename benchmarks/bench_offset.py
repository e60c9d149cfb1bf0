"""The sml@fs offset at one point with one window (session 14, s14-offset): before -> after tables.

Reads rows made by the two benchmarks, once on main (before) and once on this branch (after), and writes the
section ``bench_offset_s14`` of docs/benchmarks.md:

* ``bench_piston.py --curvature``: the lens's G channel on a symmetric curved field (geometric, telecentric, no
  noise): the pooled offset (should be ~0), its evidence weight, and the default's tile piston (mean of best
  focus minus the truth at the tile's position less the window term ``L s^2/24``);
* ``bench_band_coverage.py`` on cached renders: coverage, surface RMS in steps, piston per channel.

    python benchmarks/bench_offset.py --curv-before benchmarks/results/offset_s14/curv_before.jsonl \\
        --curv-after benchmarks/results/offset_s14/curv_after.jsonl \\
        --band-before benchmarks/results/offset_s14/band_before.jsonl \\
        --band-after benchmarks/results/offset_s14/band_after.jsonl --notes NOTES.md --docs
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

BENCH_DIR = str(Path(__file__).resolve().parent)
sys.path.insert(0, BENCH_DIR)
from _common import md_table, write_docs_section  # noqa: E402

NAME = "offset_s14"
TITLE = "The sml@fs offset at one point with one window (s14)"


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def render(cb, ca, bb, ba, notes: str = "") -> str:
    out = [f"### {TITLE}", ""]
    before = {(r["lens"], r["scale"]): r for r in cb}
    tab = []
    for r in ca:
        b = before.get((r["lens"], r["scale"]))
        if b is None:
            continue
        tab.append({"lens": r["lens"], "scale": r["scale"], "step": r["step_um"],
                    "off": f"{b['offset_um']:+.3f} @ {b['offset_weight']:.2f} → {r['offset_um']:+.3f} @ {r['offset_weight']:.2f}",
                    "geo": r.get("offset_geometry_um", float("nan")),
                    "piston": f"{b['auto_piston_um']:+.3f} → {r['auto_piston_um']:+.3f}"})
    out += ["**Symmetric curved field** (`bench_piston.py --curvature`; *offset @ weight* before → after; "
            "*geometric part*: what the change takes out of the pooled raw difference; *tile piston*: the default's "
            "tiles, best focus minus truth at the tile's position less `L s²/24`):", ""]
    out += md_table(tab, [("lens", "lens", ""), ("curvature x", "scale", "g"), ("step (µm)", "step", ".1f"),
                          ("offset (µm) @ weight", "off", ""), ("geometric part (µm)", "geo", "+.3f"),
                          ("tile piston (µm)", "piston", "")])
    out.append("")
    before = {r["lens"]: r for r in bb}
    tab = []
    for r in ba:
        b = before.get(r["lens"])
        if b is None:
            continue
        p = lambda x: " ".join(f"{v:+.3f}" for v in x)  # noqa: E731
        tab.append({"lens": r["lens"], "optics": r["optics"] + (" + SA" if r["asymmetric"] else ""),
                    "F": r["f_number"], "step": r["step_um"],
                    "cov": f"{b['cov_after']:.2f} → {r['cov_after']:.2f}",
                    "rms": f"{b['rms_um'] / b['step_um']:.4f} → {r['rms_um'] / r['step_um']:.4f}",
                    "piston": f"{p(b['piston_um'])} → {p(r['piston_um'])}",
                    "t": f"{b['time_s']:.1f} → {r['time_s']:.1f}"})
    out += ["**Band benchmark subset** (`bench_band_coverage.py`, standard, session 13's cached renders, "
            "calibrated afresh; before = main 8d45836, after = this branch; wall time under load):", ""]
    out += md_table(tab, [("lens", "lens", ""), ("optics", "optics", ""), ("F", "F", ".1f"),
                          ("step (µm)", "step", ".1f"), ("coverage", "cov", ""), ("RMS / step", "rms", ""),
                          ("piston per channel (µm)", "piston", ""), ("wall (s)", "t", "")])
    out.append("")
    if notes:
        out += [notes.rstrip(), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for k in ("curv-before", "curv-after", "band-before", "band-after"):
        ap.add_argument(f"--{k}", type=Path, required=True, help="JSONL rows")
    ap.add_argument("--notes", type=Path, default=None, help="a markdown file appended to the section")
    ap.add_argument("--docs", action="store_true", help=f"write the section bench_{NAME} of docs/benchmarks.md")
    a = ap.parse_args(argv)
    try:
        rows = [_rows(p) for p in (a.curv_before, a.curv_after, a.band_before, a.band_after)]
    except (OSError, ValueError) as e:
        print(f"bench_offset: cannot read the rows: {e}", file=sys.stderr)
        return 2
    text = render(*rows, notes=a.notes.read_text() if a.notes else "")
    if a.docs:
        write_docs_section(NAME, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
