"""The e-SFR of a stack in worker processes (fieldcal/measure/esfr_pool.py): the same records and tracks as the
threads' path, the same FieldcalError for a bad frame, no worker left behind after an error or Ctrl-C, and the
progress bar advancing per frame."""

from __future__ import annotations

import json
import os
import shutil
import time

import pytest
import tifffile

import fieldcal.measure.mtf as mtf
import fieldcal.progress
from fieldcal.cli import main
from fieldcal.errors import FieldcalError, StackError
from fieldcal.formats.stack import Stack
from fieldcal.measure import esfr_pool

N_FRAMES = 5


@pytest.fixture(scope="module")
def edge_stack(tmp_path_factory):
    path = tmp_path_factory.mktemp("esfrproc") / "stk"
    assert main(["simulate", "models/triplet-uncorrected.json", str(path), "--z", "-40", "40", "20",
                 "--size", "320x240", "--scene", "slanted-edge", "--quiet"]) == 0
    return path


@pytest.fixture(scope="module")
def scan_stack(tmp_path_factory):
    """A scan through the triplet's best foci (9 frames): most tracks give a peak, every channel a field-wide
    term."""
    path = tmp_path_factory.mktemp("esfrscan") / "stk"
    assert main(["simulate", "models/triplet-uncorrected.json", str(path), "--z", "-330", "30", "45",
                 "--size", "320x240", "--scene", "slanted-edge", "--quiet"]) == 0
    return path


