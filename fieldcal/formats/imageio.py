"""Frame files of a stack: probe a header without decoding pixels, decode one frame, encode one frame.

TIFF goes through tifffile (uncompressed contiguous pages are memory-mapped, so an ROI read touches only the
ROI's bytes; compressed pages are decoded one page at a time); PNG and JPEG through OpenCV, whose BGR(A) channel
order is turned into RGB(A) here so that the rest of fieldcal never sees BGR. JPEG frames (what most cameras
write) are read in their stored pixel order: the EXIF orientation tag is ignored, because calibration is about
the sensor's own pixel grid, not how a viewer would rotate the picture.

Everything here is about one file. Problems raise :class:`ImageFileError` (what + fix); the stack reader turns
it into a :class:`fieldcal.errors.StackError` that also names the stack.json field.
"""

from __future__ import annotations

import contextlib
import io
import logging
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: dtypes a frame may have (DESIGN.md): the reader normalises byte order to native.
SUPPORTED_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # classic and BigTIFF, both byte orders
_JPEG_MAGIC = b"\xff\xd8\xff"
# PNG colour type -> channels OpenCV returns with IMREAD_UNCHANGED (gray+alpha and palette are refused).
_PNG_CHANNELS = {0: 1, 2: 3, 6: 4}

#: Largest image (pixels) a frame may declare: 2^28 = 16384 x 16384. A header is only a few bytes, so a tiny
#: file can declare 200000 x 200000 px and make a decoder allocate tens of GiB ("image bomb"); sizes are
#: checked here, from the header, before anything is allocated. FIELDCAL_MAX_PIXELS raises the limit.
MAX_PIXELS_DEFAULT = 1 << 28
# zlib/deflate cannot compress better than about 1032:1, so a PNG that claims more is damaged or crafted
_DEFLATE_MAX_RATIO = 1100


def max_pixels() -> int:
    """The largest image (width x height) fieldcal decodes (``FIELDCAL_MAX_PIXELS``, default 2^28)."""
    import os

    try:
        v = int(os.environ.get("FIELDCAL_MAX_PIXELS", "") or MAX_PIXELS_DEFAULT)
    except ValueError:
        v = MAX_PIXELS_DEFAULT
    return max(1, v)


def _physical_memory_bytes() -> int | None:
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def check_declared_size(header: "ImageHeader", file_bytes: int, compressed_bytes: int | None = None) -> None:
    """Refuse an image whose header declares more pixels than it can hold or than this machine can decode.

    Parameters
    ----------
    header : ImageHeader
    file_bytes : int
        Size of the file on disk.
    compressed_bytes : int, optional
        Size of the deflate-compressed pixel data (PNG), for the compression-ratio bound.

    Raises
    ------
    ImageFileError
        Before any pixel buffer is allocated.
    """
    pixels = int(header.width) * int(header.height)
    decoded = pixels * int(header.n_channels) * int(np.dtype(header.dtype).itemsize)
    size = f"{header.width} x {header.height} px"
    if pixels > max_pixels():
        raise ImageFileError(f"declares {size} ({decoded / 2**30:.1f} GiB decoded), more than the "
                             f"{max_pixels():,} px fieldcal decodes (the file is {file_bytes:,} bytes)",
                             "check the file (a damaged or crafted header); for a real image this large set "
                             "FIELDCAL_MAX_PIXELS")
    if header.mmap_offset is not None and header.mmap_offset + decoded > file_bytes:
        raise ImageFileError(f"declares {size} of uncompressed data ({decoded:,} bytes from byte "
                             f"{header.mmap_offset:,}) but the file ends at byte {file_bytes:,}",
                             "re-export the frame; the file is truncated or damaged")
    if compressed_bytes is not None and decoded > _DEFLATE_MAX_RATIO * max(compressed_bytes, 1) + 4096:
        raise ImageFileError(f"declares {size} ({decoded:,} bytes) in {compressed_bytes:,} bytes of compressed "
                             "data, more than deflate can hold", "re-export the frame; the file is damaged")
    mem = _physical_memory_bytes()
    if mem is not None and decoded > mem // 2:
        raise ImageFileError(f"needs {decoded / 2**30:.1f} GiB to decode, more than half of this machine's "
                             f"{mem / 2**30:.1f} GiB of memory", "decode it on a larger machine, or crop it")


