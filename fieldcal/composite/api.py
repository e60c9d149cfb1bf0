"""One entry point for stack compositing: ``composite_stack(stack, profile, method=...)``."""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from .dff import dff_focus_map, dff_surfaces, focus_volume, hybrid_corrections
from .source import image_size
from .stack_profile import (CompositeResult, blend_kernel, check_profile_matches, composite_profile,
                            composite_with_map, select_frames)
from .stream import DEFAULT_TILE_PX
from .surface import dense_map, profile_focus_map

METHODS = ("profile", "dff", "hybrid")


def composite_stack(stack, profile=None, method: str | None = None, *, frames=None, fs_cyc_per_mm=None,
                    q: float = 0.05, min_band: float = 0.25, lateral_colour: bool = False,
                    block_px: int | None = None, tile: int = DEFAULT_TILE_PX, focus_offset_um: float = 0.0,
                    register: bool = True, z_ref_um: float | None = None, quiet: bool = False) -> CompositeResult:
    """All-in-focus composite of a stack.

    Parameters
    ----------
    stack : fieldcal.Stack or ArrayStack
    profile : lens profile or None
        ``LensProfile`` (or ``TruthProfile`` for simulated lenses). Without one only ``dff`` is possible,
        with frames assumed registered.
    method : {"profile", "dff", "hybrid"}, optional
        ``profile``: best focus and geometry from the profile. ``dff``: best focus measured from the stack
        (depth from focus, surface-fitted), geometry from the profile if given. ``hybrid``: the profile's
        surfaces refined by a low-order DFF correction bounded by the profile's uncertainty.
        Default: ``profile`` with a profile, ``dff`` without.
    frames : array of int, optional
        File indices to use (e.g. a plan's frames); default all.
    fs_cyc_per_mm, q, min_band, lateral_colour, tile
        See :func:`composite_profile`.
    block_px : int, optional
        DFF block size (px).
    focus_offset_um : float
        Added to the profile's best focus (a plan's ``refocus_um``); not used by ``dff``.
    register, z_ref_um
        ``dff`` without a profile: measure focus breathing and shift from the stack (:mod:`.register`) and
        write the output in the geometry of the frame at ``z_ref_um`` (default: the middle frame);
        ``register=False`` takes the frames as registered.
    """
    method = method or ("profile" if profile is not None else "dff")
    if method not in METHODS:
        raise ParameterError(f"unknown method {method!r}", field="--method", fix=f"use one of {', '.join(METHODS)}")
    if method in ("profile", "hybrid") and profile is None:
        raise ParameterError(f"method '{method}' needs a lens profile", field="--profile",
                             fix="give --profile PROFILE, or use --method dff")
    if method == "profile":
        return composite_profile(stack, profile, frames=frames, fs_cyc_per_mm=fs_cyc_per_mm, q=q,
                                 min_band=min_band, lateral_colour=lateral_colour, tile=tile,
                                 focus_offset_um=focus_offset_um, quiet=quiet)
    if profile is not None:
        check_profile_matches(stack, profile)
    frames = select_frames(stack, frames)
    w, h = image_size(stack)
    channels = tuple(stack.channels)
    geometry = profile
    info: dict = {"frames_used": int(len(frames))}
    if profile is None and register and len(frames) > 1:
        from .register import estimate_geometry
        geometry = estimate_geometry(stack, frames, z_ref_um=z_ref_um, quiet=quiet)
        info["registration"] = geometry.info()
    vol = focus_volume(stack, geometry, frames=frames, block_px=block_px, lateral_colour=lateral_colour,
                       quiet=quiet)
    info["block_px"] = vol.block_px
    if method == "dff":
        centre = tuple(profile.optical_centre_px()) if profile is not None else None
        surfaces = dff_surfaces(vol, w, h, channels, centre)
        zb = dff_focus_map(surfaces, w, h)
        info["surface_rms_um"] = {c: round(s.rms_um, 3) for c, s in zip(channels, surfaces)}
        info["surface_degree"] = {c: s.degree for c, s in zip(channels, surfaces)}
    else:
        zb = profile_focus_map(profile, w, h, channels, lateral_colour) + np.float32(focus_offset_um)
        corr = hybrid_corrections(vol, profile, w, h, channels, lateral_colour=lateral_colour,
                                  focus_offset_um=focus_offset_um)
        for ci, (fit, limit) in enumerate(corr):
            zb[..., ci] += np.clip(dense_map(fit, w, h), -limit, limit)
        info["correction_limit_um"] = {c: round(lim, 3) for c, (_, lim) in zip(channels, corr)}
    kernel = blend_kernel(stack, profile, frames, fs_cyc_per_mm, q, min_band)
    img = composite_with_map(stack, zb, kernel, geometry, frames, lateral_colour=lateral_colour, tile=tile,
                             quiet=quiet)
    return CompositeResult(img, method, zb, info)
