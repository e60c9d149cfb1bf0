"""Scenes with depth: steps, slopes, thin things in front of a background, a circuit-board relief.

A flat chart is in focus on the lens's best-focus surface. A 3-D scene point at ``depth_um`` is in focus
``depth_um`` further along the stage axis (a point nearer the lens focuses further behind it; ``depth_um`` is
that image-side offset, so no object distance is needed). The renderer splits the scene into depth layers
(exact for piecewise-flat scenes; a slope is cut into layers much thinner than the depth of field) and renders
each layer's premultiplied colour and its coverage (alpha) with the flat renderer at a stage position shifted
by the layer's depth, then composites them front to back with the "over" operator. Defocused foreground edges
therefore spread over what is behind them, and a blurred background does not leak in front of a sharp
foreground edge, as in a real photograph (the layered model of depth of field; partial occlusion of the
aperture by a foreground edge is approximated by the alpha blur).

Each layer continues behind the layers in front of it (its colour there filled smoothly from its own pixels,
:func:`fill_behind`), because a real background does not stop at the outline of what stands in front of it:
the lens sees around a defocused wire or step edge. A layer cut off at its visible outline would show, where the
defocused occluder becomes translucent, a sharp-edged dark hole in focus at the background's depth, a line no
camera records (and one that misleads any depth from focus).

The truth is the all-in-focus image (each layer at its own best focus, composited) and the depth map; the
oracle best focus of every pixel is the lens's surface plus its depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ParameterError
from . import noise as _noise
from .render import Renderer, _check_z, scene_to_channels

#: The depth layouts :func:`depth_scene` draws.
LAYOUTS = ("steps", "slope", "thin", "relief")


@dataclass(frozen=True)
class DepthScene:
    """A scene with depth, at the sensor size: ``image`` (float32 H x W x 3 in [0, 1]) and ``depth_um``
    (float32 H x W, the image-side best-focus offset; larger = nearer the lens, occludes smaller)."""

    image: np.ndarray
    depth_um: np.ndarray
    layout: str
    #: optional H x W x 3: the farthest surface (background, board) continued behind everything in front of it;
    #: without it the renderer fills hidden parts smoothly (:func:`fill_behind`)
    behind: np.ndarray | None = None


def _texture(width: int, height: int, seed: int) -> np.ndarray:
    from .scene import colour_leaves

    return colour_leaves(width, height, seed)


def depth_scene(layout: str, width_px: int, height_px: int, depth_range_um: float, seed: int = 0) -> DepthScene:
    """One of :data:`LAYOUTS`, textured with independent colour dead-leaves per object.

    Parameters
    ----------
    layout : {"steps", "slope", "thin", "relief"}
        ``steps``: four flat regions at different depths with straight and diagonal boundaries; ``slope``: a
        plane tilted across the field in front of a flat background; ``thin``: thin bars and a wire (2-6 px)
        in front of a background; ``relief``: a board with raised components of several heights and traces.
    width_px, height_px : int
        Sensor size in pixels.
    depth_range_um : float
        Largest depth offset (µm); depths span [0, depth_range_um].
    seed : int
        Seed of the textures and the layout.
    """
    if layout not in LAYOUTS:
        raise ParameterError(f"unknown depth layout {layout!r}", field="layout", fix=f"use one of {', '.join(LAYOUTS)}")
    if not (np.isfinite(depth_range_um) and depth_range_um >= 0):
        raise ParameterError(f"depth_range_um must be finite and >= 0, got {depth_range_um!r}",
                             field="depth_range_um", fix="give the scene's depth in µm at the sensor")
    w, h = int(width_px), int(height_px)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    d = np.zeros((h, w), np.float32)
    objects = np.zeros((h, w), np.int32)
    if layout == "steps":
        d[:, : w // 3] = 0.0
        d[:, w // 3:] = 0.35
        d[yy > 0.55 * h] = 0.7
        d[(xx - 0.75 * w) + (yy - 0.3 * h) * 0.8 > 0] = np.maximum(d[(xx - 0.75 * w) + (yy - 0.3 * h) * 0.8 > 0], 1.0)
        objects = np.round(d * 3).astype(np.int32)
    elif layout == "slope":
        inside = (xx > 0.15 * w) & (xx < 0.85 * w) & (yy > 0.15 * h) & (yy < 0.85 * h)
        ramp = (xx - 0.15 * w) / (0.7 * w)
        d[inside] = 0.2 + 0.8 * ramp[inside]
        objects[inside] = 1
    elif layout == "thin":
        for k, x0 in enumerate(np.linspace(0.15, 0.85, 5) * w):
            half = 1.0 + k % 3  # bars 2, 4 and 6 px wide
            bar = np.abs(xx - x0 - 0.15 * (yy - h / 2)) <= half
            d[bar] = 1.0
            objects[bar] = 1 + k
        wire = np.abs(yy - (0.5 * h + 0.2 * h * np.sin(2 * np.pi * xx / w))) <= 1.0
        d[wire] = 0.6
        objects[wire] = 10
    else:  # relief: a board (0) with components of three heights and raised traces
        n_parts = max(4, (w * h) // 6000)
        for k in range(n_parts):
            cw, ch = rng.uniform(0.06, 0.22) * w, rng.uniform(0.06, 0.22) * h
            cx, cy = rng.uniform(0, w - cw), rng.uniform(0, h - ch)
            part = (xx >= cx) & (xx < cx + cw) & (yy >= cy) & (yy < cy + ch)
            d[part] = rng.choice([0.4, 0.7, 1.0])
            objects[part] = 1 + k
        for k in range(6):
            y0 = rng.uniform(0.05, 0.95) * h
            trace = (np.abs(yy - y0) <= 1.0) & (d == 0)
            d[trace] = 0.1
            objects[trace] = 100 + k
    depth = (d * np.float32(depth_range_um)).astype(np.float32)
    image = np.zeros((h, w, 3), np.float32)
    behind = None
    for k, obj in enumerate(np.unique(objects)):
        tex = _texture(w, h, seed * 1000 + k)
        m = objects == obj
        image[m] = tex[m]
        if k == 0:  # the farthest object's texture goes on behind the others
            behind = tex.astype(np.float32)
    return DepthScene(image, depth, layout, behind)


def depth_layers(depth_um: np.ndarray, max_step_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Quantise a depth map into layers no thicker than ``max_step_um``: (layer index per pixel, layer depths)."""
    lo, hi = float(depth_um.min()), float(depth_um.max())
    values = np.unique(depth_um)
    if len(values) <= 64:  # piecewise flat: one layer per depth, exact
        index = np.searchsorted(values, depth_um).astype(np.int32)
        return index, values.astype(np.float64)
    n = max(1, int(np.ceil((hi - lo) / max(max_step_um, 1e-9))) + 1)
    centres = np.linspace(lo, hi, n)
    index = np.clip(np.rint((depth_um - lo) / max(centres[1] - centres[0] if n > 1 else 1.0, 1e-12)), 0,
                    n - 1).astype(np.int32)
    return index, centres


