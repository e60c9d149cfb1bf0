"""Read and write through-focus stacks in the ``fieldcal-stack/1`` folder format (DESIGN.md, docs/stack-format.md).

:class:`Stack` validates ``stack.json`` and every frame file's *header* at open (no pixels decoded), then
streams frames one at a time. :class:`StackWriter` adds frames crash-safely: frame file first (temporary name,
rename), then ``stack.json`` (atomically), so ``stack.json`` never lists a frame that is not complete on disk.

Every malformed stack raises :class:`fieldcal.errors.StackError` naming the file, the field and the fix.
"""

from __future__ import annotations

import copy
import hashlib
import math
import numbers
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Iterator

import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes, atomic_write_text
from fieldcal.errors import ParameterError, StackError
from fieldcal.formats.imageio import ImageFileError, ImageHeader, SUPPORTED_DTYPES, encode, kind_for_name, probe, read_image
from fieldcal.progress import progress

FORMAT = documents.format_id("stack")
STACK_JSON = "stack.json"
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
REQUIRED_KEYS = ("format", "pixel_pitch_um", "channels", "frames")



# ----------------------------------------------------------------------------------------------- validation
# Types, ranges and required keys are the schema's (fieldcal/formats/schemas/fieldcal-stack-1.schema.json,
# read and checked by fieldcal.formats.documents); what a schema cannot say is checked here, in one place:
# frame files inside the folder and distinct, z distinct, frame headers agreeing, levels within the dtype.


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _check_white_above_black(meta: dict, json_path: Path) -> None:
    if "black_level" in meta and "white_level" in meta and not meta["white_level"] > meta["black_level"]:
        raise StackError(f"({meta['white_level']!r}) must be above black_level ({meta['black_level']!r})",
                         path=json_path, field="white_level", fix="check the camera's black and white levels")


def _validate_meta(meta: Any, json_path: Path) -> tuple[float, tuple[str, ...]]:
    """stack.json against its schema, then the header checks a schema cannot express."""
    documents.validate(meta, "stack", json_path, error=StackError)
    _check_white_above_black(meta, json_path)
    return float(meta["pixel_pitch_um"]), tuple(meta["channels"])


def stack_chart(meta: dict, json_path: Path | None = None) -> dict | None:
    """The chart a stack shows, from stack.json's ``chart``: a record (``{"kind": "charuco", "dictionary", ...}``,
    docs/stack-format.md), or older stacks' scene name as ``{"kind": name}``; None when not recorded."""
    chart = meta.get("chart")
    if chart is None:
        return None
    if isinstance(chart, str):
        return {"kind": chart}
    if chart.get("kind") == "charuco":
        from fieldcal.charts.targets import board_from_record
        board_from_record(chart, 1, 1, json_path)  # the checks across fields the schema cannot make
    return dict(chart)


def _check_frame_entry(entry: Any, i: int, json_path: Path) -> tuple[str, float]:
    """One frames[] entry against the schema's frame definition; returns (file, z_um)."""
    documents.validate(entry, "stack", json_path, pointer="/$defs/frame", where=f"frames[{i}]", error=StackError)
    return entry["file"], float(entry["z_um"])


def _resolve_frame_path(root: Path, file: str, where: str, json_path: Path, *, symlinks_out: bool = False) -> Path:
    """The frame file inside the stack folder; refuses absolute paths and paths that escape it.

    ``symlinks_out`` (a stack made by ``fieldcal import --link symlink``, ``"links": "symlink"``) lets the frame
    file itself be a symlink to a file outside the folder; its name must still lie inside.
    """
    fix = "frame paths are relative to the stack folder and stay inside it, e.g. frames/0000.tiff"
    p = PurePosixPath(file.replace("\\", "/"))
    if p.is_absolute() or Path(file).is_absolute() or ".." in p.parts:
        raise StackError(f"{file!r} points outside the stack folder", path=json_path, field=where, fix=fix)
    full = root.joinpath(*p.parts)
    try:  # symlinks out of the folder count as escaping too
        (full.parent.resolve() if symlinks_out and full.is_symlink() else full.resolve()).relative_to(root.resolve())
    except ValueError:
        raise StackError(f"{file!r} resolves outside the stack folder", path=json_path, field=where,
                         fix=fix) from None
    except (RuntimeError, OSError):  # a loop of symbolic links (RuntimeError before Python 3.13, then ELOOP)
        raise StackError(f"{file!r} is a loop of symbolic links", path=json_path, field=where,
                         fix="replace the link with the frame file (or a link to it)") from None
    return full


