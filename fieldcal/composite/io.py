"""Composite output, chosen by the file name's extension, with what made it stored as JSON in the file:

* ``.tif``/``.tiff``: the input's dtype and scale (uint8, uint16 or float32), JSON in the ImageDescription;
* ``.png``: 8 or 16 bits (uint8 stacks give 8-bit, others 16-bit scaled from the stack's black..white range),
  JSON in an ``iTXt`` chunk (keyword ``fieldcal``);
* ``.jpg``/``.jpeg``: 8-bit, quality 95, the first frame's EXIF copied when it has any (camera, lens,
  exposure), JSON in the JPEG comment.

Lossless TIFF is the default for measurements; PNG and JPEG are for people to open.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes
from ..errors import FieldcalError, ParameterError

COMPOSITE_FORMAT = documents.format_id("composite")


#: Output file name endings and the format each writes.
OUTPUT_SUFFIXES = {".tif": "tiff", ".tiff": "tiff", ".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg"}


def check_output_path(path: str | Path) -> Path:
    """A composite goes to TIFF, PNG or JPEG by its extension; fail before any work, not after."""
    path = Path(path)
    if path.suffix.lower() not in OUTPUT_SUFFIXES:
        raise ParameterError(f"output {path.name!r} is not a .tiff, .png or .jpg file name", path=path, field="out",
                             fix="name the output IMAGE.tiff (keeps the bit depth), IMAGE.png or IMAGE.jpg")
    if path.exists() and path.is_dir():
        raise ParameterError("output is a directory", path=path, field="out", fix="give a file name")
    return path


def check_composite_output(path: str | Path, *, stack: str | Path | None = None, profile: str | Path | None = None,
                           plan: str | Path | None = None, overwrite: bool = False) -> Path:
    """All the checks of a composite's ``--out`` before any work (docs/safety.md).

    A TIFF, PNG or JPEG name; not the input stack (or a file inside it, e.g. one of its frames), the profile and its
    sidecar, the plan, or a captured sweep image; an existing file only with ``overwrite``; never a symbolic
    link. The composite API and command call this once; :func:`write_composite` writes atomically.
    """
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files

    path = check_output_path(path)
    inputs = [stack, plan, *(profile_files(profile) if profile else [])]
    return check_output(path, inputs=inputs, overwrite=overwrite, suffixes=tuple(OUTPUT_SUFFIXES))


def exif_orientation(paths) -> int:
    """The EXIF orientation (1-8) most of the frame files ``paths`` state (1 when none does).

    Frames are composited as the sensor recorded them (the readers ignore the tag), which is right even where a
    camera looking straight down flips its tag from frame to frame; the composite carries the tag most frames
    have, so a viewer shows it upright as it shows them.
    """
    from collections import Counter

    from PIL import Image

    tags = []
    for p in paths:
        try:
            with Image.open(p) as im:
                tags.append(int(im.getexif().get(0x0112, 1)))
        except Exception:  # metadata only: a frame that will not say counts as upright
            tags.append(1)
    tags = [t if 1 <= t <= 8 else 1 for t in tags]
    return Counter(tags).most_common(1)[0][0] if tags else 1


def write_composite_tiff(path: str | Path, image: np.ndarray, channels, metadata: dict, *,
                         orientation: int = 1) -> Path:
    """Write ``image`` (H x W x C) atomically, with ``metadata`` (+ format and channels) as JSON description and
    the TIFF Orientation tag when ``orientation`` is not 1.

    Returns the path. Nothing is left at ``path`` if writing fails.
    """
    import tifffile

    path = check_output_path(path)
    if OUTPUT_SUFFIXES[path.suffix.lower()] != "tiff":
        raise ParameterError(f"output {path.name!r} is not a TIFF", path=path, field="out",
                             fix="name it IMAGE.tiff, or use write_composite for PNG/JPEG")
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    meta = {"format": COMPOSITE_FORMAT, "channels": list(channels), **metadata}
    desc = documents.dumps(meta, "composite", path, indent=None)
    photometric = "rgb" if list(channels) == ["R", "G", "B"] else "minisblack"
    data = image if image.shape[2] > 1 else image[..., 0]
    import io
    buf = io.BytesIO()  # encode in memory, then the shared atomic write (temporary name, fsync, rename)
    extratags = [(274, "H", 1, int(orientation), True)] if orientation != 1 else []
    tifffile.imwrite(buf, data, photometric=photometric, description=desc, metadata=None, extratags=extratags)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _to_8_or_16_bit(image: np.ndarray, black: float, white: float, bits: int) -> np.ndarray:
    """Scale black..white to the full range of ``bits`` (8 or 16), rounded and clipped."""
    top = float(2 ** bits - 1)
    if image.dtype == np.uint8 and bits == 8 and black == 0 and white == 255:
        return image
    scaled = (image.astype(np.float64) - black) * (top / max(white - black, 1e-12))
    return np.clip(np.rint(scaled), 0, top).astype(np.uint8 if bits == 8 else np.uint16)


def write_composite(path: str | Path, image: np.ndarray, channels, metadata: dict, *,
                    black_level: float = 0.0, white_level: float | None = None,
                    exif_from: str | Path | None = None, orientation: int = 1) -> Path:
    """Write a composite as TIFF, PNG or JPEG by ``path``'s extension (see the module notes), atomically.

    Parameters
    ----------
    path : path-like
        ``.tif``/``.tiff``, ``.png`` or ``.jpg``/``.jpeg``.
    image : H x W x C array
        In the stack's dtype and scale.
    channels : sequence of str
        Channel names (``["R", "G", "B"]`` is written as colour; other sets as grey planes in TIFF only).
    metadata : dict
        What made the composite (stored as JSON, with ``format`` and ``channels``).
    black_level, white_level : float
        The stack's levels: PNG and JPEG map black..white to their full range (white defaults to the dtype's
        maximum, 1.0 for float).
    exif_from : path-like, optional
        A frame whose EXIF block is copied into a JPEG output (e.g. the first frame of a camera's stack).
    orientation : int
        EXIF orientation (1-8, :func:`exif_orientation`) for a TIFF's Orientation tag and a JPEG's EXIF (PNG
        has no tag viewers honour); the pixels are written as they are.
    """
    path = check_output_path(path)
    kind = OUTPUT_SUFFIXES[path.suffix.lower()]
    if kind == "tiff":
        return write_composite_tiff(path, image, channels, metadata, orientation=orientation)
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    names = list(channels)
    if names not in (["R", "G", "B"], ["Y"]) and names != ["R", "G", "B", "A"]:
        raise ParameterError(f"a {kind.upper()} holds grey or RGB images, not channels {names}", path=path,
                             field="out", fix="write this composite as .tiff")
    if white_level is None:
        white_level = 1.0 if image.dtype.kind == "f" else float(np.iinfo(image.dtype).max)
    bits = 8 if (kind == "jpeg" or image.dtype == np.uint8) else 16
    data = _to_8_or_16_bit(image[..., :3] if names[:3] == ["R", "G", "B"] else image, float(black_level),
                           float(white_level), bits)
    data = data[..., 0] if data.shape[2] == 1 else data
    meta = {"format": COMPOSITE_FORMAT, "channels": names[:3] if names[:3] == ["R", "G", "B"] else names,
            **metadata}
    desc = documents.dumps(meta, "composite", path, indent=None)
    import io

    from PIL import Image

    buf = io.BytesIO()
    if kind == "png":
        import cv2

        # OpenCV writes 16-bit RGB PNGs (Pillow does not); metadata goes in as an iTXt chunk afterwards.
        bgr = cv2.cvtColor(data, cv2.COLOR_RGB2BGR) if data.ndim == 3 else data
        ok, enc = cv2.imencode(".png", bgr)
        if not ok:  # pragma: no cover - layouts are checked above
            raise ParameterError("OpenCV could not encode the PNG", path=path, fix="write a .tiff")
        buf.write(_png_with_text(enc.tobytes(), "fieldcal", desc))
    else:
        exif = Image.Exif()
        if exif_from is not None:
            try:
                with Image.open(exif_from) as src:
                    exif = src.getexif()
            except Exception:  # EXIF is a courtesy copy; an unreadable source only loses it
                pass
        if orientation != 1 or 0x0112 in exif:
            exif[0x0112] = int(orientation)
        info = {"exif": exif.tobytes()} if len(exif) else {}
        Image.fromarray(data).save(buf, format="JPEG", quality=95, comment=desc.encode("utf-8"), **info)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _png_with_text(png: bytes, keyword: str, text: str) -> bytes:
    """Insert an uncompressed iTXt chunk after IHDR (PNG spec 11.3.4.5)."""
    import struct
    import zlib

    body = keyword.encode("latin-1") + b"\0" + b"\0\0" + b"\0" + b"\0" + text.encode("utf-8")
    chunk = struct.pack(">I", len(body)) + b"iTXt" + body
    chunk += struct.pack(">I", zlib.crc32(b"iTXt" + body) & 0xFFFFFFFF)
    ihdr_end = 8 + 8 + 13 + 4  # signature, IHDR length+type, IHDR data, CRC
    return png[:ihdr_end] + chunk + png[ihdr_end:]


def read_composite_metadata(path: str | Path) -> dict:
    """The metadata a composite (TIFF, PNG or JPEG) was written with, validated (``fieldcal-composite/1``)."""
    suffix = Path(path).suffix.lower()
    if suffix in (".png", ".jpg", ".jpeg"):
        from PIL import Image

        with Image.open(path) as im:
            desc = im.info.get("fieldcal") if suffix == ".png" else im.info.get("comment")
        if isinstance(desc, bytes):
            desc = desc.decode("utf-8", "replace")
    else:
        import tifffile

        with tifffile.TiffFile(path) as tf:
            desc = tf.pages[0].description
    if not isinstance(desc, str) or not desc.lstrip().startswith("{"):
        raise FieldcalError("no fieldcal metadata in this image", path=path,
                            fix="read a file written by `fieldcal composite`")
    return documents.validate(documents.loads(desc, path, where="description"), "composite", path,
                              where="description")


def read_single_image(path: str | Path) -> np.ndarray:
    """A captured image (TIFF or PNG) as H x W x C in its dtype (for captured sweep images)."""
    from fieldcal.formats.imageio import ImageFileError, check_finite, read_image

    path = Path(path)
    if not path.is_file():
        raise ParameterError("image not found", path=path, fix="give an existing TIFF or PNG file")
    try:
        img = read_image(path)
        check_finite(img)
    except ImageFileError as e:
        raise FieldcalError(f"cannot read the image: {e.what}", path=path, fix=e.fix) from None
    return img if img.ndim == 3 else img[..., None]
