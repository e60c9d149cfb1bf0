"""Run independent units of work (one stack, one lens) on Dask distributed, or in this process.

This module is the only one in fieldcal that imports Dask (the optional extra ``fieldcal[dask]``). A unit is a
picklable job given to a module-level function; :func:`run_units` submits one task per unit, shows progress as
they finish (``distributed.as_completed``) and returns one :class:`UnitResult` per unit in the order given. A
unit that fails is reported (its name, exit status and message) and the others still run: the task itself
catches the failure (:func:`run_unit`), so a bad stack never cancels the batch. A worker that dies (out of
memory, killed) fails only the units it was running.

Schedulers (``scheduler``):

* ``"local"`` — a ``LocalCluster`` of ``workers`` processes with one thread each (default: one per CPU);
* ``"threads"`` — a ``LocalCluster`` of threads inside this process (starts in well under a second; the GIL
  limits the speed-up to the parts that release it; for small batches and tests);
* ``"tcp://HOST:PORT"`` — an existing scheduler (``dask scheduler`` + ``dask worker tcp://HOST:PORT``): its
  workers need fieldcal installed and the same file paths as this machine (a shared file system);
* ``None`` — no Dask: the units run one after another in this process (benchmarks' reference runs).

Inside a task the numeric libraries use one thread (:func:`one_thread`: threadpoolctl for BLAS/OpenMP, OpenCV's
own pool), so ``N`` workers on ``N`` cores do not oversubscribe them.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import traceback
from dataclasses import asdict, dataclass
from typing import Any, Callable, Iterator, Sequence

from fieldcal.errors import (EXIT_ENVIRONMENT, EXIT_INTERNAL, FieldcalError, ParameterError, from_oserror)

INSTALL_FIX = 'install the optional extra: pip install -e ".[dask]" (dask[distributed] and threadpoolctl)'
SCHEDULER_HELP = ("local (a LocalCluster of --workers processes on this machine, default), threads (a "
                  "LocalCluster of threads in this process: quick to start, for small batches) or "
                  "tcp://HOST:PORT (an existing `dask scheduler`; docs/batch.md)")
CONNECT_TIMEOUT_S = 20.0
_ADDRESS = re.compile(r"^(tcp|tls|ws|wss|inproc)://[^\s/]+$")


class ClusterUnavailable(FieldcalError):
    """Dask is not installed, or its scheduler cannot be reached or has no usable workers (exit 4)."""

    exit_code = EXIT_ENVIRONMENT


@dataclass
class UnitResult:
    """What one unit of a batch came to.

    Attributes
    ----------
    name : str
        The unit's name (a stack's output name, ``lens-003``).
    ok : bool
        Whether the unit finished without an error.
    exit_code : int
        The exit status ``fieldcal`` gives this failure on its own (0 when ``ok``; docs/safety.md).
    error : str or None
        The failure's message (where, what, fix), as the single command prints it.
    field : str or None
        The API field the error names (the CLI renames it to its flag).
    value : Any
        The unit's return value (picklable; ``None`` when it failed).
    time_s : float
        Wall time of the unit on its worker.
    cpu_s : float
        CPU time of the worker's process during the unit (the unit's own with one task per process; any
        other threads of the process count too).
    worker : str or None
        Where it ran (the worker's address; ``None`` in this process).
    trace : str or None
        The Python traceback of an unexpected failure (shown with ``--debug``).
    """

    name: str
    ok: bool
    exit_code: int = 0
    error: str | None = None
    field: str | None = None
    value: Any = None
    time_s: float = 0.0
    cpu_s: float = 0.0
    worker: str | None = None
    trace: str | None = None

    def summary(self) -> dict:
        """The JSON-safe record of the unit (its value left out)."""
        d = asdict(self)
        d.pop("value")
        d.pop("trace")
        d["time_s"] = round(float(self.time_s), 3)
        d["cpu_s"] = round(float(self.cpu_s), 3)
        return d


def require_dask():
    """Import ``distributed`` or raise :class:`ClusterUnavailable` (exit 4) with the install command."""
    try:
        import distributed
        import threadpoolctl  # noqa: F401
    except ImportError as e:
        raise ClusterUnavailable(f"running on Dask needs the optional package {e.name or 'dask'}, which is not "
                                 "installed", fix=INSTALL_FIX) from None
    return distributed


def check_scheduler(text: str | None, workers: int | None) -> str | None:
    """Validate ``--scheduler`` and ``--workers`` before any work; returns the scheduler (None = serial)."""
    if workers is not None and workers < 1:
        raise ParameterError(f"--workers must be at least 1, got {workers}", field="workers", fix="e.g. --workers 2")
    if text is None or text in ("local", "threads"):
        return text
    if not _ADDRESS.match(text):
        raise ParameterError(f"unknown scheduler {text!r}", field="scheduler",
                             fix="give local, threads or the scheduler's address, e.g. tcp://10.0.0.5:8786")
    if workers is not None:
        raise ParameterError("--workers sizes a local cluster; an existing scheduler has its own workers",
                             field="workers", fix="drop --workers, or start more `dask worker` processes")
    return text


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """BLAS/OpenMP (threadpoolctl) and OpenCV limited to one thread for the block, then restored."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(before)


def run_unit(fn: Callable[[Any], Any], name: str, job: Any, threads_1: bool = True) -> UnitResult:
    """Run ``fn(job)`` as one unit (the task body on a worker): every failure becomes a :class:`UnitResult`.

    The failure is classified as the ``fieldcal`` command would (docs/safety.md): a
    :class:`~fieldcal.errors.FieldcalError` keeps its exit status, an ``OSError`` maps through
    :func:`~fieldcal.errors.from_oserror`, memory exhaustion is 4 and anything else is a bug (5, with the
    traceback kept for ``--debug``).
    """
    from fieldcal.formats.atomic import command_scope

    t0, c0 = time.perf_counter(), time.process_time()
    worker = _worker_address()
    res = UnitResult(name=name, ok=False, worker=worker)
    try:
        with command_scope(), (one_thread() if threads_1 else contextlib.nullcontext()):
            res.value = fn(job)
        res.ok = True
    except FieldcalError as e:
        res.exit_code, res.error, res.field = e.exit_code, str(e), e.field
    except MemoryError:
        res.exit_code = EXIT_ENVIRONMENT
        res.error = "not enough memory\n  fix: work on smaller images, or give each worker more memory"
    except OSError as e:
        err = from_oserror(e)
        res.exit_code, res.error = err.exit_code, str(err)
    except Exception as e:  # a bug in fieldcal: the unit fails, the batch goes on
        res.exit_code = EXIT_INTERNAL
        res.error = (f"internal error ({type(e).__name__}: {str(e)[:300]})\n  this is a bug in fieldcal: run "
                     "again with --debug to see the traceback, and report it")
        res.trace = traceback.format_exc()
    res.time_s = time.perf_counter() - t0
    res.cpu_s = time.process_time() - c0
    return res


def _worker_address() -> str | None:
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):  # not on a Dask worker
        return None


