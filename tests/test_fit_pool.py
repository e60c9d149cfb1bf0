"""The surface fit's worker process (fieldcal/fit/pool.py): the same result to the last bit, tasks in order."""

import json
import math

import numpy as np
import pytest

from fieldcal.calibration.pipeline import one_blas_thread
from fieldcal.fit import fit_surfaces
from fieldcal.fit import pool as fit_pool_mod
from fieldcal.fit.synthetic import random_lens, synthetic_tiles
from fieldcal.measure import esfr_pool


@pytest.fixture(scope="module")
def worker():
    """A started one-worker pool as :func:`fieldcal.fit.pool.surface_pool` makes it (None where none can be made)."""
    with esfr_pool.allow_processes(True), esfr_pool.process_pool(1, esfr_pool.init_surface_worker) as ex:
        if ex is None:
            pytest.skip("no process pool here")
        pool = fit_pool_mod._Pool(ex, 1)
        pool.ready.result(timeout=120)
        yield pool


def test_run_tasks_in_order_with_and_without_a_worker(worker):
    args = [(float(v),) for v in range(25)]
    want = [math.sqrt(v) for v in range(25)]
    assert list(fit_pool_mod.run_tasks(None, math.sqrt, args)) == want
    assert list(fit_pool_mod.run_tasks(worker, math.sqrt, args)) == want
    assert list(fit_pool_mod.run_tasks(worker, math.sqrt, args[:1])) == want[:1]
    assert list(fit_pool_mod.run_tasks(worker, math.sqrt, [])) == []


def test_run_tasks_raises_a_failed_task_at_its_place(worker):
    # whichever process computed it: the results before it arrive, then its error
    args = [(4.0,), (9.0,), (-1.0,), (16.0,)]
    got = []
    with pytest.raises(ValueError):
        got.extend(fit_pool_mod.run_tasks(worker, math.sqrt, args))
    assert got == [2.0, 3.0]
    d = fit_pool_mod.Deferred(worker, math.sqrt, -1.0)
    with pytest.raises(ValueError):
        d.result()
    assert fit_pool_mod.Deferred(worker, math.sqrt, 2.25).result() == 1.5


def test_no_pool_for_a_small_fit_or_where_processes_are_not_allowed():
    with esfr_pool.allow_processes(True), one_blas_thread(), \
            fit_pool_mod.surface_pool(fit_pool_mod.POOL_MIN_ROWS - 1) as pool:
        assert pool is None
    with esfr_pool.allow_processes(False), one_blas_thread(), \
            fit_pool_mod.surface_pool(10 * fit_pool_mod.POOL_MIN_ROWS) as pool:
        assert pool is None


def test_blas_check_follows_the_thread_limit():
    from threadpoolctl import threadpool_info, threadpool_limits
    if not [i for i in threadpool_info() if i.get("user_api") == "blas"]:
        pytest.skip("no BLAS seen by threadpoolctl")
    with threadpool_limits(limits=1, user_api="blas"):
        assert fit_pool_mod._blas_single_threaded()
    with threadpool_limits(limits=2, user_api="blas"):
        seen = [i for i in threadpool_info() if i.get("user_api") == "blas"]
        if all(int(i["num_threads"]) == 1 for i in seen):
            pytest.skip("BLAS cannot run two threads here")
        assert not fit_pool_mod._blas_single_threaded()


def _digest(fit):
    diag = dict(fit.diagnostics)
    diag.pop("time_map_s")
    diag.pop("time_total_s")
    diag.get("self_check", {}).pop("time_s", None)
    disc = fit.discrepancy
    return (fit.model.name, fit.theta_map.tobytes(), fit.samples.tobytes(),
            json.dumps(fit.candidates, sort_keys=True, default=str),
            json.dumps(diag, sort_keys=True, default=str),
            None if disc is None else (disc.beta.tobytes(), disc.beta_cov.tobytes()))


