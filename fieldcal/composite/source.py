"""How compositing reads frames: any :class:`fieldcal.formats.frames.FrameSource`.

The on-disk ``fieldcal.formats.stack.Stack`` and the in-memory :class:`ArrayStack` (both in
:mod:`fieldcal.formats`) are the sources; compositing uses ``z_um``, ``shape``, ``channels``, ``dtype``,
``black_level``, ``white_level``, ``len()`` and ``read(i, roi)``. :func:`read_roi` is the one place that knows
how a region of a frame is asked for; :class:`RowReader` is the fast path for uncompressed TIFF frames.
:class:`HeldFrames` holds frames decoded (JPEG, PNG: :func:`hold_decoded`) or registered once, so that
compositing's several passes read each file once.
"""

from __future__ import annotations

import mmap
import os

import numpy as np

from ..formats.frames import ArrayStack, FrameSource

__all__ = ["ArrayStack", "FrameSource", "HeldFrames", "RowReader", "hold_decoded", "image_size", "read_frames_parallel",
           "read_roi", "roi_readable", "z_positions"]


def read_roi(stack, i: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels ``[y0:y1, x0:x1]`` of frame ``i`` (file order) as ``h x w x C`` in the file's dtype.

    The region is given to ``stack.read`` as ``roi=(x, y, w, h)`` (the Stack API) so only that part is
    decoded where the file allows it (uncompressed or tiled TIFF).
    """
    a = stack.read(i, roi=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)))
    return a if a.ndim == 3 else a[..., None]


def z_positions(stack) -> np.ndarray:
    """Stage positions (µm) of the frames in file order."""
    return np.asarray(stack.z_um, dtype=np.float64)


def image_size(stack) -> tuple[int, int]:
    """``(W, H)`` of the stack's frames."""
    h, w = stack.shape[:2]
    return int(w), int(h)


class RowReader:
    """Regions of a stack's frames for the streaming accumulator, fast on uncompressed TIFF frames.

    A region is read with ``Stack.read(i, roi)`` (the Stack API) unless the frame is an uncompressed,
    contiguous, native-order integer TIFF (what the simulator and ``StackWriter`` write): then the rows holding
    it are memory-mapped with :mod:`mmap` and only the region is copied out (only its pages are touched), and
    the map is closed at once so the process's resident memory stays small. That skips ``numpy.memmap``'s and
    the Stack API's per-call overhead (~0.6 ms per region; a 4K run reads ~2000 regions). Anything unusual (float frames, which need the NaN check, compressed or planar files, a
    file that changed or vanished) takes the Stack API, which also gives the clear error.
    """

    def __init__(self, stack):
        self.stack = stack
        self._layouts: dict[int, tuple | None] = {}

    def prepare(self, indices) -> None:
        """Probe the frame files once, before threads share the reader."""
        for i in indices:
            self._layouts[int(i)] = self._layout(int(i))

    def _layout(self, i: int):
        frames = getattr(self.stack, "frames", None)  # FrameInfo of an on-disk Stack; an ArrayStack has none
        if frames is None or self.stack.cfa:
            return None
        try:
            from fieldcal.formats.imageio import probe
            hdr = probe(frames[i].path)
        except Exception:  # the Stack API will report it properly
            return None
        h, w = self.stack.shape[:2]
        dt = np.dtype(hdr.file_dtype) if hdr.file_dtype else None
        if (hdr.kind != "tiff" or hdr.mmap_offset is None or hdr.planar or dt is None or dt.kind not in "ui"
                or dt.byteorder not in ("=", "|", "<" if np.little_endian else ">")
                or (hdr.height, hdr.width) != (h, w) or hdr.dtype != np.dtype(self.stack.dtype)):
            return None
        return frames[i].path, int(hdr.mmap_offset), w, int(hdr.n_channels), np.dtype(hdr.dtype)

    def read(self, i: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """Pixels ``[y0:y1, x0:x1]`` of frame ``i`` as ``h x w x C`` in the file's dtype (a new array)."""
        lay = self._layouts.get(int(i))
        if lay is None:
            return read_roi(self.stack, i, x0, y0, x1, y1)
        path, base, width, nch, dtype = lay
        row_bytes = width * nch * dtype.itemsize
        start = base + y0 * row_bytes
        aligned = start - start % mmap.ALLOCATIONGRANULARITY
        length = start - aligned + (y1 - y0) * row_bytes
        try:
            with open(path, "rb") as f:
                mm = mmap.mmap(f.fileno(), length, offset=aligned, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # vanished or truncated: the Stack API raises the clear error
            return read_roi(self.stack, i, x0, y0, x1, y1)
        try:
            rows = np.frombuffer(mm, dtype=dtype, count=(y1 - y0) * width * nch, offset=start - aligned)
            box = rows.reshape(y1 - y0, width, nch)[:, x0:x1].copy()  # touches only the box's pages
            del rows
        finally:
            mm.close()
        return box


# ------------------------------------------------------------------------------------- frames held once
#: Frames compositing keeps decoded (or registered) for its several passes are held in memory up to this many
#: bytes; the frames beyond it are streamed from an unlinked temporary file (the page cache keeps what fits,
#: outside the process's own memory: a 7-frame 2048x1536 stack's registered frames all in memory would add 130 MB
#: to a peak that the depth-map pass sets). As many whole frames as fit are held in memory, the rest go to the
#: file: writing the board's 7 registered frames to the file and reading them back (~33 frame reads) took ~0.3 s
#: of CPU, the kernel's copies (docs/benchmarks.md ``bench_composite_speed_s18``).
MEMORY_BUDGET_BYTES = 96 * 2 ** 20


def roi_readable(stack, i: int) -> bool:
    """Whether a region of frame ``i`` is read without decoding the whole frame: frames already in memory, or an
    uncompressed contiguous TIFF (memory-mapped). JPEG, PNG and compressed TIFF decode the whole frame per read."""
    infos = getattr(stack, "frames", None)
    if infos is None or callable(infos):  # an ArrayStack: in memory (a lazy one renders on demand, uncached)
        return not getattr(stack, "_lazy", False)
    try:
        from ..formats.imageio import probe
        return probe(infos[int(i)].path).mmap_offset is not None
    except Exception:  # the Stack API reports a bad file when it is read
        return True


class HeldFrames:
    """A :class:`FrameSource` standing for ``source`` whose frames ``indices`` are held once, in memory (as many
    as fit in ``budget_bytes``, the others in a temporary file), in ``storage`` dtype: decoded frames, or frames
    already warped into the output geometry (:func:`fieldcal.composite.register.register_stack`).

    ``dtype``, levels, channels, ``z_um`` and ``path`` are the source's (the composite keeps the input's dtype);
    ``read`` returns the held samples (``storage`` dtype), or, with a fixed-point ``scale`` (samples held as
    ``value * scale``), new float32 arrays of the values. Frames not held are read from the source, unless
    ``strict`` (held frames were warped: the source's would be in another geometry).
    """

    def __init__(self, source, indices, storage, *, strict: bool = False, scale: float = 1.0,
                 budget_bytes: int | None = None):
        import tempfile

        self.source = source
        self.z_um = np.asarray(source.z_um, dtype=np.float64)
        self.shape = tuple(source.shape)
        self.channels = tuple(source.channels)
        self.cfa = None
        self.dtype = np.dtype(source.dtype)
        self.black_level = float(source.black_level)
        self.white_level = float(source.white_level)
        self.pixel_pitch_um = getattr(source, "pixel_pitch_um", None)
        self.path = getattr(source, "path", None)
        self.meta = dict(getattr(source, "meta", {}) or {})
        self.photometric: dict | None = None  # register_stack: the exposure and colour corrections applied
        self.strict = bool(strict)
        self.scale = float(scale)
        #: ``read`` returns a new float32 array (fixed point scaled back): callers need not copy it
        self.reads_new_float32 = self.scale != 1.0
        self.slot = {int(i): k for k, i in enumerate(indices)}
        h, w = self.shape
        self.storage = np.dtype(storage)
        self.frame_shape = (h, w, len(self.channels))
        self.frame_bytes = h * w * len(self.channels) * self.storage.itemsize
        budget = MEMORY_BUDGET_BYTES if budget_bytes is None else budget_bytes
        #: slots ``0 .. n_in_memory - 1`` are held in memory, the others in the temporary file
        self.n_in_memory = min(len(self.slot), max(0, int(budget)) // max(1, self.frame_bytes))
        self.in_memory = self.n_in_memory == len(self.slot)
        # in memory: one array a frame, the one handed to put where it is already in the storage's layout (a decoded
        # or warped frame, not copied again into fresh pages: 7 decoded 2048 x 1536 frames took 0.15 s of copying)
        self.data = [None] * self.n_in_memory
        n_file = len(self.slot) - self.n_in_memory
        if n_file:
            from .memory import check_temp_space
            check_temp_space(n_file * self.frame_bytes, f"{n_file} frames held for compositing")
        # unlinked at once: nothing is left behind, whatever happens
        self._file = None if not n_file else tempfile.TemporaryFile(prefix="fieldcal-frames-")

    def __len__(self) -> int:
        return int(self.z_um.size)

    @property
    def order_by_z(self) -> np.ndarray:
        return np.argsort(self.z_um, kind="stable")

    def put(self, i: int, image: np.ndarray, *, held_units: bool = False) -> None:
        """Hold ``image`` (``H x W x C``) as frame ``i``: cast to the storage dtype (integers rounded, clipped), and
        scaled to fixed point unless ``held_units`` (already in the storage's dtype and units). In memory, an image
        already contiguous in the storage dtype is held as it is, not copied: the caller hands it over and must not
        change it afterwards."""
        image = np.asarray(image)
        if not held_units:
            if self.scale != 1.0:
                image = image.astype(np.float32) * np.float32(self.scale)
            if self.storage.kind in "ui" and image.dtype.kind == "f":
                lim = np.iinfo(self.storage)
                image = np.clip(np.rint(image), lim.min, lim.max)
        image = np.ascontiguousarray(image.reshape(self.frame_shape), dtype=self.storage)
        k = self.slot[int(i)]
        if k < self.n_in_memory:
            self.data[k] = image
        else:
            import errno
            try:
                os.pwrite(self._file.fileno(), memoryview(image).cast("B"), self._offset(k))
            except OSError as e:
                if e.errno not in (errno.ENOSPC, errno.EDQUOT):
                    raise
                import tempfile

                from ..errors import ResourceError
                raise ResourceError(f"the temporary disk filled while holding frames for compositing "
                                    f"({(len(self.slot) - self.n_in_memory) * self.frame_bytes / 1e9:.1f} GB in all)",
                                    path=tempfile.gettempdir(), field="TMPDIR",
                                    fix="free space there, or set the environment variable TMPDIR to a folder on "
                                        "a disk with that much free") from None

    def _offset(self, k: int) -> int:
        """Where slot ``k`` (one held in the file) starts in the temporary file."""
        return (k - self.n_in_memory) * self.frame_bytes

    def _rows(self, k: int, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0:y1`` of held frame ``k`` (a view in memory, a new array from the file)."""
        if k < self.n_in_memory:
            return self.data[k][y0:y1]
        import os
        row = self.frame_bytes // self.frame_shape[0]
        out = np.empty((y1 - y0, *self.frame_shape[1:]), dtype=self.storage)
        buf = memoryview(out).cast("B")
        done = 0
        while done < len(buf):  # pread may return less than asked
            n = os.preadv(self._file.fileno(), [buf[done:]], self._offset(k) + y0 * row + done)
            if n <= 0:
                raise OSError("the temporary file of held frames is shorter than written")
            done += n
        return out

    def read(self, i: int, roi=None) -> np.ndarray:
        k = self.slot.get(int(i))
        if k is None:
            if self.strict:
                raise ValueError(f"frame {i} was not registered with the others")
            return self.source.read(i, roi)
        h, w = self.shape
        x, y, rw, rh = (0, 0, w, h) if roi is None else (int(v) for v in roi)
        a = self._rows(k, y, y + rh)
        if (x, rw) != (0, w):
            a = a[:, x:x + rw]
        if self.scale != 1.0:
            out = a.astype(np.float32)
            out *= np.float32(1.0 / self.scale)
            return out
        return a

    def read_rows_into(self, i: int, y0: int, y1: int, channels, outs) -> bool:
        """Rows ``y0:y1`` of held frame ``i``, channel ``channels[j]`` written into ``outs[j]`` (float32,
        ``(y1 - y0) x W``) in one pass: the cast, the fixed-point scale and the channel split that ``read`` and a
        copy per channel would make in three (the same numbers). False, writing nothing, for a frame not held."""
        k = self.slot.get(int(i))
        if k is None:
            return False
        a = self._rows(k, int(y0), int(y1))
        inv = np.float32(1.0 / self.scale)
        for c, o in zip(channels, outs):
            if self.scale != 1.0:
                np.multiply(a[..., c], inv, out=o)
            else:
                np.copyto(o, a[..., c], casting="unsafe")
        return True

    #: ``(raw - black) / (white - black)`` as float32: the same as an in-memory stack's
    read_normalized = ArrayStack.read_normalized

    def require_frames(self, n: int, operation: str) -> None:
        self.source.require_frames(n, operation)


def default_workers() -> int:
    """Threads for compositing: the CPUs this process may use (at most 4: memory bandwidth bound beyond)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(4, n))


def read_frames_parallel(stack, indices, consume, workers: int | None = None, *, desc: str = "",
                         quiet: bool = True) -> None:
    """Decode frames ``indices`` on a few threads (decoders release the GIL) and pass each, in order, to
    ``consume(i, image)`` in this thread; at most ``2 * workers`` frames are in flight. With ``desc`` and not
    ``quiet``, a progress bar counts the frames."""
    from concurrent.futures import ThreadPoolExecutor

    from ..progress import progress

    indices = [int(i) for i in indices]
    bar = iter(progress(range(len(indices)), total=len(indices), desc=desc, quiet=quiet or not desc, unit="frame"))
    workers = default_workers() if workers is None else max(1, int(workers))
    if workers == 1 or len(indices) < 2:
        for i in indices:
            consume(i, read_roi(stack, i, 0, 0, *image_size(stack)))
            next(bar, None)
        next(bar, None)  # closes the bar
        return
    w, h = image_size(stack)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending = [pool.submit(read_roi, stack, i, 0, 0, w, h) for i in indices[:2 * workers]]
        for k, i in enumerate(indices):
            image = pending[k].result()
            pending[k] = None
            nxt = k + 2 * workers
            if nxt < len(indices):
                pending.append(pool.submit(read_roi, stack, indices[nxt], 0, 0, w, h))
            consume(i, image)
            next(bar, None)
    next(bar, None)


def hold_decoded(stack, indices, quiet: bool = True):
    """``stack`` itself when its frames are read by region cheaply (:func:`roi_readable`), else the frames
    ``indices`` decoded once (in parallel) and held (:class:`HeldFrames`): compositing's passes then re-read
    memory instead of decoding every JPEG/PNG frame once per pass and per band."""
    indices = [int(i) for i in indices]
    if all(roi_readable(stack, i) for i in indices):
        return stack
    held = HeldFrames(stack, indices, stack.dtype)
    read_frames_parallel(stack, indices, held.put, desc="reading", quiet=quiet)
    return held


# ---------------------------------------------------------------------- frames decoded during start-up
class _Prefetch:
    """Frames of a stack folder decoded on a thread of their own while the process is still importing.

    ``fieldcal composite`` spends about half a second importing NumPy's and SciPy's modules on one core (imports
    hold the GIL) while the other idles; JPEG/PNG decoding releases the GIL, so the first frames registration will
    ask for (z order, within :data:`MEMORY_BUDGET_BYTES`) are decoded in that time. :func:`take_prefetched` hands a
    frame over only if its file is the one decoded (same path, inode, size and modification time); anything not
    taken is dropped by :func:`end_prefetch`. Errors are left for the compositor's own read to report.
    """

    def __init__(self, folder, budget_bytes: int):
        import threading

        self.folder = folder
        self.budget_bytes = int(budget_bytes)
        self.lock = threading.Lock()
        self.futures: dict = {}  # frame path -> Future of (file key, image)
        self.stopped = False
        self.ready = threading.Event()  # set once the frames to decode are known (or there are none)
        self.thread = threading.Thread(target=self._run, name="fieldcal-prefetch", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import hashlib
        from concurrent.futures import Future

        try:
            from ..formats.stack import Stack
            st = Stack.open(self.folder, verify=False)
            if st.cfa is not None:
                return
            plan, total = [], 0
            for i in (int(k) for k in st.order_by_z):
                if roi_readable(st, i):  # read by region from the file anyway: nothing to win
                    continue
                h, w = st.shape
                total += h * w * len(st.channels) * np.dtype(st.dtype).itemsize
                if total > self.budget_bytes:
                    break
                plan.append(i)
            pairs = [(i, Future()) for i in plan]
            with self.lock:
                self.futures.update((os.path.realpath(st.frames[i].path), fut) for i, fut in pairs)
        except Exception:  # the compositor opens the stack itself and reports what is wrong
            return
        finally:
            self.ready.set()
        while pairs:  # every future gets a result (a taker may be waiting on it); the taker's is its only reference
            i, fut = pairs.pop(0)
            if self.stopped:
                fut.set_result(None)
                continue
            try:
                # the bytes read once, hashed and decoded: the pixels handed over are provably of the content
                # the hash names (a file rewritten in place keeping its size and mtime is not mistaken for it)
                key = _file_key(st.frames[i].path)
                data = np.fromfile(st.frames[i].path, dtype=np.uint8)
                digest = hashlib.sha256(memoryview(data)).hexdigest()
                image = st.read(i, data=data)
                fut.set_result((key, digest, image) if key == _file_key(st.frames[i].path) else None)
            except BaseException:
                fut.set_result(None)
            del fut

    def take(self, path, sha256: str | None = None):
        """The frame decoded from ``path``, only if the file is still the one read (path, inode, size,
        modification time) and, with ``sha256`` (the stack's recorded digest, which its verification checks the
        file against), the bytes decoded hash to it: a file rewritten in place within the same mtime tick back to
        its recorded content would pass the first test and the verification, with stale pixels."""
        with self.lock:
            fut = self.futures.pop(os.path.realpath(path), None)
        if fut is None:
            return None
        got = fut.result()  # the thread is decoding it, or has
        if got is None:
            return None
        key, digest, image = got
        if key != _file_key(path) or (sha256 is not None and digest != str(sha256).lower()):
            return None
        return image

    def stop(self) -> None:
        with self.lock:
            self.stopped = True
            self.futures.clear()


_PREFETCH: _Prefetch | None = None


def _file_key(path):
    s = os.stat(path)
    return (os.path.realpath(path), s.st_ino, s.st_size, s.st_mtime_ns)


def prefetch_frames(folder, budget_bytes: int | None = None) -> None:
    """Start decoding the first frames (z order) of the stack folder ``folder`` on a thread (see :class:`_Prefetch`);
    :func:`take_prefetched` gives them to the compositor. For ``fieldcal composite``, before its heavy imports."""
    global _PREFETCH
    end_prefetch()
    _PREFETCH = _Prefetch(folder, MEMORY_BUDGET_BYTES if budget_bytes is None else budget_bytes)


def take_prefetched(stack, i: int) -> np.ndarray | None:
    """Frame ``i`` of ``stack`` (whole, as ``read_roi`` gives it) if :func:`prefetch_frames` decoded that very
    file, else None (and the caller reads it)."""
    pre = _PREFETCH
    infos = getattr(stack, "frames", None)
    if pre is None or infos is None or callable(infos) or getattr(stack, "cfa", None) is not None:
        return None
    pre.ready.wait()
    try:
        info = infos[int(i)]
        image = pre.take(info.path, getattr(info, "sha256", None))
    except (OSError, AttributeError, IndexError, TypeError):
        return None
    if image is None or image.shape[:2] != tuple(stack.shape[:2]) or image.dtype != np.dtype(stack.dtype):
        return None
    return image if image.ndim == 3 else image[..., None]


#: How long :func:`end_prefetch` waits for the frame the prefetch thread is decoding (a whole frame's decode, well
#: under a second for 24 MP; the bound only matters for a file that blocks, e.g. one replaced by a pipe)
PREFETCH_JOIN_S = 30.0


def end_prefetch() -> None:
    """Drop the frames :func:`prefetch_frames` decoded that were not taken, stop its thread's work and wait for the
    frame it is decoding. The wait matters on the way out: a daemon thread still inside OpenCV's decoder when the
    interpreter finalizes is ended by ``pthread_exit`` through C++ frames, and the process aborts ("terminate
    called without an active exception", SIGABRT) instead of exiting with fieldcal's status (an error, Ctrl-C)."""
    import threading

    global _PREFETCH
    pre, _PREFETCH = _PREFETCH, None
    if pre is not None:
        pre.stop()
        if pre.thread is not threading.current_thread():
            pre.thread.join(PREFETCH_JOIN_S)
