"""All-in-focus composite of a stack from a lens profile: each pixel and channel from the frame(s) at its
best focus, in the geometry of ``z_ref``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError, StackError
from ..optics import LensModel, MTFCriterion
from .source import image_size, z_positions
from .stream import DEFAULT_TILE_PX, accumulate
from .surface import default_fs_cyc_per_mm, profile_focus_map, profile_tolerance_um
from .weights import BlendKernel


@dataclass
class CompositeResult:
    """A composite: ``image`` in the input's dtype and scale, the best-focus map used, and what was done."""

    image: np.ndarray
    method: str
    focus_map_um: np.ndarray
    info: dict = field(default_factory=dict)


def to_input_dtype(acc: np.ndarray, dtype, white_level: float) -> np.ndarray:
    """Round and clip a float composite to the input's dtype without rescaling (12-bit stays 0-4095)."""
    dtype = np.dtype(dtype)
    if np.issubdtype(dtype, np.integer):
        top = min(float(np.iinfo(dtype).max), float(white_level))
        tmp = np.rint(acc)  # one temporary, then in place: the caller's array is left alone
        np.clip(tmp, 0, top, out=tmp)
        return tmp.astype(dtype)
    return acc.astype(dtype)


def check_profile_matches(stack, profile: LensModel, where=None) -> None:
    """The profile must describe the stack's image size and channels."""
    w, h = image_size(stack)
    size = tuple(int(v) for v in profile.image_size_px)
    if size != (w, h):
        raise ParameterError(f"the profile is for {size[0]}x{size[1]} px images but the stack has {w}x{h}",
                             path=where, field="image_size_px",
                             fix="use the profile calibrated for this camera and image size")
    missing = [c for c in stack.channels if c not in tuple(profile.channels)]
    if missing:
        raise ParameterError(f"the profile has no channel(s) {missing} (it has {list(profile.channels)})",
                             path=where, field="channels", fix="use a profile calibrated for this camera")


def select_frames(stack, frames=None) -> np.ndarray:
    """File indices to use (all by default), validated."""
    if stack.cfa:
        raise StackError(f"a raw {stack.cfa} mosaic stack cannot be composited per channel",
                         path=stack.path, field="cfa", fix="demosaic the frames first (H x W x 3)")
    n = len(stack)
    idx = np.arange(n) if frames is None else np.asarray(frames, dtype=int)
    if len(idx) == 0:
        raise StackError("too few frames for compositing: none selected", path=stack.path,
                         fix="select at least one frame")
    if idx.min() < 0 or idx.max() >= n:
        raise ParameterError(f"frame index out of range 0..{n - 1}", field="frames", fix="use valid frame indices")
    return np.unique(idx)


def blend_kernel(stack, profile, frames, fs_cyc_per_mm=None, q: float = 0.05,
                 min_band: float = 0.25) -> BlendKernel:
    """The stack-blending kernel for the chosen frames, its band set by the (median) focus tolerance."""
    w, h = image_size(stack)
    z = np.sort(z_positions(stack)[frames])
    tol = 0.0
    if profile is not None and len(z) > 1:
        fs = default_fs_cyc_per_mm(float(profile.pixel_pitch_um)) if fs_cyc_per_mm is None else fs_cyc_per_mm
        crit = MTFCriterion(fs, q)
        tol = min(profile_tolerance_um(profile, w, h, c, crit) for c in stack.channels)
    return BlendKernel(z, tol, min_band=min_band)


def composite_with_map(stack, zb: np.ndarray, kernel, profile, frames, *, lateral_colour=False,
                       tile=DEFAULT_TILE_PX, quiet=False, desc="compositing") -> np.ndarray:
    """Stream the frames through ``kernel`` at best-focus map ``zb``; result in the input's dtype."""
    dtype, white = stack.dtype, stack.white_level
    # each finished band goes straight to the input's dtype: no full-size float32 image
    return accumulate(stack, zb, kernel, profile, lateral_colour=lateral_colour, tile=tile, frames=frames,
                      desc=desc, quiet=quiet, finish=lambda band: to_input_dtype(band, dtype, white))


def composite_profile(stack, profile, *, frames=None, fs_cyc_per_mm=None, q: float = 0.05,
                      min_band: float = 0.25, lateral_colour: bool = False, tile: int = DEFAULT_TILE_PX,
                      focus_offset_um: float = 0.0, quiet: bool = False) -> CompositeResult:
    """Composite a stack with the profile's best-focus surfaces and geometry.

    Parameters
    ----------
    stack : Stack or ArrayStack
    profile : lens profile (``LensProfile`` or ``TruthProfile``)
    frames : array of int, optional
        File indices to use (default: all).
    fs_cyc_per_mm, q : float
        Frequency and MTF drop that define the focus tolerance, which sets the width of the seams
        (default: a quarter of Nyquist, 5 %).
    min_band : float
        Narrowest seam as a fraction of the frame spacing.
    lateral_colour : bool
        Also undo the per-channel scale (lateral colour).
    focus_offset_um : float
        Added to every best focus (a plan's ``refocus_um`` for another object distance).
    """
    check_profile_matches(stack, profile)
    frames = select_frames(stack, frames)
    w, h = image_size(stack)
    zb = profile_focus_map(profile, w, h, stack.channels, lateral_colour)
    zb += np.float32(focus_offset_um)
    kernel = blend_kernel(stack, profile, frames, fs_cyc_per_mm, q, min_band)
    img = composite_with_map(stack, zb, kernel, profile, frames, lateral_colour=lateral_colour, tile=tile,
                             quiet=quiet)
    return CompositeResult(img, "profile", zb, {"frames_used": int(len(frames)),
                                                "seam_half_band": float(np.max(kernel.half_band, initial=0.0))})
