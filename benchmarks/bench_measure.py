"""Benchmark of calibration measurement (fieldcal.measure): speed, peak memory and accuracy vs truth.

Renders a chart stack of the paper triplet (``models/triplet-uncorrected.json``) through the simulator to
disk, then runs ``measure_stack`` at each effort in a fresh process (so its peak RSS is its own) and compares
the tile table and geometry with the lens truth. Writes its table to docs/benchmarks.md between
``<!-- bench_measure:start -->`` and ``<!-- bench_measure:end -->``.

Full run (the speed target: 41 frames of 1920x1080 RGB):  python benchmarks/bench_measure.py
Smoke run (small, fast):                                  python benchmarks/bench_measure.py --quick
Reuse a rendered stack (its own z grid and size are used): ... --stack-dir /tmp/bench_measure_stack
Before/after: also time another checkout's fieldcal:       ... --baseline /path/to/old/checkout [--baseline-label LABEL]

Each measurement runs in a fresh process (its own peak RSS); the 1-minute load average before and after each
run is recorded, because wall times on a shared 2-core machine mean little without it.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import platform
import resource
import shlex
import sys
import tempfile
import time
from pathlib import Path

from _common import REPO, md_table, write_docs_section

import numpy as np  # noqa: E402


def _measure_child(stack_dir: str, effort: str, measure: str, fs: float, q: float, out: "mp.Queue",
                   pythonpath: str | None = None) -> None:
    import os
    os.environ["FIELDCAL_PROGRESS"] = "0"
    if pythonpath:  # a baseline checkout: its fieldcal first (the spawned child has not imported ours yet)
        sys.path.insert(0, pythonpath)
        for name in [m for m in sys.modules if m == "fieldcal" or m.startswith("fieldcal.")]:
            del sys.modules[name]
    from fieldcal.measure import measure_stack
    from fieldcal.formats.stack import Stack
    stack = Stack.open(stack_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    table, geo = measure_stack(stack, fs_cyc_per_mm=fs, q=q, effort=effort, measure=measure, quiet=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    out.put({"wall_s": wall, "cpu_s": cpu, "rss_mb": rss_mb,
             "table": {k: np.asarray(getattr(table, k)).tolist() for k in
                       ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um", "width_um", "status")},
             "tile_px": table.tile_px, "geo": geo.to_dict()})


def _run(stack_dir: Path, effort: str, measure: str, fs: float, q: float, pythonpath: str | None = None) -> dict:
    ctx = mp.get_context("spawn")
    qout = ctx.Queue()
    load0 = os.getloadavg()[0]
    p = ctx.Process(target=_measure_child, args=(str(stack_dir), effort, measure, fs, q, qout, pythonpath))
    p.start()
    res = qout.get()
    p.join()
    res["load"] = 0.5 * (load0 + os.getloadavg()[0])
    return res


def _tile_truth(tp, x, y, ch, tile):
    o = np.arange(tile) - (tile - 1) / 2.0
    ox, oy = np.meshgrid(o, o)
    return np.array([tp.best_focus_um(xi + ox, yi + oy, ch).mean() for xi, yi in zip(x, y)])


def _accuracy(res: dict, spec, fs: float, q: float, step_um: float) -> dict:
    from fieldcal.simulate.truth import TruthProfile
    # tile positions are in the geometry of the reference frame of the measurement
    tp = TruthProfile(spec, z_ref_um=float(res["geo"]["z_um"][res["geo"]["ref_index"]]))
    t = {k: np.asarray(v) for k, v in res["table"].items()}
    ok = t["status"] == "ok"
    err, chi, wrel = [], [], []
    for ch in spec.channel_names:
        rows = np.flatnonzero(ok & (t["channel"] == ch))
        if rows.size == 0:
            continue
        e = t["z_best_um"][rows] - _tile_truth(tp, t["x_px"][rows], t["y_px"][rows], ch, res["tile_px"])
        err.append(e)
        chi.append(e / t["z_sigma_um"][rows])
        w = t["width_um"][rows]
        w = w[np.isfinite(w)]
        if w.size:
            wrel.append(w / spec.focus_tolerance_um(fs, q, ch) - 1.0)
    e = np.concatenate(err) if err else np.array([np.nan])
    g = res["geo"]
    z = np.asarray(g["z_um"])
    mag = np.asarray(g["magnification"])
    sx, sy = np.asarray(g["shift_x_px"]), np.asarray(g["shift_y_px"])
    slope_true = 1.0 / (spec.exit_pupil_mm * 1000.0)
    tsx, tsy = (np.polyfit(z, v, 1)[0] for v in spec.shift_px(z))
    mag_err = max(abs(np.polyfit(z, mag[:, c], 1)[0] / slope_true - 1.0) for c in range(mag.shape[1]))
    shift_err = max(max(abs(np.polyfit(z, sx[:, c], 1)[0] - tsx), abs(np.polyfit(z, sy[:, c], 1)[0] - tsy))
                    for c in range(mag.shape[1]))
    names, counts = np.unique(t["status"], return_counts=True)
    print({str(a): int(b) for a, b in zip(names, counts)}, file=sys.stderr)
    return {"n_tiles": int(t["status"].size), "ok_frac": float(ok.mean()),
            "rms_um": float(np.sqrt(np.mean(e ** 2))), "rms_step": float(np.sqrt(np.mean(e ** 2)) / step_um),
            "chi": float(np.sqrt(np.mean(np.concatenate(chi) ** 2))) if chi else math.nan,
            "width_err": float(np.median(np.abs(np.concatenate(wrel)))) if wrel else math.nan,
            "mag_slope_err": float(mag_err), "shift_slope_err": float(shift_err)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small stack (480x270, 21 frames) for a smoke run")
    ap.add_argument("--stack-dir", type=Path, default=None, help="render into / reuse this stack folder")
    ap.add_argument("--no-docs", action="store_true", help="do not write docs/benchmarks.md")
    ap.add_argument("--baseline", default=None,
                    help="also time the fieldcal of this checkout (a folder holding fieldcal/), for before/after")
    ap.add_argument("--baseline-label", default="before", help="label of the baseline rows (default: before)")
    args = ap.parse_args(argv)

    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate import simulate_stack
    from fieldcal.formats.stack import Stack

    spec0 = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    size, n_frames = ((480, 270), 21) if args.quick else ((1920, 1080), 41)
    tmp = None
    stack_dir = args.stack_dir
    if stack_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_measure_")
        stack_dir = Path(tmp.name) / "stack"
    if (stack_dir / "stack.json").exists():  # reuse: its own size and z grid
        st = Stack.open(stack_dir)
        size, z = (st.shape[1], st.shape[0]), np.sort(st.z_um)
        n_frames, step = z.size, float(np.median(np.diff(z)))
        spec = spec0.with_sensor_size(*size)
        print(f"reusing {stack_dir}: {n_frames} frames {size[0]}x{size[1]}, step {step:.2f} um", file=sys.stderr)
    else:
        spec = spec0.with_sensor_size(*size)
        lo, hi = spec.focus_range_um()
        # frames over the focus range plus 3 steps each side (a peak needs both flanks inside the scan)
        step = (hi - lo) / (n_frames - 1 - 6)
        z = lo - 3 * step + step * np.arange(n_frames)
        t0 = time.perf_counter()
        simulate_stack(spec, stack_dir, z, seed=0, progress=True)
        print(f"rendered {n_frames} frames {size[0]}x{size[1]} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    pitch_mm = spec.sensor.pixel_pitch_um * 1e-3
    fs = min(80.0, 0.25 / pitch_mm)  # the paper's 80 cycles/mm, or 0.25 cycles/px on a coarse grid
    q = 0.05
    versions = [("this checkout", None)] + ([(args.baseline_label, str(Path(args.baseline).resolve()))]
                                            if args.baseline else [])
    rows = []
    for effort, measure in (("quick", "sml"), ("standard", "sml"), ("standard", "bandpass")):
        for label, path in versions:
            res = _run(stack_dir, effort, measure, fs, q, path)
            acc = _accuracy(res, spec, fs, q, step)
            rows.append({"code": label, "effort": effort, "measure": measure, "tile_px": res["tile_px"],
                         "wall_s": res["wall_s"], "cpu_s": res["cpu_s"], "rss_mb": res["rss_mb"],
                         "load": res["load"], **acc})
            print(json.dumps(rows[-1]), file=sys.stderr)
    cols = [("code", "code", ""), ("effort", "effort", ""), ("z measure", "measure", ""), ("tile (px)", "tile_px", "d"),
            ("tiles x ch", "n_tiles", "d"), ("accepted", "ok_frac", ".0%"), ("wall (s)", "wall_s", ".2f"),
            ("CPU (s)", "cpu_s", ".2f"), ("load avg", "load", ".1f"), ("peak RSS (MB)", "rss_mb", ".0f"),
            ("best-focus RMS (µm)", "rms_um", ".3f"), ("RMS / step", "rms_step", ".3f"),
            ("RMS err / σ", "chi", ".2f"), ("width err (median)", "width_err", ".1%"),
            ("mag slope err", "mag_slope_err", ".1%"), ("shift slope err (px/µm)", "shift_slope_err", ".1e")]
    text = "\n".join([
        "## Measurement: tiles and geometry from a chart stack",
        "",
        f"`python benchmarks/bench_measure.py {shlex.join(sys.argv[1:] if argv is None else argv)}`".replace(" `", "`")
        + " — " + ("a **--quick** smoke run; the full run (41 frames of 1920x1080 RGB) replaces it. " if args.quick else "")
        + f"Paper triplet at {size[0]}x{size[1]} px ({spec.sensor.pixel_pitch_um:.2f} µm pixels), {n_frames} frames "
        f"every {step:.2f} µm from {z[0]:.1f} to {z[-1]:.1f} µm, fs = {fs:.0f} cycles/mm, q = {q}. Time and peak RSS "
        f"are `measure_stack` alone in a fresh process reading the TIFF stack ({platform.machine()}, "
        f"{mp.cpu_count()} cores, shared: 'load avg' is the 1-minute load average around each run; wall time "
        "scales with it, CPU time much less). "
        + (f"Rows '{args.baseline_label}' run the fieldcal of `{args.baseline}` on the same stack. " if args.baseline
           else "")
        + "Errors against the truth surface averaged over each "
        "tile; widths against the lens model's `focus_tolerance_um`; slopes of m(z) and s(z) fitted to the "
        "measured per-frame geometry (targets: 5 %, 5e-4 px/µm).",
        "",
        *md_table(rows, cols),
    ])
    if not args.no_docs:
        write_docs_section("measure", text)
    print(text)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