def _read_json(json_path: Path) -> Any:
    return documents.read_json(json_path, error=StackError, not_found="not found: a stack folder holds a stack.json",
                               not_found_fix="give the stack folder (the one that contains stack.json)",
                               fix="repair the JSON syntax (see docs/stack-format.md for an example)")


def _levels(meta: dict, dtype: np.dtype) -> tuple[float, float]:
    """(black, white): white_level, else 2**bit_depth - 1, else dtype max (float 1.0); black_level else 0."""
    if "white_level" in meta:
        white = float(meta["white_level"])
    elif "bit_depth" in meta:
        white = float(2 ** int(meta["bit_depth"]) - 1)
    elif dtype.kind == "f":
        white = 1.0
    else:
        white = float(np.iinfo(dtype).max)
    return float(meta.get("black_level", 0.0)), white


def _check_levels(meta: dict, dtype: np.dtype, json_path: Path) -> tuple[float, float]:
    black, white = _levels(meta, dtype)
    if dtype.kind == "u":
        top = np.iinfo(dtype).max
        if "bit_depth" in meta and meta["bit_depth"] > dtype.itemsize * 8:
            raise StackError(f"is {meta['bit_depth']} but the frames are {dtype} ({dtype.itemsize * 8} bits)",
                             path=json_path, field="bit_depth", fix="set bit_depth to the camera's ADC bit depth")
        if white > top:
            raise StackError(f"({white:g}) exceeds the largest {dtype} value {top}", path=json_path,
                             field="white_level", fix="set white_level to the raw saturation value")
    if not white > black:
        raise StackError(f"black level {black:g} is not below white level {white:g}", path=json_path,
                         field="black_level", fix="check black_level / white_level / bit_depth")
    return black, white


# ----------------------------------------------------------------------------------------------- reader


@dataclass(frozen=True)
class FrameInfo:
    """One frame of a stack.

    Attributes
    ----------
    index : int
        Position in ``stack.json``'s frames list (file order).
    file : str
        Path relative to the stack folder, as written in ``stack.json``.
    path : pathlib.Path
        Absolute-or-as-given path of the frame file.
    z_um : float
        Commanded stage position (µm).
    meta : dict
        The whole frame entry (``file``, ``z_um`` and optional/unknown keys).
    """

    index: int
    file: str
    path: Path
    z_um: float
    meta: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def z_measured_um(self) -> float | None:
        v = self.meta.get("z_measured_um")
        return None if v is None else float(v)

    @property
    def exposure_ms(self) -> float | None:
        v = self.meta.get("exposure_ms")
        return None if v is None else float(v)

    @property
    def sha256(self) -> str | None:
        return self.meta.get("sha256")


def _norm_roi(roi, height: int, width: int, cfa: str | None) -> tuple[int, int, int, int] | None:
    """ROI ``(x, y, w, h)`` in px or ``(slice_y, slice_x)`` -> checked half-open ``(y0, y1, x0, x1)``."""
    if roi is None:
        return None
    if len(roi) == 2 and all(isinstance(s, slice) for s in roi):
        sy, sx = roi
        if (sy.step or 1) != 1 or (sx.step or 1) != 1:
            raise ParameterError(f"ROI slices must have step 1, got {roi!r}", field="roi",
                                 fix="read the ROI and subsample the result")
        y0, y1, _ = sy.indices(height)
        x0, x1, _ = sx.indices(width)
    elif len(roi) == 4 and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in roi):
        x0, y0, w, h = (int(v) for v in roi)
        x1, y1 = x0 + w, y0 + h
        if x0 < 0 or y0 < 0 or w < 1 or h < 1 or x1 > width or y1 > height:
            raise ParameterError(f"ROI (x={x0}, y={y0}, w={w}, h={h}) is empty or outside the "
                                 f"{width} x {height} px frame", field="roi",
                                 fix="give an ROI inside the frame: 0 <= x, x + w <= width (same for y)")
    else:
        raise ParameterError(f"ROI must be (x, y, w, h) integers or (slice_y, slice_x), got {roi!r}", field="roi",
                             fix="e.g. roi=(0, 0, 64, 64)")
    if y1 <= y0 or x1 <= x0:
        raise ParameterError(f"ROI {roi!r} is empty", field="roi", fix="give a non-empty ROI inside the frame")
    if cfa is not None and (x0 % 2 or y0 % 2):
        raise ParameterError(f"ROI origin ({x0}, {y0}) is odd on a {cfa} Bayer mosaic", field="roi",
                             fix="start CFA ROIs at even x and y so the Bayer pattern stays the same")
    return y0, y1, x0, x1


