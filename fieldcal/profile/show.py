"""A lens profile summarised for a person (``fieldcal profile show``).

:func:`profile_summary` collects the numbers (a JSON-safe dict); :func:`format_summary` lays them out as text.
Every number comes from the profile's public API, so what the summary says is what planning and compositing use.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fieldcal.errors import FieldcalError
from fieldcal.profile.uncertainty import geometry_rates

BAND_LEVEL = 0.9


def _corners(profile) -> tuple[np.ndarray, np.ndarray]:
    w, h = profile.image_size_px
    return np.array([0.0, w - 1.0, 0.0, w - 1.0]), np.array([0.0, 0.0, h - 1.0, h - 1.0])


def channel_summary(profile, ch: str) -> dict[str, Any]:
    """Best focus, tilt, curvature, band and tolerance of one channel."""
    w, h = profile.image_size_px
    cx, cy = profile.optical_centre_px()
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, max(3, round(17 * h / w))))
    z = profile.best_focus_um(gx, gy, ch)
    z_c = float(profile.best_focus_um(cx, cy, ch))
    kx, ky = _corners(profile)
    z_k = profile.best_focus_um(kx, ky, ch)
    lo, hi = profile.best_focus_interval_um(gx, gy, ch, BAND_LEVEL)
    half = 0.5 * (hi - lo)
    lo_k, hi_k = profile.best_focus_interval_um(kx, ky, ch, BAND_LEVEL)
    coef = profile.surfaces.coefficients_um(ch)
    out: dict[str, Any] = {
        "best_focus_mean_um": float(np.mean(z)), "best_focus_centre_um": z_c,
        "best_focus_range_um": [float(np.min(z)), float(np.max(z))],
        "sag_centre_to_corner_um": float(np.mean(z_k) - z_c),
        "tilt_um_per_mm": [coef.get("tilt_x_um_per_mm", 0.0), coef.get("tilt_y_um_per_mm", 0.0)],
        "band_level": BAND_LEVEL, "band_half_width_median_um": float(np.median(half)),
        "band_half_width_corner_um": float(np.max(0.5 * (hi_k - lo_k))),
    }
    if getattr(profile.surfaces.model, "astig", False):
        out["astigmatism_corner_um"] = float(np.max(np.abs(profile.surfaces.astigmatism_um(kx, ky, ch))))
    fs, q = profile.calibration.get("fs_cyc_per_mm"), profile.calibration.get("q")
    if fs and q:
        try:
            t_c = float(np.ravel(profile.focus_tolerance_um(cx, cy, ch, fs, q))[0])
            t_k = float(np.max(profile.focus_tolerance_um(kx, ky, ch, fs, q)))
            out["tolerance_um"] = {"fs_cyc_per_mm": fs, "q": q, "centre": t_c, "corner": t_k,
                                   "source": "measured widths" if profile.has_measured_tolerance
                                   else "defocus model (F-number)"}
        except FieldcalError as e:  # a profile without F-number or widths: say so, do not fail
            out["tolerance_um"] = {"fs_cyc_per_mm": fs, "q": q, "note": getattr(e, "what", str(e))}
    return out


def geometry_summary(profile) -> dict[str, Any]:
    """Breathing, drift and lateral colour per channel at z_ref; distortion when the profile holds maps."""
    z0, z1 = profile.z_range_um
    chans = {}
    for ch in profile.channels:
        r = geometry_rates(profile, ch, profile.z_ref_um)
        if not r:
            continue
        m0, m1 = (float(profile.magnification(z, ch)) for z in (z0, z1))
        chans[ch] = {k: {"value": v.value, "sd": v.sd} for k, v in r.items()}
        chans[ch]["magnification_over_scan"] = [m0, m1]
    out: dict[str, Any] = {"z_ref_um": profile.z_ref_um, "channels": chans}
    gm = getattr(profile, "geometry_map", None)
    if gm is not None and hasattr(gm, "channels"):
        out["maps"] = {ch: sorted({str(t) for t, _ in getattr(m, "columns", ())}) for ch, m in gm.channels.items()}
        out["distortion"] = "dense maps (terms per channel listed)"
    else:
        out["distortion"] = "not in this profile (scalar magnification and shift vs z)"
    return out


def absolute_distortion_summary(profile, n: int = 33) -> dict[str, Any] | None:
    """The absolute distortion block (ChArUco; None without one): terms with their sd, the board fit, and the
    largest distortion of the reference channel at the block's z over the board's hull (the measured field;
    outside it the polynomial is extrapolated) with its 1-sigma there and the largest 1-sigma inside.

    The sd comes from the board fit's covariance composed with the maps'; on rendered stacks it was measured
    about 3x smaller than the error against the simulator's truth (docs/geometry.md), so read it as a floor."""
    from fieldcal.profile.lensfun import _in_hull
    d = getattr(profile, "absolute_distortion", None)
    if d is None:
        return None
    w, h = profile.image_size_px
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, max(3, round(n * h / w))))
    inside = _in_hull(d.hull_px, gx, gy)
    x, y = gx[inside], gy[inside]
    fx, fy = profile.distortion_px(x, y)
    sx, sy = profile.distortion_sd_px(x, y)
    mag, sd = np.hypot(fx - x, fy - y), np.hypot(sx, sy)
    i = int(np.argmax(mag))
    cov = np.asarray(d.cov, dtype=np.float64).reshape(len(d.terms), len(d.terms))
    return {"z_um": float(d.z_um), "reference_channel": d.reference_channel, "source": d.source,
            "n_points": int(d.n_points), "rms_px": float(d.rms_px),
            "terms": {t: {"value": float(c), "sd": float(math.sqrt(max(cov[k, k], 0.0)))}
                      for k, (t, c) in enumerate(zip(d.terms, d.coef))},
            "hull_fraction": float(inside.mean()),
            "max_distortion_px": float(mag[i]), "at_px": [float(x[i]), float(y[i])], "sd_at_max_px": float(sd[i]),
            "max_sd_px": float(np.max(sd)),
            "sd_note": "the sd is about 3x too small on rendered stacks (docs/geometry.md): a floor, not a band"}


