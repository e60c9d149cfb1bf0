"""Compositing's public entry points.

* :func:`composite_stack` — an all-in-focus composite of a stack (profile / depth from focus / hybrid);
* :func:`select_plan_frames` — the stack frames a stack plan asked for, and the plan's criterion;
* :func:`composite_sweep` — emulate a focal sweep from a stack and deconvolve it;
* :func:`restore_sweep_image` — deconvolve a captured sweep image;
* :func:`composite_to_file` — the whole ``fieldcal composite`` path: any of the above from files, to a TIFF.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._numeric import channel_mean
from ..errors import ParameterError, SpecError, StackError
from .dff import dff_focus_map, dff_surfaces, focus_volume, hybrid_corrections, pixel_misfit_fraction, row_bands
from .source import hold_decoded, image_size, z_positions
from .stack_profile import (CompositeResult, blend_kernel, check_profile_matches, composite_profile,
                            composite_with_map, select_frames)
from .stream import DEFAULT_TILE_PX
from .surface import dense_map, profile_focus_map

METHODS = ("profile", "dff", "hybrid")
DEPTH_MODES = ("auto", "flat", "3d")
#: ``depth="auto"``: the scene has depth when more than these fractions of the confident DFF blocks lie off the
#: smooth surface fitted to them by (a) a frame spacing, (b) half the curves' width (see
#: :func:`surface_misfit_fractions`). Measured (simulated triplet at 160 and 320 px, steps of 1 and 1.5
#: tolerances, without a profile): (a) flat chart and colour scenes 0-0.9 %, a flat chart with a textureless
#: quarter at fine 4 µm steps 6.4 %; steps 14-35 %, slopes 17-38 %, reliefs 8-25 %, thin bars 4-17 %; the real
#: circuit-board stack 12.6 %. (b) flat 0-4.1 %; reliefs 4.6-15 %, slopes 7-12 %, thin bars 3.9-13 %. Thin bars
#: at 320 px (4-5 %, 3.9-4.1 %) are taken as flat: few blocks see them.
DEPTH_BLOCK_FRACTION = (0.1, 0.05)
#: ... or when more than this fraction of the textured pixels peak a frame spacing and a third of a curve width
#: or more off that surface (:func:`fieldcal.composite.dff.pixel_misfit_fraction`: thin or small things that
#: blocks average away). Measured (simulated triplet, layers continued behind nearer ones, 160 px; steps of 0.5,
#: 1, 1.5, 2.5 and 3.5 tolerances): flat texture chart and colour dead leaves 0-0.17 % (0 % at 320 px); thin bars
#: 11-19 %, slopes 4.5-20 %, steps 3-14 % (0 at 3.5 tolerances a frame), reliefs 1.5-7 %.
DEPTH_PIXEL_FRACTION = 0.01
#: Scenes with depth: a pixel takes the depth map's composite in full where its confidence reaches this fraction
#: (second) of the given percentile (first) of the image's confidences, the multi-scale fusion where it has none.
FUSION_CONFIDENCE = (75.0, 0.5)
#: ... and where the fusion's own frame choice does not contradict the depth map: it lies within this many frame
#: steps of the depths the map gives within the choice's reach (:func:`fusion_contradicts`). One step: the map's
#: sub-frame peak is good to a tenth or two of a step (its measured error σ_k 0.03-0.13 step), the fusion's choice
#: is a whole frame.
FUSION_AGREEMENT_FRAMES = 1.0
#: A defocus measured from the stack (no lens model): the Wiener combination's depth labels this many frame steps
#: apart (or :data:`~.depth_wiener.LABEL_DISC_PX` of disc, if more); the per-pixel depth map's sub-frame peak is
#: good to a tenth or two of a step, so finer labels add work (one inverse FFT per label, channel and tile), not
#: accuracy.
LABEL_FRAMES = 0.125
#: A measured defocus (the same disc in every channel) on RGB: the Wiener combination in YCbCr (JPEG's, Rec. 601
#: full range), luma on labels :data:`LABEL_FRAMES` apart and chroma, whose fine detail is weaker, on labels this
#: many frame steps apart (fewer filters); None filters R, G and B on the luma's labels.
CHROMA_LABEL_FRAMES: float | None = 1.0
YCBCR = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])


def composite_stack(stack, profile=None, method: str | None = None, *, frames=None, fs_cyc_per_mm=None,
                    q: float = 0.05, min_band: float = 0.25, lateral_colour: bool = False,
                    block_px: int | None = None, tile: int = DEFAULT_TILE_PX, focus_offset_um: float = 0.0,
                    register: bool = True, z_ref_um: float | None = None, depth: str = "auto",
                    fine_detail: bool = True, measured_defocus: bool = True, max_memory=None,
                    quiet: bool = False) -> CompositeResult:
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
        ``dff`` without a profile: register the frames to the frame at ``z_ref_um`` (default: the middle frame)
        with the simplest model the data support — scale and shift (breathing, stage axis), similarity,
        affine or homography (:func:`.register.choose_model`) — and write the output in its geometry; each
        frame is read and warped once (:func:`.register.register_stack`), brought to the reference frame's
        exposure and white balance (:mod:`.photometric`), and a frame that does not show what its neighbours
        show is refused (StackError). ``register=False`` takes the frames as registered (and their levels).
    depth : {"auto", "flat", "3d"}
        ``dff`` and ``hybrid``: is the scene a surface (a chart, a flat object) or does it have depth (steps,
        things in front of a background)? ``auto`` decides from the data: when the smooth surface fitted to
        the block depths misses them by more than half a frame spacing (RMS), the scene has depth, and best
        focus is taken per pixel (:func:`fieldcal.composite.fusion.depth_map`, edge-aware) instead of from
        the surface. The profile (``hybrid``) keeps the pixels the data cannot tell apart from it. With a lens
        model that states its F-number, the best focus is made occlusion-aware and the frames around each
        pixel's depth are combined by a multi-frame Wiener filter (:mod:`fieldcal.composite.depth_wiener`).
    fine_detail : bool
        A scene with depth composited without the Wiener filter (no profile, or no F-number): the two finest
        pyramid levels per coefficient from the sharpest frame near the depth map's choice
        (:mod:`fieldcal.composite.detail`). ``False`` keeps the depth map's blend there.
    measured_defocus : bool
        A scene with depth and registered frames but no lens model with an F-number: measure the blur disc's
        growth per frame step from the stack (:mod:`fieldcal.composite.defocus_rate`) and, where that measurement
        is reliable, combine the frames by the multi-frame Wiener filter of that disc's OTF as with a profile;
        where it is not (too little texture, frames that barely change focus, a blur that does not grow
        linearly) the frames are chosen as without it, and ``info["defocus_rate"]["reason"]`` says why.
    max_memory : int or str, optional
        ``dff`` and ``hybrid``: the memory the composite may take (bytes, or ``"8G"``); default the memory
        available now. A composite whose measured peak (:func:`fieldcal.composite.memory.estimate_peak_bytes`:
        it grows with the pixels, not the frames) exceeds it is refused before any work (ResourceError).
    """
    if depth not in DEPTH_MODES:
        raise ParameterError(f"unknown depth mode {depth!r}", field="depth", fix=f"use one of {', '.join(DEPTH_MODES)}")
    method = method or ("profile" if profile is not None else "dff")
    if method not in METHODS:
        raise ParameterError(f"unknown method {method!r}", field="method", fix=f"use one of {', '.join(METHODS)}")
    if method in ("profile", "hybrid") and profile is None:
        raise ParameterError(f"method '{method}' needs a lens profile", field="profile",
                             fix="give a lens profile, or use the dff method (depth from focus)")
    if method == "profile":
        # JPEG/PNG frames decode whole per read: decoded once here instead of once per band
        check_profile_matches(stack, profile)
        src = hold_decoded(stack, select_frames(stack, frames), quiet=quiet)
        return composite_profile(src, profile, frames=frames, fs_cyc_per_mm=fs_cyc_per_mm, q=q,
                                 min_band=min_band, lateral_colour=lateral_colour, tile=tile,
                                 focus_offset_um=focus_offset_um, quiet=quiet)
    if profile is not None:
        check_profile_matches(stack, profile)
    frames = select_frames(stack, frames)
    w, h = image_size(stack)
    channels = tuple(stack.channels)
    geometry = profile
    info: dict = {"frames_used": int(len(frames))}
    # before minutes of work: the out-of-memory killer would end it without a word (composite/memory.py)
    from .memory import check_memory, parse_memory_bytes
    check_memory(w, h, len(channels), len(frames), max_memory_bytes=parse_memory_bytes(max_memory),
                 where=getattr(stack, "path", None))
    if profile is None and register and len(frames) > 1:
        # each frame decoded once and warped once into the reference geometry; every pass below reads those
        from .register import register_stack
        stack, reg = register_stack(stack, frames, z_ref_um=z_ref_um, quiet=quiet)
        info["registration"] = reg.info()
        info["photometric"] = stack.photometric
        geometry = None
    else:
        if profile is None and register and z_ref_um is not None:
            # one frame is its own reference: a position away from it is refused as for a longer stack (never
            # ignore a flag)
            from .register import _sorted_frames
            _sorted_frames(stack, frames, z_ref_um)
        stack = hold_decoded(stack, frames)
    vol = focus_volume(stack, geometry, frames=frames, block_px=block_px, lateral_colour=lateral_colour,
                       quiet=quiet)
    info["block_px"] = vol.block_px
    centre = tuple(profile.optical_centre_px()) if profile is not None else None
    surfaces = dff_surfaces(vol, w, h, channels, centre)
    spacing = float(np.median(np.diff(vol.z_um))) if len(vol.z_um) > 1 else 0.0
    off_spacing, off_width = surface_misfit_fractions(vol, surfaces, spacing)
    off_pixels = pixel_misfit_fraction(vol, surfaces, spacing)
    # a flat scene's confident blocks lie on a smooth surface within their own noise; a scene with depth puts a
    # good part of them (a step, an object in front) a spacing, and a curve width, or more away from any, or
    # (thin things) a part of its textured pixels
    has_depth = depth == "3d" or (depth == "auto" and len(vol.z_um) > 2 and (
        off_spacing > DEPTH_BLOCK_FRACTION[0] or off_width > DEPTH_BLOCK_FRACTION[1]
        or off_pixels > DEPTH_PIXEL_FRACTION))
    info.update({"surface_rms_um": {c: round(s.rms_um, 3) for c, s in zip(channels, surfaces)},
                 "frame_spacing_um": round(spacing, 3),
                 "blocks_off_surface": {"by_a_spacing": round(off_spacing, 4), "by_half_a_width": round(off_width, 4)},
                 "pixels_off_surface": round(off_pixels, 4),
                 "scene": "3d" if has_depth else "flat"})
    fallback = dmap = noise_probe = None
    if (has_depth and measured_defocus and geometry is None and not getattr(profile, "f_number", None)
            and CHROMA_LABEL_FRAMES and channels == ("R", "G", "B")):
        # the YCbCr Wiener step of a measured defocus (below) needs the frames' noise, and only the frames: it is
        # measured on a thread of its own while the depth map's serial stretches, the defocus measurement (mostly
        # serial), the cones (serial) and the blend run; the luma and chroma calls share it (unused where the
        # defocus is not measured reliably)
        noise_probe = _background(_probe_ycc, stack, frames, geometry, lateral_colour)
    if method == "dff":
        zb = dff_focus_map(surfaces, w, h)
        info["surface_degree"] = {c: s.degree for c, s in zip(channels, surfaces)}
        if has_depth:
            zb, fallback, dmap = _per_pixel_focus(stack, geometry, frames, zb, quiet)
    else:
        zb = profile_focus_map(profile, w, h, channels, lateral_colour) + np.float32(focus_offset_um)
        corr = hybrid_corrections(vol, profile, w, h, channels, lateral_colour=lateral_colour,
                                  focus_offset_um=focus_offset_um)
        info["correction_limit_um"] = {c: round(lim, 3) for c, (_, lim) in zip(channels, corr)}
        if not has_depth:
            for ci, (fit, limit) in enumerate(corr):
                zb[..., ci] += np.clip(dense_map(fit, w, h), -limit, limit)
        else:
            # the data where they differ from the profile by more than its band allows, the profile elsewhere; the
            # profile uncorrected, as the low-order correction would be fitted to the scene's own depth (steps pull
            # it up to its limit off the profile where the scene does lie on it: -0.5 dB, bench_depth_scenes)
            per_pixel, fallback, dmap = _per_pixel_focus(stack, geometry, frames, zb, quiet)
            limit = np.array([lim for _, lim in corr], dtype=np.float32)
            off = np.abs(per_pixel - zb) > limit
            zb = np.where(off, per_pixel, zb).astype(np.float32)
            info["pixels_from_data"] = round(float(off.mean()), 4)
    defocus = profile if profile is not None and getattr(profile, "f_number", None) else None
    if has_depth and defocus is None and measured_defocus and dmap is not None and geometry is None:
        # no lens model: the defocus per frame step measured on the registered frames (composite/defocus_rate.py)
        defocus = _measured_defocus(stack, frames, dmap, info, quiet)
    wiener = has_depth and defocus is not None
    measured = wiener and defocus is not profile
    ycc_split = measured and CHROMA_LABEL_FRAMES and channels == ("R", "G", "B")
    if ycc_split and noise_probe is None:  # (with a geometry: the frames warped to it, as the Wiener step reads them)
        noise_probe = _background(_probe_ycc, stack, frames, geometry, lateral_colour)
    signal = None
    if ycc_split and fallback is not None:
        # the Wiener step's reference (the fusion's image, _depth_composite) in its planes and their signal power
        # laws, fitted on a thread while this one makes the occlusion cones (serial) below
        from .depth_wiener import reference_signal
        probe, fused = noise_probe, fallback[0]
        signal = _background(lambda: reference_signal(fused, defocus, channels, probe.result(), mix=YCBCR,
                                                      label_um=_ycc_label_um(spacing)))
    if wiener:
        # a nearer object's blur disc kept off the pixels beside it (composite/depth_wiener.py)
        from .depth_wiener import occlusion_focus_um
        um_per_px = 2.0 * float(defocus.f_number) * float(defocus.pixel_pitch_um)
        if measured:
            # one depth map plus each channel's smooth offset (_per_pixel_focus): the cones of their mean, the
            # offsets kept (a third of the work; a measured disc is the same in every channel)
            mean = _channel_mean(zb)
            cones = occlusion_focus_um(mean, um_per_px)
            zb_cones = np.empty(zb.shape, np.result_type(zb, mean, cones))

            def rows(a: int, b: int, zb=zb) -> None:
                zb_cones[a:b] = (zb[a:b] - mean[a:b, :, None]) + cones[a:b, :, None]

            row_bands(rows, zb.shape[0])
            zb = zb_cones
            del cones, zb_cones
        else:
            zb = occlusion_focus_um(zb, um_per_px)
    if fallback is not None:
        fallback = (fallback[0], fallback[1].result())  # the trust weight (_per_pixel_focus)
    detail = has_depth and (not wiener or measured) and fine_detail
    if detail:
        # the fine detail's frame index per pixel, interpolated from the final map's mean (taken here: the thread
        # reads no array the blend might share) beside the blend, not in a serial pass after it
        z_sorted = np.sort(z_positions(stack)[np.asarray(frames, dtype=int)])
        zb_mean = _channel_mean(zb)
        kd = _background(lambda: np.interp(zb_mean, z_sorted,
                                           np.arange(len(z_sorted), dtype=np.float64)).astype(np.float32))
    img = _depth_composite(stack, profile, frames, zb, defocus, fallback, info, geometry=geometry,
                           has_depth=has_depth, wiener=wiener, measured=measured, ycc_split=ycc_split,
                           noise_probe=noise_probe, signal=signal, spacing=spacing, lateral_colour=lateral_colour,
                           fs_cyc_per_mm=fs_cyc_per_mm, q=q, min_band=min_band, tile=tile, quiet=quiet)
    if detail:
        # the finest octaves per coefficient from the sharpest frame near the depth map's choice
        # (composite/detail.py): what a blend of two frames dilutes, without a far frame's noise or ghost. (Run
        # beside the blend and Wiener step on threads of its own it cost 7 % more CPU, page faults, and 5 % more
        # wall on two cores: bench_composite_speed_s15.)
        from .detail import fine_detail as add_fine_detail
        from .stack_profile import to_input_dtype
        sharp, info["fine_detail"] = add_fine_detail(stack, img, kd.result(), frames, geometry=geometry,
                                                     support=getattr(stack, "support", None), keep_base=measured,
                                                     quiet=quiet)
        img = to_input_dtype(sharp, img.dtype, float(stack.white_level))
    return CompositeResult(img, method, zb, info)


