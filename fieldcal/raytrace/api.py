"""What ``fieldcal lens`` does, as Python: check a prescription's first order, build a lens spec by ray tracing.

:func:`check_prescription` needs only numpy; :func:`lens_from_prescription` traces real rays with the optional
optiland (``pip install -e ".[raytrace]"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ParameterError, SpecError


@dataclass
class PrescriptionCheck:
    """A prescription table and its paraxial data; ``efl_mm``/``bfl_mm`` are the values it was checked against
    (given, or the table's design values; None when neither)."""

    prescription: object
    paraxial: object
    efl_mm: float | None
    bfl_mm: float | None


@dataclass
class TracedLens:
    """A ray-traced lens spec with what it was made from: the traced focus table, paraxial data, the image
    heights (mm), F-number and largest image height (mm)."""

    spec: object
    table: object
    paraxial: object
    heights_mm: np.ndarray
    f_number: float
    image_height_mm: float


def _positive(name: str, v):
    if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise ParameterError(f"{name} must be a positive number, got {v}", field=name, fix="give a positive value")
    return v


def check_prescription(table: str | Path, efl_mm: float | None = None, bfl_mm: float | None = None,
                       tolerance: float = 0.005) -> PrescriptionCheck:
    """Load a prescription table (CSV or JSON), trace it paraxially and check EFL/BFL.

    ``efl_mm``/``bfl_mm`` default to the table's ``# efl_mm:`` / ``# bfl_mm:`` design values; a relative
    difference beyond ``tolerance`` is a :class:`SpecError` naming the table.
    """
    from .build import check_first_order
    from .paraxial import paraxial
    from .prescription import load_prescription, meta_number

    rx = load_prescription(table)
    efl = _positive("efl_mm", efl_mm) or meta_number(rx, "efl_mm")
    bfl = _positive("bfl_mm", bfl_mm) or meta_number(rx, "bfl_mm")
    try:
        parax = paraxial(rx)
    except ValueError as e:
        raise SpecError(f"{e}", path=table, field="radius", fix="check the radii and indices") from None
    check_first_order(parax, efl, bfl, tolerance, path=table)
    return PrescriptionCheck(rx, parax, efl, bfl)


def lens_from_prescription(table: str | Path, *, fs_cyc_per_mm: float = 80.0, f_number: float | None = None,
                           image_height_mm: float | None = None,
                           sensor: tuple[int, int, float | None] | None = None, heights: int = 9,
                           channels_nm: dict[str, float] | None = None, terms: int = 2, num_rays: int = 64,
                           name: str | None = None, efl_mm: float | None = None, bfl_mm: float | None = None,
                           tolerance: float = 0.005, quiet: bool = False, on_start=None) -> TracedLens:
    """Trace a prescription with optiland and build a ``fieldcal-lens/1`` spec (docs/raytrace.md).

    Parameters
    ----------
    table : path
        Prescription table; its ``# f_number:`` and ``# image_height_mm:`` lines give the defaults.
    fs_cyc_per_mm : float
        Frequency of the best-focus criterion (peak of the mean tangential/sagittal MTF).
    f_number, image_height_mm : float, optional
        Image-space F-number and largest image height (mm). Without an image height anywhere, the sensor's
        half diagonal is used (``sensor`` must then carry its pitch).
    sensor : (W, H, pitch_um or None), optional
        Sensor pixels and pitch (default 3840x2160 with the corner at the image height).
    heights : int
        Number of image heights traced, 0 .. image height (2..41).
    channels_nm : dict, optional
        Channel name -> wavelength (nm); default R, G, B at 656.3, 546.1, 486.1 nm.
    terms : int
        Curvature terms rho^2 .. rho^2K of the spec's polynomial (1..4, fewer than ``heights``).
    on_start : callable, optional
        Called with ``(channels, heights_mm, f_number)`` just before the (long) trace, e.g. to print a line.
    """
    from .bestfocus import DEFAULT_CHANNELS_NM, SearchSettings, trace_focus_table
    from .build import build_lens_spec, sensor_geometry
    from .optiland_backend import require_optiland
    from .prescription import meta_number

    chk = check_prescription(table, efl_mm, bfl_mm, tolerance)
    rx, parax = chk.prescription, chk.paraxial
    f_number = _positive("f_number", f_number) or meta_number(rx, "f_number")
    if f_number is None:
        raise ParameterError("the F-number is not known", field="f_number",
                             fix="give the F-number (or '# f_number: N' in the table)")
    h_max = _positive("image_height_mm", image_height_mm) or meta_number(rx, "image_height_mm")
    sensor = sensor or (3840, 2160, None)
    if h_max is None:
        w, h, pitch = sensor
        if pitch is None:
            raise ParameterError("the image height is not known", field="image_height_mm",
                                 fix="give the image height (mm), or the sensor's pitch (its half diagonal is used)")
        h_max = math.hypot(w / 2.0, h / 2.0) * pitch / 1000.0
    if isinstance(heights, bool) or not isinstance(heights, int) or not (2 <= heights <= 41):
        raise ParameterError(f"the number of heights must be in 2..41, got {heights}", field="heights", fix="e.g. 9")
    if isinstance(terms, bool) or not isinstance(terms, int) or not (1 <= terms <= 4) or terms > heights - 1:
        raise ParameterError(f"{terms} curvature terms need 1..4 and fewer than the heights ({heights})",
                             field="terms", fix="e.g. 2 terms with 9 heights")
    _positive("fs_cyc_per_mm", fs_cyc_per_mm)
    sensor_geometry(sensor, h_max)  # a sensor beyond the traced field: say so before tracing for minutes
    channels_nm = dict(channels_nm or DEFAULT_CHANNELS_NM)
    settings = SearchSettings(fs_cyc_per_mm=fs_cyc_per_mm, num_rays=num_rays)
    require_optiland()
    hs = np.linspace(0.0, h_max, heights)
    if on_start is not None:
        on_start(channels_nm, hs, f_number)
    traced = trace_focus_table(rx, hs, channels_nm, f_number, settings, quiet=quiet)
    spec = build_lens_spec(traced, parax, name=name or rx.name, image_height_mm=h_max, sensor=sensor,
                           n_terms=terms, description=str(rx.meta.get("description", "")))
    return TracedLens(spec, traced, parax, hs, float(f_number), float(h_max))
