"""From a traced best-focus table to a ``fieldcal-lens/1`` spec, and the comparison of a spec with a trace.

Pure functions over a :class:`~fieldcal.raytrace.bestfocus.FocusTable` and paraxial data; the tracing itself
lives in ``bestfocus.py``. How each field of the spec is derived is written into its ``sources`` block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError, SpecError
from fieldcal.optics import diffraction_mtf
from fieldcal.simulate.lens import ChannelSpec, LensSpec, SensorSpec
from .bestfocus import FocusTable
from .paraxial import ParaxialData


@dataclass(frozen=True)
class FirstOrderCheck:
    """Paraxial EFL/BFL against the values the user expects."""

    efl_mm: float
    bfl_mm: float
    expected_efl_mm: float | None
    expected_bfl_mm: float | None
    rel_tolerance: float


def check_first_order(parax: ParaxialData, expected_efl_mm: float | None, expected_bfl_mm: float | None,
                      rel_tolerance: float = 0.005, path=None) -> FirstOrderCheck:
    """Raise :class:`SpecError` when the traced EFL/BFL disagree with the expected ones beyond the tolerance.

    A mistyped radius, thickness or index shows up here long before anyone looks at an MTF.
    """
    if not (0.0 < rel_tolerance < 1.0):
        raise ParameterError(f"relative tolerance must be in (0, 1), got {rel_tolerance}", field="tolerance",
                             fix="e.g. 0.005 (0.5%)")
    for key, got, want in (("efl_mm", parax.efl_mm, expected_efl_mm), ("bfl_mm", parax.bfl_mm, expected_bfl_mm)):
        if want is None:
            continue
        if not (math.isfinite(got) and abs(got - want) <= rel_tolerance * abs(want)):
            name = "EFL" if key == "efl_mm" else "BFL"
            raise SpecError(
                f"the paraxial {name} of the table is {got:.4f} mm, expected {want:.4f} mm "
                f"(differs by {100 * abs(got - want) / abs(want):.2f}%, tolerance {100 * rel_tolerance:.2f}%)",
                path=path, field=key,
                fix="check the radii, thicknesses and nd of the table (sign of each radius, the stop row, "
                    "a missing surface), or correct the expected value")
    return FirstOrderCheck(parax.efl_mm, parax.bfl_mm, expected_efl_mm, expected_bfl_mm, rel_tolerance)


def fit_even_polynomial(h_mm, z_um, image_height_mm: float, n_terms: int) -> tuple[float, tuple[float, ...], float]:
    """Least-squares ``z = a0 + sum_k a_k rho^(2k)`` (rho = h / image_height); returns (a0, (a1..), rms_um)."""
    h = np.asarray(h_mm, dtype=np.float64)
    z = np.asarray(z_um, dtype=np.float64)
    if h.size < n_terms + 1:
        raise ParameterError(f"{h.size} image heights cannot fix {n_terms + 1} coefficients", field="heights",
                             fix=f"trace at least {n_terms + 1} heights or use fewer terms")
    r2 = (h / image_height_mm) ** 2  # normalised: the design matrix stays well conditioned
    a = np.stack([r2 ** k for k in range(n_terms + 1)], axis=1)
    coef, *_ = np.linalg.lstsq(a, z, rcond=None)
    rms = float(np.sqrt(np.mean((a @ coef - z) ** 2)))
    return float(coef[0]), tuple(float(c) for c in coef[1:]), rms


def residual_blur_um(peak_mtf: float, fs_cyc_per_mm: float, wavelength_nm: float, f_number: float) -> float:
    """Gaussian RMS (µm) bringing the model's diffraction-limited in-focus MTF at fs down to the traced peak."""
    d = float(diffraction_mtf(fs_cyc_per_mm, wavelength_nm, f_number))
    if not (0.0 < peak_mtf < d):
        return 0.0  # traced peak at (or numerically above) the diffraction limit: no residual blur
    return float(math.sqrt(-math.log(peak_mtf / d) / 2.0) / (math.pi * fs_cyc_per_mm / 1000.0))


