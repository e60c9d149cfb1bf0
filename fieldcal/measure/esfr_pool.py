"""The e-SFR of a stack's frames in worker processes (:func:`fieldcal.measure.mtf.measure_mtf`).

The e-SFR core is mostly small-array NumPy and Python that holds the GIL: two threads measure a 1080p stack
only ~1.2-1.4x faster than one. Two worker *processes* each read (from the stack folder: the parent sends a frame
index, never pixels) and measure whole frames; the parent adds the results in z order, so records and tracks are
those of one thread.

Processes start through a ``forkserver`` (``spawn`` where there is none), never a plain ``fork`` of a parent
whose threads (the stack verification, the progress bar, BLAS and OpenCV pools) may hold locks. Each worker
limits its own BLAS/OpenMP/OpenCV threads to one (set before NumPy loads in it), and ignores Ctrl-C: the parent
takes the interrupt, cancels the frames not started and waits for the (sub-second) running ones, so no worker
outlives the call.

A worker process re-imports the parent's ``__main__`` module (multiprocessing's rule for spawn and forkserver):
harmless for ``python -m fieldcal``, the ``fieldcal`` command and any script whose work is under
``if __name__ == "__main__":``, but a script without that guard would run again in each worker. So processes are
used only where that is known to be safe (:func:`processes_allowed`): inside the ``fieldcal`` command
(:func:`fieldcal.cli.main` allows them for its duration), under ``python -m`` of a package, or an interactive
session; a library caller whose script is guarded opts in with :func:`allow_processes`.

This module imports only the standard library at its top: a worker imports it before its thread limits are set.
"""

from __future__ import annotations

import contextlib
import os
import sys

#: environment variables that size a native thread pool, set to 1 in each worker before NumPy loads there
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")

_state: dict = {}
_allowed: list[bool] = []  # a stack of allow_processes() settings (the innermost decides)


@contextlib.contextmanager
def allow_processes(flag: bool = True):
    """Within the ``with`` block, measure stacks in worker processes (``True``) or never (``False``), whatever
    :func:`processes_allowed` would decide from ``__main__``. Use ``True`` only from a script whose top-level work
    is under ``if __name__ == "__main__":`` (each worker re-imports it)."""
    _allowed.append(bool(flag))
    try:
        yield
    finally:
        _allowed.pop()


def processes_allowed() -> bool:
    """Whether worker processes may be started here: never in a daemonic process (a pool's worker: dask's, this
    module's); else as set by :func:`allow_processes`, else only when the
    ``__main__`` module is a package's ``__main__`` (``python -m``: multiprocessing does not re-run it) or has no
    file (``python -c``, an interactive session)."""
    import multiprocessing as mp
    if mp.current_process().daemon:  # a daemonic process (a process pool's worker) may not have children
        return False
    if _allowed:
        return _allowed[-1]
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None) or ""
    if name == "__main__" or name.endswith(".__main__"):
        return True
    return name == "" and getattr(main, "__file__", None) is None


def context():
    """The multiprocessing context of the pool: forkserver where the platform has it, else spawn."""
    import multiprocessing as mp
    methods = mp.get_all_start_methods()
    return mp.get_context("forkserver" if "forkserver" in methods else "spawn")


def _forkserver():
    """multiprocessing's forkserver object (None where there is none)."""
    try:
        from multiprocessing import forkserver
    except ImportError:
        return None
    return getattr(forkserver, "_forkserver", None)


def forkserver_running() -> bool:
    server = _forkserver()
    return getattr(server, "_forkserver_pid", None) is not None


def stop_forkserver() -> None:
    """Stop the forkserver and reap it (so the workers' CPU time, which it reaped, counts in this process's
    children's times, as a benchmark's ``wait4`` reads them). Only for a server this module started; a no-op
    where the interpreter has no such method (it then ends with this process)."""
    stop = getattr(_forkserver(), "_stop", None)
    if stop is not None:
        try:
            stop()
        except OSError:
            pass


def _limit_threads() -> None:
    """A worker's native thread pools to one thread each, and Ctrl-C left to the parent."""
    import signal
    for var in THREAD_VARS:
        os.environ[var] = "1"
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # NumPy may have loaded before this (the options carry arrays): its BLAS pool is limited here too
    from threadpoolctl import threadpool_limits
    _state["limits"] = threadpool_limits(limits=1)


def init_fit_worker() -> None:
    """Initializer of the track fits' workers (:func:`fieldcal.measure.edge_tiles.track_foci`): thread limits,
    then the fits' modules (scipy), imported while the parent still prepares the channels."""
    _limit_threads()
    from . import edge_tiles  # noqa: F401


def init_surface_worker() -> None:
    """Initializer of the surface fit's own worker (:func:`fieldcal.fit.pool.surface_pool`): thread limits, then
    :func:`prepare_surface_worker`, while the parent fits the first candidates."""
    _limit_threads()
    prepare_surface_worker()


