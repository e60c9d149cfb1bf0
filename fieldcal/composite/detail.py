"""Fine detail for scenes with depth: per-coefficient selection at the finest pyramid levels, held to the depth map.

A depth-map composite (:func:`fieldcal.composite.fusion.depth_map`, blended by :mod:`.stack_profile`) chooses
frames by a focus measure aggregated over an object, so it has no halo at depth edges and little noise, but
where a pixel's depth falls between two frames it blends them, and the finest octave of the sharper one is
diluted. Pyramid and wavelet stackers (Burt & Kolczynski 1993; focus-stack's complex-wavelet rule; Zerene's
PMax, Helicon's method B) take, per coefficient, the frame with the most local energy: all the fine detail, but
also noise and the blurred ghost of a near object wherever no frame is sharp. This step combines the two:

* the coarse levels (and the base) are the depth-map composite's;
* at the ``levels`` finest Laplacian-pyramid levels each coefficient comes from the frame with the largest
  local energy of the luminance's coefficients (squared, Gaussian-weighted over ``window_px`` at that level),
  among the frames within ``reach_frames`` of the depth map's (sub-frame) choice at that place (the sharpest
  of the frames the depth map allows), or a frame further off where its detail stands well out of its own
  noise (``significance``: the depth map is unsure or wrong there), never a far frame's noise or ghost --
  focus-stack's rule of all frames competing, held to what stands out of each frame's own noise;
* the choice is made spatially consistent by a median filter (``consistency_px``) of the chosen frame index
  (focus-stack's consistency step): an isolated pixel does not switch frames on its noise alone;
* where even the best frame's energy is what noise alone puts there (no frame is sharp: defocused background,
  blank surfaces), the frames within reach are averaged instead, so the composite has less noise there than a
  frame, not the noise of whichever frame happened to be loudest; a ramp (:data:`NOISE_RATIO`) joins the two;
* one choice per place for all channels (made on the luminance), so the colours come from one frame and no
  colour fringes appear.

The choice needs the final index before the coefficients are gathered, so the frames stream through twice
(measure, then gather); memory holds the choice, the gathered levels and a few frames' planes. Keeping the base's
own fine levels (``keep_base``: a Wiener composite) gathers nothing by the choice, so the frames stream through
once: each frame's channels' fine levels give both its salience (their sum: the luminance's) and its share of the
average within reach.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np

from ..errors import ParameterError
from ..progress import progress
from .dff import frame_planes, map_in_order
from .fusion import _BORDER, _level_shapes, masked_copy  # the same pyramid as the fusion's (levels, border)
from .source import image_size, z_positions

#: Finest pyramid levels selected per coefficient: the two octaves above a quarter of the sampling frequency,
#: where a blend of two frames loses most; coarser levels follow the depth map (no halo wider than level 1's
#: ~4 px support at depth edges).
FINE_LEVELS = 2
#: Frames either side of the depth map's choice that may lend a coefficient: the depth map is right to about a
#: frame (its sub-frame peak), and a frame further off is defocused by more than a step.
REACH_FRAMES = 1.0
#: Salience window (Gaussian sigma, px at each level): wide enough that one noisy coefficient does not decide,
#: narrow enough to follow a fine edge.
WINDOW_PX = 1.0
#: Median filter of the chosen frame index (px, odd): the consistency check.
CONSISTENCY_PX = 3



#: Local energy, in units of the noise's (the most defocused frame's typical energy at that level), up to which
#: the frames within reach are averaged rather than one chosen: at 1 nothing but noise, from 4 (2x in amplitude)
#: the sharpest is taken outright.
NOISE_RATIO = 4.0
#: A frame beyond the reach may still lend a coefficient where its local energy exceeds this many times the median
#: of its own energy at that level (its typical, mostly noise, coefficient): the same 2x in amplitude as
#: :data:`NOISE_RATIO`, the one criterion for "detail, not noise". Real detail the depth map missed (it is unsure,
#: or wrong, there: thin structures) stands that far out; a frame's own noise, whatever its spectrum (raw, JPEG)
#: and however loud, next to never does (the energy is a Gaussian-weighted mean of ~12 squared coefficients), and a
#: defocused ghost has next to no energy at these levels. All frames compete then, as in the per-coefficient
#: stackers, but a louder frame's noise does not. (Against 9x: the simulated scenes without a profile -0.05 to
#: +0.12 dB, the real circuit board +1 % mean squared Laplacian; any frame beyond the reach with no test would let
#: a noisier frame's noise in.)
SIGNIFICANCE = NOISE_RATIO


def _fine_levels(plane: np.ndarray, levels: int) -> list[np.ndarray]:
    """The ``levels`` finest Laplacian-pyramid levels of one float32 plane (as :mod:`.fusion` builds them)."""
    out, cur = [], plane
    for _ in range(levels):
        hh, ww = cur.shape
        down = cv2.pyrDown(cur, borderType=_BORDER)
        up = cv2.pyrUp(down, dstsize=(ww, hh), borderType=_BORDER)
        out.append(np.subtract(cur, up, out=up))
        cur = down
    return out


def _level_index(depth_index: np.ndarray, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
    """The depth map's frame index at each level's resolution (area-averaged)."""
    out = [np.asarray(depth_index, dtype=np.float32)]
    for hh, ww in shapes[1:]:
        out.append(cv2.resize(out[-1], (ww, hh), interpolation=cv2.INTER_AREA))
    return out


def fine_detail(stack, base: np.ndarray, depth_index: np.ndarray, frames=None, *, geometry=None, levels: int = FINE_LEVELS,
                reach_frames: float = REACH_FRAMES, window_px: float = WINDOW_PX,
                consistency_px: int = CONSISTENCY_PX, significance: float | None = SIGNIFICANCE, support=None,
                keep_base: bool = False, quiet: bool = False) -> tuple[np.ndarray, dict]:
    """Replace the finest pyramid levels of a depth-map composite by per-coefficient selection near its depth.

    Parameters
    ----------
    stack : FrameSource
        The frames: registered to the output geometry (e.g. :func:`fieldcal.composite.register.register_stack`'s),
        or warped to it by ``geometry`` (a lens profile; ``None``: taken as registered).
    base : H x W x C array
        The depth-map composite (any dtype; its coarse levels are kept).
    depth_index : H x W array
        The depth map as a frame position in z order (0 = the lowest frame of ``frames``; sub-frame values).
    frames : array of int, optional
        File indices to use (default all), as for the depth map.
    levels, reach_frames, window_px, consistency_px, significance
        See :data:`FINE_LEVELS`, :data:`REACH_FRAMES`, :data:`WINDOW_PX`, :data:`CONSISTENCY_PX`,
        :data:`SIGNIFICANCE` (``None``: never beyond the reach).
    support : callable, optional
        ``support(i)``: an ``H x W`` bool mask of where frame ``i`` holds recorded pixels (registered frames
        repeat their edge beyond it); a frame is never chosen outside it.
    keep_base : bool
        Keep the base's own fine levels where a frame is sharp (a multi-frame Wiener composite, which already
        holds more than any one frame there) and average the frames within reach only where no frame is: a
        noise gate, no frame chosen.
    quiet : bool
        No progress bar.

    Returns
    -------
    (image, info)
        The composite (``H x W x C`` float32, the frames' units) and what was chosen: the share of
        coefficients taken from another frame than the depth map's nearest, per level.

    Examples
    --------
    >>> from fieldcal.composite.source import ArrayStack
    >>> rng = np.random.default_rng(0)
    >>> sharp = rng.random((32, 32, 1)).astype(np.float32)
    >>> soft = cv2.GaussianBlur(sharp, (0, 0), 2.0)[..., None]
    >>> st = ArrayStack([soft, sharp], [0.0, 10.0], ["Y"])
    >>> mix = 0.5 * (soft + sharp)  # a depth-map blend half-way between the frames
    >>> out, _ = fine_detail(st, mix, np.full((32, 32), 0.5, np.float32), quiet=True)
    >>> bool(np.abs(out - sharp).mean() < 0.5 * np.abs(mix - sharp).mean())
    True
    """
    w, h = image_size(stack)
    channels = tuple(stack.channels)
    base = np.asarray(base)
    if base.shape[:2] != (h, w) or np.shape(depth_index) != (h, w):
        raise ParameterError(f"composite {base.shape[:2]} or depth map {np.shape(depth_index)} is not the stack's "
                             f"{h}x{w}", field="base", fix="give the composite and depth map of this stack")
    levels = int(levels)
    if levels < 1 or (min(w, h) >> levels) < 2:
        raise ParameterError(f"{levels} fine levels do not fit a {w}x{h} image", field="levels",
                             fix="use fewer levels")
    if consistency_px < 1 or consistency_px % 2 == 0:
        raise ParameterError(f"consistency filter of {consistency_px} px", field="consistency_px",
                             fix="use an odd width (1 = no filter)")
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    # the chosen frame per coefficient: 8 bits up to 255 frames, 16 beyond (a deep macro stack on a rail can
    # have hundreds; OpenCV's median filter takes 16-bit input up to 5 px)
    choice_dtype = np.uint8 if len(order) <= 255 else np.uint16
    if choice_dtype == np.uint16 and consistency_px > 5:
        raise ParameterError(f"a consistency filter of {consistency_px} px on {len(order)} frames",
                             field="consistency_px", fix="use a filter of at most 5 px with more than 255 frames")
    shapes = _level_shapes(h, w, levels - 1)  # the fine levels' own sizes
    kd = _level_index(depth_index, shapes)
    reach = np.float32(reach_frames)

    def planes_of(i: int) -> list[np.ndarray]:
        return frame_planes(stack, geometry, float(z_all[i]), int(i), channels, w, h)

    def salience(k_i, lum_levels=None, dist=None):
        k, i = k_i
        if lum_levels is None:
            planes = planes_of(i)
            lum = planes[0]
            for p in planes[1:]:
                lum += p
            lum_levels = _fine_levels(lum, levels)
        sal = []
        for lev, lap in enumerate(lum_levels):
            e = np.multiply(lap, lap, out=lap)
            e = cv2.GaussianBlur(e, (0, 0), float(window_px), dst=e, borderType=_BORDER)
            step = max(1, int(np.sqrt(e.size / 50_000)))  # ~50 000 samples pin a median to ~0.5 %
            typical = float(np.median(e[::step, ::step]))
            # a frame beyond the depth map's reach only where its detail stands out of its noise; outside its
            # recorded support, never
            far = (np.abs(kd[lev] - np.float32(k)) if dist is None else dist[lev]) > reach
            if significance is not None:
                far &= e < np.float32(significance * typical)
            # OpenCV's masked copy: the same values as e[far] = -1.0, which took ~15 ms a full-size plane (most of
            # a frame's pixels are beyond the reach)
            masked_copy(e, -1.0, far)
            m = recorded(i, lev)
            if m is not None:
                masked_copy(e, -1.0, ~m)
            sal.append((e, typical))
        return sal

    def recorded(i, lev: int) -> np.ndarray | None:
        m = support(int(i)) if support is not None else None
        if m is not None and lev:
            hh, ww = shapes[lev]
            m = cv2.resize(m.view(np.uint8), (ww, hh), interpolation=cv2.INTER_NEAREST) > 0
        return m

    # the frames' fine levels averaged where they lie within reach of the depth map (the noise gate's average)
    total = [np.zeros((len(channels), *s), np.float32) for s in shapes]
    count = [np.zeros(s, np.float32) for s in shapes]
    lock = threading.Lock()

    def near_of(k: int, i, dist=None) -> list[np.ndarray]:
        near = []
        for lev in range(levels):
            m = (np.abs(kd[lev] - np.float32(k)) if dist is None else dist[lev]) <= reach
            rec = recorded(i, lev)
            near.append(m if rec is None else m & rec)
        return near

    def accumulate(laps: list[tuple[int, int, np.ndarray]], near: list[np.ndarray]) -> None:
        with lock:  # the averages are shared by every frame within reach
            for lev, ci, lap in laps:
                total[lev][ci] += lap
            for lev in range(levels):
                count[lev] += near[lev]

    def measure_and_average(k_i):
        """keep_base: the salience and the average within reach from one read of the frame, the luminance's
        levels the channels' summed (the pyramid is linear): no second pass, as no frame's coefficients are
        gathered by the final choice."""
        k, i = k_i
        chan_levels = [_fine_levels(plane, levels) for plane in planes_of(i)]
        lum_levels = []
        for lev in range(levels):
            lum = chan_levels[0][lev].copy()
            for cl in chan_levels[1:]:
                lum += cl[lev]
            lum_levels.append(lum)
        # each level's distance from the depth map's choice, for both the average's reach and the salience's
        dist = [np.abs(kd[lev] - np.float32(k)) for lev in range(levels)]
        near = near_of(k, i, dist)
        laps = []
        for ci, cl in enumerate(chan_levels):
            for lev, lap in enumerate(cl):
                lap *= near[lev]
                laps.append((lev, ci, lap))
        accumulate(laps, near)
        return salience(k_i, lum_levels, dist)

    best = [np.full(s, -2.0, np.float32) for s in shapes]
    choice = [np.zeros(s, choice_dtype) for s in shapes]
    noise = [np.inf] * levels
    items = list(enumerate(order))
    for k, sal in progress(zip(range(len(items)), map_in_order(measure_and_average if keep_base else salience, items)),
                           total=len(items), desc="fine detail", quiet=quiet, unit="frame"):
        for lev, (e, typical) in enumerate(sal):
            take = e > best[lev]
            masked_copy(best[lev], e, take)
            masked_copy(choice[lev], k, take)
            noise[lev] = min(noise[lev], typical)
    # Where even the best frame's energy is what noise alone puts there (the typical energy of the most
    # defocused frame, mostly noise), no frame is sharp: the frames within reach are averaged (their noise
    # falls) rather than one chosen for its noise; a ramp up to NOISE_RATIO times that energy joins the two.
    select = []
    for lev, b in enumerate(best):
        r = np.divide(b, np.float32(max(noise[lev], 1e-30)))
        r -= np.float32(1.0)
        r *= np.float32(1.0 / (NOISE_RATIO - 1.0))
        np.clip(r, 0.0, 1.0, out=r)
        select.append(cv2.GaussianBlur(r, (0, 0), float(window_px), borderType=_BORDER))
    del best
    if consistency_px > 1:
        choice = [cv2.medianBlur(c, int(consistency_px)) for c in choice]
    nearest = [np.clip(np.rint(d), 0, len(order) - 1).astype(choice_dtype) for d in kd]
    info = {"fine_levels": levels, "reach_frames": float(reach_frames),
            "coefficients_off_depth_map": [round(float(np.mean(c != n)), 4) for c, n in zip(choice, nearest)]}
    info["coefficients_averaged"] = [round(float(np.mean(sel < 0.5)), 4) for sel in select]
    # channel-first: each channel's plane contiguous, so the per-frame copies and sums run at full speed
    # (with keep_base, the base's own fine levels: made after the gathering pass, not held through it)
    gathered = None if keep_base else [np.zeros((len(channels), *s), np.float32) for s in shapes]

    def gather(k_i) -> None:
        k, i = k_i
        chosen = [c == k for c in choice]
        near = near_of(k, i)
        laps = []
        for ci, plane in enumerate(planes_of(i)):
            for lev, lap in enumerate(_fine_levels(plane, levels)):
                # each frame writes only where it was chosen: the threads' writes never overlap
                masked_copy(gathered[lev][ci], lap, chosen[lev])
                lap *= near[lev]
                laps.append((lev, ci, lap))
        accumulate(laps, near)

    if not keep_base:
        for _ in progress(map_in_order(gather, items), total=len(items), desc="fine detail, gathering",
                          quiet=quiet, unit="frame"):
            pass
    for lev in range(levels):
        sel, n = select[lev], count[lev]
        sel[n == 0] = 1.0  # nothing recorded within reach: the chosen frame
        np.maximum(n, np.float32(1.0), out=n)
    if keep_base:
        gathered = [np.empty((len(channels), *s), np.float32) for s in shapes]
    out = np.empty((h, w, len(channels)), np.float32)

    def finish(ci: int) -> None:
        """Channel ci's fine levels mixed (g = sel g + (1 - sel) mean, in place) and the image rebuilt on the
        base's coarse part: channels touch only their own planes, so they run on the compositor's threads."""
        cur = np.ascontiguousarray(base[..., ci], dtype=np.float32)
        if keep_base:
            for lev, lap in enumerate(_fine_levels(cur, levels)):
                gathered[lev][ci] = lap
        for lev in range(levels):
            g, t = gathered[lev][ci], total[lev][ci]
            t /= count[lev]
            g -= t
            g *= select[lev]
            g += t
        for _ in range(levels):  # the base's coarse part: its Gaussian level below the fine ones
            cur = cv2.pyrDown(cur, borderType=_BORDER)
        for lev in range(levels - 1, -1, -1):
            hh, ww = shapes[lev]
            cur = cv2.pyrUp(cur, dstsize=(ww, hh), borderType=_BORDER)
            cur += gathered[lev][ci]
        out[..., ci] = cur

    for _ in map_in_order(finish, list(range(len(channels)))):
        pass
    return out, info