def profile_summary(profile) -> dict[str, Any]:
    """The numbers :func:`format_summary` shows (JSON-safe)."""
    prov = profile.provenance or {}
    meta = prov.get("stack_meta") or {}
    w, h = profile.image_size_px
    cal = profile.calibration
    sc = (profile.surfaces.diagnostics or {}).get("self_check") or {}
    return {
        "path": profile.source_path,
        "lens": meta.get("lens") or meta.get("lens_model"),
        "camera": {"image_size_px": [w, h], "pixel_pitch_um": profile.pixel_pitch_um, "cfa": profile.cfa,
                   "camera": meta.get("camera") or meta.get("camera_model"),
                   "sensor_mm": [w * profile.pixel_pitch_um / 1000.0, h * profile.pixel_pitch_um / 1000.0]},
        "optics": {"f_number": profile.f_number, "focal_length_mm": profile.focal_length_mm,
                   "object_distance_mm": profile.object_distance_mm},
        "channels": list(profile.channels),
        "calibration": {"effort": cal.get("effort"), "fs_cyc_per_mm": cal.get("fs_cyc_per_mm"), "q": cal.get("q"),
                        "measure": cal.get("measure"), "tile_px": cal.get("tile_px"), "n_frames": cal.get("n_frames"),
                        "z_range_um": list(profile.z_range_um), "z_step_um": cal.get("z_step_um"),
                        "z_ref_um": profile.z_ref_um},
        "surface_model": profile.surfaces.model.name,
        "self_check": {"coverage": sc.get("coverage"), "level": sc.get("level"), "status": sc.get("status"),
                       "band_scale": sc.get("band_scale"), "warning": sc.get("warning"),
                       # session 11 on: coverage is the band's estimated truth coverage, with its 5-95 % range
                       "coverage_range": sc.get("coverage_range"), "tile_coverage": sc.get("tile_coverage"),
                       "coverage_abs_dev": sc.get("coverage_abs_dev"),
                       "estimates": sc.get("estimates")} if sc else None,
        # calibrate's warning when the calibrated focus (the optical centre) is far from every fitted tile
        "centre_support_warning": (((profile.diagnostics or {}).get("surface_support") or {}).get("centre")
                                   or {}).get("warning"),
        "surfaces": {ch: channel_summary(profile, ch) for ch in profile.channels},
        "geometry": geometry_summary(profile),
        "absolute_distortion": absolute_distortion_summary(profile),
        "provenance": {"created_utc": prov.get("created_utc"), "tool": prov.get("tool"), "stack": prov.get("stack"),
                       "inputs_sha256": prov.get("inputs_sha256")},
    }


def _f(v, fmt=".1f", unit="") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    return f"{v:{fmt}}{unit}"