def prepare_surface_worker() -> None:
    """Make this worker ready for the surface fit's tasks (once per process): glibc's allocator keeping freed
    memory (:func:`fieldcal.composite.memory.tune_allocator`), then the fit's modules. A worker of the track fits'
    pool kept for the fit (:func:`keep_pool`) runs it before its first fit task.

    The allocator: a fresh process maps each of the discrepancy fit's ~1.5 MB covariance matrices afresh and
    gives it back on free, and the kernel zeroes its pages again on first touch: on the 1080p slanted-edge
    triplet that fit took 1.3 s of CPU in a new process (0.45 s of it system time, 370 k page faults) against
    0.77 s in the calibrating process, whose allocator earlier, larger blocks had already moved off mapping."""
    if _state.get("surface_ready"):
        return
    from ..composite.memory import tune_allocator
    tune_allocator()
    from ..fit import discrepancy, selfcheck  # noqa: F401
    from ..fit.map import fit_map  # noqa: F401
    _state["surface_ready"] = True


_keepers: list[dict] = []  # a stack of keep_pool() blocks, each holding the pool handed over to it (or none)


def _close(pool, own_server: bool) -> None:
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)
    if own_server and forkserver_running():
        stop_forkserver()


@contextlib.contextmanager
def keep_pool():
    """Within the block, a pool made with ``keep=True`` (:func:`process_pool`: the track fits') is not closed when
    its own block ends but kept for a later user of the same process (:func:`kept_pool`: the surface fit), and
    closed -- with its forkserver -- when this block ends, also on an error or Ctrl-C. Its workers have then
    imported NumPy and SciPy already: a new pool for the fit would start (~0.5 s of CPU) to do the same."""
    slot: dict = {}
    _keepers.append(slot)
    try:
        yield
    finally:
        _keepers.pop()
        if slot:
            _close(slot["pool"], slot["own_server"])


def kept_pool():
    """The pool the innermost :func:`keep_pool` block holds, or None."""
    return _keepers[-1].get("pool") if _keepers else None


@contextlib.contextmanager
def process_pool(workers: int, initializer, initargs: tuple = (), keep: bool = False):
    """A process pool of ``workers``, every worker started at once (a pool starts one per task waiting), or
    ``None`` where none can be made here (no semaphores without /dev/shm, no forkserver). On leaving -- also on
    an error or Ctrl-C -- the tasks not started are cancelled, the running ones waited for, and a forkserver the
    pool started is stopped: nothing of the pool outlives the block, unless ``keep`` and a :func:`keep_pool` block
    holds no pool yet: a pool whose block ended without an error is then handed to it."""
    from concurrent.futures import ProcessPoolExecutor
    own_server = not forkserver_running()
    pool = None
    keeper = _keepers[-1] if keep and _keepers and not _keepers[-1] else None
    ok = False
    try:
        try:
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=context(), initializer=initializer,
                                       initargs=initargs)
            for _ in range(workers):
                pool.submit(os.getpid)
        except (OSError, ImportError, NotImplementedError):
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
            pool = None
        yield pool
        ok = True
    finally:
        if ok and keeper is not None and pool is not None:
            keeper.update(pool=pool, own_server=own_server)
        else:
            _close(pool, own_server)


def fit_pool(workers: int):
    """The track fits' pool (:func:`process_pool` with :func:`init_fit_worker`), kept for the surface fit within a
    :func:`keep_pool` block."""
    return process_pool(workers, init_fit_worker, keep=True)


def init_worker(stack_path: str, expect: tuple, options: dict) -> None:
    """Pool initializer: thread limits, Ctrl-C to the parent, then open the stack (without re-hashing it: the
    parent verified it) and keep it with the measurement options for :func:`measure_index`."""
    _limit_threads()
    import cv2
    cv2.setNumThreads(1)
    from ..formats.stack import Stack
    stack = Stack.open(stack_path, verify=False)
    _state.update(stack=stack, expect=expect, options=options)


def measure_index(k: int):
    """``(k, z_um, records, detections)`` of frame ``k`` (file order) of the worker's stack."""
    from ..errors import StackError
    from .mtf import measure_frame
    stack, options = _state["stack"], _state["options"]
    info = stack.frames[k]
    if (info.file, float(info.z_um)) != tuple(_state["expect"][k]):  # stack.json rewritten since the parent read it
        raise StackError(f"stack.json changed while it was being measured (frames[{k}] is now {info.file!r} at "
                         f"z_um={info.z_um:g})", path=stack.json_path, field=f"frames[{k}]",
                         fix="do not edit or re-capture a stack while fieldcal reads it; run the command again")
    z = float(info.z_um)
    return (k, z) + measure_frame(stack.read_normalized(k), frame_index=k, z_um=z, **options)
