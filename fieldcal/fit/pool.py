"""Independent pieces of the surface fit in one worker process beside this one (:func:`surface_pool`, :func:`run_tasks`).

The fit is serial Python and small linear algebra that holds the GIL; its independent pieces -- the candidate
models' MAP fits (:func:`fieldcal.fit.map.fit_map`), and the discrepancy fit beside the posterior sampling -- run
in a worker *process* while this one works on the others. Each piece is a deterministic function of its
arguments, and the worker's BLAS runs one thread as this process's does under
:func:`fieldcal.calibration.pipeline.one_blas_thread`, so the result is the same to the last bit whichever
process computed a piece (``tests/test_fit_pool.py``).

A worker is used only where worker processes are allowed (:func:`fieldcal.measure.esfr_pool.processes_allowed`:
the ``fieldcal`` command), this process's NumPy/SciPy BLAS runs one thread, and the fit is large enough
(:data:`POOL_MIN_ROWS`): one of the track fits' workers kept for the fit by ``fieldcal calibrate`` on slanted
edges, else a new one for a large fit only (:data:`NEW_POOL_MIN_ROWS`: its start pays only where a core is free).
Elsewhere :func:`surface_pool` gives ``None`` and everything runs here, with the same result.
"""

from __future__ import annotations

import contextlib
import threading

#: rows (focus + astigmatism) from which the fit uses a worker: the track fits' workers kept for it
#: (:func:`fieldcal.measure.esfr_pool.keep_pool`; started, NumPy and SciPy loaded), or a new one from
#: :data:`NEW_POOL_MIN_ROWS`. What a worker takes over -- the decentred candidates' MAP fits, the discrepancy fit
#: -- grows with the rows: ~1.7 s of the 2.8 s serial fit of the 1080p slanted-edge triplet (1296 rows).
POOL_MIN_ROWS = 600
#: rows from which a new worker is started when none is kept. Its start (a forkserver, then ~0.45 s of CPU of
#: imports on the other core) pays only where that core is free: on the triplet's 1296 rows the fit took 2.15-2.25 s
#: against 2.8-2.9 s serial at a 1-minute load of ~1.5 (2 cores), but 2.9-3.9 s against 2.8-2.9 s at a load of 3;
#: on 648 rows 1.7-2.3 s against 1.6 s at loads of 2.4-3.5 (docs/benchmarks.md "bench_fit_speed_s19").
NEW_POOL_MIN_ROWS = 1200


def _blas_single_threaded() -> bool:
    """Whether NumPy's and SciPy's BLAS run one thread here, the worker's setting (so results equal bit for bit).

    The BLAS libraries of the NumPy and SciPy wheels (in ``numpy.libs``, ``scipy.libs``) decide; another package's
    own BLAS (OpenCV's wheel carries one, loaded after :func:`fieldcal.calibration.pipeline.one_blas_thread`
    limited the others) does not compute the fit. Where neither wheel's is found (a system or conda BLAS),
    every BLAS loaded must run one thread.
    """
    import os

    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return False
    import numpy
    import scipy
    dirs = tuple(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(m.__file__))), m.__name__ + ".libs")
                 for m in (numpy, scipy))
    blas = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    own = [i for i in blas if os.path.dirname(os.path.abspath(str(i.get("filepath", "")))) in dirs]
    return bool(blas) and all(int(i.get("num_threads", 0)) == 1 for i in (own or blas))


@contextlib.contextmanager
def surface_pool(n_rows: int):
    """A one-worker process pool for the fit of ``n_rows`` rows, or ``None`` (everything here) for a small fit,
    one core, processes not allowed here, or a BLAS running more than one thread. Nothing of it outlives the
    block (:func:`fieldcal.measure.esfr_pool.process_pool`)."""
    import os

    from ..measure import esfr_pool
    if (n_rows < POOL_MIN_ROWS or (os.cpu_count() or 1) < 2 or not esfr_pool.processes_allowed()
            or not _blas_single_threaded()):
        yield None
        return
    kept = esfr_pool.kept_pool()
    if kept is not None:  # the track fits' workers (NumPy, SciPy loaded): closed by their keep_pool block
        yield _Pool(kept, getattr(kept, "_max_workers", 1))
        return
    if n_rows < NEW_POOL_MIN_ROWS:
        yield None
        return
    with esfr_pool.process_pool(1, esfr_pool.init_surface_worker) as pool:
        yield None if pool is None else _Pool(pool, 1)