def parse_sensor(text: str, image_height_mm: float | None) -> tuple[int, int, float | None]:
    """``WxH@PITCH`` (pitch in µm) or ``WxH`` (pitch then puts the corner at the image height)."""
    import re

    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*(?:@\s*([0-9.eE+-]+)\s*(?:um|µm)?)?\s*", text or "")
    if not m:
        raise ParameterError(f"cannot read the sensor {text!r}", field="sensor",
                             fix="write WIDTHxHEIGHT@PITCH_UM, e.g. 3840x2160@1.6342, or WIDTHxHEIGHT")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 8 or h < 8:
        raise ParameterError(f"sensor {w}x{h} px is too small", field="sensor", fix="use at least 8x8 pixels")
    pitch = None
    if m.group(3) is not None:
        try:
            pitch = float(m.group(3))
        except ValueError:
            pitch = -1.0
        if not (math.isfinite(pitch) and pitch > 0):
            raise ParameterError(f"pixel pitch {m.group(3)!r} is not a positive number", field="sensor",
                                 fix="e.g. 3840x2160@1.6342 (µm)")
    return w, h, pitch


def sensor_geometry(sensor: tuple[int, int, float | None], image_height_mm: float):
    """(w, h, pitch_um, corner_mm); the pitch defaults to putting the corner at the image height."""
    w, h, pitch = sensor
    if pitch is None:
        pitch = image_height_mm * 1000.0 / math.hypot(w / 2.0, h / 2.0)
    corner_mm = math.hypot(w / 2.0, h / 2.0) * pitch / 1000.0
    if corner_mm > image_height_mm * 1.0005:
        raise ParameterError(f"the sensor corner is at {corner_mm:.3f} mm, beyond the image height "
                             f"{image_height_mm:g} mm the lens is traced to", field="sensor",
                             fix="use a smaller sensor or pitch, or a larger image height")
    return w, h, pitch, corner_mm