class Stack:
    """A validated ``fieldcal-stack/1`` folder whose frames are decoded lazily, one at a time.

    Use :meth:`Stack.open`. Attributes: ``path`` (folder), ``meta`` (all of stack.json, unknown keys kept),
    ``pixel_pitch_um``, ``channels``, ``cfa`` (Bayer pattern or None), ``frames`` (FrameInfo, file order),
    ``shape`` (H, W), ``dtype``, ``black_level``, ``white_level``.

    Examples
    --------
    >>> stack = Stack.open("STACK")                              # doctest: +SKIP
    >>> for info, frame in stack.iter_frames(order="z"):         # doctest: +SKIP
    ...     print(info.z_um, frame.shape)
    """

    def __init__(self, path: Path, meta: dict, frames: tuple[FrameInfo, ...], headers: tuple[ImageHeader, ...],
                 pixel_pitch_um: float, channels: tuple[str, ...]):
        self.path = path
        self.meta = meta
        self.frames = frames
        self._headers = headers
        self.pixel_pitch_um = pixel_pitch_um
        self.channels = channels
        self.cfa: str | None = meta.get("cfa")
        self.shape: tuple[int, int] = (headers[0].height, headers[0].width)
        self.dtype: np.dtype = headers[0].dtype
        self.black_level, self.white_level = _levels(meta, self.dtype)
        self._sha256_cache: dict[int, str] = {}
        self._verifying = None  # a concurrent.futures.Future while start_verify's thread runs

    # -- opening -------------------------------------------------------------------------------------------

    @classmethod
    def open(cls, path: str | os.PathLike, *, verify: bool = True) -> "Stack":
        """Open and validate a stack folder (or its stack.json) without decoding any pixels.

        With ``verify`` (the default) every frame file whose entry records a ``sha256`` is hashed and compared
        (:meth:`verify`): a frame altered, truncated or swapped since it was written is refused. Hashing reads
        each file once (about 40 ms per 1920x1080 RGB 16-bit frame); ``verify=False`` (``--no-verify``)
        skips it.

        Raises
        ------
        StackError
            Anything that does not follow ``fieldcal-stack/1``, naming the file, the field and the fix.
        """
        path = Path(path)
        if path.name == STACK_JSON and path.is_file():
            path = path.parent
        if not path.is_dir():
            raise StackError("is not a folder" if path.exists() else "does not exist", path=path,
                             fix="give the stack folder (the one that contains stack.json)")
        json_path = path / STACK_JSON
        meta = _read_json(json_path)
        pitch, channels = _validate_meta(meta, json_path)
        if not meta["frames"]:
            raise StackError("is empty: the stack has no frames", path=json_path, field="frames",
                             fix="capture at least one frame (an interrupted capture can be resumed with "
                                 "StackWriter.open_existing)")
        infos, headers = _load_frames(path, meta, json_path, len(channels), meta.get("cfa"))
        stack = cls(path, meta, infos, headers, pitch, channels)
        _check_levels(meta, stack.dtype, json_path)
        if verify:
            stack.verify()
        return stack

    # -- geometry and metadata -----------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return (f"Stack({str(self.path)!r}, {len(self)} frames, {self.shape[1]}x{self.shape[0]} px, "
                f"{self.dtype}, channels={list(self.channels)}{', cfa=' + self.cfa if self.cfa else ''})")

    @property
    def json_path(self) -> Path:
        return self.path / STACK_JSON

    @property
    def z_um(self) -> np.ndarray:
        """Stage positions (µm) in file order."""
        return np.array([f.z_um for f in self.frames], dtype=np.float64)

    @property
    def order_by_z(self) -> np.ndarray:
        """Frame indices sorted by increasing z."""
        return np.argsort(self.z_um, kind="stable")

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @property
    def bit_depth(self) -> int | None:
        return self.meta.get("bit_depth")

    def require_frames(self, n: int, operation: str) -> None:
        """Raise StackError if the stack has fewer than ``n`` frames for ``operation``."""
        if len(self) < n:
            raise StackError(f"too few frames for {operation}: it needs at least {n}, the stack has {len(self)}",
                             path=self.json_path, field="frames",
                             fix=f"capture at least {n} sensor positions for {operation}")

    # -- pixels --------------------------------------------------------------------------------------------

    def _index(self, i: int) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -len(self) <= i < len(self):
            raise ParameterError(f"frame index {i!r} is outside 0..{len(self) - 1}", path=self.json_path,
                                 field="index", fix=f"use an index from 0 to {len(self) - 1}")
        return int(i) % len(self)

    def read(self, i: int, roi=None, data: np.ndarray | None = None) -> np.ndarray:
        """Decode frame ``i`` (file order), or an ROI of it, touching no other frame.

        Parameters
        ----------
        i : int
            Index into :attr:`frames`.
        roi : (x, y, w, h) or (slice_y, slice_x), optional
            Pixel region; for a CFA stack its origin must be even.
        data : uint8 array, optional
            The PNG or JPEG file's bytes, already read (:func:`fieldcal.formats.imageio.read_image`).

        Returns
        -------
        numpy.ndarray
            H x W x C in the file's dtype (H x W for a CFA mosaic), RGB channel order.

        Raises
        ------
        StackError
            The frame file is missing, damaged, or (float) holds NaN/Inf.
        """
        i = self._index(i)
        info, header = self.frames[i], self._headers[i]
        box = _norm_roi(roi, *self.shape, self.cfa)
        where = f"frames[{i}].file"
        try:
            image = read_image(info.path, box, header) if data is None else read_image(info.path, box, header,
                                                                                        data=data)
        except FileNotFoundError:
            raise StackError(f"frame file {info.file!r} has disappeared since the stack was opened",
                             path=info.path, field=where, fix="restore the frame file or re-capture it") from None
        except ImageFileError as exc:
            raise StackError(f"frame {info.file!r} {exc.what}", path=info.path, field=where, fix=exc.fix) from None
        if image.dtype.kind == "f" and not np.isfinite(image).all():
            bad = int(np.count_nonzero(~np.isfinite(image)))
            raise StackError(f"frame {info.file!r} (z_um={info.z_um:g}) holds {bad} NaN/Inf pixel(s)",
                             path=info.path, field=where,
                             fix="replace non-finite pixels (e.g. with 0 or the saturation value) before calibrating")
        if self.cfa is None and image.ndim == 2:
            image = image[:, :, None]  # always H x W x C inside fieldcal
        elif self.cfa is not None and image.ndim == 3:
            image = image[:, :, 0]  # an H x W x 1 mosaic file
        return image

    def read_normalized(self, i: int, roi=None) -> np.ndarray:
        """Frame ``i`` as float32 ``(raw - black_level) / (white_level - black_level)`` (not clipped)."""
        image = self.read(i, roi).astype(np.float32)
        image -= np.float32(self.black_level)
        image *= np.float32(1.0 / (self.white_level - self.black_level))  # white > black checked at open
        return image

    def iter_frames(self, order: str = "z", *, roi=None, normalized: bool = False,
                    desc: str | None = None) -> Iterator[tuple[FrameInfo, np.ndarray]]:
        """Yield ``(FrameInfo, array)`` one frame at a time, by increasing z (``order="z"``) or file order.

        ``desc`` shows a progress bar with that label.
        """
        if order == "z":
            indices = [int(k) for k in self.order_by_z]
        elif order == "file":
            indices = list(range(len(self)))
        else:
            raise ParameterError(f"order must be 'z' or 'file', got {order!r}", field="order",
                                 fix="use order='z' or order='file'")
        _norm_roi(roi, *self.shape, self.cfa)  # a bad ROI fails here, not at the first frame
        reader = self.read_normalized if normalized else self.read
        it = indices if desc is None else progress(indices, total=len(indices), desc=desc, unit="frame")
        return ((self.frames[k], reader(k, roi)) for k in it)

    def frame_sha256(self, i: int) -> str:
        """sha256 of frame ``i``'s file content (hashed once, then remembered)."""
        cache = self._sha256_cache
        if i not in cache:
            info = self.frames[i]
            try:
                cache[i] = _sha256_file(info.path)
            except OSError as exc:
                raise StackError(f"frame {info.file!r} cannot be read ({exc.strerror or exc})", path=info.path,
                                 field=f"frames[{i}].file", fix="restore the frame file or check its "
                                                                "permissions") from None
        return cache[i]

    def _try_hash(self, i: int) -> None:
        """Fill the sha256 cache for frame ``i``; a read error is left for :meth:`frame_sha256` to raise."""
        try:
            self._sha256_cache[i] = _sha256_file(self.frames[i].path)
        except OSError:
            pass

    def verify(self, *, threads: int | None = None) -> None:
        """Refuse the stack if a frame file no longer matches the ``sha256`` its entry records.

        ``threads``: how many frames hash at once (default: up to 4, one per core).

        Raises
        ------
        StackError
            Naming the frames that differ and the fix (re-capture, or ``--no-verify`` to use them anyway).
        """
        todo = [i for i, info in enumerate(self.frames) if info.sha256 is not None]
        threads = min(4, os.cpu_count() or 1) if threads is None else max(1, int(threads))
        if len(todo) > 1 and threads > 1:
            # hashlib releases the GIL on large blocks: the frames hash in parallel (0.33 -> ~0.17 s for 42
            # 1080p frames on 2 cores); errors surface in frame order, as in the serial loop
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(max_workers=threads) as pool:
                list(pool.map(self._try_hash, todo))
        bad = [self.frames[i] for i in todo if self.frame_sha256(i) != str(self.frames[i].sha256).lower()]
        if bad:
            names = ", ".join(f"{b.file} (frames[{b.index}])" for b in bad[:5]) + (" ..." if len(bad) > 5 else "")
            raise StackError(f"{len(bad)} frame file(s) changed since they were written (sha256 differs): {names}",
                             path=self.json_path, field=f"frames[{bad[0].index}].sha256",
                             fix="restore or re-capture those frames; if you edited them on purpose, pass "
                                 "--no-verify (Stack.open(verify=False)) to use them as they are")

    def start_verify(self) -> None:
        """Begin :meth:`verify` in a background thread and return at once; :meth:`finish_verify` waits for it
        and raises what it found.

        For a caller with work that does not depend on the hashes: ``fieldcal calibrate`` imports its modules
        and looks at the middle frame (single-threaded, ~0.5 s) while the frames hash (hashlib and file reads
        release the GIL), then calls :meth:`finish_verify` before it measures anything. Calling it again while
        a verification runs does nothing. One thread hashes: the caller's own work keeps a core to itself (on
        two cores, two hashing threads beside it would slow it by a third).
        """
        if self._verifying is not None:
            return
        from concurrent.futures import Future
        import threading
        done: Future = Future()

        def run():
            try:
                self.verify(threads=1)
            except BaseException as exc:  # handed to finish_verify's caller, in its thread
                done.set_exception(exc)
            else:
                done.set_result(None)

        self._verifying = done
        threading.Thread(target=run, name="fieldcal-verify", daemon=True).start()

    def finish_verify(self) -> None:
        """Wait for the verification :meth:`start_verify` began (nothing to do if none) and raise its
        :class:`StackError` if a frame differs from its recorded ``sha256``."""
        done = self._verifying
        if done is None:
            return
        done.result()  # raises the verification's StackError; kept, so a second call raises it again
        self._verifying = None

    def verify_checksums(self) -> list[FrameInfo]:
        """Frames whose file no longer matches its ``sha256`` (missing files included; no sha256 = skipped)."""
        bad = []
        for info in self.frames:
            if info.sha256 is None:
                continue
            try:
                digest = _sha256_file(info.path)
            except OSError:
                bad.append(info)
                continue
            if digest != info.sha256.lower():
                bad.append(info)
        return bad


