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
* the lens's ``center`` (offset of the models' centre from the image centre, in units of half the image's
  shorter side -- measured against lensfunpy): radial distortion about an off-centre axis is what fieldcal's
  tangential terms p1, p2 describe to first order, so a free centre carries them;
* vignetting: fieldcal measures none (a chart's white squares show the lighting's fall-off as much as the
  lens's), so the entry has no vignetting element and Lensfun leaves it alone.

All of it at one sensor position, the *calibrated focus*: the stage position where the reference channel is
sharpest at the optical centre (clipped to the scan). The distortion is the profile's **absolute** distortion
there (:meth:`fieldcal.profile.LensProfile.distortion_px`, measured from the ChArUco board); the TCA is the
other channels' distortion against the reference channel's. Profiles without absolute distortion (texture-only)
are refused unless ``allow_no_distortion``: the entry then has TCA only, no distortion element, and says so.

The entry is fitted to the profile over the **whole frame** (a dense grid), minimising the largest error
(:func:`minimax_fit`), since a Lensfun user undistorts the whole frame. Lensfun's models are radial, so the
profile's tangential terms are carried by the centre only to first order: the second-order remainder (the k2
term about the shifted centre) is what is left, ~0.05 px at 480x360 for the benchmark's barrel lens (k1 -0.04,
k2 0.008, p1 5e-4, p2 -3e-4 in half-diagonal units; a least-squares fit leaves 0.135 px in the corners) and
it grows with the image size in pixels and with (p / k1)^2. Beyond the board's convex hull the profile itself
is an extrapolation: the fit's largest error inside and outside the hull are reported, and the file's comment
gives the board's coverage and the profile's own 1-sigma beyond it.
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


def lensfun_centre_unit_px(width_px: int, height_px: int) -> float:
    """The pixel length of Lensfun's ``center`` unit: half the image's shorter side (measured with lensfunpy)."""
    return 0.5 * (min(width_px, height_px) - 1)


@dataclass(frozen=True)
class LensfunModel:
    """What the Lensfun entry holds, in Lensfun's normalisation, and how well it fits the profile."""

    k1: float | None                              # None: no absolute distortion (no distortion element)
    k2: float | None
    centre_px: tuple[float, float]                # the models' centre (px)
    tca: dict[str, tuple[float, float, float]]   # channel -> (v, c, b) of r_c = r (b r^2 + c r + v)
    focal_mm: float
    aperture: float | None
    distance_m: float
    crop_factor: float
    z_um: float
    fit_rms_px: dict[str, float]                  # inside the board's hull
    max_err_px: dict[str, float]                  # inside the board's hull
    max_err_outside_px: dict[str, float]          # extrapolated beyond the hull (nan: the hull covers the frame)
    source: str
    notes: tuple[str, ...] = ()

    def distort_px(self, x, y, width_px: int, height_px: int):
        """Undistorted -> distorted pixel, as Lensfun's poly5 maps it about :attr:`centre_px` (for checks)."""
        r_n = lensfun_norm_radius_px(width_px, height_px)
        cx, cy = self.centre_px
        ux, uy = (np.asarray(x, float) - cx) / r_n, (np.asarray(y, float) - cy) / r_n
        r2 = ux * ux + uy * uy
        f = 1.0 + (self.k1 or 0.0) * r2 + (self.k2 or 0.0) * r2 * r2
        return cx + r_n * ux * f, cy + r_n * uy * f


def calibrated_focus_um(profile, channel: str | None = None) -> float:
    """The stage position where ``channel`` (default: the geometry's reference channel) is sharpest at the
    optical centre."""
    ch = channel or _reference_channel(profile)
    cx, cy = profile.optical_centre_px()
    return float(np.ravel(profile.best_focus_um(cx, cy, ch))[0])


def _reference_channel(profile) -> str:
    ref = getattr(profile, "reference_channel", None)
    if not isinstance(ref, str):
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


