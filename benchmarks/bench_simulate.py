"""Simulator speed: frames/s at 1920x1080 RGB (paper triplet), blur levels per frame, peak memory.

Writes a table between ``<!-- bench_simulate:start -->`` and ``<!-- bench_simulate:end -->`` in
docs/benchmarks.md (the rest of the file is left alone). ``--quick`` renders a small size for a smoke run.

    python benchmarks/bench_simulate.py            # full: 1920x1080, 9 frames over -200..200 µm
    python benchmarks/bench_simulate.py --quick    # 320x180, 3 frames, does not touch docs/ unless --write
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
START, END = "<!-- bench_simulate:start -->", "<!-- bench_simulate:end -->"


def levels_used(renderer, z_um: float) -> int:
    """Number of blur levels (inverse FFTs per channel) a frame at z needs."""
    from fieldcal.simulate.render import fractional_level
    spec = renderer.spec
    n = 0
    for ch in spec.channel_names:
        aff = renderer._affine(z_um, ch)
        b = renderer.diameter_px(renderer._defocus_at(z_um, ch, aff))
        k = fractional_level(b.astype(np.float32), renderer.level_ratio, renderer.level_floor_px)
        n += int(math.ceil(k.max())) - int(math.floor(k.min())) + 1
    return n


def run(width: int, height: int, z_list, lens: str) -> dict:
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate import Renderer
    from fieldcal.charts.targets import chart_image

    spec = LensSpec.load(REPO / "models" / f"{lens}.json").with_sensor_size(width, height)
    t0 = time.perf_counter()
    scene = chart_image("texture", width, height, 0)
    t_chart = time.perf_counter() - t0
    tracemalloc.start()
    t0 = time.perf_counter()
    r = Renderer(spec, scene)
    times, levels = [], []
    for z in z_list:
        t1 = time.perf_counter()
        r.render(float(z))
        times.append(time.perf_counter() - t1)
        levels.append(levels_used(r, float(z)))
    t_truth = time.perf_counter()
    r.truth()
    t_truth = time.perf_counter() - t_truth
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"lens": lens, "size": f"{width}x{height}", "channels": len(spec.channels), "frames": len(z_list),
            "s_per_frame": float(np.mean(times)), "fps": 1.0 / float(np.mean(times)),
            "levels_min": min(levels), "levels_max": max(levels), "truth_s": t_truth, "chart_s": t_chart,
            "peak_traced_mb": peak / 2**20,
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def table(rows: list[dict]) -> str:
    head = ("| lens | size | frames | s/frame | frames/s | blur levels per frame (all channels) | truth (s) | "
            "peak numpy memory (MB, tracemalloc) | max RSS (MB) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    lines = [head]
    for r in rows:
        lines.append(f"| {r['lens']} | {r['size']} x{r['channels']} | {r['frames']} | {r['s_per_frame']:.2f} | "
                     f"{r['fps']:.2f} | {r['levels_min']}–{r['levels_max']} | {r['truth_s']:.2f} | "
                     f"{r['peak_traced_mb']:.0f} | {r['max_rss_mb']:.0f} |")
    note = (f"\nMachine: {platform.processor() or platform.machine()}, Python {platform.python_version()}. "
            "Renderer defaults: level ratio 1.25, floor 0.5 px; frames include photon/read noise and "
            "quantisation. Level count = inverse FFTs per frame summed over channels.\n")
    return "\n".join(lines) + "\n" + note


def write_section(text: str, path: Path) -> None:
    from fieldcal.formats.atomic import atomic_write_text
    body = f"{START}\n{text}{END}"
    if path.exists():
        old = path.read_text()
        if START in old and END in old:
            new = old[:old.index(START)] + body + old[old.index(END) + len(END):]
        else:
            new = old.rstrip("\n") + "\n\n## Simulator\n\n" + body + "\n"
    else:
        new = "# Benchmarks\n\n## Simulator\n\n" + body + "\n"
    atomic_write_text(path, new)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small size smoke run (320x180, 3 frames)")
    p.add_argument("--write", action="store_true", help="with --quick: still write docs/benchmarks.md")
    p.add_argument("--out", default=str(REPO / "docs" / "benchmarks.md"))
    a = p.parse_args(argv)
    if a.quick:
        rows = [run(320, 180, [-200, 0, 150], "triplet-uncorrected")]
    else:
        z = np.linspace(-200, 200, 9)
        rows = [run(1920, 1080, z, "triplet-uncorrected"), run(1920, 1080, z[::2], "doublet-mono")]
    text = table(rows)
    print(text)
    if not a.quick or a.write:
        write_section(text, Path(a.out))
        print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
