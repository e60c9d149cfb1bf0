"""Cost of the geometric renderer's anisotropic astigmatism against the isotropic disc (cProfile, CPU, memory).

For each size: ``Renderer(spec, texture chart, astigmatism=MODE)``, ``prepare`` over 42 stage positions (the
lens's focus range ± 50 µm: the blur levels, once), then 5 frames with noise across the stack. The channels run
in one thread here so that cProfile sees all the work (the renderer normally runs them in parallel). Each mode
runs in its own process (clean peak RSS).

Usage::

    python benchmarks/bench_astig_render.py --lens models/triplet-astigmatic.json --size 640x480 --size 1920x1080

Prints one line per (size, mode) and a markdown table of the ratios (docs/simulator.md, "Astigmatism").
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def run_one(lens: str, w: int, h: int, mode: str) -> dict:
    from fieldcal.charts.targets import chart_image
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.render import Renderer

    spec = LensSpec.load(lens).with_sensor_size(w, h)
    scene = chart_image("texture", w, h, seed=0)
    lo, hi = spec.focus_range_um()
    zs = np.linspace(lo - 50.0, hi + 50.0, 42)
    box = {}

    def levels():
        r = Renderer(spec, scene, seed=0, astigmatism=mode)
        r._per_channel = lambda fn: [fn(i) for i in range(len(r.channels))]  # one thread: cProfile sees it all
        r.prepare(zs)
        box["r"] = r

    def frames():
        for z in zs[::10]:
            box["r"].render(float(z))

    row = {"size": f"{w}x{h}", "mode": mode}
    for name, fn in (("levels", levels), ("frames", frames)):
        prof = cProfile.Profile()
        c0 = time.process_time()
        prof.enable()
        fn()
        prof.disable()
        row[f"{name}_cpu_s"] = time.process_time() - c0
        row[f"{name}_profiled_s"] = pstats.Stats(prof).total_tt
    r = box["r"]
    row["level_mib"] = (sum(s.nbytes for s in r._stacks)
                        + sum(s.nbytes for v in r._wedge_stacks.values() for s in v)) / 2**20
    row["wedges"] = r.settings().get("orientation_wedges", {})
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lens", default=str(REPO / "models" / "triplet-astigmatic.json"))
    ap.add_argument("--size", action="append", default=[])
    ap.add_argument("--mode", choices=("anisotropic", "isotropic"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    sizes = args.size or ["640x480", "1920x1080"]
    if args.mode:  # the child process
        w, h = (int(v) for v in sizes[0].split("x"))
        print(json.dumps(run_one(args.lens, w, h, args.mode)))
        return 0
    rows = []
    for size in sizes:
        for mode in ("isotropic", "anisotropic"):
            out = subprocess.run([sys.executable, __file__, "--lens", args.lens, "--size", size, "--mode", mode],
                                 check=True, capture_output=True, text=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    print("| size | wedges K | levels: profiled s iso → aniso (ratio) | 5 frames: profiled s iso → aniso (ratio) "
          "| CPU ratio levels / frames | level memory MiB (ratio) | peak RSS MB |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for iso, ani in zip(rows[::2], rows[1::2]):
        k = ", ".join(f"{c} {v}" for c, v in ani["wedges"].items())
        print(f"| {iso['size']} | {k} | {iso['levels_profiled_s']:.2f} → {ani['levels_profiled_s']:.2f} "
              f"({ani['levels_profiled_s'] / iso['levels_profiled_s']:.1f}×) | {iso['frames_profiled_s']:.2f} → "
              f"{ani['frames_profiled_s']:.2f} ({ani['frames_profiled_s'] / iso['frames_profiled_s']:.1f}×) | "
              f"{ani['levels_cpu_s'] / iso['levels_cpu_s']:.1f} / {ani['frames_cpu_s'] / iso['frames_cpu_s']:.1f} | "
              f"{iso['level_mib']:.0f} → {ani['level_mib']:.0f} ({ani['level_mib'] / iso['level_mib']:.1f}×) | "
              f"{iso['peak_rss_mb']:.0f} → {ani['peak_rss_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
