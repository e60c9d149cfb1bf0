"""Wall and CPU time of ``fieldcal calibrate`` and of its fit phase, a base commit against this tree, alternated.

Session 19 (issue 13's speed item): the surface fit's independent pieces run in one worker process beside the
calibrating one (fieldcal/fit/pool.py). Each run is a child ``python -m fieldcal calibrate STACK`` from a
temporary folder, with ``PYTHONPATH`` selecting the tree (the base commit checked out in a temporary worktree);
``os.wait4`` gives its CPU time (user + sys, the workers' included: their forkserver is stopped and reaped) and
peak RSS; the profile gives the fit's own times (``diagnostics.timing_s``, ``surfaces.diagnostics.time_map_s``
and ``time_total_s``). Every profile must equal the first without its time keys
(:func:`fieldcal.batch.calibrate.profile_without_times`).

    python benchmarks/bench_fit_speed.py /tmp/s18edge1080 --fs 76.49 --base f9b888a --pairs 3

(``--section NAME`` writes the table alone as docs/benchmarks.md section bench_NAME; session 19's section
``bench_fit_speed_s19`` adds the text around three such tables.)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import REPO, write_docs_section


def run_once(tree: Path, stack: Path, fs: float, effort: str, out: Path, cwd: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    child = subprocess.Popen([sys.executable, "-m", "fieldcal", "calibrate", str(stack), "--out", str(out),
                              "--fs", f"{fs:g}", "--effort", effort, "--quiet", "--overwrite"],
                             cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = os.times().elapsed
    _, status, ru = os.wait4(child.pid, 0)
    wall = os.times().elapsed - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"calibrate failed in {tree}")
    doc = json.loads(out.read_text())
    sd = doc["surfaces"]["diagnostics"]
    with open("/proc/loadavg") if os.path.exists("/proc/loadavg") else open(os.devnull) as f:
        load = (f.read().split() or ["nan"])[0]
    return {"wall_s": wall, "user_s": ru.ru_utime, "sys_s": ru.ru_stime, "rss_mb": ru.ru_maxrss / 1024.0,
            "measure_s": doc["diagnostics"]["timing_s"]["measure"], "fit_s": doc["diagnostics"]["timing_s"]["fit"],
            "map_s": sd["time_map_s"], "surface_s": sd["time_total_s"], "load": load}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stack")
    ap.add_argument("--fs", type=float, required=True)
    ap.add_argument("--effort", default="standard")
    ap.add_argument("--base", required=True, help="commit to compare against (checked out in a temporary worktree)")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--section", default=None, help="write docs/benchmarks.md section bench_SECTION")
    args = ap.parse_args()
    from fieldcal.batch.calibrate import profile_without_times

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        base = tmp / "base"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-q", "--detach", str(base), args.base], check=True)
        try:
            ref = None
            for k in range(args.pairs):
                for label, tree in (("base", base), ("this", REPO)):
                    out = tmp / f"{label}{k}.json"
                    r = run_once(tree, Path(args.stack).resolve(), args.fs, args.effort, out, tmp)
                    same = profile_without_times(out)
                    ref = same if ref is None else ref
                    r.update(label=label, pair=k + 1, same=same == ref)
                    rows.append(r)
                    print(json.dumps(r), flush=True)
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(base)], check=False)
    head = ("| run | tree | wall s | user s | sys s | peak RSS MB | measure s | fit s | model search s | surface fit s "
            "| load (1 min) | profile = first |\n|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [f"| {r['pair']} | {r['label']} | {r['wall_s']:.2f} | {r['user_s']:.2f} | {r['sys_s']:.2f} | "
             f"{r['rss_mb']:.0f} | {r['measure_s']:.2f} | {r['fit_s']:.2f} | {r['map_s']:.2f} | {r['surface_s']:.2f} | "
             f"{r['load']} | {'yes' if r['same'] else 'NO'} |" for r in rows]
    table = "\n".join([head] + lines)
    print(table)
    if args.section:
        write_docs_section(args.section, f"### Fit phase in a worker process (session 19)\n\n{table}\n")
    return 0 if all(r["same"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