class DepthRenderer:
    """Frames of a :class:`DepthScene` through a simulated lens (same sensor, noise and geometry as
    :class:`fieldcal.simulate.render.Renderer`).

    Parameters
    ----------
    spec : LensSpec
        Lens and sensor (the scene must have the sensor's size).
    scene : DepthScene
    seed : int
        Noise seed.
    max_layer_um : float, optional
        Thickness of the layers a continuous depth is cut into; default a quarter of the lens's focus
        tolerance at a quarter of the sampling frequency (well inside the depth of field).
    """

    def __init__(self, spec, scene: DepthScene, seed: int = 0, max_layer_um: float | None = None):
        s = spec.sensor
        if scene.depth_um.shape != (s.height_px, s.width_px):
            raise ParameterError(f"depth map is {scene.depth_um.shape[::-1]} px, the sensor {s.width_px}x"
                                 f"{s.height_px}", field="scene", fix="draw the scene at the sensor size")
        if max_layer_um is None:
            fs = 0.25 / (s.pixel_pitch_um * 1e-3)
            max_layer_um = 0.25 * min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
        self.spec = spec
        self.scene = scene
        self.seed = int(seed)
        colour = scene_to_channels(scene.image, spec.channel_names, s.width_px, s.height_px)
        behind = (None if scene.behind is None or scene.behind.shape[:2] != scene.depth_um.shape else
                  scene_to_channels(scene.behind, spec.channel_names, s.width_px, s.height_px))
        index, self.layer_depth_um = depth_layers(scene.depth_um, float(max_layer_um))
        full = Renderer(spec, colour, seed=seed)
        self.exposure = full.exposure
        self._full = full
        self._layers = []
        for k, d in enumerate(self.layer_depth_um):
            own = index == k
            if not own.any():
                continue
            # the layer, and behind every nearer layer its continuation (hidden where those are opaque)
            alpha = (index >= k).astype(np.float32)
            if k == 0 and behind is not None:  # the background's own texture behind what stands on it
                under = np.where(own[..., None], colour, behind)
            else:
                under = fill_behind(colour, own, index > k)
            rc = Renderer(spec, under * alpha[..., None], seed=seed)
            ra = Renderer(spec, np.repeat(alpha[..., None], len(spec.channel_names), axis=2), seed=seed)
            rc.exposure = self.exposure  # one exposure for the whole scene
            ra.exposure = 1.0
            self._layers.append((float(d), rc, ra))
        self._layers.sort(key=lambda t: -t[0])  # nearest (largest depth) first

    @staticmethod
    def _layer(rend: Renderer, z_um: float, depth_um: float) -> np.ndarray:
        """One layer at stage position z: blurred as a flat scene at ``z - depth`` (where it is in focus
        ``depth`` further along the axis), but warped with the geometry of the sensor's real position z."""
        out = np.empty((rend.height_px, rend.width_px, len(rend.channels)), dtype=np.float32)
        for ci, ch in enumerate(rend.channels):
            aff = rend._affine(z_um, ch, True)
            img = rend._warp(rend.sensor_blur(ch, z_um - depth_um, aff), aff)  # astigmatism: the ellipse
            np.multiply(img, rend._illum * np.float32(rend.exposure), out=out[:, :, ci])
        return np.maximum(out, 0.0, out=out)

    def render_float(self, z_um: float) -> np.ndarray:
        """Linear signal at stage position z (float32 H x W x C, 1 = white), before noise."""
        z = _check_z(z_um)
        out = None
        transmit = None
        for d, rc, ra in self._layers:
            c = self._layer(rc, z, d)
            a = np.clip(self._layer(ra, z, d) / np.maximum(ra._illum[..., None], 1e-6), 0.0, 1.0)
            if out is None:
                out, transmit = c, 1.0 - a
            else:
                out = out + transmit * c
                transmit = transmit * (1.0 - a)
        return out

    def render(self, z_um: float, noise: bool = True) -> np.ndarray:
        """The frame the camera records at z (dtype from the bit depth; a mosaic for a Bayer sensor)."""
        z = _check_z(z_um)
        signal = self.render_float(z)
        if self.spec.sensor.cfa:
            signal = _noise.mosaic(signal, self.spec.channel_names, self.spec.sensor.cfa)
        rng = _noise.frame_rng(self.seed, z) if noise else None
        return _noise.to_dn(signal, self.spec.sensor, rng)

    def truth(self) -> np.ndarray:
        """All-in-focus image in the geometry of z_ref (each layer at its own focus), no noise."""
        out = None
        transmit = None
        for _, rc, ra in self._layers:
            c = rc._linear(None)
            a = np.clip(ra._linear(None) / np.maximum(ra._illum[..., None], 1e-6), 0.0, 1.0)
            if out is None:
                out, transmit = c, 1.0 - a
            else:
                out = out + transmit * c
                transmit = transmit * (1.0 - a)
        return _noise.to_dn(out, self.spec.sensor, None)

    def best_focus_um(self, x, y, channel: str) -> np.ndarray:
        """Oracle best focus of the scene at z_ref pixel (x, y): the lens's surface plus the depth there."""
        xi = np.clip(np.rint(np.asarray(x)).astype(int), 0, self.scene.depth_um.shape[1] - 1)
        yi = np.clip(np.rint(np.asarray(y)).astype(int), 0, self.scene.depth_um.shape[0] - 1)
        xm, ym = self.spec.pixel_to_mm(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return self.spec.best_focus_um(xm, ym, channel) + self.scene.depth_um[yi, xi]


def fill_behind(colour: np.ndarray, own: np.ndarray, behind: np.ndarray) -> np.ndarray:
    """``colour`` with the pixels ``behind`` replaced by a smooth fill from the pixels ``own`` (normalised
    Gaussian convolution at growing scales: each hidden pixel takes the local mean colour of the nearest
    visible part of its layer, with no edges of its own)."""
    out = colour.astype(np.float32, copy=True)
    todo = behind.copy()
    if not todo.any():
        return out
    m = own.astype(np.float32)
    cm = colour * m[..., None]
    sigma = 2.0
    while todo.any():
        num = cv2.GaussianBlur(cm, (0, 0), sigma, borderType=cv2.BORDER_REFLECT101)
        den = cv2.GaussianBlur(m, (0, 0), sigma, borderType=cv2.BORDER_REFLECT101)
        ok = todo & (den > 1e-3)
        out[ok] = num[ok] / den[ok][:, None]
        todo &= ~ok
        if sigma > 2 * max(colour.shape[:2]):
            out[todo] = cm.reshape(-1, cm.shape[2]).sum(0) / max(m.sum(), 1.0)
            break
        sigma *= 2.0
    return out


def depth_edges(depth_um: np.ndarray, min_step_um: float) -> np.ndarray:
    """Boolean map of pixels next to a depth step larger than ``min_step_um`` (for halo measurements)."""
    d = depth_um.astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = cv2.dilate(d, k) - cv2.erode(d, k)
    return jump > min_step_um


def halo_width_px(image: np.ndarray, truth: np.ndarray, depth_um: np.ndarray, min_step_um: float,
                  factor: float = 1.5, far_px: int = 12) -> int:
    """Width (px) of the band around depth edges where a composite's error stands out.

    The mean absolute error (over channels) against the all-in-focus ``truth`` is taken in 1-px rings of distance
    from the depth edges (:func:`depth_edges` with ``min_step_um``; ring 0 is the edge band itself, the pixels
    whose 3x3 neighbourhood straddles a step). The width is the first ring whose error is no more than ``factor``
    times the error farther than ``far_px`` from any edge: 1 when only the edge band itself is worse (the least
    any composite can do: a pixel on a step mixes two depths), ``far_px`` when the halo reaches that far.
    """
    err = np.abs(np.asarray(image, np.float64)[..., :truth.shape[2]] - np.asarray(truth, np.float64)).mean(axis=2)
    edges = depth_edges(depth_um, min_step_um)
    if not edges.any():
        return 0
    dist = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 3)
    far = float(err[dist > far_px].mean()) if np.any(dist > far_px) else float(err.mean())
    for d in range(far_px):
        ring = (dist >= d) & (dist < d + 1)
        if ring.any() and err[ring].mean() <= factor * far:
            return d
    return far_px