def minimax_fit(resid, x0, x_scale=1.0, scale_px=None, iterations: int = 40) -> np.ndarray:
    """Parameters minimising the largest per-point error ``hypot`` of ``resid(p)`` (x residuals, then y), each
    point's error in units of ``scale_px`` (default 1).

    Lawson's algorithm: weighted least squares (``scipy.optimize.least_squares``) whose weights grow with each
    point's error until the error is levelled; the best iterate (smallest maximum) is returned. The export is
    used over the whole frame, so its largest error, not its RMS, is what a user meets (a least-squares fit of a
    radial model to a decentred lens leaves ~2.5x larger errors in the corners).
    """
    from scipy.optimize import least_squares
    x0 = np.asarray(x0, float)
    n = np.asarray(resid(x0)).size // 2
    inv = np.ones(n) if scale_px is None else 1.0 / np.asarray(scale_px, float).ravel()
    inv2 = np.concatenate([inv, inv])
    p = least_squares(lambda q: resid(q) * inv2, x0, method="lm", x_scale=x_scale).x
    e = np.hypot(*resid(p).reshape(2, -1)) * inv
    best, best_max = p, float(e.max())
    w = np.full(e.size, 1.0 / e.size)
    for _ in range(iterations):
        w = w * e / max(float(w @ e), 1e-300)
        sw = np.sqrt(np.concatenate([w, w])) * inv2
        p = least_squares(lambda q: resid(q) * sw, p, method="lm", x_scale=x_scale).x
        e = np.hypot(*resid(p).reshape(2, -1)) * inv
        if e.max() < best_max:
            best, best_max = p, float(e.max())
    return best