@pytest.fixture
def paths(monkeypatch):
    """Which path measure_mtf takes: ``paths["processes"]`` counts the calls of the process path; the
    thresholds are lowered so that a 5-frame 320x240 stack goes to processes when they are allowed."""
    calls = {"processes": 0}
    real = mtf._measure_in_processes

    def spy(*args, **kwargs):
        calls["processes"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(mtf, "_measure_in_processes", spy)
    monkeypatch.setattr(mtf, "PROCESS_MIN_FRAMES", 1)
    monkeypatch.setattr(mtf, "PROCESS_MIN_MPX", 0.0)
    return calls


def _workers_alive() -> list[int]:
    """Live descendants of this process started by multiprocessing's forkserver (the server and the pool's
    workers, which share its command line); multiprocessing's resource tracker is not one of them."""
    if not os.path.isdir("/proc"):  # not Linux: nothing to look at (the tests' other assertions still run)
        return []
    parent, cmd = {}, {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = open(f"/proc/{d}/stat").read()
            line = open(f"/proc/{d}/cmdline", "rb").read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        rest = stat[stat.rindex(")") + 2:].split()
        if rest[0] != "Z":
            parent[int(d)], cmd[int(d)] = int(rest[1]), line
    me, alive = os.getpid(), []
    for pid in parent:
        p, seen = parent[pid], 0
        while p not in (0, 1, me) and p in parent and seen < 64:
            p, seen = parent[p], seen + 1
        if p == me and "multiprocessing.forkserver" in cmd[pid]:
            alive.append(pid)
    return alive


def _no_workers_left(timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while _workers_alive():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: measure_mtf uses one thread, never a pool")
def test_processes_give_the_threads_records(edge_stack, paths):
    stack = Stack.open(edge_stack)
    with esfr_pool.allow_processes(False):
        ref = mtf.measure_mtf(stack)
    assert paths["processes"] == 0
    with esfr_pool.allow_processes(True):
        got = mtf.measure_mtf(stack)
    assert paths["processes"] == 1
    assert {e["frame"] for e in got.edges} == set(range(N_FRAMES))
    assert len(ref.edges) > 100 * N_FRAMES  # ~130 edges x 3 channels per frame
    # bit-identical: JSON keeps every float's repr; records in the same (z) order with the same tracks
    a, b = ref.to_dict(), got.to_dict()
    assert json.dumps(a["edges"]) == json.dumps(b["edges"])
    assert [e["track"] for e in ref.edges] == [e["track"] for e in got.edges]
    assert _no_workers_left()


def test_in_memory_stacks_and_small_jobs_stay_on_threads(edge_stack, paths, monkeypatch):
    """An ArrayStack has no folder for a worker to read; a job under the thresholds does not pay the start-up."""
    from fieldcal.formats.frames import ArrayStack
    stack = Stack.open(edge_stack)
    arr = ArrayStack([stack.read_normalized(i) for i in range(len(stack))], stack.z_um, stack.channels,
                     pixel_pitch_um=stack.pixel_pitch_um)
    with esfr_pool.allow_processes(True):
        mtf.measure_mtf(arr)
        assert paths["processes"] == 0
        monkeypatch.setattr(mtf, "PROCESS_MIN_FRAMES", N_FRAMES + 1)
        mtf.measure_mtf(stack)
        assert paths["processes"] == 0


def test_main_module_decides_by_default():
    """A script's __main__ would run again in each worker: processes only where that is known to be harmless."""
    import sys
    import types
    saved = sys.modules["__main__"]
    try:
        script = types.ModuleType("__main__")
        script.__file__ = "/somewhere/script.py"
        sys.modules["__main__"] = script
        assert not esfr_pool.processes_allowed()
        with esfr_pool.allow_processes(True):
            assert esfr_pool.processes_allowed()
        package = types.ModuleType("__main__")
        package.__file__ = "/somewhere/fieldcal/__main__.py"
        package.__spec__ = types.SimpleNamespace(name="fieldcal.__main__")
        sys.modules["__main__"] = package
        assert esfr_pool.processes_allowed()
        with esfr_pool.allow_processes(False):
            assert not esfr_pool.processes_allowed()
    finally:
        sys.modules["__main__"] = saved


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: no pool")
def test_a_corrupt_frame_gives_the_same_error_through_processes(edge_stack, tmp_path, paths):
    bad = tmp_path / "stk"
    shutil.copytree(edge_stack, bad)
    stack = Stack.open(bad)
    middle = int(stack.order_by_z[N_FRAMES // 2])
    f = stack.frames[middle].path
    # a zlib TIFF whose compressed data are damaged: its header passes Stack.open, its pixels do not decode
    tifffile.imwrite(f, tifffile.imread(f), compression="zlib", photometric="rgb")
    data = bytearray(f.read_bytes())
    n = len(data)
    data[n // 3: n // 3 + 200] = bytes(v ^ 0x5A for v in data[n // 3: n // 3 + 200])
    f.write_bytes(bytes(data))
    stack = Stack.open(bad, verify=False)  # past the hash check: the read itself must fail clearly
    errors = []
    for allowed in (False, True):
        with esfr_pool.allow_processes(allowed), pytest.raises(FieldcalError) as info:
            mtf.measure_mtf(stack)
        errors.append(info.value)
    assert paths["processes"] == 1
    thread_err, proc_err = errors
    assert isinstance(proc_err, StackError)
    assert type(proc_err) is type(thread_err)
    assert str(proc_err) == str(thread_err)
    assert (proc_err.path, proc_err.field, proc_err.fix) == (thread_err.path, thread_err.field, thread_err.fix)
    assert proc_err.field == f"frames[{middle}].file"
    assert proc_err.__cause__ is None and proc_err.__suppress_context__  # no worker traceback chained to it
    assert _no_workers_left()


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: no pool")
def test_ctrl_c_leaves_no_worker_and_progress_advances_per_frame(edge_stack, paths, monkeypatch):
    seen = []

    def bar(futures, *, total=None, desc="", unit="it", quiet=False):
        assert (total, desc, unit) == (N_FRAMES, "e-SFR", "frame")
        for fut in futures:
            yield fut
            seen.append(fut.done())  # the loop has added this frame's result before asking for the next

    monkeypatch.setattr(fieldcal.progress, "progress", bar)
    stack = Stack.open(edge_stack)
    with esfr_pool.allow_processes(True):
        res = mtf.measure_mtf(stack, quiet=False)
    assert len(seen) == N_FRAMES and all(seen)
    assert {e["frame"] for e in res.edges} == set(range(N_FRAMES))

    during = []

    def interrupted(futures, **kwargs):
        for k, fut in enumerate(futures):
            if k == 2:
                during.extend(_workers_alive())
                raise KeyboardInterrupt
            yield fut

    monkeypatch.setattr(fieldcal.progress, "progress", interrupted)
    with esfr_pool.allow_processes(True), pytest.raises(KeyboardInterrupt):
        mtf.measure_mtf(stack, quiet=False)
    assert paths["processes"] == 2
    if os.path.isdir("/proc"):
        assert len(during) >= 2  # the forkserver and at least one worker were running when Ctrl-C came
    assert _no_workers_left()


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: no pool")
def test_track_fits_in_processes_give_the_same_table(scan_stack, monkeypatch):
    """edge_table's channels fitted in worker processes (all but the first) give this thread's table, summary
    and field-wide terms to the bit."""
    from fieldcal.measure import edge_tiles
    stack = Stack.open(scan_stack)
    res = mtf.measure_mtf(stack)
    h, w = stack.shape
    kw = dict(fs_cyc_per_mm=0.25 / (stack.pixel_pitch_um / 1000.0), q=0.05, pixel_pitch_um=stack.pixel_pitch_um,
              z_um=stack.z_um, image_size_px=(w, h), z_ref_um=-150.0, channels=tuple(stack.channels))
    pools = []
    real = esfr_pool.fit_pool

    def spy(workers):
        pools.append(workers)
        return real(workers)

    monkeypatch.setattr(esfr_pool, "fit_pool", spy)
    with esfr_pool.allow_processes(False):
        ref_table, ref_summary = edge_tiles.edge_table(res, **kw)
    assert pools == []
    monkeypatch.setattr(edge_tiles, "FIT_PROCESS_MIN_TRACKS", 1)
    with esfr_pool.allow_processes(True):
        table, summary = edge_tiles.edge_table(res, **kw)
    assert pools == [2]  # three channels: the first here, two in workers
    assert int(ref_table.ok.sum()) > 100
    assert all(v["sd_um"] > 0 for v in ref_summary["common_mode"].values())
    assert json.dumps(table.to_dict(), sort_keys=True, default=str) == \
        json.dumps(ref_table.to_dict(), sort_keys=True, default=str)
    assert json.dumps(summary, sort_keys=True, default=str) == json.dumps(ref_summary, sort_keys=True, default=str)
    assert _no_workers_left()