def _fieldcal_version() -> str:
    import fieldcal
    return fieldcal.__version__


def default_workers() -> int:
    """Local worker processes: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def open_client(scheduler: str = "local", workers: int | None = None):
    """A ``distributed.Client`` on a new local cluster or an existing scheduler, closed afterwards.

    Raises
    ------
    ClusterUnavailable
        Dask is missing, the scheduler does not answer within ``CONNECT_TIMEOUT_S``, or its workers cannot run
        fieldcal (not installed there, or another version).
    """
    distributed = require_dask()
    import logging

    with contextlib.ExitStack() as stack:
        if scheduler in ("local", "threads"):
            cluster = stack.enter_context(distributed.LocalCluster(
                n_workers=workers or default_workers(), threads_per_worker=1,
                processes=scheduler == "local", dashboard_address=":0", silence_logs=logging.ERROR))
            client = stack.enter_context(distributed.Client(cluster))
        else:
            try:
                client = stack.enter_context(distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S))
            except (OSError, TimeoutError) as e:
                raise ClusterUnavailable(f"cannot reach the Dask scheduler at {scheduler} ({e})", field="scheduler",
                                         fix="start one with `dask scheduler` and workers with `dask worker "
                                             f"{scheduler}`, or use --scheduler local") from None
            _check_workers(client, scheduler)
        yield client


def _check_workers(client, scheduler: str) -> None:
    """Every worker of an existing cluster imports the same fieldcal as this process."""
    from fieldcal import __version__

    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError):
        raise ClusterUnavailable(f"the Dask scheduler at {scheduler} has no workers", field="scheduler",
                                 fix=f"start workers with `dask worker {scheduler}`") from None
    try:
        versions = client.run(_fieldcal_version)
    except Exception as e:  # the function cannot even be unpickled there: fieldcal is not importable
        raise ClusterUnavailable(f"the workers of {scheduler} cannot import fieldcal ({type(e).__name__}: "
                                 f"{str(e)[:200]})", field="scheduler",
                                 fix="install fieldcal (the same version) in the workers' Python environment") \
            from None
    other = {w: v for w, v in versions.items() if v != __version__}
    if other:
        w, v = next(iter(other.items()))
        raise ClusterUnavailable(f"worker {w} runs fieldcal {v}, this machine {__version__}", field="scheduler",
                                 fix="install the same fieldcal version on every worker")


def run_units(fn: Callable[[Any], Any], jobs: Sequence[tuple[str, Any]], *, scheduler: str | None = "local",
              workers: int | None = None, desc: str = "units", unit: str = "unit", quiet: bool = False,
              on_result: Callable[[UnitResult], None] | None = None) -> list[UnitResult]:
    """Run ``fn(job)`` for each ``(name, job)``: one Dask task per unit, results in the order given.

    Parameters
    ----------
    fn : callable
        A module-level function (workers import it by name). Its return value must be picklable.
    jobs : sequence of (name, job)
        Unit names (unique) and their picklable arguments.
    scheduler : {"local", "threads"} or "tcp://HOST:PORT" or None
        Where to run (module docstring); ``None`` runs the units in this process, one after another.
    workers : int, optional
        Size of a local cluster (default: one per CPU).
    desc, unit : str
        Progress-bar label and unit name (fieldcal.progress).
    on_result : callable, optional
        Called in this process with each result as it arrives (status lines).

    Returns
    -------
    list of UnitResult
    """
    from fieldcal.progress import progress

    names = [n for n, _ in jobs]
    if len(set(names)) != len(names):  # pragma: no cover - callers name units uniquely
        raise ValueError("unit names must be unique")
    results: dict[str, UnitResult] = {}

    def done(r: UnitResult) -> None:
        results[r.name] = r
        if on_result is not None:
            on_result(r)

    if scheduler is None:
        for name, job in progress(jobs, total=len(jobs), desc=desc, unit=unit, quiet=quiet):
            done(run_unit(fn, name, job, threads_1=False))
        return [results[n] for n in names]
    distributed = require_dask()
    with open_client(scheduler, workers) as client:
        futures = [client.submit(run_unit, fn, name, job, pure=False) for name, job in jobs]
        name_of = {f.key: name for f, name in zip(futures, names)}
        for f in progress(distributed.as_completed(futures), total=len(futures), desc=desc, unit=unit,
                          quiet=quiet):
            try:
                r = f.result()
            except Exception as e:  # the task never ran to its end: its worker died (memory?) or it was lost
                r = UnitResult(name=name_of[f.key], ok=False, exit_code=EXIT_ENVIRONMENT,
                               error=f"the task did not finish on its worker ({type(e).__name__}: {str(e)[:300]})"
                                     "\n  fix: check the worker's log and memory (a worker killed for memory "
                                     "fails its task), then run the unit again")
            done(r)
    return [results[n] for n in names]
