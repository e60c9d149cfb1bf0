"""A lens profile as a Lensfun database entry (``fieldcal profile export --format lensfun``).

Lensfun (https://lensfun.github.io; the ``lensfunpy`` bindings bundle a Lensfun that reads database version 1)
describes a lens by radial models in *normalised* coordinates: the image centre is the origin and r = 1 is half
the shorter side of a 3:2 frame with the image's diagonal, i.e. ``r_norm_px = hypot(W - 1, H - 1) / 2 /
hypot(1, 1.5)`` for an image of W x H px (lens and camera share one crop factor here, so no crop rescaling).
Checked against lensfunpy 1.18: its geometry and sub-pixel maps agree with these formulas to 0.001 px.

* distortion, model ``poly5``: ``r_d = r_u (1 + k1 r_u^2 + k2 r_u^4)`` -- the Brown-Conrady radial model, so a
  radial (k1, k2) in any other normalisation converts exactly (:func:`brown_to_poly5`);
* transverse chromatic aberration, model ``poly3``: ``r_c = r (b r^2 + c r + v)`` for red and blue against green;
  a constant lateral-colour scale is ``v`` alone (the ``linear`` model's ``k``);
* vignetting: fieldcal measures none, so the entry has no vignetting element (Lensfun then leaves it alone).

All of it at one sensor position, the *calibrated focus*: the stage position where the reference channel is
sharpest at the optical centre. The radial models come from the profile's geometry at that position: its
``warp_px`` maps when it has them, else the scalar model (breathing, shift and lateral colour: no distortion).
Lensfun centres every model on the image centre; fieldcal's optical centre may differ by a few pixels, so
the fit is about the image centre and its residual is reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from fieldcal.errors import ParameterError

LENSFUN_ASPECT = 1.5       # Lensfun's default calibration aspect ratio (3:2)
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def lensfun_norm_radius_px(width_px: int, height_px: int, aspect: float = LENSFUN_ASPECT) -> float:
    """The pixel length of Lensfun's unit radius for a W x H image (lens and camera of one crop factor)."""
    return 0.5 * math.hypot(width_px - 1, height_px - 1) / math.hypot(1.0, aspect)


def brown_to_poly5(k1: float, k2: float, r_model_px: float, r_lensfun_px: float) -> tuple[float, float]:
    """Radial Brown-Conrady coefficients in a normalisation of ``r_model_px`` as Lensfun ``poly5`` (k1, k2).

    ``r_d = r (1 + k1 r^2 + k2 r^4)`` with ``r = rho / r_model_px``; with ``r' = rho / r_lensfun_px`` and
    ``s = r_lensfun_px / r_model_px`` it reads ``r'_d = r' (1 + k1 s^2 r'^2 + k2 s^4 r'^4)``: exact.
    """
    if not (r_model_px > 0 and r_lensfun_px > 0):
        raise ParameterError("normalisation radii must be > 0", field="r_model_px",
                             fix="give the radii in pixels")
    s2 = (float(r_lensfun_px) / float(r_model_px)) ** 2
    return float(k1) * s2, float(k2) * s2 * s2


@dataclass(frozen=True)
class LensfunModel:
    """What the Lensfun entry holds, in Lensfun's normalisation."""

    k1: float
    k2: float
    tca: dict[str, tuple[float, float, float]]   # channel -> (v, c, b) of r_c = r (b r^2 + c r + v)
    focal_mm: float
    aperture: float | None
    distance_m: float
    crop_factor: float
    z_um: float
    fit_rms_px: dict[str, float]
    source: str

    def distort_px(self, x, y, width_px: int, height_px: int):
        """Undistorted -> distorted pixel, as Lensfun's poly5 maps it (for checks)."""
        r_n = lensfun_norm_radius_px(width_px, height_px)
        cx, cy = 0.5 * (width_px - 1), 0.5 * (height_px - 1)
        ux, uy = (np.asarray(x, float) - cx) / r_n, (np.asarray(y, float) - cy) / r_n
        r2 = ux * ux + uy * uy
        f = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return cx + r_n * ux * f, cy + r_n * uy * f


def calibrated_focus_um(profile, channel: str | None = None) -> float:
    """The stage position where ``channel`` (default: the geometry's reference channel) is sharpest at the
    optical centre."""
    ch = channel or _reference_channel(profile)
    cx, cy = profile.optical_centre_px()
    return float(np.ravel(profile.best_focus_um(cx, cy, ch))[0])


def _reference_channel(profile) -> str:
    ref = getattr(profile.geometry_fit, "reference_channel", None)
    return ref if ref in profile.channels else ("G" if "G" in profile.channels else profile.channels[0])


def scalar_warp_px(profile, x, y, z_um: float, channel: str):
    """The scalar geometry as a map: ``c + m(z) s_c (p - c) + shift(z)`` (no distortion), for profiles without
    ``warp_px``."""
    cx, cy = profile.optical_centre_px()
    m = float(profile.magnification(z_um, channel)) * profile.lateral_colour_scale(channel)
    sx, sy = profile.shift_px(z_um, channel)
    x, y = np.asarray(x, float), np.asarray(y, float)
    return cx + m * (x - cx) + float(sx), cy + m * (y - cy) + float(sy)


def _radial_fit(rho_u, rho_d, powers):
    """Least squares of ``rho_d / rho_u = sum a_p r^p`` weighted by rho_u (pixel errors), r normalised."""
    A = np.stack([rho_u * rho_u ** p for p in powers], axis=1)
    coef, *_ = np.linalg.lstsq(A, rho_d, rcond=None)
    return coef, A @ coef - rho_d


