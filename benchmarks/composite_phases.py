"""Wall and CPU time per phase of a no-profile composite, and the main thread's share of each phase's CPU.

``python benchmarks/composite_phases.py STACK OUT.tiff [Z_REF_UM]`` (with ``PYTHONPATH`` at the checkout to
measure). A phase's CPU is the whole process's (``time.process_time``: every thread); ``main-thread`` is
``time.thread_time`` of the caller's thread. Work done on the main thread while the compositor's threads wait
is what keeps one of two cores idle: a phase whose main-thread share is near 100 % is serial. Wall figures
need a quiet machine; the main-thread share does not. The process is set up as ``fieldcal composite`` sets it
(glibc's allocator, BLAS threads: :mod:`fieldcal.composite.memory`), where the checkout measured has those.
"""
from __future__ import annotations

import functools
import importlib
import sys
import time

PHASES = [("fieldcal.composite.register", "register_stack"), ("fieldcal.composite.api", "focus_volume"),
          ("fieldcal.composite.api", "_per_pixel_focus"),
          ("fieldcal.composite.fusion", "fuse_pyramid"), ("fieldcal.composite.fusion", "depth_map"), ("fieldcal.composite.api", "_measured_defocus"),
          ("fieldcal.composite.depth_wiener", "occlusion_focus_um"), ("fieldcal.composite.api", "composite_with_map"),
          ("fieldcal.composite.depth_wiener", "wiener_composite"), ("fieldcal.composite.detail", "fine_detail"),
          ("fieldcal.composite.api", "_write"), ("fieldcal.composite.api", "composite_stack")]


def _timed(module: str, name: str, rows: list) -> None:
    """Replace ``module.name`` by a wrapper appending ``(name, wall_s, cpu_s, main_thread_s)`` to ``rows``."""
    mod = importlib.import_module(module)
    fn = getattr(mod, name)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            rows.append((name, time.perf_counter() - w0, time.process_time() - c0, time.thread_time() - t0))

    setattr(mod, name, wrapper)


def main(argv: list[str]) -> None:
    if len(argv) not in (2, 3):
        sys.exit(__doc__)
    import fieldcal.composite.api as api
    from fieldcal.composite import memory

    # the process as `fieldcal composite` sets it up (commands/composite.py), where this checkout has it
    for setup in ("tune_allocator", "single_threaded_blas", "single_threaded_opencv"):
        if hasattr(memory, setup):
            getattr(memory, setup)()
    rows: list = []
    for module, name in PHASES:
        _timed(module, name, rows)
    z_ref = float(argv[2]) if len(argv) == 3 else None
    w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
    api.composite_to_file(argv[0], argv[1], z_ref_um=z_ref, quiet=True, overwrite=True)
    rows.append(("total", time.perf_counter() - w0, time.process_time() - c0, time.thread_time() - t0))
    print(f"{'phase':22s} {'wall s':>7s} {'cpu s':>7s} {'main s':>7s} {'main/cpu':>8s}")
    for name, wall, cpu, main_s in rows:
        print(f"{name:22s} {wall:7.2f} {cpu:7.2f} {main_s:7.2f} {main_s / max(cpu, 1e-9):8.0%}")


if __name__ == "__main__":
    main(sys.argv[1:])
