"""The profile's self-check as an estimator of its band's truth coverage (issue 14: "agrees with the measured
coverage within 0.05").

Reads what two benchmarks already produced and runs nothing slow: the rows of ``bench_band_coverage.py --jsonl``
with the profiles it kept (``--keep``), and the profiles ``bench_cleanroom.py`` cached under its ``--work``
folder (evaluated against the clean-room truth again here). Per group (own simulator: geometric, wave, wave with
spherical aberration; clean room: texture, edges; each effort) it states:

* the mean self-check (``diagnostics.surface.self_check.coverage``, the expected truth coverage) against the mean
  measured coverage, with the difference in units of its own standard error (the draws' ``coverage_sd`` over
  sqrt(n): how far apart the means of an exactly honest model would fall);
* the mean |self-check − measured| per lens, and the mean the profiles themselves predict (``coverage_abs_dev``);
* how many measured coverages fall inside the stated 5-95 % range (≈ 0.9 of them when the range is calibrated);
* with ``--compare``, the same means for the held-out tiles' coverage (``tile_coverage``, the self-check of
  session 10) and for the estimate with kappa's posterior always integrated (``kappa_mode="posterior"``).

    python benchmarks/bench_band_coverage.py --lenses 20 --keep KEEP --jsonl own.jsonl
    python benchmarks/bench_band_coverage.py --start 20 --lenses 20 --only wave --sa only --keep KEEP --jsonl own.jsonl
    python benchmarks/bench_cleanroom.py --work CR
    python benchmarks/bench_selfcheck.py --jsonl own.jsonl --keep KEEP --cleanroom CR --compare [--docs]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._common import md_table, write_docs_section  # noqa: E402

TOL = 0.005   # a grid's coverage is a fraction of a finite grid: "inside the range" to this


def _record(group: str, effort: str, lens: str, measured: float, sc: dict, prof, compare: bool) -> dict:
    from fieldcal.fit.selfcheck import coverage_estimate

    r = {"group": group, "effort": effort, "lens": lens, "measured": float(measured), "self_check": sc["coverage"],
         "lo": sc["coverage_range"][0], "hi": sc["coverage_range"][1], "sd": sc["coverage_sd"],
         "abs_dev": sc["coverage_abs_dev"], "share": sc["field_wide_share"], "tiles": sc["tile_coverage"],
         "kappa_90": sc["kappa_90"], "evidence": bool(sc.get("kappa_evidence")), "warning": bool(sc.get("warning"))}
    if compare:
        r["posterior"] = coverage_estimate(prof, math.log(sc["kappa"]), sc["log_kappa_sd"],
                                           kappa_mode="posterior")["coverage"]
    return r


def own_rows(jsonl: Path, keep: Path, compare: bool) -> list[dict]:
    from fieldcal.profile.lens_profile import LensProfile

    out = []
    for line in jsonl.read_text().splitlines():
        if not line.strip():
            continue
        r = json.loads(line)
        prof = LensProfile.load(keep / f"lens{r['lens']:02d}-{r['effort']}.json")
        group = "own: " + r["optics"] + (" + SA" if r["asymmetric"] else "")
        out.append(_record(group, r["effort"], str(r["lens"]), r["cov_after"],
                           prof.diagnostics["surface"]["self_check"], prof, compare))
    return out


def cleanroom_rows(work: Path, compare: bool) -> list[dict]:
    from benchmarks.bench_cleanroom import CHARTS, EFFORTS, FS, Q, _load_truth
    from benchmarks.cleanroom.evaluate import evaluate_profile
    from fieldcal.profile.lens_profile import LensProfile

    out = []
    for d in sorted(p for p in work.iterdir() if (p / "truth.json").exists()):
        truth, meta = _load_truth(d / "truth.json")
        for chart in CHARTS:
            for eff in EFFORTS:
                if not (d / f"{chart}-{eff}.json").exists():
                    continue
                prof = LensProfile.load(d / f"{chart}-{eff}.json")
                ev = evaluate_profile(prof, truth, np.asarray(meta["xs"]), np.asarray(meta["ys"]), chart,
                                      float(meta["step_um"]), FS, Q)
                out.append(_record(f"clean room: {chart}", eff, d.name, ev["coverage"],
                                   prof.diagnostics["surface"]["self_check"], prof, compare))
    return out


def summary(rows: list[dict], compare: bool) -> list[dict]:
    out = []
    groups = sorted({r["group"] for r in rows})
    for eff in ("quick", "standard"):
        for g in groups + ["own: all", "clean room: all"]:
            R = [r for r in rows if r["effort"] == eff
                 and (r["group"] == g or (g.endswith(": all") and r["group"].startswith(g[:-4])))]
            if not R or (g.endswith(": all") and len({r["group"] for r in R}) < 2):
                continue
            a = lambda k: np.array([r[k] for r in R], dtype=float)  # noqa: E731
            m, s = a("measured"), a("self_check")
            se = math.sqrt(float(np.sum(a("sd") ** 2))) / len(R)
            row = {"effort": eff, "group": g, "n": len(R), "sc": s.mean(), "meas": m.mean(),
                   "diff": f"{s.mean() - m.mean():+.3f} ({(s.mean() - m.mean()) / max(se, 1e-9):+.1f})",
                   "abs": float(np.mean(np.abs(s - m))), "within": f"{int(np.sum(np.abs(s - m) <= 0.05))}/{len(R)}",
                   "pred_abs": a("abs_dev").mean(),
                   "inside": f"{int(np.sum((m >= a('lo') - TOL) & (m <= a('hi') + TOL)))}/{len(R)}",
                   "evidence": int(a("evidence").sum()), "warnings": int(a("warning").sum())}
            if compare:
                row["tiles"] = f"{a('tiles').mean() - m.mean():+.3f} / {np.mean(np.abs(a('tiles') - m)):.3f}"
                row["post"] = f"{a('posterior').mean() - m.mean():+.3f} / {np.mean(np.abs(a('posterior') - m)):.3f}"
            out.append(row)
    return out


def render(rows: list[dict], compare: bool, command: str, note: str = "") -> str:
    cols = [("effort", "effort", ""), ("group", "group", ""), ("lenses", "n", ""),
            ("mean self-check", "sc", ".3f"), ("mean measured", "meas", ".3f"),
            ("mean difference (in its standard errors)", "diff", ""), ("mean abs(self-check − measured)", "abs", ".3f"),
            ("within 0.05", "within", ""), ("predicted mean abs (coverage_abs_dev)", "pred_abs", ".3f"),
            ("measured inside the stated 5-95 %", "inside", ""), ("kappa evidence", "evidence", ""),
            ("warnings", "warnings", "")]
    if compare:
        cols += [("held-out tiles (s10): mean diff / mean abs", "tiles", ""),
                 ("kappa's posterior always: mean diff / mean abs", "post", "")]
    per = [{**r, "range": f"{r['lo']:.2f}-{r['hi']:.2f}", "k90": f"{r['kappa_90'][0]:.2f}-{r['kappa_90'][1]:.2f}",
            "d": abs(r["self_check"] - r["measured"])} for r in rows]
    per_cols = [("group", "group", ""), ("lens", "lens", ""), ("effort", "effort", ""),
                ("measured", "measured", ".2f"), ("self-check", "self_check", ".2f"), ("stated 5-95 %", "range", ""),
                ("abs diff", "d", ".2f"), ("predicted abs dev", "abs_dev", ".2f"), ("field-wide share", "share", ".2f"),
                ("kappa 90 %", "k90", ""), ("held-out tiles", "tiles", ".2f")]
    return "\n".join(["## Self-check as a coverage estimator (s11)", "", f"`{command}`" + (" — " + note if note else ""),
                      "", *md_table(summary(rows, compare), cols), "", "Per lens:", "", *md_table(per, per_cols)])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jsonl", type=Path, help="rows of bench_band_coverage.py --jsonl")
    ap.add_argument("--keep", type=Path, help="the --keep folder of that run (its profiles)")
    ap.add_argument("--cleanroom", type=Path, help="the --work folder of bench_cleanroom.py")
    ap.add_argument("--compare", action="store_true",
                    help="also the held-out tiles' coverage and the estimate with kappa's posterior always integrated")
    ap.add_argument("--note", default="", help="a sentence after the command")
    ap.add_argument("--notes", type=Path, default=None, help="a markdown file appended to the section (the reading)")
    ap.add_argument("--docs", action="store_true", help="write the section into docs/benchmarks.md")
    args = ap.parse_args(argv)
    if (args.jsonl is None) != (args.keep is None):
        ap.error("--jsonl and --keep go together")
    rows = []
    if args.jsonl:
        rows += own_rows(args.jsonl, args.keep, args.compare)
    if args.cleanroom:
        rows += cleanroom_rows(args.cleanroom, args.compare)
    if not rows:
        ap.error("nothing to read: give --jsonl/--keep and/or --cleanroom")
    raw = list(argv if argv is not None else sys.argv[1:])
    skip = {"--note", "--notes"}   # the caption's own options
    command = "python benchmarks/bench_selfcheck.py " + " ".join(
        a for i, a in enumerate(raw) if a not in skip and (i == 0 or raw[i - 1] not in skip))
    text = render(rows, args.compare, command.strip(), args.note)
    if args.notes:
        text += "\n\n" + args.notes.read_text().strip()
    print(text)
    if args.docs:
        write_docs_section("selfcheck_s11", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
