"""Scenes for the simulator: the calibration charts by name, an image file, or an array, at the sensor size."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import ParameterError

#: scene names understood by :func:`load_scene` -> the chart kind of :func:`fieldcal.charts.targets.chart_image`.
CHARTS = {"chart": "texture", "texture": "texture", "charuco": "charuco", "slanted-edge": "slanted-edge"}

#: synthetic colour scenes (test scenes for compositing, not charts).
COLOUR_SCENES = ("colour-leaves",)


def colour_leaves(width_px: int, height_px: int, seed: int = 0) -> np.ndarray:
    """A natural-looking colour test scene: dead-leaves luminance (edges at every scale, 1/f² spectrum up to
    Nyquist) tinted by smooth random colour fields, so the channels are correlated like a photograph's but not
    identical (per-channel focus matters). float32 H x W x 3 in [0.04, 0.96]."""
    import cv2

    from fieldcal.charts.targets import random_texture
    lum = random_texture(width_px, height_px, seed).astype(np.float32)
    sigma = max(width_px, height_px) / 60.0
    tints = []
    for c in range(3):
        t = random_texture(width_px, height_px, seed + 7919 * (c + 1), r_min_px=2.0).astype(np.float32)
        t = cv2.GaussianBlur(t, (0, 0), sigma)
        t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
        tints.append(t)
    img = lum[..., None] * (0.45 + 0.55 * np.stack(tints, axis=-1))
    return np.clip(0.04 + 0.92 * img / max(float(img.max()), 1e-6), 0.0, 1.0).astype(np.float32)


#: most pixels the dead-leaves chart is drawn at before the sensor's area average (memory: 5 bytes each).
MAX_DRAWN_PX = 64_000_000


def sensor_texture(width_px: int, height_px: int, seed: int = 0, oversample: int = 4) -> np.ndarray:
    """The dead-leaves chart as the sensor's pixels integrate it: drawn ``oversample`` times finer (radii and the
    default radius range scaled with it, so the same discs), then area-averaged (``cv2.INTER_AREA``).

    Why: OpenCV's antialiased sub-pixel discs are not isotropic: at 0.3 cycles/px the texture drawn at the
    sensor size holds 42 % of its energy in x and 58 % in y (0.40/0.60 at 0.45 cycles/px). Isotropic
    optics do not care, but an astigmatic lens's texture focus measure weights the tangential and sagittal
    foci by the chart's energy along them, so the anisotropy moved the measured surface off the mean of T and
    S by about 6 % of T - S times cos(2 theta) (0.43 µm RMS on the 1080p triplet). Drawn 4x finer and averaged
    the shares are 0.497/0.503 at 0.3 cycles/px, 0.493 at 0.45. The factor drops (never below 1) so the drawn
    image stays under ``MAX_DRAWN_PX``.
    """
    from fieldcal.charts.targets import random_texture
    s = max(int(oversample), 1)
    while s > 1 and width_px * height_px * s * s > MAX_DRAWN_PX:
        s -= 1
    if s == 1:
        return random_texture(width_px, height_px, seed=seed).astype(np.float32)
    big = random_texture(width_px * s, height_px * s, seed=seed, r_min_px=0.5 * s,
                         r_max_px=0.1 * min(width_px, height_px) * s)
    return cv2.resize(big, (width_px, height_px), interpolation=cv2.INTER_AREA).astype(np.float32)


def load_scene(scene, width_px: int, height_px: int, seed: int = 0) -> tuple[np.ndarray, str]:
    """Return ``(image, name)``: a float32 H x W or H x W x 3 (RGB) image in [0, 1] at the given size.

    Parameters
    ----------
    scene : str, path or array
        ``"chart"`` (the dead-leaves texture), ``"charuco"``, ``"slanted-edge"``, ``"colour-leaves"`` (a colour
        test scene, :func:`colour_leaves`), an image file (any size and
        format OpenCV or tifffile reads), or an array (uint8/uint16 scaled to [0, 1], floats taken as they
        are). Files and arrays of another size are centre-cropped to the sensor's aspect ratio, then resized
        with ``cv2.INTER_AREA`` (averaging, no aliasing when shrinking).
    width_px, height_px : int
        Sensor size in pixels.
    seed : int
        Seed of the random texture chart.
    """
    if isinstance(scene, str) and scene in CHARTS:
        from fieldcal.charts.targets import chart_image
        if CHARTS[scene] == "texture":
            return sensor_texture(width_px, height_px, seed), scene
        img = chart_image(CHARTS[scene], width_px, height_px, seed).astype(np.float32)
        if CHARTS[scene] == "charuco":
            # the printed board as the sensor's pixels integrate it: a binary image's hard edges ring past the
            # white level (clipped, saturated tiles) and lock sub-pixel corners to the pixel grid
            import cv2
            img = np.clip(cv2.GaussianBlur(img, (0, 0), 0.5), 0.0, 1.0)
        return img, scene
    if isinstance(scene, str) and scene in COLOUR_SCENES:
        return colour_leaves(width_px, height_px, seed), scene
    if isinstance(scene, (str, Path)):
        path = Path(scene)
        return fit_to_sensor(_read_file(path), width_px, height_px), path.name
    return fit_to_sensor(np.asarray(scene), width_px, height_px), "array"


def _read_frame_layout(path: Path) -> np.ndarray | None:
    """A scene in a layout the frame reader knows (grey/RGB(A) PNG, JPEG, TIFF), decoded by it, which refuses
    damaged data (a JPEG cut short decodes with OpenCV's imread as a half-grey picture and a libjpeg warning).
    None for the other layouts (palette PNG, float TIFF, ...), which the permissive readers below take."""
    from fieldcal.formats.imageio import ImageFileError, probe, read_image

    try:
        header = probe(path)
    except OSError:
        return None
    except ImageFileError as e:
        if e.what.startswith("has an unreadable"):  # a damaged header, not merely a layout frames do not use
            raise ParameterError(f"scene image {e.what}", path=path, field="scene", fix=e.fix) from None
        return None
    try:
        return read_image(path, header=header)
    except ImageFileError as e:
        raise ParameterError(f"scene image {e.what}", path=path, field="scene", fix=e.fix) from None


def _read_file(path: Path) -> np.ndarray:
    if not path.is_file():
        raise ParameterError("scene image not found", path=path, field="scene",
                             fix="give chart, charuco, slanted-edge or the path of an image file")
    from fieldcal.formats.imageio import ImageFileError, check_image_file
    try:
        check_image_file(path)  # a tiny file may declare a gigapixel image: refuse before decoding
    except ImageFileError as e:
        raise ParameterError(f"scene image {e.what}", path=path, field="scene", fix=e.fix) from None
    img = _read_frame_layout(path)
    if img is None and path.suffix.lower() in (".tif", ".tiff"):
        try:
            import tifffile
            img = tifffile.imread(path)
        except Exception:  # not a TIFF tifffile understands: let OpenCV try
            img = None
    if img is None:
        from fieldcal.formats.imageio import _PNG_SIGNATURE, check_png_chunks, cv2_quiet

        try:
            with open(path, "rb") as f:
                is_png = f.read(8) == _PNG_SIGNATURE
            if is_png:  # libpng's own error line would come before ours
                check_png_chunks(np.fromfile(path, dtype=np.uint8))
        except ImageFileError as e:
            raise ParameterError(f"scene image {e.what}", path=path, field="scene", fix=e.fix) from None
        with cv2_quiet():  # our error replaces its warnings
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
        if img is not None and img.ndim == 3:
            code = cv2.COLOR_BGRA2RGBA if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
            img = cv2.cvtColor(img, code)
    if img is None:
        raise ParameterError("scene image cannot be read (not an image format OpenCV or tifffile decodes)",
                             path=path, field="scene", fix="convert it to PNG, JPEG or TIFF")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]  # drop alpha
    if img.ndim == 3 and img.shape[2] not in (1, 3):
        raise ParameterError(f"scene image has {img.shape[2]} channels", path=path, field="scene",
                             fix="use a grey or RGB image")
    return img


def _to_unit(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if np.issubdtype(img.dtype, np.floating):
        a = img.astype(np.float32)
        if not np.all(np.isfinite(a)):
            raise ParameterError("scene has NaN or infinite values", field="scene", fix="repair the image")
        return np.clip(a, 0.0, 1.0)
    if img.dtype == bool:
        return img.astype(np.float32)
    raise ParameterError(f"scene of dtype {img.dtype} is not supported", field="scene",
                         fix="use uint8, uint16 or float data in [0, 1]")


def fit_to_sensor(img: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Centre-crop to the sensor aspect ratio and resize with INTER_AREA; float32 in [0, 1]."""
    if img.ndim not in (2, 3) or img.shape[0] < 1 or img.shape[1] < 1:
        raise ParameterError(f"scene must be an H x W or H x W x C image, got shape {img.shape}", field="scene",
                             fix="pass a 2-D (grey) or 3-D (RGB) image")
    a = _to_unit(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    h, w = a.shape[:2]
    if (w, h) == (width_px, height_px):
        return a
    target = width_px / height_px
    if w / h > target:  # too wide: crop columns
        cw = max(1, round(h * target))
        x0 = (w - cw) // 2
        a = a[:, x0:x0 + cw]
    else:
        ch = max(1, round(w / target))
        y0 = (h - ch) // 2
        a = a[y0:y0 + ch]
    interp = cv2.INTER_AREA if a.shape[1] >= width_px else cv2.INTER_CUBIC  # AREA shrinks, cubic enlarges
    out = cv2.resize(np.ascontiguousarray(a), (width_px, height_px), interpolation=interp)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