def _in_worker(fn, args: tuple):
    """``fn(*args)`` in a pool's worker, made ready for the fit first (once per process)."""
    from ..measure.esfr_pool import prepare_surface_worker
    prepare_surface_worker()
    return fn(*args)


class _Pool:
    """The executor and a future that is done once a worker is ready for the fit (its imports done)."""

    def __init__(self, executor, workers: int):
        import os
        self.executor = executor
        ready = [executor.submit(_in_worker, os.getpid, ()) for _ in range(max(1, workers))]
        self.ready = ready[0]

    def submit(self, fn, *args):
        return self.executor.submit(_in_worker, fn, args)


def _broken(exc: BaseException) -> bool:
    from concurrent.futures.process import BrokenProcessPool
    return isinstance(exc, BrokenProcessPool)


def run_tasks(pool: _Pool | None, fn, arglist: list[tuple]):
    """Yield ``fn(*args)`` for each tuple of ``arglist``, in order.

    This process takes the tasks from the front, the pool's worker (once started) from the back, so neither
    waits for the other while work is left; without a pool, every task runs here, in order. An exception of a
    task is raised when its result is reached; a task whose worker died is computed here.
    """
    n = len(arglist)
    if pool is None or n < 2:
        for args in arglist:
            yield fn(*args)
        return
    lock = threading.Lock()
    bounds = [0, n]  # [next front task, one past the last unclaimed task]
    results: list = [None] * n
    errors: list = [None] * n
    done = [threading.Event() for _ in range(n)]

    def claim(front: bool) -> int | None:
        with lock:
            if bounds[0] >= bounds[1]:
                return None
            if front:
                bounds[0] += 1
                return bounds[0] - 1
            bounds[1] -= 1
            return bounds[1]

    def feed():
        try:
            pool.ready.result()
        except BaseException:  # noqa: BLE001 -- no worker: this process takes every task
            return
        while (i := claim(front=False)) is not None:
            try:
                results[i] = pool.submit(fn, *arglist[i]).result()
            except BaseException as e:  # noqa: BLE001 -- handed to the caller at this task's result
                errors[i] = e
            done[i].set()

    first = claim(front=True)  # this process's first task is claimed before the worker's thread starts
    threading.Thread(target=feed, daemon=True, name="fieldcal-fit-feed").start()
    try:
        yield from _collect(fn, arglist, results, errors, done, claim, first)
    finally:  # the caller stopped early (or a task failed): the worker takes nothing more
        with lock:
            bounds[0] = bounds[1]


def _collect(fn, arglist, results, errors, done, claim, i):
    """:func:`run_tasks`' loop in this process: its own tasks from the front, the results in order."""
    n = len(arglist)
    nxt = 0
    while nxt < n:
        if i is not None:  # an error of this process's own task is raised at once
            results[i] = fn(*arglist[i])
            done[i].set()
            i = claim(front=True)
        while nxt < n and done[nxt].is_set():
            if errors[nxt] is not None:
                if _broken(errors[nxt]):
                    errors[nxt], results[nxt] = None, fn(*arglist[nxt])
                else:
                    raise errors[nxt]
            yield results[nxt]
            results[nxt] = None
            nxt += 1
        if i is None and nxt < n:
            done[nxt].wait()


class Deferred:
    """``fn(*args)`` computed in the pool's worker while this process does other work; here, at :meth:`result`,
    without a pool, where its worker has not started yet (this process would wait for its start) or died."""

    def __init__(self, pool: _Pool | None, fn, *args):
        self.fn, self.args = fn, args
        started = pool is not None and pool.ready.done() and pool.ready.exception() is None
        self.future = pool.submit(fn, *args) if started else None

    def result(self):
        if self.future is not None:
            try:
                return self.future.result()
            except BaseException as e:
                if not _broken(e):
                    raise
        return self.fn(*self.args)