def _sha256_file(path: Path) -> str:
    # file_digest reads into one reused buffer: a new 1 MiB bytes object per block cost ~20 000 page faults
    # (0.05 s of system time) for 42 frames of 1080p RGB 16-bit
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _load_frames(root: Path, meta: dict, json_path: Path, n_channels: int,
                 cfa: str | None) -> tuple[tuple[FrameInfo, ...], tuple[ImageHeader, ...]]:
    """Validate every frame entry and frame header; the first frame fixes size, dtype and layout."""
    infos, headers = [], []
    seen_z: dict[float, int] = {}
    seen_file: dict[Path, int] = {}
    for i, entry in enumerate(meta["frames"]):
        file, z = _check_frame_entry(entry, i, json_path)
        where = f"frames[{i}].file"
        path = _resolve_frame_path(root, file, where, json_path, symlinks_out=meta.get("links") == "symlink")
        if z in seen_z:
            j = seen_z[z]
            raise StackError(f"frames[{j}] ({meta['frames'][j]['file']}) and frames[{i}] ({file}) both have "
                             f"z_um={z:g}; z values must be distinct", path=json_path, field=f"frames[{i}].z_um",
                             fix="remove the repeated frame or correct its z_um")
        seen_z[z] = i
        key = path.resolve()
        if key in seen_file:
            raise StackError(f"frames[{seen_file[key]}] and frames[{i}] both use file {file!r}", path=json_path,
                             field=where, fix="give every frame its own file")
        seen_file[key] = i
        if os.path.exists(path) and not path.is_file():
            raise StackError(f"frame file {file!r} is not a regular file (a folder, device or pipe)", path=json_path,
                             field=where, fix="replace it with the frame's image file")
        if not path.is_file():
            raise StackError(f"frame file {file!r} does not exist", path=json_path, field=where,
                             fix="restore the frame file, or remove its entry from stack.json")
        try:
            header = probe(path)
        except ImageFileError as exc:
            raise StackError(f"frame {file!r} {exc.what}", path=path, field=where, fix=exc.fix) from None
        except OSError as exc:
            raise StackError(f"frame {file!r} cannot be read ({exc.strerror or exc})", path=path, field=where,
                             fix="check the file's permissions") from None
        _check_frame_layout(header, i, file, path, where, n_channels, cfa, headers[0] if headers else None,
                            meta["frames"][0]["file"] if headers else None)
        infos.append(FrameInfo(i, file, path, z, copy.deepcopy(entry)))
        headers.append(header)
    return tuple(infos), tuple(headers)


