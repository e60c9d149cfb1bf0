"""Memory and temporary disk a composite from depth from focus needs, checked before the work starts.

Compositing streams the frames: every pass (registration, focus volume, fusion, depth map, blending, fine
detail) holds a few frames' float32 planes and a few full-size maps, never the stack, so its peak memory grows
with the image's pixels and channels, not with the number of frames (measured, docs/benchmarks.md section
``bench_big_stack``: 10 and 30 frames of 12 MP peak within 5 % of each other). The registered frames go to an
unlinked temporary file (:class:`fieldcal.composite.source.HeldFrames`) beyond a small budget: that takes disk,
``frames x pixels x channels x 2`` bytes (8-bit frames are held as 16-bit fixed point), and the page cache,
which the kernel gives back under pressure.

:func:`check_memory` refuses, with a :class:`~fieldcal.errors.ResourceError` saying what to do, a composite whose
measured peak would not fit the memory available (or ``max_memory_bytes``): the kernel's out-of-memory killer
would otherwise end it minutes in, with no message. :func:`check_temp_space` does the same for the temporary file.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from ..errors import ParameterError, ResourceError

#: Peak resident memory of ``fieldcal composite`` without a profile (depth from focus, a scene with depth: the
#: most memory of its paths) per pixel and channel, and what the process holds before any image (interpreter,
#: NumPy, OpenCV, SciPy). Measured with ``/usr/bin/time -v`` (benchmarks/bench_big_stack.py) on RGB stacks:
#: 2048x1536 7-10 frames 633-659 MiB, 4000x3000 10-30 frames (JPEG, 16-bit TIFF) 1990-2079 MiB, 6000x4000 60
#: frames 3933 MiB; the estimate is above each (868, 2185, 3970 MiB).
BYTES_PER_SAMPLE = 52.0
BASE_BYTES = 400 * 2 ** 20
#: Headroom on top of the estimate: other processes' memory changes while a composite runs for minutes.
HEADROOM = 1.1

GB = 1e9


def estimate_peak_bytes(width: int, height: int, channels: int) -> int:
    """Estimated peak resident memory (bytes) of a composite by depth from focus of ``width x height`` frames
    with ``channels`` channels, any number of frames (:data:`BYTES_PER_SAMPLE`, :data:`BASE_BYTES`)."""
    return int(BASE_BYTES + BYTES_PER_SAMPLE * int(width) * int(height) * int(channels))


def available_memory_bytes() -> int | None:
    """Memory this process may still take (bytes): the kernel's ``MemAvailable`` (free memory plus the page cache
    it can drop), capped by a cgroup v2 limit (a container's ``memory.max`` less its ``memory.current``); None
    where neither can be read (not Linux)."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        avail = None
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            room = max(0, int(limit) - used)
            avail = room if avail is None else min(avail, room)
    except (OSError, ValueError):
        pass
    return avail


def parse_memory_bytes(value, field: str = "max_memory") -> int | None:
    """A memory size from a number of bytes, or a string with a unit (``"8G"``, ``"512M"``, ``"8 GB"``;
    powers of 1024 for K/M/G/T, as ``free -h`` shows them); None stays None."""
    if value is None:
        return None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        n = float(value)
    else:
        text = str(value).strip().upper().removesuffix("IB").removesuffix("B").strip()
        mult = {"K": 2 ** 10, "M": 2 ** 20, "G": 2 ** 30, "T": 2 ** 40}.get(text[-1:], 1) if text else 1
        try:
            n = float(text[:-1] if mult != 1 else text) * mult
        except ValueError:
            n = float("nan")
    if not (n == n and n > 0):
        raise ParameterError(f"memory limit {value!r} is not a size", field=field,
                             fix="give a size such as 8G, 512M or a number of bytes")
    return int(n)


def check_memory(width: int, height: int, channels: int, n_frames: int, *, max_memory_bytes: int | None = None,
                 where=None) -> dict:
    """Refuse a composite whose estimated peak (:func:`estimate_peak_bytes`, with :data:`HEADROOM`) exceeds
    ``max_memory_bytes`` (the whole process's), or whose images' part (the estimate less :data:`BASE_BYTES`,
    which the process already holds) exceeds :func:`available_memory_bytes`. Returns what was checked.

    Raises
    ------
    ResourceError
        Naming the need, the limit and what to do.
    """
    need = estimate_peak_bytes(width, height, channels)
    given = max_memory_bytes is not None
    limit = max_memory_bytes if given else available_memory_bytes()
    info = {"estimated_peak_bytes": need, "limit_bytes": limit, "limit_from": "max_memory" if given else "available"}
    # a limit given is the whole process's; the memory available now excludes what the process already holds
    # (the interpreter and libraries, BASE_BYTES): only the images' part must fit in it
    base = 0 if given else BASE_BYTES
    if limit is None or (need - base) * HEADROOM <= limit:
        return info
    # what fits: the largest image of this aspect ratio and channels within the limit
    room = max(0.0, limit / HEADROOM - (BASE_BYTES - base))
    scale = min(1.0, (room / max(BYTES_PER_SAMPLE * width * height * channels, 1.0)) ** 0.5)
    fits = f"{int(width * scale)}x{int(height * scale)}" if scale > 0.05 else "no image of this size"
    source = "the limit given (max_memory)" if max_memory_bytes is not None else "the memory available now"
    raise ResourceError(
        f"compositing {n_frames} frames of {width}x{height} px x {channels} channel(s) by depth from focus needs "
        f"about {(need - base) * HEADROOM / GB:.1f} GB {'more ' if base else ''}of memory at its peak (whatever "
        f"the number of frames); {source} is {limit / GB:.1f} GB. Frames of up to about {fits} px would fit",
        path=where, field="max_memory",
        fix="free memory (close other programs) and run again; or composite frames downscaled or cropped to that "
            "size; or, with a profile, use the profile method (it streams in bands); --max-memory SIZE sets the "
            "limit when you know more can be used (e.g. swap)")


def check_temp_space(nbytes: int, what: str) -> None:
    """Refuse to start when the temporary folder (``TMPDIR``, :func:`tempfile.gettempdir`) has less than
    ``nbytes`` free for ``what``: the work would stop with 'disk full' minutes in."""
    folder = tempfile.gettempdir()
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < nbytes:
        raise ResourceError(f"{what} need {nbytes / GB:.1f} GB of temporary disk space; {folder} has "
                            f"{free / GB:.1f} GB free", path=folder, field="TMPDIR",
                            fix=f"free space there, or set the environment variable TMPDIR to a folder on a disk "
                                f"with {nbytes / GB:.0f} GB free (e.g. TMPDIR=/data/tmp fieldcal composite ...)")


#: glibc's allocator for a compositing process (:func:`tune_allocator`): at most this many arenas, blocks up to
#: this size taken from the heap rather than mapped afresh, and freed heap kept up to this much. One arena: a
#: second one (the threads') lives in 64 MB heaps that glibc unmaps when they empty and maps again on the next
#: plane, each time faulted and zeroed afresh; with one (and NumPy's huge pages off), the 7-frame board faulted
#: 268-291 k instead of 341-408 k pages (4 kB) and peaked 686-703 instead of 718-789 MiB, user time the same
#: (docs/benchmarks.md ``bench_composite_speed_s16``).
MALLOC_ARENAS = 1
MALLOC_MMAP_THRESHOLD_BYTES = 32 * 2 ** 20
MALLOC_TRIM_THRESHOLD_BYTES = 256 * 2 ** 20


def tune_allocator() -> bool:
    """Set glibc's ``malloc`` for compositing (Linux only; call before any thread starts): False where it cannot.

    Compositing makes and drops full-size planes (12 MB at 2048 x 1536) thousands of times. By default glibc maps
    each one afresh and gives it back on free, so the kernel zeroes its pages again on first touch (a tenth of the
    CPU of ``fieldcal composite`` on the 7-frame 2048 x 1536 circuit board went to that), and every thread that
    allocates gets its own arena, which keeps its own free memory. One arena (:data:`MALLOC_ARENAS`), planes from
    the heap (blocks below :data:`MALLOC_MMAP_THRESHOLD_BYTES`) and freed heap kept up to
    :data:`MALLOC_TRIM_THRESHOLD_BYTES`: half the page faults, and a peak resident memory 5-13 % lower on the real
    board (7 and 10 frames), not higher (docs/benchmarks.md ``bench_composite_speed_s13``).

    NumPy's transparent huge pages are turned off too (:func:`no_huge_pages`). Settings of the process as a whole:
    the ``fieldcal composite`` command sets them; a program calling the library decides for itself.
    """
    import ctypes
    import sys

    no_huge_pages()
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt  # glibc's; musl has none
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8
    return all(mallopt(param, value) == 1 for param, value in ((m_arena_max, MALLOC_ARENAS),
                                                                (m_mmap_threshold, MALLOC_MMAP_THRESHOLD_BYTES),
                                                                (m_trim_threshold, MALLOC_TRIM_THRESHOLD_BYTES)))


def no_huge_pages() -> bool:
    """Stop NumPy asking the kernel for transparent huge pages for its large arrays (``madvise(MADV_HUGEPAGE)`` on
    every array of 4 MB or more, NumPy's default); returns whether NumPy had been asking.

    A huge page is zeroed whole (2 MB) on its first touch, and the kernel zeroes it again each time the allocator
    has given the memory back. On the 7-frame 2048 x 1536 board (``fieldcal composite``, no profile) the kernel's
    ``clear_page_erms`` under huge-page faults took 10 % of the process's CPU; without them the system time fell from
    1.9-2.1 s to 1.1-1.2 s and the user time stayed the same, 10.9-11.2 s: the planes are streamed through once or
    twice each, so the fewer TLB misses of huge pages buy nothing back (docs/benchmarks.md
    ``bench_composite_speed_s16``). The same as ``NUMPY_MADVISE_HUGEPAGE=0`` in the environment before NumPy loads.
    """
    import numpy as np

    core = getattr(np, "_core", None) or getattr(np, "core", None)
    setter = getattr(getattr(core, "multiarray", None), "_set_madvise_hugepage", None)
    if setter is None:  # a NumPy without the switch (it has had it since 1.20)
        return False
    return bool(setter(False))


def single_threaded_blas() -> None:
    """BLAS (NumPy's and SciPy's OpenBLAS) on one thread for the rest of the process.

    Compositing's matrix products are thin (a whole image's pixels by 3 channels, 3 x 3 solves): memory-bound,
    no faster on several threads, and after each one OpenBLAS's threads spin waiting for more (~2 % of the CPU of
    ``fieldcal composite`` on the real 7-frame board) while the compositor's own threads have both cores busy.
    A limit set through threadpoolctl reaches only the libraries loaded when it is set (NumPy's); SciPy's OpenBLAS
    loads with ``scipy.linalg``, which compositing does not import, and reads ``OPENBLAS_NUM_THREADS`` when it
    loads, so that is set instead of importing ``scipy.linalg`` (~50 ms of start-up) only to limit it.
    """
    import os

    from threadpoolctl import threadpool_limits

    os.environ["OPENBLAS_NUM_THREADS"] = "1"  # BLAS libraries loaded from now on (SciPy's, if ever)
    threadpool_limits(limits=1, user_api="blas")


def single_threaded_opencv() -> None:
    """OpenCV's own parallel loops on one thread for the rest of the process.

    Compositing runs its planes, tiles and row bands on its own threads, a core each; OpenCV splitting each of
    their filters, warps and resamplings over its thread pool again only adds hand-overs, and its pool's threads
    spin waiting for the next loop. On the 7-frame 2048 x 1536 board that was ~0.3 s of the ~10 s of CPU, the
    output the same to the bit (docs/benchmarks.md ``bench_composite_speed_s18``; the calibration's tile pass
    found the same, :mod:`fieldcal.measure.tiles`). Like :func:`single_threaded_blas`, set by the
    ``fieldcal composite`` command; a program calling the library decides for itself.
    """
    import cv2

    cv2.setNumThreads(1)
