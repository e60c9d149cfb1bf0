"""Compositing with a *calibrated* profile (issue 18): before/after the discrepancy fast path, against a truth profile.

A calibrated profile's best-focus surface carries a kriged discrepancy term (``fieldcal.fit.discrepancy``). Before,
``fieldcal composite`` evaluated it with its kriging variance at every node of the best-focus map's grid, five
times (the breathing fixed point); after, the polynomial is evaluated exactly and the discrepancy once on its own
grid (``fieldcal.composite.surface.FocusEvaluator``), and the mean never computes the variance.

Three modes, each ``fieldcal composite SCENE --profile P --out ...`` in a fresh process (wall time including start-up
and reading, median of --repeat runs):

* **truth**: the lens spec's truth profile (no discrepancy term; the figure the speed table was measured with);
* **before**: the calibrated profile through the old path (exact map, kriging mean with variance: the code before
  this change, reproduced by patching the two switches it added);
* **after**: the calibrated profile through the fast path.

Accuracy: the best-focus map of the fast path against the exact one (max |difference|, µm) and the composites
made from both maps (RMS and max difference, DN). The data (chart stack, calibration, scene stack) are made in
--work on first use and reused.

    python benchmarks/bench_composite_profile.py --work /tmp/bcp                      # 1920x1080, 12 scene frames
    python benchmarks/bench_composite_profile.py --work /tmp/bcp-small --size 960x540 --frames 30

The section goes between ``<!-- bench_composite_profile:start -->`` and ``<!-- bench_composite_profile:end -->``
in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _common import REPO, flag_slowdowns, slowdown_note, write_docs_section

MODEL = REPO / "models" / "triplet-uncorrected.json"

# Run in a fresh interpreter: "before" switches the two new fast paths off, then the CLI runs as users run it.
DRIVER = r"""
import sys, time
mode = sys.argv[1]
if mode == "before":
    import functools
    import fieldcal.composite.stack_profile as sp
    import fieldcal.composite.surface as surface
    from fieldcal.fit.discrepancy import Discrepancy
    exact_map = functools.partial(surface.profile_focus_map, exact=True)
    sp.profile_focus_map = exact_map
    predict = Discrepancy.predict
    Discrepancy.predict = lambda self, x, y, ci, with_variance=True: predict(self, x, y, ci, True)