def lensfun_model(profile, z_um: float | None = None, n: int = 41) -> LensfunModel:
    """Fit Lensfun's poly5 distortion and poly3 TCA to the profile's geometry at ``z_um`` (default: the
    calibrated focus)."""
    w, h = profile.image_size_px
    z = calibrated_focus_um(profile) if z_um is None else float(z_um)
    warp = getattr(profile, "warp_px", None)
    source = "warp_px maps" if callable(warp) else "scalar model (no distortion)"
    if not callable(warp):
        warp = lambda x, y, zz, ch: scalar_warp_px(profile, x, y, zz, ch)  # noqa: E731
    r_n = lensfun_norm_radius_px(w, h)
    cx, cy = 0.5 * (w - 1), 0.5 * (h - 1)
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, max(5, round(n * h / w))))
    gx, gy = gx.ravel(), gy.ravel()
    ref = _reference_channel(profile)
    qx, qy = (np.asarray(v, float).ravel() for v in warp(gx, gy, z, ref))
    # remove the frame's shift (Lensfun has no translation): the map's mean displacement
    qx, qy = qx - np.mean(qx - gx), qy - np.mean(qy - gy)
    rho_u = np.hypot(gx - cx, gy - cy)
    rho_d = np.hypot(qx - cx, qy - cy)
    keep = rho_u > 1e-6 * r_n
    r = rho_u[keep] / r_n
    # r_d = m r (1 + k1 r^2 + k2 r^4): m is the breathing scale at z (a focal length, not distortion)
    coef, res = _radial_fit(r, rho_d[keep] / r_n, (0, 2, 4))
    m = coef[0]
    k1, k2 = coef[1] / m, coef[2] / m
    fit_rms = {ref: float(np.sqrt(np.mean((res * r_n) ** 2)))}
    tca = {}
    for ch in profile.channels:
        if ch == ref:
            continue
        px, py = (np.asarray(v, float).ravel() for v in warp(gx, gy, z, ch))
        px, py = px - np.mean(px - gx), py - np.mean(py - gy)
        rho_c = np.hypot(px - cx, py - cy)[keep]
        # r_c = r_g (b r_g^2 + c r_g + v), in the reference channel's distorted radius
        rg = rho_d[keep] / r_n
        (v, c, b), res_c = _radial_fit(rg, rho_c / r_n, (0, 1, 2))
        tca[ch] = (float(v), float(c), float(b))
        fit_rms[ch] = float(np.sqrt(np.mean((res_c * r_n) ** 2)))
    diag_mm = math.hypot(w, h) * profile.pixel_pitch_um / 1000.0
    return LensfunModel(float(k1), float(k2), tca, float(profile.focal_length_mm or 50.0), profile.f_number,
                        float((profile.object_distance_mm or 1000.0) / 1000.0), FULL_FRAME_DIAGONAL_MM / diag_mm,
                        z, fit_rms, source)


def _clean(v: float) -> float:
    """Round-off of an exact zero (a scalar model has no distortion) written as 0."""
    return 0.0 if abs(v) < 1e-12 else float(v)


def _tca_xml(model: LensfunModel, channels) -> str:
    red = next((c for c in channels if c.upper().startswith("R")), None)
    blue = next((c for c in channels if c.upper().startswith("B")), None)
    if red not in model.tca and blue not in model.tca:
        return ""
    vr, cr, br = (_clean(v) for v in model.tca.get(red, (1.0, 0.0, 0.0)))
    vb, cb, bb = (_clean(v) for v in model.tca.get(blue, (1.0, 0.0, 0.0)))
    return (f'            <tca model="poly3" focal="{model.focal_mm:.6g}" vr="{vr:.9g}" vb="{vb:.9g}" '
            f'cr="{cr:.9g}" cb="{cb:.9g}" br="{br:.9g}" bb="{bb:.9g}"/>\n')


def lensfun_xml(profile, model: LensfunModel, maker: str = "fieldcal", lens_name: str | None = None,
                camera_name: str | None = None) -> str:
    """The Lensfun database (version 1) text: one mount, one camera, one lens with its calibration."""
    meta = (profile.provenance or {}).get("stack_meta") or {}
    lens = lens_name or meta.get("lens") or Path(profile.source_path or "lens").stem
    camera = camera_name or meta.get("camera") or "calibrated camera"
    mount = f"fieldcal {camera}"
    e = lambda s: escape(str(s))  # noqa: E731
    aperture = f'        <aperture min="{model.aperture:.6g}"/>\n' if model.aperture else ""
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        f"<!-- written by fieldcal from {e(profile.source_path or 'a lens profile')}: geometry at the calibrated "
        f"focus z = {model.z_um:.1f} um ({e(model.source)}); fieldcal measures no vignetting -->\n"
        '<lensdatabase version="1">\n'
        f"    <mount>\n        <name>{e(mount)}</name>\n    </mount>\n"
        f"    <camera>\n        <maker>{e(maker)}</maker>\n        <model>{e(camera)}</model>\n"
        f"        <mount>{e(mount)}</mount>\n        <cropfactor>{model.crop_factor:.6g}</cropfactor>\n    </camera>\n"
        f"    <lens>\n        <maker>{e(maker)}</maker>\n        <model>{e(lens)}</model>\n"
        f"        <mount>{e(mount)}</mount>\n        <focal value=\"{model.focal_mm:.6g}\"/>\n{aperture}"
        f"        <cropfactor>{model.crop_factor:.6g}</cropfactor>\n"
        "        <calibration>\n"
        f'            <distortion model="poly5" focal="{model.focal_mm:.6g}" k1="{_clean(model.k1):.9g}" '
        f'k2="{_clean(model.k2):.9g}"/>\n'
        f"{_tca_xml(model, profile.channels)}"
        "        </calibration>\n    </lens>\n</lensdatabase>\n")
