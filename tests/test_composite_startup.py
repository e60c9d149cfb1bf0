"""Frames decoded during `fieldcal composite`'s start-up (composite/source.py prefetch_frames): handed over only
when they are the very file the compositor would read, never left behind, and the composite is the same."""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
import pytest

from fieldcal.composite import source
from fieldcal.formats.importer import import_stack
from fieldcal.formats.stack import Stack


def _jpeg_stack(tmp_path, n=4, seed=0):
    rng = np.random.default_rng(seed)
    folder = tmp_path / "jpg"
    folder.mkdir()
    base = cv2.GaussianBlur(rng.uniform(0, 255, (96, 128, 3)).astype(np.float32), (0, 0), 2.0)
    paths = []
    for k in range(n):
        p = folder / f"f{k}.jpg"
        cv2.imwrite(str(p), np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8))
        paths.append(p)
    out = tmp_path / "stack"
    # z in reverse file order: the prefetch follows z, as registration reads
    import_stack(paths[::-1], out, z_start_um=0, z_step_um=5, pixel_pitch_um=2)
    return out


@pytest.fixture(autouse=True)
def _no_leftover():
    yield
    source.end_prefetch()


def test_prefetched_frames_are_the_reads_and_are_taken_once(tmp_path):
    folder = _jpeg_stack(tmp_path)
    source.prefetch_frames(folder)
    st = Stack.open(folder, verify=False)
    for i in (int(k) for k in st.order_by_z):
        got = source.take_prefetched(st, i)
        assert got is not None and np.array_equal(got, st.read(i))
        assert source.take_prefetched(st, i) is None  # handed over once: not held twice
    source.end_prefetch()
    assert source.take_prefetched(st, 0) is None


def test_a_frame_changed_after_its_decode_is_not_handed_over(tmp_path):
    folder = _jpeg_stack(tmp_path)
    source.prefetch_frames(folder)
    st = Stack.open(folder, verify=False)
    source._PREFETCH.thread.join(10)
    victim = st.frames[int(st.order_by_z[0])].path
    img = cv2.imread(str(victim))
    cv2.imwrite(str(victim), 255 - img)  # a new file content (size or mtime differ)
    later = time.time() + 5
    os.utime(victim, (later, later))
    assert source.take_prefetched(st, int(st.order_by_z[0])) is None
    assert source.take_prefetched(st, int(st.order_by_z[1])) is not None


def test_budget_limits_the_frames_decoded_and_the_rest_are_read(tmp_path):
    folder = _jpeg_stack(tmp_path)
    st = Stack.open(folder, verify=False)
    one = 96 * 128 * 3
    source.prefetch_frames(folder, budget_bytes=2 * one)
    order = [int(k) for k in st.order_by_z]
    assert [source.take_prefetched(st, i) is not None for i in order] == [True, True, False, False]


def test_a_broken_stack_leaves_the_error_to_the_compositor(tmp_path):
    source.prefetch_frames(tmp_path / "nothing-here")
    source._PREFETCH.thread.join(10)
    st = Stack.open(_jpeg_stack(tmp_path), verify=False)
    assert source.take_prefetched(st, 0) is None


def test_cli_composite_with_prefetch_equals_the_library_call(tmp_path, monkeypatch):
    from fieldcal.cli import main
    from fieldcal.composite.api import composite_to_file
    import tifffile

    folder = _jpeg_stack(tmp_path, n=5, seed=3)
    taken, take = [], source.take_prefetched
    monkeypatch.setattr(source, "take_prefetched", lambda st, i: taken.append(take(st, i)) or taken[-1])
    assert main(["composite", str(folder), "--out", str(tmp_path / "cli.tiff"), "--quiet"]) == 0
    assert source._PREFETCH is None  # nothing left held after the command
    assert len(taken) == 5 and all(t is not None for t in taken)  # registration read the decoded frames
    composite_to_file(folder, tmp_path / "lib.tiff", quiet=True)
    assert np.array_equal(tifffile.imread(tmp_path / "cli.tiff"), tifffile.imread(tmp_path / "lib.tiff"))


def test_single_threaded_blas_reaches_scipy_blas_loaded_later():
    import subprocess
    import sys

    code = ("import sys; from fieldcal.composite.memory import single_threaded_blas; single_threaded_blas(); "
            "assert 'scipy.linalg' not in sys.modules; import scipy.linalg; from threadpoolctl import "
            "threadpool_info; print(sorted({d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas'}))")
    env = dict(os.environ)
    env.pop("OPENBLAS_NUM_THREADS", None)
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[1]"


def test_cli_start_imports_no_compositor_before_the_prefetch(tmp_path):
    """`fieldcal composite` starts decoding before importing the compositor (fieldcal.composite is lazy)."""
    import subprocess
    import sys

    code = "import sys, fieldcal.composite; print('fieldcal.composite.api' in sys.modules, 'scipy' in sys.modules)"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.stdout.split() == ["False", "False"], out.stderr


def test_exit_while_the_prefetch_decodes_keeps_the_exit_status(tmp_path):
    """A process that ends (an error reported, Ctrl-C) after end_prefetch() while the prefetch thread is inside a
    frame's decode exits with its own status, not SIGABRT (a daemon thread ended by pthread_exit inside OpenCV's
    C++ decoder at interpreter shutdown: "terminate called without an active exception")."""
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    shots = tmp_path / "shots"
    shots.mkdir()
    base = rng.integers(0, 65535, (1080, 1920, 3), dtype=np.uint16)  # noise: a slow PNG decode (~0.1 s)
    paths = []
    for k in range(6):
        p = shots / f"f{k}.png"
        cv2.imwrite(str(p), np.roll(base, k, axis=1), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        paths.append(p)
    folder = tmp_path / "stack"
    import_stack(paths, folder, z_start_um=0, z_step_um=5, pixel_pitch_um=2)
    code = ("import sys, time\nfrom fieldcal.composite import source\nsource.prefetch_frames(sys.argv[1])\n"
            "source._PREFETCH.ready.wait()\ntime.sleep(float(sys.argv[2]))\nsource.end_prefetch()\nsys.exit(2)\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    codes = [subprocess.run([sys.executable, "-c", code, str(folder), str(pause)], env=env, capture_output=True,
                            text=True, timeout=120).returncode for pause in (0.05, 0.1, 0.15, 0.2, 0.25, 0.3)]
    assert codes == [2] * len(codes)


def test_stale_pixels_of_a_file_rewritten_in_the_same_tick_are_not_handed_over(tmp_path):
    """Review finding (s17-review D2): the file key (path, inode, size, mtime) cannot tell a file rewritten in
    place within one mtime tick; a frame decoded before such a rewrite back to its recorded content was handed
    over while the stack's sha256 check (which hashes the file as it is now) passed. The decoded bytes are hashed
    and must match the recorded sha256."""
    folder = _jpeg_stack(tmp_path)
    st = Stack.open(folder, verify=False)
    k = int(st.order_by_z[0])
    victim = st.frames[k].path
    assert st.frames[k].sha256 is not None
    good = victim.read_bytes()
    bad = bytearray(good)
    bad[len(bad) // 2] ^= 0x55  # the same size: a different content that still decodes
    victim.write_bytes(bytes(bad))
    stat = os.stat(victim)
    source.prefetch_frames(folder)
    source._PREFETCH.thread.join(10)
    victim.write_bytes(good)  # back to the recorded content, same size, same mtime
    os.utime(victim, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert source.take_prefetched(st, k) is None
    assert source.take_prefetched(st, int(st.order_by_z[1])) is not None