from fieldcal.cli import main
t = time.perf_counter()
rc = main(sys.argv[2:])
print(f"INNER {time.perf_counter() - t:.4f}")
sys.exit(rc)
"""


def _run(args, env):
    subprocess.run([sys.executable, "-m", "fieldcal", *args, "--quiet"], check=True, env=env, cwd=REPO)


def make_data(work: Path, size: str, frames: int, env) -> tuple[Path, Path]:
    """Chart stack -> calibrated profile (standard effort), and a scene stack of ``frames`` frames."""
    work.mkdir(parents=True, exist_ok=True)
    chart, lens, scene = work / "chart", work / "lens.json", work / f"scene{frames}"
    if not (chart / "stack.json").exists():
        _run(["simulate", str(MODEL), str(chart), "--z", "-370", "60", "10", "--size", size], env)
    if not lens.exists():
        _run(["calibrate", str(chart), "--out", str(lens), "--fs", "40", "--effort", "standard"], env)
    if not (scene / "stack.json").exists():
        step = 340.0 / max(frames - 1, 1)
        _run(["simulate", str(MODEL), str(scene), "--z", "-300", f"{40 + 0.5 * step:.3f}", f"{step:.4f}",
              "--size", size, "--scene", "colour-leaves"], env)
    return lens, scene


def time_mode(mode: str, profile: Path, scene: Path, out: Path, env) -> tuple[float, float]:
    """(wall seconds of the whole process, seconds inside the CLI)."""
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", DRIVER, mode, "composite", str(scene), "--profile", str(profile),
                        "--out", str(out), "--overwrite"], env=env, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise SystemExit(f"{mode} failed:\n{p.stderr}")
    inner = float([ln for ln in p.stdout.splitlines() if ln.startswith("INNER")][-1].split()[1])
    return wall, inner


def accuracy(lens: Path, scene: Path) -> dict:
    """Fast vs exact best-focus map (µm) and the composites from both (DN)."""
    import numpy as np

    from fieldcal.composite.source import image_size
    from fieldcal.composite.stack_profile import blend_kernel, composite_with_map, select_frames
    from fieldcal.composite.surface import FocusEvaluator, profile_focus_map
    from fieldcal.formats.stack import Stack
    from fieldcal.profile.lens_profile import LensProfile

    prof, stack = LensProfile.load(lens), Stack.open(scene)
    w, h = image_size(stack)
    t = time.perf_counter()
    fast = profile_focus_map(prof, w, h, stack.channels)
    t_fast = time.perf_counter() - t
    t = time.perf_counter()
    exact = profile_focus_map(prof, w, h, stack.channels, exact=True)
    t_exact = time.perf_counter() - t
    frames = select_frames(stack)
    kernel = blend_kernel(stack, prof, frames)
    a = composite_with_map(stack, fast, kernel, prof, frames, quiet=True).astype(np.float64)
    b = composite_with_map(stack, exact, kernel, prof, frames, quiet=True).astype(np.float64)
    ev = [FocusEvaluator(prof, ch, w, h) for ch in stack.channels]
    return {"map_max_um": float(np.abs(fast - exact).max()), "rms_dn": float(np.sqrt(np.mean((a - b) ** 2))),
            "max_dn": float(np.abs(a - b).max()), "t_map_fast": t_fast, "t_map_exact": t_exact,
            "step_px": [e.step_px for e in ev], "estimate_um": max(e.error_estimate_um for e in ev),
            "bound_um": max(e.error_bound_um for e in ev), "n_tiles": int(prof.surfaces.discrepancy.x_hat.size)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the stacks and profile (reused)")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--frames", type=int, default=12, help="scene frames")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-docs", action="store_true", help="do not write docs/benchmarks.md")
    a = ap.parse_args(argv)
    env = dict(os.environ, PYTHONPATH=str(REPO), FIELDCAL_PROGRESS="0")
    lens, scene = make_data(a.work, a.size, a.frames, env)
    load0 = os.getloadavg()[0]
    res = {m: [] for m in ("truth", "before", "after")}
    for _ in range(a.repeat):  # interleaved: load changes hit every mode alike
        for m in res:
            res[m].append(time_mode(m, MODEL if m == "truth" else lens, scene, a.work / f"out-{m}.tiff", env))
    load1 = os.getloadavg()[0]
    acc = accuracy(lens, scene)
    med = {m: (statistics.median(v[0] for v in r), statistics.median(v[1] for v in r)) for m, r in res.items()}
    for m, (wall, inner) in med.items():
        print(f"{m:7s} wall {wall:6.2f} s  in-CLI {inner:6.2f} s  (runs: {', '.join(f'{v[0]:.2f}' for v in res[m])})")
    print(f"after / truth {med['after'][0] / med['truth'][0]:.2f}x   before / after {med['before'][0] / med['after'][0]:.1f}x")
    print(f"map fast vs exact: max {acc['map_max_um']:.5f} µm; composite RMS {acc['rms_dn']:.4f} DN, "
          f"max {acc['max_dn']:.0f} DN; grid step {acc['step_px']} px, estimate {acc['estimate_um']:.5f} µm, "
          f"bound {acc['bound_um']:.4f} µm; load {load0:.1f} -> {load1:.1f}")
    if a.no_docs:
        return 0
    w, h = a.size.split("x")
    text = "\n".join([
        "## Compositing with a calibrated profile: the discrepancy fast path (issue 18)",
        "",
        f"`python benchmarks/bench_composite_profile.py --work DIR --size {a.size} --frames {a.frames}`: "
        f"`fieldcal composite` of {a.frames} frames of {w}x{h} RGB16 (colour-leaves scene, the paper's triplet), "
        f"whole process (start-up, reading, writing), median of {a.repeat} interleaved runs on the shared "
        f"2-core machine (load average {load0:.1f} at the start, {load1:.1f} at the end: expect ±20 %). "
        f"The calibrated profile: standard effort, fs 40 cy/mm, {acc['n_tiles']} tile rows in its discrepancy.",
        "",
        "| profile | path | wall s (median) | in-CLI s | vs truth |",
        "| --- | --- | --- | --- | --- |",
        *(f"| {'truth (no discrepancy)' if m == 'truth' else 'calibrated'} | {m} | {med[m][0]:.2f} | "
          f"{med[m][1]:.2f} | {med[m][0] / med['truth'][0]:.2f}x |" for m in ("truth", "before", "after")),
        "",
        f"Best-focus map alone (in process): exact {acc['t_map_exact']:.2f} s, fast {acc['t_map_fast']:.2f} s. "
        f"Fast vs exact: map within {acc['map_max_um']:.4f} µm (max over every pixel and channel); composites "
        f"differ by {acc['rms_dn']:.4f} DN RMS (max {acc['max_dn']:.0f} DN, a rounding flip). Discrepancy grid step "
        f"{', '.join(f'{s:.1f}' for s in acc['step_px'])} px (R, G, B); bilinear error estimate "
        f"{acc['estimate_um']:.5f} µm, rigorous bound {acc['bound_um']:.4f} µm (docs/compositing.md).",
        "",
        "The 'before' path is this code with the two new switches off (exact map; kriging variance computed and "
        "discarded), i.e. the computation the previous release made.",
    ])
    # a figure 2x slower than the stored table's is flagged, here and under the table
    flags = flag_slowdowns("composite_profile", text, ("profile", "path"), ("wall s (median)", "in-CLI s"))
    if flags:
        text += "\n\n" + slowdown_note(flags)
    write_docs_section("composite_profile", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
