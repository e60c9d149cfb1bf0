"""The Wiener step's tile grid on synthetic frames of several sizes: the rule (``depth_wiener.tile_grid``) against
fixed 512-px squares (session 19's tiling), by the rule's cost model and by timing.

``PYTHONPATH=. python benchmarks/bench_wiener_tiles.py [--sizes 1920x1080,2048x1536] [--reps 2]
[--depth cells|slope] [--workers N]``

Each size: 7 random-texture RGB uint8 frames 50 µm apart, a measured-defocus lens model as the real board's (12.1 px
of blur disc per frame step, depth error 0.13 step), the composite's YCbCr split as ``fieldcal composite`` makes it
(luma on labels 1/8 frame apart, Cb and Cr on labels one frame apart, in one call). ``--depth cells``: the
best focus drawn per 24-px cell over the whole stack (every tile uses every label, as on the board); ``slope``: a
plane across the image (each tile uses the labels of its own depths only). The two grids run in turn in one
process, ``--reps`` times each, in turn (the order reversed every other time; a 320 x 240 call first, untimed);
CPU is the process's (``time.process_time``: all threads).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _grid_512(w, h, margin, workers, max_samples=None, label_maps=None):
    """Session 19's tiles: 512-px squares from the top left (partial ones at the right and bottom)."""
    from scipy import fft

    core = min(512, max(w, h))
    return (list(range(0, w, core)) + [w], list(range(0, h, core)) + [h],
            fft.next_fast_len(min(core, h) + 2 * margin, real=True),
            fft.next_fast_len(min(core, w) + 2 * margin, real=True))


def _model_cost(grid, w, h, margin, workers):
    """Tiles, block and label-blind model cost of a grid (a function, or its ``(ex, ey, by, bx)``)."""
    ex, ey, by, bx = grid(w, h, margin, workers) if callable(grid) else grid
    n = (len(ex) - 1) * (len(ey) - 1)
    slots = -(-n // workers) * workers
    return n, by, bx, slots * by * bx * np.log2(by * bx)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1920x1080,2048x1536")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--depth", choices=("cells", "slope"), default="cells")
    ap.add_argument("--model-only", action="store_true", help="the cost model only (no timing)")
    ap.add_argument("--workers", type=int, default=None, help="the compositor's threads (default: its own)")
    args = ap.parse_args()

    import fieldcal.composite.depth_wiener as dw
    from fieldcal.composite import memory, source
    from fieldcal.composite.defocus_rate import DefocusRate, MeasuredDefocus
    from fieldcal.formats.frames import ArrayStack

    for setup in ("tune_allocator", "single_threaded_blas", "single_threaded_opencv"):
        if hasattr(memory, setup):
            getattr(memory, setup)()
    if args.workers:
        source.default_workers = lambda n=args.workers: n
    workers = source.default_workers()
    margin = int(np.ceil(0.5 * dw.REACH_DISC_PX)) + 16 + dw.TILE_MARGIN_PX
    ycc = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
    spacing = 50.0
    model = MeasuredDefocus(DefocusRate(disc_px_per_step=12.1, sd_px_per_step=0.1, spacing_um=spacing,
                                        reliable=True), pixel_pitch_um=1.12, depth_sd_steps=0.13)
    grids = {"rule": dw.tile_grid, "512 squares": _grid_512}
    print(f"workers {workers}, margin {margin} px, depth {args.depth}")
    print("| size | grid | tiles | block | model cost (rel.) | filters | CPU s | wall s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for k, size in enumerate(["320x240"] + args.sizes.split(",")):
        w, h = (int(v) for v in size.split("x"))
        warmup = k == 0  # (imports and first-call costs, untimed)
        if warmup and args.model_only:
            continue
        costs = {name: _model_cost(g, w, h, margin, workers) for name, g in grids.items()}
        if args.model_only:
            for name, (n, by, bx, c) in costs.items():
                print(f"| {w} x {h} | {name} | {n} | {by} x {bx} | {c / costs['512 squares'][3]:.3f} | | | |")
            continue
        rng = np.random.default_rng(1)
        z = spacing * np.arange(7)
        base = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        frames = [np.roll(base, k, axis=1) for k in range(7)]  # texture everywhere (the content does not matter)
        st = ArrayStack(frames, z, ["R", "G", "B"])
        reference = base.astype(np.float32)
        if args.depth == "cells":
            cells = rng.uniform(z[0], z[-1], (-(-h // 24), -(-w // 24))).astype(np.float32)
            zb1 = np.repeat(np.repeat(cells, 24, axis=0), 24, axis=1)[:h, :w]
        else:
            zb1 = np.broadcast_to(np.linspace(z[0], z[-1], w, dtype=np.float32), (h, w))
        zb = np.repeat(zb1[..., None], 3, axis=2)
        del zb1
        times = {name: [] for name in grids}
        filters = {}
        chosen = {}
        for r in range(1 if warmup else args.reps):
            for name, g in (list(grids.items()) if r % 2 == 0 else list(grids.items())[::-1]):  # in turn
                def recording(*a, g=g, name=name, **k):
                    chosen[name] = g(*a, **k)
                    return chosen[name]

                dw.tile_grid = recording
                w0, c0 = time.perf_counter(), time.process_time()
                _, info = dw.wiener_composite(st, zb, model, np.arange(7), reference, mix=ycc,
                                              label_um=[0.125 * spacing, spacing, spacing],
                                              plane_sigma=[1.0, 0.5, 0.5], quiet=True)
                times[name].append((time.process_time() - c0, time.perf_counter() - w0))
                filters[name] = info["filters"]
        dw.tile_grid = grids["rule"]
        for name in ([] if warmup else grids):
            n, by, bx, c = _model_cost(chosen[name], w, h, margin, workers)  # the grid the call chose
            cpu = " / ".join(f"{t[0]:.2f}" for t in times[name])
            wall = " / ".join(f"{t[1]:.2f}" for t in times[name])
            print(f"| {w} x {h} | {name} | {n} | {by} x {bx} | {c / costs['512 squares'][3]:.3f} | {filters[name]} "
                  f"| {cpu} | {wall} |", flush=True)
        del frames, st, reference, zb


if __name__ == "__main__":
    main()