def _check_frame_layout(h: ImageHeader, i: int, file: str, path: Path, where: str, n_channels: int,
                        cfa: str | None, first: ImageHeader | None, first_file: str | None) -> None:
    if cfa is not None:
        if h.n_channels != 1:
            raise StackError(f"frame {file!r} has {h.n_channels} channels, but cfa={cfa} means a raw Bayer "
                             "mosaic (H x W, one sample per pixel)", path=path, field=where,
                             fix="store the undemosaicked H x W mosaic, or remove 'cfa' from stack.json for "
                                 "demosaicked frames")
    elif h.n_channels != n_channels:
        raise StackError(f"frame {file!r} has {h.n_channels} channel(s), but 'channels' lists {n_channels}",
                         path=path, field=where,
                         fix="make 'channels' in stack.json match the images (e.g. [\"Y\"] for mono, "
                             "[\"R\", \"G\", \"B\"] for colour)")
    if first is not None:
        if (h.height, h.width) != (first.height, first.width):
            raise StackError(f"frame {file!r} is {h.width}x{h.height} px but frames[0] ({first_file}) is "
                             f"{first.width}x{first.height} px", path=path, field=where,
                             fix="all frames of a stack must have the same size (same ROI and binning)")
        if h.dtype != first.dtype:
            raise StackError(f"frame {file!r} is {h.dtype} but frames[0] ({first_file}) is {first.dtype}",
                             path=path, field=where, fix="all frames of a stack must have the same sample type")


