"""Composite output: a TIFF in the input's dtype and scale, with what made it in the ImageDescription (JSON)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes
from ..errors import FieldcalError, ParameterError

COMPOSITE_FORMAT = documents.format_id("composite")


def check_output_path(path: str | Path) -> Path:
    """A composite goes to ``.tif``/``.tiff``; fail before any work, not after."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise ParameterError(f"output {path.name!r} is not a TIFF", path=path, field="out",
                             fix="name the output IMAGE.tiff (TIFF keeps the bit depth and the metadata)")
    if path.exists() and path.is_dir():
        raise ParameterError("output is a directory", path=path, field="out", fix="give a file name")
    return path


def check_composite_output(path: str | Path, *, stack: str | Path | None = None, profile: str | Path | None = None,
                           plan: str | Path | None = None, overwrite: bool = False) -> Path:
    """All the checks of a composite's ``--out`` before any work (docs/safety.md).

    A TIFF name; not the input stack (or a file inside it, e.g. one of its frames), the profile and its
    sidecar, the plan, or a captured sweep image; an existing file only with ``overwrite``; never a symbolic
    link. The composite API and command call this once; :func:`write_composite_tiff` writes atomically.
    """
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files

    path = check_output_path(path)
    inputs = [stack, plan, *(profile_files(profile) if profile else [])]
    return check_output(path, inputs=inputs, overwrite=overwrite, suffixes=(".tif", ".tiff"))


def write_composite_tiff(path: str | Path, image: np.ndarray, channels, metadata: dict) -> Path:
    """Write ``image`` (H x W x C) atomically, with ``metadata`` (+ format and channels) as JSON description.

    Returns the path. Nothing is left at ``path`` if writing fails.
    """
    import tifffile

    path = check_output_path(path)
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    meta = {"format": COMPOSITE_FORMAT, "channels": list(channels), **metadata}
    desc = documents.dumps(meta, "composite", path, indent=None)
    photometric = "rgb" if list(channels) == ["R", "G", "B"] else "minisblack"
    data = image if image.shape[2] > 1 else image[..., 0]
    import io
    buf = io.BytesIO()  # encode in memory, then the shared atomic write (temporary name, fsync, rename)
    tifffile.imwrite(buf, data, photometric=photometric, description=desc, metadata=None)
    atomic_write_bytes(path, buf.getvalue())
    return path


def read_composite_metadata(path: str | Path) -> dict:
    """The metadata a composite TIFF was written with."""
    import tifffile

    with tifffile.TiffFile(path) as tf:
        desc = tf.pages[0].description
    if not isinstance(desc, str) or not desc.lstrip().startswith("{"):
        raise FieldcalError("no fieldcal metadata in this TIFF", path=path,
                            fix="read a file written by `fieldcal composite`")
    return documents.validate(documents.loads(desc, path, where="ImageDescription"), "composite", path,
                              where="ImageDescription")


def read_single_image(path: str | Path) -> np.ndarray:
    """A captured image (TIFF or PNG) as H x W x C in its dtype (for captured sweep images)."""
    from fieldcal.formats.imageio import ImageFileError, read_image

    path = Path(path)
    if not path.is_file():
        raise ParameterError("image not found", path=path, fix="give an existing TIFF or PNG file")
    try:
        img = read_image(path)
    except ImageFileError as e:
        raise FieldcalError(f"cannot read the image: {e.what}", path=path, fix=e.fix) from None
    return img if img.ndim == 3 else img[..., None]