class ImageFileError(ValueError):
    """A frame file that cannot be used; ``what`` says why, ``fix`` says what to do."""

    def __init__(self, what: str, fix: str):
        self.what = what
        self.fix = fix
        super().__init__(what)


@dataclass(frozen=True)
class ImageHeader:
    """What a frame file holds, read from its header only.

    Attributes
    ----------
    kind : {"tiff", "png", "jpeg"}
    height, width : int
        Image size in px.
    n_channels : int
        Samples per pixel (1 for an H x W image).
    ndim : int
        2 for an H x W file, 3 for H x W x C (an H x W x 1 file counts as 3).
    dtype : numpy.dtype
        Native-byte-order sample type.
    planar : bool
        TIFF stored channel-first (C x H x W); transposed on read.
    mmap_offset : int or None
        Byte offset of an uncompressed, contiguous TIFF image (read by memory mapping), else None.
    file_dtype : str
        Sample type with the file's byte order (for memory mapping).
    """

    kind: str
    height: int
    width: int
    n_channels: int
    ndim: int
    dtype: np.dtype
    planar: bool = False
    mmap_offset: int | None = None
    file_dtype: str = ""

    @property
    def shape(self) -> tuple[int, ...]:
        """Shape of the array :func:`read_image` returns."""
        if self.ndim == 2:
            return (self.height, self.width)
        return (self.height, self.width, self.n_channels)


def _native(dtype: np.dtype) -> np.dtype:
    return np.dtype(dtype).newbyteorder("=")


class _Silencer:
    """A library's log silenced while fieldcal reads, so that only fieldcal's own what/where/fix message is shown.
    Frames are read on several threads: the first in saves the level and the last out restores it (a save/restore
    per call let an overlapping call restore "silent" for good)."""

    def __init__(self, get_level, set_level, silent):
        self.get_level, self.set_level, self.silent = get_level, set_level, silent
        self.lock, self.depth, self.saved = threading.Lock(), 0, None

    @contextlib.contextmanager
    def __call__(self):
        with self.lock:
            if self.depth == 0:
                self.saved = self.get_level()
                self.set_level(self.silent())
            self.depth += 1
        try:
            yield
        finally:
            with self.lock:
                self.depth -= 1
                if self.depth == 0:
                    self.set_level(self.saved)


def _cv2_logging():
    import cv2

    return cv2.utils.logging


#: tifffile logs a damaged file's faults as warnings (Python's last-resort handler prints them on stderr, e.g.
#: "<tifffile.TiffPages @25070> invalid offset to first page") before fieldcal's message
_tifffile_quiet = _Silencer(lambda: logging.getLogger("tifffile").level,
                            lambda level: logging.getLogger("tifffile").setLevel(level), lambda: logging.ERROR + 1)
#: OpenCV's decoders warn on damaged files before fieldcal's message
cv2_quiet = _Silencer(lambda: _cv2_logging().getLogLevel(), lambda level: _cv2_logging().setLogLevel(level),
                      lambda: _cv2_logging().LOG_LEVEL_SILENT)