def build_lens_spec(table: FocusTable, parax: ParaxialData, *, name: str, image_height_mm: float,
                    sensor: tuple[int, int, float | None] = (3840, 2160, None), n_terms: int = 2,
                    reference_channel: str | None = None, object_distance_mm: float = 1000.0,
                    description: str = "") -> LensSpec:
    """A ``fieldcal-lens/1`` spec from a traced table (see ``sources`` in the result for each derivation)."""
    heights = table.heights_mm
    if heights.max() < image_height_mm * (1 - 1e-9):
        raise ParameterError(f"the table is traced to {heights.max():g} mm but the spec's image height is "
                             f"{image_height_mm:g} mm: the fit would extrapolate", field="image_height_mm",
                             fix="trace out to the image height")
    w, h, pitch, corner_mm = sensor_geometry(sensor, image_height_mm)
    chans = table.channels
    ref = reference_channel or ("G" if "G" in chans else chans[len(chans) // 2])
    fs = table.settings.fs_cyc_per_mm
    channels, rms_all, astig_note = [], {}, {}
    for c in chans:
        hs = np.array(sorted(p.h_mm for p in table.points if p.channel == c))
        z = table.column(c, "z_um")
        a0, curv, rms = fit_even_polynomial(hs, z, image_height_mm, n_terms)
        rms_all[c] = rms
        # tangential - sagittal = A rho^2 (the spec's astigmatism model): least squares through the origin
        r2 = (hs / image_height_mm) ** 2
        dts = table.column(c, "z_tangential_um") - table.column(c, "z_sagittal_um")
        den = float(np.dot(r2, r2))
        astig = float(np.dot(r2, dts) / den) if den > 0 else 0.0
        astig_note[c] = astig
        # lateral colour: chief-ray height of this wavelength / d-line height, at the outermost traced height
        edge = next(p for p in table.points if p.channel == c and p.h_mm == hs.max())
        lat = float(edge.chief_ray_h_mm / edge.h_mm - 1.0) if edge.h_mm > 0 else 0.0
        wl = next(p.wavelength_nm for p in table.points if p.channel == c)
        channels.append(ChannelSpec(name=c, wavelength_nm=wl, focus_offset_um=round(a0, 3),
                                    curvature_um=tuple(round(v, 3) for v in curv), astigmatism_um=round(astig, 3),
                                    lateral_colour=round(lat, 7)))
    on_axis = min(heights)
    ref_pt = table.get(ref, on_axis)
    blur = residual_blur_um(ref_pt.peak_mtf, fs, ref_pt.wavelength_nm, table.f_number)
    max_angle = max(p.field_angle_deg for p in table.points)
    ri = max(0.05, math.cos(math.radians(max_angle)) ** 4)
    z_all = np.concatenate([table.column(c) for c in chans])
    sources = {
        "prescription": f"{table.prescription} (traced with optiland, object at infinity; fieldcal.raytrace, "
                        "docs/raytrace.md)",
        "focal_length_mm": f"paraxial EFL at the d line: {parax.efl_mm:.4f} mm (BFL {parax.bfl_mm:.4f} mm)",
        "channels[*].focus_offset_um, curvature_um": (
            f"least-squares z = a0 + sum a_k rho^(2k), {n_terms} terms, through the traced best focus (peak of "
            f"the mean of T and S MTF at {fs:g} cy/mm) at h = {', '.join(f'{v:g}' for v in heights)} mm; fit RMS "
            + ", ".join(f"{c} {rms_all[c]:.2f}" for c in chans) + f" um; traced D = {np.ptp(z_all):.1f} um"),
        "channels[*].astigmatism_um": "least squares of (tangential - sagittal traced focus) = A rho^2: "
                                      + ", ".join(f"{c} {astig_note[c]:.2f}" for c in chans) + " um",
        "channels[*].lateral_colour": "chief-ray height of the channel's wavelength / d-line height at the "
                                      "outermost traced height, minus 1",
        "exit_pupil_mm": f"paraxial chief-ray trace from the stop (d line): exit pupil {parax.exit_pupil_to_image_mm:.3f} "
                         "mm before the stated image plane",
        "residual_blur_um": f"Gaussian that brings the model's in-focus MTF at {fs:g} cy/mm (diffraction "
                            f"{float(diffraction_mtf(fs, ref_pt.wavelength_nm, table.f_number)):.3f} at "
                            f"{ref_pt.wavelength_nm:g} nm, F/{table.f_number:g}) down to the traced on-axis peak "
                            f"{ref_pt.peak_mtf:.3f} ({ref})",
        "relative_illumination_edge": f"cos^4 of the traced edge field angle {max_angle:.3f} deg",
        "sensor": f"{w}x{h} px at {pitch:.4f} um (corner at {corner_mm:.3f} mm); noise parameters are fieldcal's "
                  "defaults, not traced",
    }
    return LensSpec(
        name=name, focal_length_mm=round(parax.efl_mm, 4), f_number=table.f_number,
        image_height_max_mm=float(image_height_mm), channels=tuple(channels),
        sensor=SensorSpec(width_px=w, height_px=h, pixel_pitch_um=float(round(pitch, 6))),
        object_distance_mm=float(object_distance_mm), exit_pupil_mm=round(parax.exit_pupil_to_image_mm, 4),
        residual_blur_um=round(blur, 4), relative_illumination_edge=round(ri, 4),
        description=description or f"built by 'fieldcal lens from-prescription' from {table.prescription}",
        sources=sources,
        extra={"traced_best_focus": [p.to_dict() for p in table.points],
               "trace_settings": {"fs_cyc_per_mm": fs, "f_number": table.f_number,
                                  "num_rays": table.settings.num_rays, "object": "infinity"}},
    )


def compare_with_spec(table: FocusTable, spec: LensSpec) -> list[dict]:
    """Traced minus spec best focus (µm) for every traced (channel, height) the spec also has."""
    rows = []
    for p in table.points:
        if p.channel not in spec.channel_names:
            continue
        model = float(spec.best_focus_um(p.h_mm, 0.0, p.channel))
        rows.append(dict(channel=p.channel, h_mm=p.h_mm, traced_um=p.z_um, model_um=model,
                         diff_um=p.z_um - model))
    return rows