def format_summary(s: dict[str, Any]) -> str:
    """The summary as text, one topic per block."""
    cam, opt, cal = s["camera"], s["optics"], s["calibration"]
    w, h = cam["image_size_px"]
    L = [f"profile  {s['path']}",
         f"lens     {s['lens'] or '(not recorded)'}; F/{_f(opt['f_number'], 'g')}, f = "
         f"{_f(opt['focal_length_mm'], 'g', ' mm')}, object at {_f(opt['object_distance_mm'], 'g', ' mm')}",
         f"camera   {cam['camera'] or '(not recorded)'}; {w}x{h} px of {cam['pixel_pitch_um']:g} µm "
         f"({cam['sensor_mm'][0]:.2f} x {cam['sensor_mm'][1]:.2f} mm), "
         f"{'CFA ' + cam['cfa'] if cam['cfa'] else 'no CFA'}; channels {', '.join(s['channels'])}",
         f"effort   {cal['effort']}; {cal['measure']} at fs = {_f(cal['fs_cyc_per_mm'], 'g')} cycles/mm, "
         f"q = {_f(cal['q'], 'g')}; {cal['n_frames']} frames over {cal['z_range_um'][0]:g}..{cal['z_range_um'][1]:g} "
         f"µm (step {_f(cal['z_step_um'], 'g')}), z_ref {cal['z_ref_um']:g} µm; tiles {cal['tile_px']} px",
         f"surface  {s['surface_model']}"]
    sc = s.get("self_check")
    if sc and sc.get("coverage") is not None and sc.get("coverage_range") and sc.get("tile_coverage") is not None:
        lo_c, hi_c = sc["coverage_range"]
        dev = sc.get("coverage_abs_dev")
        L.append(f"self-check  expected truth coverage of the {100 * (sc.get('level') or 0.9):.0f}% band "
                 f"{100 * sc['coverage']:.0f}% (one lens: {100 * lo_c:.0f}-{100 * hi_c:.0f}%, 5-95%"
                 + (f", on average {100 * dev:.0f} points off" if dev is not None else "") + "); "
                 f"{100 * sc['tile_coverage']:.0f}% of held-out tiles inside theirs (band scale "
                 f"{_f(sc.get('band_scale'), '.2f')})" + (f"; warning: {sc['warning']}" if sc.get("warning") else ""))
    elif sc and sc.get("coverage") is not None:
        L.append(f"self-check  {100 * sc['coverage']:.0f}% of held-out tiles inside the "
                 f"{100 * (sc.get('level') or 0.9):.0f}% band (band scale {_f(sc.get('band_scale'), '.2f')})"
                 + (f"; warning: {sc['warning']}" if sc.get("warning") else ""))
    if s.get("centre_support_warning"):
        L.append(f"warning  {s['centre_support_warning']}")
    L.append("")
    L.append("best focus (stage µm)   mean    centre  sag c->corner  tilt x, y (µm/mm)   90% band ± (median, corner)"
             "   tolerance ± (centre, corner)")
    for ch, c in s["surfaces"].items():
        tol = c.get("tolerance_um") or {}
        tol_s = (f"{tol['centre']:.1f}, {tol['corner']:.1f} ({tol['source']})" if "centre" in tol
                 else (tol.get("note") or "—"))
        L.append(f"  {ch:<20s} {c['best_focus_mean_um']:8.1f} {c['best_focus_centre_um']:8.1f} "
                 f"{c['sag_centre_to_corner_um']:+12.1f}   {c['tilt_um_per_mm'][0]:+7.2f}, "
                 f"{c['tilt_um_per_mm'][1]:+7.2f}      {c['band_half_width_median_um']:6.2f}, "
                 f"{c['band_half_width_corner_um']:6.2f}            {tol_s}"
                 + (f"; astigmatism {c['astigmatism_corner_um']:.1f} µm at the corner"
                    if "astigmatism_corner_um" in c else ""))
    g = s["geometry"]
    L.append("")
    L.append(f"geometry at z_ref = {g['z_ref_um']:g} µm")
    for ch, c in g["channels"].items():
        b = c["breathing_per_um"]
        m0, m1 = c["magnification_over_scan"]
        parts = [f"breathing {1e6 * b['value']:+.2f} ± {1e6 * b['sd']:.2f} ppm/µm (m {m0:.5f}..{m1:.5f} over "
                 "the scan)",
                 f"drift at the frame centre ({1e3 * c['drift_x_px_per_um']['value']:+.2f}, "
                 f"{1e3 * c['drift_y_px_per_um']['value']:+.2f}) px/mm of z"]
        if "lateral_colour_scale" in c:
            lc = c["lateral_colour_scale"]
            parts.append(f"lateral colour {1e6 * (lc['value'] - 1):+.0f} ± {1e6 * lc['sd']:.0f} ppm")
        L.append(f"  {ch}: " + "; ".join(parts))
    L.append(f"  distortion: {g['distortion']}")
    for ch, terms in (g.get("maps") or {}).items():
        L.append(f"    {ch}: {', '.join(terms)}")
    L += _absolute_distortion_lines(s.get("absolute_distortion"))
    p = s["provenance"]
    L.append("")
    tool = p.get("tool") or {}
    L.append(f"written  {p.get('created_utc') or '—'} by {tool.get('name', 'fieldcal')} {tool.get('version', '')}"
             f" from {p.get('stack') or '—'} (inputs sha256 {(p.get('inputs_sha256') or '—')[:16]})")
    return "\n".join(L)


def _absolute_distortion_lines(a: dict[str, Any] | None) -> list[str]:
    if a is None:
        return ["  absolute distortion: none (no ChArUco board in the stack; texture shows no straight lines)"]
    terms = ", ".join(f"{t} {v['value']:+.3g} ± {v['sd']:.1g}" for t, v in a["terms"].items()) or "none (BIC)"
    return [f"  absolute distortion at z = {a['z_um']:g} µm ({a['reference_channel']}, {a['source']}: "
            f"{a['n_points']} corners, fit rms {a['rms_px']:.3f} px): {terms}",
            f"    over the board's hull ({100 * a['hull_fraction']:.0f}% of the frame): max {a['max_distortion_px']:.2f}"
            f" px at ({a['at_px'][0]:.0f}, {a['at_px'][1]:.0f}) px, sd {a['sd_at_max_px']:.3f} px there, "
            f"<= {a['max_sd_px']:.3f} px (about 3x too small on rendered stacks: a floor)"]