def _in_hull(hull: np.ndarray | None, x, y) -> np.ndarray:
    """Points inside a convex polygon (vertices in order); everything when there is no hull."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if hull is None or len(hull) < 3:
        return np.ones(x.shape, bool)
    h = np.asarray(hull, float)
    e = np.roll(h, -1, axis=0) - h
    cross = e[:, 0, None] * (y.ravel()[None, :] - h[:, 1, None]) - e[:, 1, None] * (x.ravel()[None, :] - h[:, 0, None])
    return (np.all(cross >= -1e-9, axis=0) | np.all(cross <= 1e-9, axis=0)).reshape(x.shape)


def _scan_focus(profile, z_um: float | None) -> tuple[float, list[str]]:
    """The export's stage position: the calibrated focus clipped to the scan (a fit's extrapolation is no
    calibration), or the one asked for."""
    lo, hi = getattr(profile, "z_range_um", (-np.inf, np.inf))
    if z_um is not None:
        z = float(z_um)
        if not math.isfinite(z):
            raise ParameterError(f"the stage position z = {z_um!r} µm is not a finite number", field="z_um",
                                 fix="give the stage position of the exported geometry in µm, or leave it unset "
                                     "for the calibrated focus")
        if not (lo <= z <= hi):
            return z, [f"z = {z:.1f} um lies outside the scan [{lo:.1f}, {hi:.1f}] um: the exported geometry is "
                       "the fit's extrapolation, not a calibration"]
        return z, []
    z = calibrated_focus_um(profile)
    if not (lo <= z <= hi):
        zc = float(np.clip(z, lo, hi))
        return zc, [f"the calibrated focus {z:.1f} um lies outside the scan [{lo:.1f}, {hi:.1f}] um: "
                    f"exported at {zc:.1f} um"]
    return z, []


def lensfun_model(profile, z_um: float | None = None, n: int = 41, allow_no_distortion: bool = False,
                  tolerance_px: float = 0.1) -> LensfunModel:
    """Fit Lensfun's poly5 distortion (with its centre) and poly3 TCA to the profile's absolute distortion at
    ``z_um`` (default: the calibrated focus), over the whole frame on an ``n``-point-wide grid, minimising the
    largest error in units of ``hypot(profile's 1-sigma, tolerance_px)`` (:func:`minimax_fit`): where the
    profile knows the lens far better than ``tolerance_px`` every point counts alike; beyond the board, where
    the profile's extrapolation grows uncertain, a point counts less.

    Raises :class:`ParameterError` when the profile has no absolute distortion (texture-only), unless
    ``allow_no_distortion``: the model then has no distortion (``k1 = k2 = None``) and its TCA comes from the
    maps' lateral colour.
    """
    w, h = profile.image_size_px
    z, notes = _scan_focus(profile, z_um)
    absolute = bool(getattr(profile, "has_absolute_distortion", False))
    r_n = lensfun_norm_radius_px(w, h)
    c0 = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, max(5, round(n * h / w))))
    gx, gy = gx.ravel(), gy.ravel()
    ref = _reference_channel(profile)
    if absolute:
        dist = lambda x, y, ch: profile.distortion_px(x, y, z, ch)  # noqa: E731
        hull = getattr(profile.absolute_distortion, "hull_px", None) if hasattr(profile, "absolute_distortion") else None
        inside = _in_hull(hull, gx, gy)
        source = "absolute distortion (ChArUco board) composed with the geometry maps"
    else:
        if not allow_no_distortion:
            why = ("its geometry maps come from texture" if getattr(getattr(profile, "geometry_map", None), "source",
                                                                     None) == "texture" else "it has no board geometry")
            raise ParameterError(f"the profile has no absolute distortion ({why}): a Lensfun entry would claim a "
                                 "distortion-free lens", path=getattr(profile, "source_path", None),
                                 field="absolute_distortion",
                                 fix="calibrate a ChArUco stack (--chart), or export TCA only with "
                                     "--allow-no-distortion")
        warp = getattr(profile, "warp_px", None)
        if not callable(warp):
            warp = lambda x, y, zz, ch: scalar_warp_px(profile, x, y, zz, ch)  # noqa: E731

        def dist(x, y, ch):
            qx, qy = (np.asarray(v, float) for v in warp(x, y, z, ch))
            rx, ry = (np.asarray(v, float) for v in warp(x, y, z, ref))
            # the reference channel's geometry at z is the identity here: other channels relative to it
            return x + (qx - rx), y + (qy - ry)
        inside = np.ones(gx.shape, bool)
        source = "NO absolute distortion (texture-only or no board): TCA from the geometry only"
        notes.append("this profile has no absolute distortion: the entry holds TCA only, no distortion element "
                     "(Lensfun leaves the geometry alone)")
    qx, qy = (np.asarray(v, float).ravel() for v in dist(gx, gy, ref))
    fit_rms, max_in, max_out = {}, {}, {}

    def report(ch, e):
        fit_rms[ch] = float(np.sqrt(np.mean(e[inside] ** 2)))
        max_in[ch] = float(e[inside].max())
        max_out[ch] = float(e[~inside].max()) if (~inside).any() else float("nan")
    def scale(ch):
        """Each grid point's weight in the fit: the profile's own 1-sigma there beside the export's tolerance
        (where the profile is known far better than the tolerance, every point counts alike; beyond the board,
        where it extrapolates, a point counts less as its uncertainty grows)."""
        if not absolute:
            return None
        sx, sy = profile.distortion_sd_px(gx, gy, z, ch)
        return np.hypot(np.hypot(np.ravel(sx), np.ravel(sy)), tolerance_px)
    if absolute:
        def resid(p):
            c = c0 + p[2:4]
            ux, uy = (gx - c[0]) / r_n, (gy - c[1]) / r_n
            r2 = ux * ux + uy * uy
            f = 1.0 + p[0] * r2 + p[1] * r2 * r2
            return np.concatenate([c[0] + r_n * ux * f - qx, c[1] + r_n * uy * f - qy])
        p = minimax_fit(resid, np.zeros(4), x_scale=np.array([0.01, 0.01, 1.0, 1.0]),
                        scale_px=scale(ref))
        k1, k2 = (float(v) for v in p[:2])
        centre = c0 + p[2:4]
        report(ref, np.hypot(*resid(p).reshape(2, -1)))
    else:
        k1 = k2 = None
        centre = c0
    tca = {}
    rho_g = np.hypot(qx - centre[0], qy - centre[1])
    rg = rho_g / r_n
    for ch in profile.channels:
        if ch == ref:
            continue
        px, py = (np.asarray(v, float).ravel() for v in dist(gx, gy, ch))

        # r_c = r_g (b r_g^2 + c r_g + v), in the reference channel's distorted radius about the centre
        def resid_tca(p, px=px, py=py):
            f = p[2] * rg * rg + p[1] * rg + p[0]
            return np.concatenate([centre[0] + (qx - centre[0]) * f - px, centre[1] + (qy - centre[1]) * f - py])
        v, c, b = (float(t) for t in minimax_fit(resid_tca, np.array([1.0, 0.0, 0.0]), scale_px=scale(ch)))
        tca[ch] = (v, c, b)
        report(ch, np.hypot(*resid_tca(np.array([v, c, b])).reshape(2, -1)))
    if absolute and (~inside).any():
        worst = max(max_out.values())
        sx, sy = profile.distortion_sd_px(gx[~inside], gy[~inside], z, ref)
        notes.append(f"the board covered {100 * inside.mean():.0f} % of the frame: the entry is fitted to the "
                     f"profile over the whole frame, and beyond the board that is the profile's extrapolation "
                     f"(its own 1-sigma there reaches {float(np.max(np.hypot(sx, sy))):.2f} px; the entry and the "
                     f"profile differ by up to {worst:.2f} px there)")
    diag_mm = math.hypot(w, h) * profile.pixel_pitch_um / 1000.0
    return LensfunModel(k1, k2, (float(centre[0]), float(centre[1])), tca, float(profile.focal_length_mm or 50.0),
                        profile.f_number, float((profile.object_distance_mm or 1000.0) / 1000.0),
                        FULL_FRAME_DIAGONAL_MM / diag_mm, z, fit_rms, max_in, max_out, source, tuple(notes))


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
    w, h = profile.image_size_px
    unit = lensfun_centre_unit_px(w, h)
    ox, oy = ((model.centre_px[0] - 0.5 * (w - 1)) / unit, (model.centre_px[1] - 0.5 * (h - 1)) / unit)
    centre = f'        <center x="{_clean(ox):.9g}" y="{_clean(oy):.9g}"/>\n' if (ox or oy) else ""
    distortion = ("" if model.k1 is None else
                  f'            <distortion model="poly5" focal="{model.focal_mm:.6g}" k1="{_clean(model.k1):.9g}" '
                  f'k2="{_clean(model.k2):.9g}"/>\n')
    notes = "".join(f"<!-- {e(n)} -->\n" for n in model.notes)
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        f"<!-- written by fieldcal from {e(profile.source_path or 'a lens profile')}: geometry at the calibrated "
        f"focus z = {model.z_um:.1f} um ({e(model.source)}); fieldcal measures no vignetting -->\n{notes}"
        '<lensdatabase version="1">\n'
        f"    <mount>\n        <name>{e(mount)}</name>\n    </mount>\n"
        f"    <camera>\n        <maker>{e(maker)}</maker>\n        <model>{e(camera)}</model>\n"
        f"        <mount>{e(mount)}</mount>\n        <cropfactor>{model.crop_factor:.6g}</cropfactor>\n    </camera>\n"
        f"    <lens>\n        <maker>{e(maker)}</maker>\n        <model>{e(lens)}</model>\n"
        f"        <mount>{e(mount)}</mount>\n        <focal value=\"{model.focal_mm:.6g}\"/>\n{aperture}"
        f"        <cropfactor>{model.crop_factor:.6g}</cropfactor>\n{centre}"
        "        <calibration>\n"
        f"{distortion}"
        f"{_tca_xml(model, profile.channels)}"
        "        </calibration>\n    </lens>\n</lensdatabase>\n")