def _channel_mean(zb: np.ndarray) -> np.ndarray:
    """``zb.mean(axis=2)`` of an ``H x W x C`` map, made in row bands on the compositor's threads (each pixel's
    mean is the same sum; the strided reduction took ~0.06-0.08 s a call with one core idle)."""
    out = np.empty(zb.shape[:2], zb[:1, :1].mean(axis=2).dtype)

    def rows(a: int, b: int) -> None:
        channel_mean(zb[a:b], out=out[a:b])  # the same numbers as zb[a:b].mean(axis=2), ~4x faster

    row_bands(rows, zb.shape[0])
    return out


def _background(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` started on a thread of its own; its :class:`~concurrent.futures.Future`."""
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fieldcal-background")
    try:
        return pool.submit(fn, *args, **kwargs)
    finally:
        pool.shutdown(wait=False)  # the call runs on; its result is taken from the future


def _ycc_label_um(spacing: float) -> list[float]:
    """The YCbCr Wiener step's label spacing per plane (µm): luma LABEL_FRAMES of a frame step apart (the measured
    depth map is known no better), chroma CHROMA_LABEL_FRAMES (its fine detail is weaker)."""
    return [LABEL_FRAMES * spacing] + [CHROMA_LABEL_FRAMES * spacing] * 2


def _probe_ycc(stack, frames, geometry, lateral_colour: bool) -> list[float]:
    """The frames' noise in the YCbCr planes the measured-defocus Wiener step filters (in ``geometry``)."""
    from .depth_wiener import probe_plane_sigma

    return probe_plane_sigma(stack, frames, geometry=geometry, lateral_colour=lateral_colour, mix=YCBCR)


def _depth_composite(stack, profile, frames, zb, defocus, fallback, info: dict, *, geometry, has_depth: bool,
                     wiener: bool, measured: bool, ycc_split: bool, noise_probe, signal, spacing: float,
                     lateral_colour: bool, fs_cyc_per_mm, q, min_band, tile, quiet: bool) -> np.ndarray:
    """The blend along the best-focus map ``zb``, combined by the Wiener filter where there is a defocus model and
    mixed with the multi-scale fusion where the depth map is unsure (scenes with depth): the image that fine
    detail is added to. With a measured defocus the fusion's image is the Wiener step's reference and no blend is
    made (``signal``, when given, is that reference's :class:`~.depth_wiener.ReferenceSignal`, made on a thread)."""
    dtype = np.dtype(stack.dtype)
    if wiener and measured and fallback is not None:
        # A measured defocus's Wiener step is used only where the depth map is trusted and the fusion is taken
        # elsewhere (the weight below): the blend along the map would serve only as the Wiener step's reference
        # (its signal spectrum, and its pixels where the weight is below 1/256, i.e. < 1/256 of the final value).
        # The fusion's image is a composite of the same scene as well: it is the reference, and the blend is not
        # made (bench_composite_speed_s20)
        img = fallback[0]
    else:
        kernel = blend_kernel(stack, profile, frames, fs_cyc_per_mm, q, min_band)
        img = composite_with_map(stack, zb, kernel, geometry, frames, lateral_colour=lateral_colour, tile=tile,
                                 quiet=quiet)
    if wiener:
        # the frames around each pixel's depth combined by the lens's defocus OTF, not one frame chosen
        from .depth_wiener import wiener_composite
        from .stack_profile import to_input_dtype
        # with a measured defocus, labels LABEL_FRAMES of a frame step apart (the depth map is known no better)
        label_um = LABEL_FRAMES * spacing if measured else None
        # ... and filtered only where it will be used: the fusion takes the pixels the depth map is unsure of
        needed = fallback[1] >= np.float32(1.0 / 256.0) if measured and fallback is not None else None
        if ycc_split:
            # luma and chroma apart, the chroma on coarser labels (CHROMA_LABEL_FRAMES), in one pass over the
            # tiles (each tile's frames read once for the three planes; the same numbers as a call per group); the
            # noise of all three planes from one read of the probe frames
            ycc, winfo = wiener_composite(stack, zb, defocus, frames, img, geometry=geometry,
                                          lateral_colour=lateral_colour, needed=needed, mix=YCBCR,
                                          label_um=_ycc_label_um(spacing), plane_sigma=noise_probe.result(),
                                          signal=signal.result() if signal is not None else None, quiet=quiet)
            to_rgb = np.linalg.inv(YCBCR).T.astype(np.float32)
            rgb = np.empty(img.shape, dtype)  # the luma and chroma planes back to the three channels

            def rows(a: int, b: int) -> None:  # per pixel, in row bands on the compositor's threads (was serial)
                rgb[a:b] = to_input_dtype(ycc[a:b] @ to_rgb, rgb.dtype, float(stack.white_level))

            row_bands(rows, rgb.shape[0])
            img = rgb
            luma, chroma = ({k: v for k, v in g.items() if k != "plane_index"} for g in winfo["groups"])
            info["wiener"] = {**luma, "filters": winfo["filters"], "chroma": chroma}
        else:
            combined, info["wiener"] = wiener_composite(stack, zb, defocus, frames, img, geometry=geometry,
                                                        lateral_colour=lateral_colour, label_um=label_um,
                                                        needed=needed, quiet=quiet)
            img = to_input_dtype(combined, dtype, float(stack.white_level))
    if has_depth and fallback is not None and (not wiener or defocus is not profile):
        # where the depth map is unsure (little texture), the multi-scale fusion's pixels: it needs no depth
        from .stack_profile import to_input_dtype
        fused, weight = fallback
        mixed = np.empty(np.broadcast_shapes(img.shape, fused.shape), img.dtype)

        def rows(a: int, b: int, img=img) -> None:  # per pixel, in row bands on the compositor's threads
            w = weight[a:b, :, None]
            # rounded to the input's dtype in the band as well (per pixel: the same numbers as after the bands)
            mixed[a:b] = to_input_dtype(w * img[a:b].astype(np.float32) + (1.0 - w) * fused[a:b], mixed.dtype,
                                        float(stack.white_level))

        row_bands(rows, mixed.shape[0])
        img = mixed
        info["pixels_from_fusion"] = round(float(np.mean(1.0 - weight)), 4)
    return img


def surface_misfit_fractions(vol, surfaces, spacing_um: float) -> tuple[float, float]:
    """How far the confident DFF blocks (all channels) lie from the smooth surface fitted to them
    (:func:`fieldcal.composite.dff.dff_surfaces`): the fraction off by a frame spacing or more, and the fraction
    off by more than half the through-focus curves' median width at half height (the blocks' own peak noise
    scales with that width, which fine steps make larger than a spacing)."""
    from .dff import _block_weights, peak_depth

    zbest, conf = peak_depth(vol)
    xx, yy = np.meshgrid(vol.x_px, vol.y_px)
    v = vol.values.astype(np.float64)
    half = 0.5 * (v.max(axis=0) + np.median(v, axis=0))
    width = np.sum(v >= half[None], axis=0) * spacing_um  # frames above half height x spacing (FWHM)
    res, widths = [], []
    for ci, s in enumerate(surfaces):
        w = _block_weights(conf[..., ci])
        r = zbest[..., ci] - s(xx, yy)
        ok = (w > 0) & np.isfinite(r)
        res.append(np.abs(r[ok]))
        widths.append(width[..., ci][ok])
    r = np.concatenate(res) if res else np.zeros(0)
    if r.size == 0:
        return 0.0, 0.0
    fwhm = float(np.median(np.concatenate(widths)))
    return float(np.mean(r >= spacing_um)), float(np.mean(r > max(spacing_um, 0.5 * fwhm)))


def _measured_defocus(stack, frames, dmap, info: dict, quiet: bool):
    """The defocus model measured from registered frames and their depth map (a
    :class:`~fieldcal.composite.defocus_rate.MeasuredDefocus`), or None where the measurement is unreliable;
    ``info["defocus_rate"]`` records it either way, and a fallback is said on stderr."""
    import sys

    from .defocus_rate import MeasuredDefocus, estimate_defocus_rate

    z_sorted = np.sort(z_positions(stack)[np.asarray(frames, dtype=int)])
    kd = np.interp(dmap.z_um, z_sorted, np.arange(len(z_sorted), dtype=np.float64))
    est = estimate_defocus_rate(stack, frames, kd, dmap.confidence)
    info["defocus_rate"] = est.info()
    if not est.reliable:
        if not quiet:
            print(f"fieldcal composite: defocus not measured reliably ({est.reason}); frames chosen per pixel, "
                  "not combined", file=sys.stderr)
        return None
    pitch = getattr(stack, "pixel_pitch_um", None)
    # the depth map's own scatter (in frame steps) makes the filter robust to it (composite/defocus_rate.py)
    return MeasuredDefocus(est, float(pitch) if pitch else 1.0, est.depth_sd_steps)


def fusion_contradicts(index: np.ndarray, fused_index: np.ndarray, reach_px: float,
                       tolerance_frames: float = FUSION_AGREEMENT_FRAMES) -> np.ndarray:
    """Where the fusion's frame choice contradicts the depth map (H x W bool): no pixel within ``reach_px`` (a
    square of that half-width) has a depth within ``tolerance_frames`` of it (both maps in frame indices, z
    order; the fusion's choice a whole frame).

    The fusion's choice (:attr:`.fusion.FusionResult.depth_index`) is the most salient frame of a coarse pyramid
    level over a window, median-filtered: it is the depth of *something* within ``reach_px``
    (:func:`.fusion.index_reach_px`), not necessarily of the pixel itself. Over a stretch of one depth it is an
    independent measurement of that depth; beside a depth edge or over a structure narrower than the reach (a
    thin bar, a wire: they take the surroundings' frame, or lend theirs to them) it is either side's, and only a
    choice that is no depth the map finds nearby is a contradiction. The pixel-wise test ``|index - fused| > 1``
    flagged 64 % of the simulated thin bars' pixels, whose depth the map had right (docs/compositing.md, step 6).
    """
    import cv2

    ix = np.asarray(index, dtype=np.float32)
    choice = np.rint(np.asarray(fused_index, dtype=np.float32)).astype(np.int32)
    r = max(int(np.ceil(reach_px)), 0)
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)  # square: separable in OpenCV
    tol = np.float32(tolerance_frames)
    h, w = ix.shape
    out = np.zeros(ix.shape, bool)
    for k in range(int(choice.min()), int(choice.max()) + 1):
        # one dilation per frame the fusion chose, "is depth k (+- tol) within reach?", over the rows and columns
        # around the pixels that chose it
        at_k = choice == k
        rows, cols = np.flatnonzero(at_k.any(axis=1)), np.flatnonzero(at_k.any(axis=0))
        if rows.size == 0:
            continue
        y0, y1 = max(int(rows[0]) - r, 0), min(int(rows[-1]) + r + 1, h)
        x0, x1 = max(int(cols[0]) - r, 0), min(int(cols[-1]) + r + 1, w)
        near = (np.abs(ix[y0:y1, x0:x1] - np.float32(k)) <= tol).view(np.uint8)
        if r:
            near = cv2.dilate(near, kernel, borderType=cv2.BORDER_REPLICATE)
        out[y0:y1, x0:x1] |= at_k[y0:y1, x0:x1] & (near == 0)
    return out


def _per_pixel_focus(stack, geometry, frames, zb_smooth: np.ndarray, quiet: bool):
    """Best focus per pixel for a scene with depth: the edge-aware depth map of the stack, plus each channel's
    offset from the others as the smooth map ``zb_smooth`` has it (chromatic focus is the lens's, not the scene's).
    Also returns the multi-scale fusion and a per-pixel weight (0 where the depth map has no texture to go on,
    1 where it is confident, a :class:`~concurrent.futures.Future` of it: made on a thread) for the final image,
    and the depth map (:class:`.fusion.DepthMap`).
    """
    from .fusion import depth_map, fuse_pyramid

    import cv2

    fusion = fuse_pyramid(stack, geometry, frames, quiet=quiet)
    guide = fusion.image
    dm = depth_map(stack, geometry, frames, guide=guide, quiet=quiet)
    per_pixel = np.empty(zb_smooth.shape, np.float32)

    def rows(a: int, b: int) -> None:  # per pixel, in row bands on the compositor's threads (was serial, ~0.07 s)
        smooth = zb_smooth[a:b]
        per_pixel[a:b] = dm.z_um[a:b, :, None] + (smooth - channel_mean(smooth)[:, :, None])

    row_bands(rows, per_pixel.shape[0])
    # Trust in the depth map: its confidence against that of the image's well-textured pixels, and no
    # contradiction from the frame the fusion took its detail from, an independent choice of the depth of
    # something within its reach (fusion_contradicts). Where the map is unsure or contradicted (low-contrast
    # texture, compression noise) the fusion's pixels are kept: they need no depth.
    def trust():
        conf = dm.confidence
        ref = float(np.percentile(conf, FUSION_CONFIDENCE[0])) if conf.size else 0.0
        weight = np.clip(conf / max(FUSION_CONFIDENCE[1] * ref, 1e-12), 0.0, 1.0).astype(np.float32)
        index = np.interp(dm.z_um, fusion.z_um, np.arange(len(fusion.z_um), dtype=np.float64)).astype(np.float32)
        weight *= ~fusion_contradicts(index, fusion.depth_index, fusion.index_reach_px)
        return cv2.GaussianBlur(weight, (0, 0), 2.0)

    # the weight is first needed by the blend's Wiener step: made on a thread of its own (NumPy and OpenCV release
    # the GIL) beside the defocus measurement and the cones, which would otherwise keep a core idle (~0.2 s)
    return per_pixel, (guide, _background(trust)), dm


# ------------------------------------------------------------------------------------------------ plans
@dataclass(frozen=True)
class PlanSelection:
    """The frames of a stack that a stack plan asked for, and the plan's criterion.

    ``frames`` are file indices into the stack (sorted, unique); ``fs_cyc_per_mm`` and ``q`` are the plan's
    (None when it does not say); ``refocus_um`` is the plan's refocus offset; ``info`` goes into metadata.
    """

    frames: np.ndarray
    fs_cyc_per_mm: float | None
    q: float | None
    refocus_um: float
    info: dict = field(default_factory=dict)


def select_plan_frames(plan, stack) -> PlanSelection:
    """Match a stack plan's positions to a stack's frames.

    Parameters
    ----------
    plan : path or dict
        A ``fieldcal-plan/1`` file (or its loaded document) of kind ``stack``.
    stack : FrameSource
        The stack captured with that plan.

    Raises
    ------
    SpecError
        The plan is not a stack plan.
    StackError
        A planned position has no frame within a quarter of the plan's frame spacing (at least 1 µm).
    """
    from ..plan.planfile import read_plan, validate_plan

    if isinstance(plan, dict):
        doc, where = validate_plan(plan, check_files=False), None
    else:
        doc, where = read_plan(plan), str(plan)
    if doc["kind"] != "stack":
        raise SpecError(f"a {doc['kind']} plan cannot select stack frames", path=where, field="kind",
                        fix="give the stack plan the stack was captured with (or no plan)")
    z_plan = np.array([f["z_um"] for f in doc["frames"]], dtype=np.float64)
    z = np.asarray(stack.z_um, dtype=np.float64)
    spacing = float(np.min(np.abs(np.diff(np.sort(z_plan))))) if len(z_plan) > 1 else np.inf
    tol = max(1.0, 0.25 * spacing) if np.isfinite(spacing) else 1.0
    idx = []
    for zp in z_plan:
        k = int(np.argmin(np.abs(z - zp)))
        if abs(z[k] - zp) > tol:
            raise StackError(f"the plan's frame at z = {zp:g} µm is not in the stack (nearest {z[k]:g} µm)",
                             path=stack.path, field="frames",
                             fix="composite without the plan, or capture the stack with this plan")
        idx.append(k)
    params = doc.get("parameters", {})
    fs = params.get("fs_cyc_per_mm")
    q = params.get("q")
    refocus = float(doc.get("refocus_um") or 0.0)
    return PlanSelection(np.array(sorted(set(idx))),
                         float(fs) if isinstance(fs, (int, float)) and not isinstance(fs, bool) else None,
                         float(q) if isinstance(q, (int, float)) and not isinstance(q, bool) else None,
                         refocus, {"path": where, "kind": "stack", "n_frames": len(z_plan), "refocus_um": refocus})


# ----------------------------------------------------------------------------------------------- sweeps
DECONVOLUTIONS = ("wiener", "rl", "none")


@dataclass
class SweepComposite:
    """A (deconvolved) focal-sweep image in the input's dtype and scale, and what was done (``info``)."""

    image: np.ndarray
    info: dict = field(default_factory=dict)


def _check_sweep_args(alpha_um, deconvolve: str) -> None:
    if alpha_um is None or not (np.isfinite(alpha_um) and alpha_um > 0):
        raise ParameterError(f"the sweep half-range must be > 0 µm, got {alpha_um}", field="sweep_alpha_um",
                             fix="e.g. 20 µm (the paper's)")
    if deconvolve not in DECONVOLUTIONS:
        raise ParameterError(f"unknown deconvolution {deconvolve!r}", field="deconvolve",
                             fix=f"use one of {', '.join(DECONVOLUTIONS)}")


def composite_sweep(stack, profile, alpha_um: float, *, frames=None, deconvolve: str = "wiener",
                    rl_iterations: int = 30, lateral_colour: bool = False, quiet: bool = False) -> SweepComposite:
    """Emulate a per-pixel focal sweep of half-range ``alpha_um`` from a stack, then deconvolve it.

    Parameters
    ----------
    stack : FrameSource
        A dense through-focus stack (frames at most ``2 alpha_um`` apart).
    profile : lens profile
        Each pixel's best focus and the integrated PSF.
    deconvolve : {"wiener", "rl", "none"}
        Deconvolution with the integrated PSF (Richardson-Lucy takes ``rl_iterations``).
    frames : array of int, optional
        File indices to use (e.g. :func:`select_plan_frames`'s); default all.
    """
    from .stack_profile import to_input_dtype
    from .sweep import deconvolve_sweep, emulate_sweep

    _check_sweep_args(alpha_um, deconvolve)
    if profile is None:
        raise ParameterError("sweep emulation needs a profile (each pixel's best focus and the PSF)",
                             field="profile", fix="give the lens profile")
    stack.require_frames(2, "sweep emulation")
    stack = hold_decoded(stack, select_frames(stack, frames))  # JPEG/PNG: decoded once, not once per band
    sw = emulate_sweep(stack, profile, alpha_um, frames=frames, lateral_colour=lateral_colour, quiet=quiet)
    info = dict(sw.info)
    img = sw.image
    if deconvolve != "none":
        res = deconvolve_sweep(img, profile, alpha_um, stack.channels, black=stack.black_level,
                               white=stack.white_level, method=deconvolve, rl_iterations=rl_iterations,
                               noise_sigma=sw.info["noise_sigma"])
        img = res.image
        info.update(res.info)
    info.update({"method": "sweep-emulated", "z_ref_um": float(profile.z_ref_um)})
    return SweepComposite(to_input_dtype(img, stack.dtype, stack.white_level), info)


def profile_breathes(profile, span_um: float = 100.0) -> bool:
    """Whether the image moves with the stage: dense geometry maps, or a magnification or shift that changes
    within ``span_um`` of ``z_ref`` (then a captured sweep needs the breathing-aware deconvolution)."""
    if getattr(profile, "has_geometry_map", False):
        return True
    z = float(profile.z_ref_um) + np.array([-span_um, span_um])
    ch = profile.channels[0]
    m = np.asarray(profile.magnification(z, ch), dtype=np.float64)
    sx, sy = (np.asarray(v, dtype=np.float64) for v in profile.shift_px(z, ch))
    return bool(np.any(np.abs(m - 1.0) > 1e-9) or np.any(np.abs(sx) > 1e-9) or np.any(np.abs(sy) > 1e-9))


def resolve_breathing(breathing: str | None, profile, deconvolve: str) -> str | None:
    """``"auto"``: ``"aware"`` when the profile breathes (:func:`profile_breathes`) and the deconvolution is
    Wiener (the per-zone kernels are Wiener only), else None (one kernel, the image taken as it is)."""
    if breathing != "auto":
        return breathing
    return "aware" if deconvolve == "wiener" and profile_breathes(profile) else None


def restore_sweep_image(image: np.ndarray, profile, alpha_um: float, *, deconvolve: str = "wiener",
                        rl_iterations: int = 30, where=None, breathing: str | None = None,
                        refocus_um: float = 0.0, zone_px: int | None = None,
                        camera_noise: tuple[float, float] | None = None) -> SweepComposite:
    """Deconvolve a captured focal-sweep image (``H x W x C``, raw, black level 0) with the integrated PSF.

    The profile must be of this camera: same channels and image size. ``where`` names the image in errors.
    ``breathing="aware"`` deconvolves per field zone with the image motion during the sweep and registers the
    result to the profile's ``z_ref`` geometry (``"blind"``: the same without the motion; None: one kernel, the
    image taken as it is; ``"auto"``: :func:`resolve_breathing`); ``refocus_um`` is the sweep plan's; ``zone_px``
    the zone size (default 64). ``camera_noise`` = (gain DN per electron, read noise in electrons) of the camera
    sets the Wiener filter's noise (:func:`~fieldcal.composite.sweep.sensor_noise_sigma`, black level 0 as the
    image is); without it the noise is estimated from the image.
    """
    from .stack_profile import to_input_dtype
    from .sweep import deconvolve_sweep, sensor_noise_sigma

    _check_sweep_args(alpha_um, deconvolve)
    if deconvolve == "none":
        raise ParameterError("nothing to do for a captured sweep without deconvolution", field="deconvolve",
                             fix="use wiener or rl")
    if zone_px is not None and not (isinstance(zone_px, (int, np.integer)) and zone_px >= 8):
        raise ParameterError(f"zone size {zone_px} px must be a whole number >= 8", field="zone_px",
                             fix="e.g. 64 (the default); smaller zones follow faster-changing breathing")
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    h, w = image.shape[:2]
    channels = tuple(profile.channels)
    if len(channels) != image.shape[2]:
        raise ParameterError(f"the image has {image.shape[2]} channel(s), the profile {len(channels)}",
                             path=where, field="channels", fix="use the profile of the camera that took it")
    if tuple(profile.image_size_px) != (w, h):
        raise ParameterError(f"the profile is for {profile.image_size_px} px images, the image is {w}x{h}",
                             path=where, field="image_size_px", fix="use the profile of this camera")
    white = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    noise = None if camera_noise is None else sensor_noise_sigma(image, *camera_noise)
    res = deconvolve_sweep(image.astype(np.float32), profile, alpha_um, channels, black=0.0, white=white,
                           method=deconvolve, rl_iterations=rl_iterations, noise_sigma=noise,
                           breathing=resolve_breathing(breathing, profile, deconvolve), refocus_um=refocus_um,
                           zone_px=zone_px)
    return SweepComposite(to_input_dtype(res.image, image.dtype, white), {"method": "sweep-captured", **res.info})


# ------------------------------------------------------------------------------------------ whole path
@dataclass
class CompositeOutput:
    """What :func:`composite_to_file` wrote: the TIFF's path, the method and the metadata stored with it."""

    path: Path
    method: str
    metadata: dict


def composite_to_file(stack, out, *, profile=None, method: str | None = None, plan=None,
                      sweep_alpha_um: float | None = None, deconvolve: str = "wiener", rl_iterations: int = 30,
                      fs_cyc_per_mm: float | None = None, q: float | None = None, z_ref_um: float | None = None,
                      register: bool = True, lateral_colour: bool = False, depth: str = "auto",
                      overwrite: bool = False, verify: bool = True, quiet: bool = False,
                      breathing: str | None = "auto", zone_px: int | None = None,
                      camera_noise: tuple[float, float] | None = None, max_memory=None,
                      measured_defocus: bool = True) -> CompositeOutput:
    """Composite a stack folder (or restore a captured sweep image) into a TIFF with its metadata.

    Parameters
    ----------
    stack : path or FrameSource
        A ``fieldcal-stack/1`` folder or an open stack; or a captured sweep image file (TIFF/PNG), which
        needs ``profile`` and ``sweep_alpha_um``.
    out : path
        The output image: ``.tif``/``.tiff`` (the stack's dtype), ``.png`` or ``.jpg`` (by extension, :func:`~fieldcal.composite.io.write_composite`).
    profile : path or lens profile, optional
        A ``fieldcal-profile/1`` file, a ``fieldcal-lens/1`` spec (its truth, for simulated data), or a loaded
        profile. Without one only depth from focus is possible.
    method : {"profile", "dff", "hybrid"}, optional
        See :func:`composite_stack`.
    plan : path, optional
        A stack plan: use its frames, and its ``fs_cyc_per_mm``, ``q`` and refocus where not given here.
    sweep_alpha_um : float, optional
        Emulate a focal sweep of this half-range (µm) and deconvolve it (``deconvolve``, ``rl_iterations``).
    fs_cyc_per_mm, q : float, optional
        The focus tolerance that sets the seam width (default: the plan's, else Nyquist/4 and 0.05).
    z_ref_um, register, lateral_colour, depth, max_memory, measured_defocus, quiet
        See :func:`composite_stack`.
    overwrite : bool
        Replace an existing output file (never an input: the stack, its frames, the profile, the plan).
    verify : bool
        Check the frames against their recorded sha256 (docs/safety.md).
    breathing : {"auto", "aware", "blind", None}
        A captured sweep image only: deconvolve per field zone with the image motion during the sweep
        (``"aware"``), per zone without it (``"blind"``), or with one kernel (None); ``"auto"`` (default):
        aware when the profile breathes or has geometry maps and the deconvolution is Wiener
        (:func:`resolve_breathing`). ``zone_px``: the zone size (default 64). ``camera_noise``: the camera's
        (gain DN per electron, read noise in electrons) for the Wiener filter's noise (default: estimated from
        the image).
    """
    from ..formats.stack import Stack
    from ..profile.lens_profile import load_profile_or_truth
    from .io import check_composite_output, read_single_image, write_composite

    out = check_composite_output(out, stack=stack if isinstance(stack, (str, Path)) else getattr(stack, "path", None),
                                 profile=profile if isinstance(profile, (str, Path)) else None,
                                 plan=plan if isinstance(plan, (str, Path)) else None, overwrite=overwrite)
    if q is not None and not 0.0 < q < 1.0:
        raise ParameterError(f"q must be in (0, 1), got {q}", field="q", fix="e.g. 0.05 (5 % MTF loss)")
    if fs_cyc_per_mm is not None and not (np.isfinite(fs_cyc_per_mm) and fs_cyc_per_mm > 0):
        raise ParameterError(f"fs must be > 0 cycles/mm, got {fs_cyc_per_mm}", field="fs_cyc_per_mm",
                             fix="e.g. 80")
    if z_ref_um is not None and not (np.isfinite(z_ref_um) and abs(z_ref_um) <= 1e9):
        raise ParameterError(f"z_ref must be a finite stage position in µm, got {z_ref_um}", field="z_ref_um",
                             fix="give a position within the stack's z range, or leave it unset for the middle "
                                 "frame")
    if z_ref_um is not None and (profile is not None or not register or sweep_alpha_um is not None):
        # never ignore a flag: with a profile the output is in the profile's z_ref geometry, unregistered frames
        # keep their own, and a sweep is made at the profile's z_ref
        raise ParameterError("a reference frame position applies only to a stack composited without a profile, "
                             "with registration: " + ("the profile's z_ref sets the output geometry"
                                                      if profile is not None else "--no-register keeps the "
                                                      "frames' own geometry"), field="z_ref_um",
                             fix="drop --z-ref-um, or composite without --profile / --no-register")
    if sweep_alpha_um is not None:
        _check_sweep_args(sweep_alpha_um, deconvolve)

    def load(size_px):
        if profile is None or not isinstance(profile, (str, Path)):
            return profile, (None if profile is None else {"source": type(profile).__name__})
        return load_profile_or_truth(profile, size_px)

    if isinstance(stack, (str, Path)) and Path(stack).is_file():  # a captured sweep image
        src = Path(stack)
        for name, value in (("sweep_alpha_um", sweep_alpha_um), ("profile", profile)):
            if value is None:
                raise ParameterError(f"{src} is a single image, so a captured sweep: it needs the sweep's "
                                     "half-range alpha (µm) and the lens profile", field=name,
                                     fix="give both, or give a stack folder instead of the image")
        img = read_single_image(src)
        prof, pinfo = load((img.shape[1], img.shape[0]))
        res = restore_sweep_image(img, prof, sweep_alpha_um, deconvolve=deconvolve, rl_iterations=rl_iterations,
                                  where=src, breathing=breathing, zone_px=zone_px, camera_noise=camera_noise)
        meta = {"input": str(src), "profile": pinfo, "method": res.info.pop("method"), "sweep": res.info}
        white = 1.0 if img.dtype.kind == "f" else float(np.iinfo(img.dtype).max)
        write_composite(out, res.image, prof.channels, meta, white_level=white)
        return CompositeOutput(out, meta["method"], meta)

    if breathing not in ("auto", None) or zone_px is not None or camera_noise is not None:  # never ignore a flag
        raise ParameterError("breathing-aware or zoned deconvolution and the camera's noise model apply to a "
                             "captured sweep image, not a stack (an emulated sweep is made of frames already "
                             "registered to z_ref, its noise measured from them)",
                             field="camera_noise" if camera_noise is not None else
                             ("breathing" if zone_px is None else "zone_px"),
                             fix="give the captured sweep image instead of the stack, or drop the flag")
    on_disk = isinstance(stack, (str, Path))
    st = Stack.open(stack, verify=False) if on_disk else stack
    # The frames' sha256 are checked while compositing runs (hashing reads every file whole: ~55 ms a 4K RGB16
    # frame, as long as the compositing of a 42-frame stack), and before anything is written.
    with _BackgroundCheck(st.verify if verify and on_disk else None) as checked:
        if st.cfa is not None:
            raise StackError(f"a raw {st.cfa} mosaic stack cannot be composited per channel",
                             path=st.path, field="cfa", fix="demosaic the frames first (H x W x 3)")
        prof, pinfo = load((st.shape[1], st.shape[0]))
        meta: dict = {"input": str(st.path or stack), "profile": pinfo}
        frames, offset = None, 0.0
        if plan is not None:
            sel = select_plan_frames(plan, st)
            frames, offset = sel.frames, sel.refocus_um
            meta["plan"] = sel.info
            fs_cyc_per_mm = fs_cyc_per_mm or sel.fs_cyc_per_mm
            q = q if q is not None else sel.q
        if sweep_alpha_um is not None:
            res = composite_sweep(st, prof, sweep_alpha_um, frames=frames, deconvolve=deconvolve,
                                  rl_iterations=rl_iterations, lateral_colour=lateral_colour, quiet=quiet)
            info = dict(res.info)
            meta.update({"method": info.pop("method"), "z_ref_um": info.pop("z_ref_um"), "sweep": info})
            checked()
            _write(out, res.image, st, frames, meta)
            return CompositeOutput(out, meta["method"], meta)
        res = composite_stack(st, prof, method, frames=frames, fs_cyc_per_mm=fs_cyc_per_mm,
                              q=0.05 if q is None else q, lateral_colour=lateral_colour, focus_offset_um=offset,
                              register=register, z_ref_um=z_ref_um, depth=depth, max_memory=max_memory,
                              measured_defocus=measured_defocus, quiet=quiet)
        z_ref = float(prof.z_ref_um) if prof is not None else res.info.get("registration", {}).get("z_ref_um")
        meta.update({"method": res.method, "z_ref_um": z_ref, "lateral_colour_corrected": bool(lateral_colour),
                     **res.info})
        checked()
        _write(out, res.image, st, frames, meta)
        return CompositeOutput(out, res.method, meta)


class _BackgroundCheck:
    """Runs ``check`` (e.g. ``Stack.verify``) on a thread while the caller works. Calling the object waits for it
    and re-raises its error; if the work fails first, the check's error (the root cause: a changed frame file)
    replaces the work's."""

    def __init__(self, check):
        import threading

        self._error: BaseException | None = None
        self._thread = None
        if check is not None:
            def run():
                try:
                    check()
                except BaseException as exc:  # handed to the caller's thread
                    self._error = exc
            self._thread = threading.Thread(target=run, name="fieldcal-verify", daemon=True)
            self._thread.start()

    def __call__(self) -> None:
        if self._thread is not None:
            self._thread.join()
        if self._error is not None:
            raise self._error

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if exc is not None and self._thread is not None and not isinstance(exc, KeyboardInterrupt):
            self()  # raises the check's error instead, if it failed
        return False


def _write(out: Path, image: np.ndarray, stack, frames, meta: dict) -> None:
    """The composite as TIFF/PNG/JPEG by ``out``'s extension; a JPEG gets the first used frame's EXIF, and a TIFF
    or JPEG the EXIF orientation most used frames have."""
    from .io import exif_orientation, write_composite

    first, orientation = None, 1
    infos = getattr(stack, "frames", None)
    if infos:
        used = [int(k) for k in frames] if frames is not None and len(frames) else list(range(len(infos)))
        first = getattr(infos[used[0]], "path", None)
        paths = [getattr(infos[k], "path", None) for k in used]
        orientation = exif_orientation([p for p in paths if p is not None])
    write_composite(out, image, stack.channels, meta, black_level=float(stack.black_level),
                    white_level=float(stack.white_level), exif_from=first, orientation=orientation)