def check_png_chunks(data) -> None:
    """Walk a PNG's chunks and check each one's CRC (ISO/IEC 15948 §5.3) up to IEND: a damaged or truncated file
    is refused here, by fieldcal's message, before libpng prints its own "libpng error: ..." line on stderr
    (its default error handler writes there, beyond OpenCV's log level). ``data``: the file's bytes."""
    import zlib

    buf = memoryview(np.asarray(data, dtype=np.uint8)).cast("B")
    if bytes(buf[:8]) != _PNG_SIGNATURE:
        raise ImageFileError("is not a PNG file (no PNG signature)", "give a PNG, JPEG or TIFF image")
    pos = 8
    while True:
        if pos + 8 > len(buf):
            raise ImageFileError("is a truncated PNG (it ends before its IEND chunk)", "re-export or re-capture "
                                 "the frame")
        length, kind = struct.unpack(">I4s", buf[pos:pos + 8])
        end = pos + 8 + length + 4
        if length > 0x7FFFFFFF or end > len(buf):
            raise ImageFileError(f"is a truncated PNG (its {kind.decode('latin-1')!r} chunk runs past the end of "
                                 "the file)", "re-export or re-capture the frame")
        crc = struct.unpack(">I", buf[end - 4:end])[0]
        if zlib.crc32(buf[pos + 4:end - 4]) != crc:
            raise ImageFileError(f"is a damaged PNG (the CRC of its {kind.decode('latin-1')!r} chunk at byte {pos} "
                                 "does not match)", "re-export or re-capture the frame")
        if kind == b"IEND":
            return
        pos = end


def sniff_kind(path: Path) -> str:
    """Return ``"tiff"``, ``"png"`` or ``"jpeg"`` from the file's magic bytes (the extension is not trusted).

    A path that is not a regular file (a pipe or a device would block the read, or never end) is refused."""
    import os
    import stat

    if not stat.S_ISREG(os.stat(path).st_mode):  # FileNotFoundError passes through
        raise ImageFileError("is not a regular file (a folder, pipe or device)", "give an image file")
    with open(path, "rb") as f:
        head = f.read(8)
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head[:4] in _TIFF_MAGICS:
        return "tiff"
    if head.startswith(_JPEG_MAGIC):
        return "jpeg"
    raise ImageFileError("is not a TIFF, PNG or JPEG file (unknown magic bytes)",
                         "write frames as TIFF (.tiff), PNG (.png) or JPEG (.jpg); bring camera raw files in "
                         "with 'fieldcal import'")


def probe(path: str | Path) -> ImageHeader:
    """Read a frame file's header (shape, dtype, channels) without decoding its pixels.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ImageFileError
        Not a TIFF/PNG, unreadable header, unsupported layout or dtype.
    """
    path = Path(path)
    kind = sniff_kind(path)
    if kind == "png":
        header, idat_bytes = _probe_png(path)
    elif kind == "jpeg":
        header, idat_bytes = _probe_jpeg(path), None
    else:
        header, idat_bytes = _probe_tiff(path), None
    if header.height >= 1 and header.width >= 1:
        check_declared_size(header, path.stat().st_size, idat_bytes)
    if header.dtype not in SUPPORTED_DTYPES:
        raise ImageFileError(f"has unsupported sample type {header.dtype}",
                             "store frames as uint8, uint16 or float32")
    if header.height < 1 or header.width < 1 or header.n_channels < 1:
        raise ImageFileError(f"has an empty image (shape {header.shape})", "re-export the frame")
    return header


def _png_idat_bytes(path: Path) -> int:
    """Total length of the IDAT (compressed pixel) chunks, read from the chunk headers only."""
    total = 0
    with open(path, "rb") as f:
        f.seek(8)
        while True:
            head = f.read(8)
            if len(head) < 8:
                break
            length, ctype = struct.unpack(">I4s", head)
            if ctype == b"IDAT":
                total += length
            elif ctype == b"IEND":
                break
            f.seek(length + 4, 1)  # data + CRC
    return total