@pytest.mark.parametrize("seed", [3, 8])
def test_fit_with_a_worker_equals_the_serial_fit_bit_for_bit(worker, seed):
    # a decentred, astigmatic random lens: decentred candidates (their siblings' starts), the model choice, the
    # discrepancy fit -- the pieces the worker takes -- all enter the result
    rng = np.random.default_rng(seed)
    tiles, geom, _ = synthetic_tiles(random_lens(rng), rng, nx=11, ny=8, underestimate=1.5, outlier_fraction=0.03)
    sent = []

    class Counting(fit_pool_mod._Pool):  # the worker, counting what it was given
        def __init__(self):
            self.executor, self.ready = worker.executor, worker.ready

        def submit(self, fn, *args):
            sent.append(getattr(fn, "__name__", ""))
            return super().submit(fn, *args)

    counted = Counting()
    with one_blas_thread():
        serial = fit_surfaces(tiles, geom, effort="quick", seed=seed, quiet=True)
        pooled = fit_surfaces(tiles, geom, effort="quick", seed=seed, quiet=True, pool=counted)
    assert any("decentre" in e["name"] and e.get("bic") is not None for e in serial.candidates)
    assert "_discrepancy_and_check" in sent and "_fit_candidate" in sent
    assert _digest(pooled) == _digest(serial)


def test_decentred_candidates_start_from_their_centred_siblings(worker):
    # the batched search fits each decentred candidate as the one-at-a-time search did: fit_map started from its
    # centred sibling's MAP (its scales and dof), whichever process ran it
    from dataclasses import replace

    from fieldcal.fit.map import fit_map
    from fieldcal.fit.posterior import EFFORTS
    from fieldcal.fit.select import build_rows, candidate_models

    rng = np.random.default_rng(3)
    tiles, geom, _ = synthetic_tiles(random_lens(rng), rng, nx=11, ny=8, underestimate=1.5, outlier_fraction=0.03)
    with one_blas_thread():
        fit = fit_surfaces(tiles, geom, effort="quick", seed=3, quiet=True, pool=worker)
        rows, _, _ = build_rows(tiles, geom, tiles.channels)
        models = {m.name: m for m in candidate_models(tiles.channels, EFFORTS["quick"].max_order, True)}
        checked = 0
        for e in fit.candidates:
            m = models.get(e["name"])
            if m is None or not m.decentre or e.get("log_likelihood") is None:
                continue
            sibling = fit_map(replace(m, decentre=False), rows)
            assert e["log_likelihood"] == fit_map(m, rows, start_from=sibling).log_likelihood
            checked += 1
    assert checked >= 2


def test_a_kept_pool_outlives_its_block_until_the_keeper_ends():
    import os
    with esfr_pool.allow_processes(True):
        with esfr_pool.keep_pool():
            with esfr_pool.fit_pool(1) as ex:
                if ex is None:
                    pytest.skip("no process pool here")
                pid = ex.submit(os.getpid).result(timeout=120)
            kept = esfr_pool.kept_pool()
            assert kept is ex and kept.submit(os.getpid).result(timeout=60) == pid
            with one_blas_thread(), fit_pool_mod.surface_pool(10 * fit_pool_mod.POOL_MIN_ROWS) as pool:
                assert pool is not None and pool.executor is ex
                assert list(fit_pool_mod.run_tasks(pool, math.sqrt, [(1.0,), (4.0,), (9.0,)])) == [1.0, 2.0, 3.0]
            assert kept.submit(os.getpid).result(timeout=60) == pid  # the fit does not close it
        assert esfr_pool.kept_pool() is None
        with pytest.raises(RuntimeError):  # closed with the keeper
            ex.submit(os.getpid)
        with esfr_pool.fit_pool(1) as ex2:  # no keeper: closed with its own block
            pass
        if ex2 is not None:
            with pytest.raises(RuntimeError):
                ex2.submit(os.getpid)