# ----------------------------------------------------------------------------------------------- writer


class StackWriter:
    """Build a stack frame by frame, crash-safely.

    Each :meth:`add_frame` writes the frame file under a temporary name and renames it, then rewrites
    ``stack.json`` atomically; ``stack.json`` therefore always parses and never lists an incomplete frame.
    Until the first frame is added the folder holds a ``stack.json`` with an empty frames list, which
    :meth:`open_existing` resumes and :meth:`Stack.open` refuses ("no frames"). One writer per folder.

    Examples
    --------
    >>> w = StackWriter.create("STACK", pixel_pitch_um=3.45, channels=["R", "G", "B"], bit_depth=12)  # doctest: +SKIP
    >>> w.add_frame(image, z_um=-140.0, exposure_ms=20.0)                                            # doctest: +SKIP
    >>> stack = w.stack()                                                                             # doctest: +SKIP
    """

    def __init__(self, path: Path, meta: dict, headers: list[ImageHeader]):
        self.path = path
        self.meta = meta
        self._shape: tuple[int, ...] | None = headers[0].shape if headers else None
        self._dtype: np.dtype | None = headers[0].dtype if headers else None
        self._z = {float(e["z_um"]): k for k, e in enumerate(meta["frames"])}
        self._files = {PurePosixPath(e["file"].replace("\\", "/")) for e in meta["frames"]}

    @property
    def json_path(self) -> Path:
        return self.path / STACK_JSON

    def __len__(self) -> int:
        return len(self.meta["frames"])

    @classmethod
    def create(cls, path: str | os.PathLike, *, pixel_pitch_um: float, channels, overwrite: bool = False,
               **optional) -> "StackWriter":
        """Start a new stack folder and write its ``stack.json`` (no frames yet).

        Parameters
        ----------
        path : path-like
            The folder; created if missing. An existing non-empty folder is refused unless ``overwrite``
            (then only a folder that holds a stack.json is cleared).
        pixel_pitch_um : float
            Sensor pixel pitch (µm).
        channels : sequence of str
            Channel names in image order, e.g. ``["R", "G", "B"]`` or ``["Y"]``.
        **optional
            Optional and unknown top-level keys (``bit_depth``, ``black_level``, ``white_level``, ``f_number``,
            ``exposure_ms``, ``object_distance_mm``, ``lens``, ``chart``, ``cfa``, ...), stored as given.
        """
        path = Path(path)
        json_path = path / STACK_JSON
        reserved = set(optional) & set(REQUIRED_KEYS)
        if reserved:
            raise ParameterError(f"{sorted(reserved)} are set by the writer, not as optional keys",
                                 path=json_path, field=sorted(reserved)[0], fix="remove them from the call")
        meta = {"format": FORMAT, "pixel_pitch_um": pixel_pitch_um, "channels": list(channels), **optional,
                "frames": []}
        meta["pixel_pitch_um"] = float(pixel_pitch_um) if _is_number(pixel_pitch_um) else pixel_pitch_um
        _validate_meta(documents.loads(_dump(meta, json_path), json_path, error=StackError), json_path)
        text = _dump(meta, json_path)
        if path.exists() and not path.is_dir():
            raise StackError("exists and is not a folder", path=path, fix="choose another output path")
        if path.is_dir() and any(path.iterdir()):
            if not overwrite:
                raise StackError("already exists and is not empty; refusing to overwrite it", path=path,
                                 fix="choose a new folder, or pass overwrite=True (CLI: --overwrite) to replace it")
            if not json_path.is_file():
                raise StackError("is not empty and holds no stack.json; refusing to delete a folder that is not "
                                 "a stack", path=path, fix="choose a new or empty folder")
            shutil.rmtree(path)
        (path / "frames").mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, text)
        return cls(path, meta, [])

    @classmethod
    def open_existing(cls, path: str | os.PathLike) -> "StackWriter":
        """Reopen a stack to append frames (e.g. a resumed capture); existing frames are validated."""
        path = Path(path)
        if path.name == STACK_JSON and path.is_file():
            path = path.parent
        json_path = path / STACK_JSON
        meta = _read_json(json_path)
        _validate_meta(meta, json_path)
        headers: list[ImageHeader] = []
        if meta["frames"]:
            stack = Stack.open(path)
            headers = list(stack._headers)
        return cls(path, meta, headers)

    def stack(self) -> Stack:
        """Open what has been written so far as a :class:`Stack`."""
        return Stack.open(self.path)

    def _next_file(self, kind: str) -> str:
        n = len(self.meta["frames"])
        ext = ".tiff" if kind == "tiff" else ".png"
        while PurePosixPath(f"frames/{n:04d}{ext}") in self._files:
            n += 1
        return f"frames/{n:04d}{ext}"

    def add_frame(self, image: np.ndarray, z_um: float, *, file: str | None = None, kind: str = "tiff",
                  **frame_meta) -> FrameInfo:
        """Write one frame (file, then stack.json, both atomically) and return its :class:`FrameInfo`.

        Parameters
        ----------
        image : numpy.ndarray
            H x W or H x W x C (RGB order), uint8/uint16/float32, finite; H x W for a CFA stack. Same shape and
            dtype as the frames already written.
        z_um : float
            Stage position (µm), distinct from the other frames'.
        file : str, optional
            Relative path to use (``.tiff``, ``.tif`` or ``.png``); default ``frames/NNNN.tiff``.
        kind : {"tiff", "png"}
            File type when ``file`` is not given.
        **frame_meta
            Optional and unknown per-frame keys (``z_measured_um``, ``exposure_ms``, ``time``, ...).
        """
        json_path = self.json_path
        i = len(self.meta["frames"])
        where = f"frames[{i}]"
        image = np.asarray(image)
        if image.dtype.newbyteorder("=") not in SUPPORTED_DTYPES:
            raise StackError(f"image has unsupported dtype {image.dtype}", path=json_path, field=where,
                             fix="convert frames to uint8, uint16 or float32")
        image = image.astype(image.dtype.newbyteorder("="), copy=False)
        cfa = self.meta.get("cfa")
        n_ch = len(self.meta["channels"])
        if image.ndim == 3 and image.shape[2] == 1 and cfa is None:
            image = image[:, :, 0]  # store mono as a plain H x W file
        if image.ndim not in (2, 3) or min(image.shape) < 1:
            raise StackError(f"image has shape {image.shape}; a frame is H x W or H x W x C", path=json_path,
                             field=where, fix="pass one 2-D image per frame")
        c = 1 if image.ndim == 2 else image.shape[2]
        if cfa is not None and image.ndim != 2:
            raise StackError(f"image has shape {image.shape}, but cfa={cfa} stacks hold H x W Bayer mosaics",
                             path=json_path, field=where, fix="pass the raw mosaic, not a demosaicked image")
        if cfa is None and c != n_ch:
            raise StackError(f"image has {c} channel(s), channels is {self.meta['channels']}", path=json_path,
                             field=where, fix="pass H x W x C images with C = number of channels")
        if self._shape is not None and (image.shape[:2] != self._shape[:2] or image.dtype != self._dtype):
            raise StackError(f"image is {image.dtype} {image.shape[:2]}, earlier frames are {self._dtype} "
                             f"{self._shape[:2]}", path=json_path, field=where,
                             fix="all frames of a stack must have the same size and dtype")
        if image.dtype.kind == "f" and not np.isfinite(image).all():
            raise StackError("image holds NaN/Inf pixels", path=json_path, field=where,
                             fix="replace non-finite pixels before writing")
        if not _is_number(z_um) or not math.isfinite(z_um):
            raise StackError(f"must be a finite number, got {z_um!r}", path=json_path, field=f"{where}.z_um",
                             fix="pass the stage position in µm")
        z = float(z_um)
        if z in self._z:
            raise StackError(f"z_um={z:g} is already used by frames[{self._z[z]}] "
                             f"({self.meta['frames'][self._z[z]]['file']})", path=json_path, field=f"{where}.z_um",
                             fix="z values must be distinct; skip or re-number the repeated position")
        reserved = set(frame_meta) & {"file", "z_um", "sha256"}
        if reserved:
            raise ParameterError(f"{sorted(reserved)} are set by the writer", path=json_path, field=where,
                                 fix="pass file= as the keyword argument, and no sha256")
        try:
            if file is None:
                file = self._next_file(kind)
            kind = kind_for_name(file)
            data = encode(image, kind)
        except ImageFileError as exc:
            raise StackError(exc.what, path=json_path, field=f"{where}.file", fix=exc.fix) from None
        entry = {"file": file, "z_um": z, **frame_meta}
        _check_frame_entry(documents.loads(_dump(entry, json_path), json_path, error=StackError), i, json_path)
        frame_path = _resolve_frame_path(self.path, file, f"{where}.file", json_path)
        if PurePosixPath(file.replace("\\", "/")) in self._files:
            raise StackError(f"file {file!r} is already used by another frame", path=json_path,
                             field=f"{where}.file", fix="give every frame its own file")
        entry["sha256"] = hashlib.sha256(data).hexdigest()
        new_meta = dict(self.meta)
        new_meta["frames"] = [*self.meta["frames"], entry]
        text = _dump(new_meta, json_path)  # refuse non-JSON metadata before anything is written
        atomic_write_bytes(frame_path, data)
        atomic_write_text(json_path, text)
        self.meta = new_meta
        self._z[z] = i
        self._files.add(PurePosixPath(file.replace("\\", "/")))
        if self._shape is None:
            self._shape, self._dtype = image.shape, image.dtype
        return FrameInfo(i, file, frame_path, z, copy.deepcopy(entry))


def _dump(meta: dict, json_path: Path) -> str:
    """stack.json text (numpy values as plain JSON; NaN/Infinity and other non-JSON values refused)."""
    return documents.dumps(meta, path=json_path, error=StackError)


def record_chart(path: str | os.PathLike, chart: dict) -> None:
    """Write the chart record (:func:`stack_chart`) into an existing stack's ``stack.json`` (atomically), e.g.
    after ``import`` or ``capture`` with ``--chart``."""
    path = Path(path)
    json_path = path / STACK_JSON if path.is_dir() else path
    meta = _read_json(json_path)
    meta["chart"] = chart
    _validate_meta(meta, json_path)
    stack_chart(meta, json_path)
    atomic_write_text(json_path, _dump(meta, json_path))