def _probe_png(path: Path) -> tuple[ImageHeader, int]:
    with open(path, "rb") as f:
        data = f.read(33)
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ImageFileError("has a truncated or invalid PNG header (no IHDR chunk)",
                             "re-export the frame; the file is damaged")
    width, height, bit_depth, colour_type, _comp, _filt, _interlace = struct.unpack(">IIBBBBB", data[16:29])
    if colour_type not in _PNG_CHANNELS:
        names = {3: "palette", 4: "gray+alpha"}
        raise ImageFileError(f"is a {names.get(colour_type, f'colour type {colour_type}')} PNG",
                             "save the frame as grayscale, RGB or RGBA PNG (or as TIFF)")
    if bit_depth not in (8, 16):
        raise ImageFileError(f"has PNG bit depth {bit_depth}",
                             "save the frame with 8 or 16 bits per sample (uint8 or uint16)")
    n = _PNG_CHANNELS[colour_type]
    dtype = np.dtype(np.uint8 if bit_depth == 8 else np.uint16)
    return ImageHeader("png", height, width, n, 2 if n == 1 else 3, dtype), _png_idat_bytes(path)


def _probe_jpeg(path: Path) -> ImageHeader:
    """Size and components from the JPEG's frame header (Pillow reads only the header here)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            width, height, mode = im.width, im.height, im.mode
    except Exception as exc:  # Pillow raises several types for damaged headers (and for decompression bombs)
        raise ImageFileError(f"has an unreadable JPEG header ({exc})", "re-export the frame; the file is damaged")
    if mode not in ("L", "RGB"):
        raise ImageFileError(f"is a {mode} JPEG", "save the frame as a grayscale or RGB JPEG (or as TIFF)")
    n = 1 if mode == "L" else 3
    return ImageHeader("jpeg", height, width, n, 2 if n == 1 else 3, np.dtype(np.uint8))


def _probe_tiff(path: Path) -> ImageHeader:
    import tifffile

    try:
        with _tifffile_quiet(), tifffile.TiffFile(path) as tf:
            if not tf.series:
                raise ImageFileError("has an unreadable TIFF header (no image found)",
                                     "re-export the frame; the file is damaged")
            if len(tf.series) != 1:
                raise ImageFileError(f"holds {len(tf.series)} image series",
                                     "write one 2-D image (H x W or H x W x C) per frame file")
            series = tf.series[0]
            shape, axes, dtype = tuple(series.shape), series.axes, series.dtype
            n_pages = len(series.pages)
            page = series.pages[0]
            offset = int(page.dataoffsets[0]) if n_pages == 1 and page.is_memmappable else None
            file_dtype = np.dtype(dtype).newbyteorder(tf.byteorder).str
    except ImageFileError:
        raise
    except Exception as exc:  # tifffile raises many types for damaged files
        raise ImageFileError(f"has an unreadable TIFF header ({exc})", "re-export the frame; the file is damaged")
    if n_pages != 1 or axes not in ("YX", "YXS", "SYX"):
        raise ImageFileError(f"holds an image of shape {shape} (axes {axes!r}), not one 2-D image",
                             "write one 2-D image (H x W or H x W x C) per frame file")
    if axes == "YX":
        return ImageHeader("tiff", shape[0], shape[1], 1, 2, _native(dtype), False, offset, file_dtype)
    if axes == "YXS":
        return ImageHeader("tiff", shape[0], shape[1], shape[2], 3, _native(dtype), False, offset, file_dtype)
    return ImageHeader("tiff", shape[1], shape[2], shape[0], 3, _native(dtype), True, None, file_dtype)


def check_image_file(path: str | Path) -> None:
    """Size check of any PNG/TIFF (e.g. a scene image) from its header, before a decoder allocates it.

    Unlike :func:`probe` it accepts every PNG colour type and TIFF layout; other formats are left to their
    decoder (OpenCV refuses images above 2^30 px itself).

    Raises
    ------
    ImageFileError
        The header declares more pixels than :func:`max_pixels` or than the file/memory can hold.
    """
    path = Path(path)
    try:
        kind = sniff_kind(path)
    except (ImageFileError, OSError):
        return
    size = path.stat().st_size
    if kind == "png":
        with open(path, "rb") as f:
            data = f.read(33)
        if len(data) < 33 or data[12:16] != b"IHDR":
            return
        width, height, bit_depth, colour_type = struct.unpack(">IIBB", data[16:26])
        n = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour_type, 4)
        dtype = np.dtype(np.uint16 if bit_depth == 16 else np.uint8)
        check_declared_size(ImageHeader("png", height, width, n, 3, dtype), size, _png_idat_bytes(path))
        return
    import tifffile

    try:
        with _tifffile_quiet(), tifffile.TiffFile(path) as tf:
            shapes = [(tuple(sr.shape), sr.dtype) for sr in tf.series]
    except Exception:
        return  # the decoder reports a damaged file itself
    for shape, dtype in shapes:
        if len(shape) >= 2:  # the two largest axes are the image, the rest are samples/pages
            dims = sorted(int(v) for v in shape)
            h, w, n = dims[-1], dims[-2], int(np.prod(dims[:-2], dtype=object))
            check_declared_size(ImageHeader("tiff", h, w, max(1, n), 3, np.dtype(dtype)), size)


def read_image(path: str | Path, roi: tuple[int, int, int, int] | None = None,
               header: ImageHeader | None = None, data: np.ndarray | None = None) -> np.ndarray:
    """Decode one frame file (or an ROI of it) into a native-order array, RGB(A) channel order.

    Parameters
    ----------
    path : path-like
        The frame file.
    roi : (y0, y1, x0, x1) or None
        Half-open pixel bounds, already checked against the image size.
    header : ImageHeader, optional
        The result of :func:`probe` if known (saves re-reading the header); the decoded array is checked
        against it.
    data : uint8 array, optional
        The file's bytes, already read (PNG and JPEG): decoded instead of reading the file again, so that a
        caller who hashed them knows which content the pixels are (``composite``'s start-up decoding).

    Returns
    -------
    numpy.ndarray
        ``header.shape`` (cropped to the ROI), native byte order; a fresh array, no file stays open.

    Raises
    ------
    ImageFileError
        The pixel data cannot be decoded or disagree with the header.
    """
    path = Path(path)
    if header is None:
        header = probe(path)
    try:
        if header.kind == "png":
            image, cropped = _read_png(path, data), False
        elif header.kind == "jpeg":
            image, cropped = _read_jpeg(path, header, data), False
        else:
            image, cropped = _read_tiff(path, header, roi)
    except (ImageFileError, FileNotFoundError):
        raise
    except Exception as exc:  # decoder errors on damaged data (zlib, mmap beyond EOF, ...)
        raise ImageFileError(f"cannot be decoded ({type(exc).__name__}: {exc})",
                             "re-export or re-capture the frame; the file is damaged or truncated")
    expected = header.shape
    if cropped:
        y0, y1, x0, x1 = roi
        expected = (y1 - y0, x1 - x0) + header.shape[2:]
    if image.shape != expected or _native(image.dtype) != header.dtype:
        raise ImageFileError(f"decodes to {image.dtype} {image.shape}, but its header says "
                             f"{header.dtype} {header.shape}", "re-export the frame; the file is damaged")
    if roi is not None and not cropped:
        y0, y1, x0, x1 = roi
        image = image[y0:y1, x0:x1]
    if image.dtype.byteorder not in ("=", "|"):
        image = image.astype(header.dtype)
    return np.ascontiguousarray(image)


def check_finite(image: np.ndarray) -> None:
    """Refuse a float frame holding NaN or infinite pixels (no measurement or blend is defined on them).

    Raises
    ------
    ImageFileError
        Naming how many pixels are not finite.
    """
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        bad = int(np.count_nonzero(~np.isfinite(image)))
        raise ImageFileError(f"holds {bad} NaN/Inf pixel(s)",
                             "replace non-finite pixels (e.g. with 0 or the saturation value) and export again")


def _read_tiff(path: Path, header: ImageHeader, roi) -> tuple[np.ndarray, bool]:
    """Memory-map uncompressed pages (an ROI read copies only the ROI), else decode the one page.

    Returns the array and whether it is already cropped to ``roi``.
    """
    import tifffile

    if header.mmap_offset is not None:
        mm = np.memmap(path, dtype=np.dtype(header.file_dtype), mode="r", offset=header.mmap_offset,
                       shape=header.shape)  # raises ValueError if the file is shorter than the image
        try:
            if roi is not None:
                y0, y1, x0, x1 = roi
                return np.array(mm[y0:y1, x0:x1]), True
            return np.array(mm), False
        finally:
            del mm  # release the mapping now, not at garbage collection
    with _tifffile_quiet():
        image = tifffile.imread(path)
    if header.planar:
        image = np.moveaxis(image, 0, -1)
    if image.size == int(np.prod(header.shape)):
        image = image.reshape(header.shape)
    return image, False


def _read_png(path: Path, data: np.ndarray | None = None) -> np.ndarray:
    import cv2

    if data is None:
        data = np.fromfile(path, dtype=np.uint8)  # imdecode: non-ASCII paths work, and we control the errors
    check_png_chunks(data)
    with cv2_quiet():
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageFileError("cannot be decoded as PNG (damaged or truncated)",
                             "re-export or re-capture the frame")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


def _read_jpeg(path: Path, header: ImageHeader, data: np.ndarray | None = None) -> np.ndarray:
    import cv2

    if data is None:
        data = np.fromfile(path, dtype=np.uint8)
    flags = (cv2.IMREAD_GRAYSCALE if header.n_channels == 1 else cv2.IMREAD_COLOR) | cv2.IMREAD_IGNORE_ORIENTATION
    with cv2_quiet():
        image = cv2.imdecode(data, flags)
    if image is None:
        raise ImageFileError("cannot be decoded as JPEG (damaged or truncated)", "re-export or re-capture the frame")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if image.ndim == 3 else image


def encode(image: np.ndarray, kind: str) -> bytes:
    """Encode one frame as ``"tiff"`` (uncompressed, memory-mappable) or ``"png"`` bytes.

    ``image`` is H x W or H x W x C in RGB(A) order; PNG takes only uint8/uint16 with 1, 3 or 4 channels.
    """
    image = np.ascontiguousarray(image)
    if kind == "tiff":
        import tifffile

        buf = io.BytesIO()
        if image.ndim == 2:
            tifffile.imwrite(buf, image, photometric="minisblack")
        elif image.shape[2] == 3:
            tifffile.imwrite(buf, image, photometric="rgb", planarconfig="contig")
        else:
            tifffile.imwrite(buf, image, photometric="minisblack", planarconfig="contig")
        return buf.getvalue()
    if kind == "png":
        import cv2

        if image.dtype not in (np.uint8, np.uint16):
            raise ImageFileError(f"PNG cannot hold {image.dtype} samples", "write float32 frames as TIFF")
        channels = 1 if image.ndim == 2 else image.shape[2]
        if channels not in (1, 3, 4):
            raise ImageFileError(f"PNG cannot hold {channels} channels", "write the frames as TIFF")
        if channels == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        elif channels == 4:
            image = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA)
        ok, buf = cv2.imencode(".png", image)
        if not ok:  # pragma: no cover - OpenCV only fails on layouts refused above
            raise ImageFileError("OpenCV could not encode the frame as PNG", "write the frames as TIFF")
        return buf.tobytes()
    if kind == "jpeg":
        raise ImageFileError("fieldcal does not write .jpg frames (JPEG is lossy and 8-bit)",
                             "use a .tiff, .tif or .png file name; bring a camera's JPEGs in with `fieldcal import`")
    raise ImageFileError(f"unknown frame file type {kind!r}", "use a .tiff, .tif or .png file name")


def kind_for_name(name: str) -> str:
    """File type from a frame file name's extension (for writing)."""
    suffix = Path(name).suffix.lower()
    if suffix in (".tif", ".tiff"):
        return "tiff"
    if suffix == ".png":
        return "png"
    if suffix in (".jpg", ".jpeg"):
        return "jpeg"
    raise ImageFileError(f"frame file name {name!r} has extension {suffix or '(none)'!r}",
                         "name frame files *.tiff, *.tif, *.png or *.jpg")
