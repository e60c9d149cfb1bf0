"""Through-focus optics of a simple lens: geometric defocus, diffraction, residual blur, focus tolerance.

Physics, not simulation: the simulator renders with it, the profile answers with it when it has no measured
widths, the planner derives tolerances and MTF losses from it, the through-focus curve fits use its shape.

The OTF at spatial frequency f (cycles/mm) and defocus dz (µm) is the product of

* geometric defocus: a uniform disc of diameter ``b = |dz| / N`` (image-side F-number N) whose OTF is
  ``2 J1(x) / x`` with ``x = pi b f`` (goes negative: contrast reversal);
* diffraction: the incoherent MTF of a circular pupil, cut-off ``1 / (lambda N)``;
* residual aberrations at best focus: a Gaussian of RMS ``residual_blur_um``.

The product is exact at focus and at large defocus and a few-percent approximation between (Stokseth 1969
gives the full defocused-diffraction OTF); docs/simulator.md states this. Only the first factor depends on
dz, so the product model's focus tolerance δ(fs, q) solves ``2 J1(x)/x = 1 - q`` (:func:`focus_tolerance_um`,
the *geometric* δ: the simulator's geometric path renders this model, so its truth is this δ).

A real aberration-free lens's δ is wider: defocus and diffraction do not multiply, the pupil's autocorrelation
(Hopkins) mixes them, and at F/5.6-F/8 and fs = 80 cycles/mm the true δ is 1.3-1.6x the geometric one
(docs/planning.md "The defocus model"). :func:`pupil_tolerance_um` is that δ, from the exact pupil OTF
(:mod:`fieldcal.optics.pupil`); the planner and the profile's fallback use it (:func:`model_tolerance_um`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import special

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for the annotation only: criterion.py uses this module
    from .criterion import MTFCriterion

# Default wavelengths (nm) of the usual channels: the C, e and F lines (Y: a monochrome sensor, e line).
DEFAULT_WAVELENGTH_NM = {"R": 656.3, "G": 546.1, "B": 486.1, "Y": 546.1}

#: Wavelength (nm) the tolerance model takes for a channel when the stack records none: the *short* end
#: (half-maximum) of the channel's usual passband behind an IR-cut filter (Bayer colour filters: B ~440-500, G
#: ~500-580, R ~580-650 nm; a monochrome sensor behind a visible filter ~450-650). The aberration-free δ
#: grows with wavelength (diffraction widens the through-focus curve: at F/8, 80 cycles/mm, q = 0.05 it is 28.7
#: µm at 440 nm and 34.0 at 610), and the δ of a band's summed MTF is at least its shortest wavelength's (each
#: wavelength's curve stays within q of its peak out to its own δ). So the short end keeps the model below the
#: truth wherever the planner uses it as a bound (docs/planning.md "The defocus model").
TOLERANCE_BAND_NM = {"R": (580.0, 650.0), "G": (500.0, 580.0), "B": (440.0, 500.0), "Y": (450.0, 650.0)}
TOLERANCE_WAVELENGTH_NM = {c: b[0] for c, b in TOLERANCE_BAND_NM.items()}
_OTHER_BAND_NM = (450.0, 650.0)

#: First zero of J1: 2 J1(x)/x falls monotonically from 1 to 0 on [0, DISC_FIRST_ZERO].
DISC_FIRST_ZERO = float(special.jn_zeros(1, 1)[0])


def default_wavelength_nm(channel: str) -> float:
    """Wavelength (nm) a channel stands for when nothing else says (550 nm for unknown names)."""
    return DEFAULT_WAVELENGTH_NM.get(channel, 550.0)


def tolerance_wavelength_nm(channel: str, recorded=None) -> float:
    """Wavelength (nm) of the tolerance model for ``channel``: the stack's recorded one (``recorded``: a
    ``{channel: nm}`` mapping, e.g. a profile's ``optics["wavelength_nm"]``) when it has a finite positive value
    for the channel, else :data:`TOLERANCE_WAVELENGTH_NM` (the band's short end; 450 nm for unknown names)."""
    return tolerance_band_nm(channel, recorded)[0]


def tolerance_band_nm(channel: str, recorded=None) -> tuple[float, float]:
    """(short, long) ends (nm) of ``channel``'s band for the tolerance model: the recorded wavelength at both
    ends when the stack gives one (see :func:`tolerance_wavelength_nm`), else :data:`TOLERANCE_BAND_NM`."""
    if isinstance(recorded, dict):
        try:
            v = float(recorded.get(channel))
            if math.isfinite(v) and v > 0:
                return v, v
        except (TypeError, ValueError):
            pass
    return TOLERANCE_BAND_NM.get(channel, _OTHER_BAND_NM)


def disc_otf(x):
    """``2 J1(x) / x`` (1 at x = 0): the OTF of a uniform disc at ``x = pi * diameter * f``."""
    x = np.asarray(x, dtype=np.float64)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)  # guard the 0/0 at focus; the series is exact to 1e-17 there
    return np.where(small, 1.0 - x * x / 8.0, 2.0 * special.j1(xs) / xs)


def disc_otf_derivative(x):
    """d/dx of ``2 J1(x) / x``, which is ``-2 J2(x) / x``.

    J2 by the recurrence ``J2 = 2 J1 / x - J0`` (``special.jv(2, .)``, the general order, is 10x slower and this
    sits in the curve fits' inner loop); below |x| = 0.1, where the recurrence cancels, its series
    ``x^2/8 - x^4/96 + x^6/3072`` (next term 5e-11 of it there).
    """
    x = np.asarray(x, dtype=np.float64)
    small = np.abs(x) < 0.1
    xs = np.where(small, 1.0, x)
    x2 = x * x
    series = -2.0 * x * (1.0 / 8.0 - x2 * (1.0 / 96.0 - x2 / 3072.0))  # -2 J2(x) / x
    return np.where(small, series, -2.0 * (2.0 * special.j1(xs) / xs - special.j0(xs)) / xs)


def defocus_otf(f_cyc_per_mm, defocus_um, f_number: float):
    """Geometric-optics OTF of a uniform blur disc of diameter ``|dz| / N``."""
    b_mm = np.abs(np.asarray(defocus_um, dtype=np.float64)) / float(f_number) / 1000.0
    return disc_otf(np.pi * b_mm * np.asarray(f_cyc_per_mm, dtype=np.float64))


def diffraction_mtf(f_cyc_per_mm, wavelength_nm: float, f_number: float):
    """Incoherent MTF of an aberration-free circular pupil."""
    fc = 1.0 / (wavelength_nm * 1e-6 * f_number)  # cycles/mm
    v = np.clip(np.abs(np.asarray(f_cyc_per_mm, dtype=np.float64)) / fc, 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(v) - v * np.sqrt(1.0 - v * v))


def gaussian_mtf(f_cyc_per_mm, sigma_um: float):
    """MTF of a Gaussian blur of RMS ``sigma_um``."""
    s_mm = sigma_um / 1000.0
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    return np.exp(-2.0 * (np.pi * s_mm * f) ** 2)


def through_focus_otf(f_cyc_per_mm, defocus_um, f_number: float, wavelength_nm: float,
                      residual_blur_um: float = 0.0):
    """Signed OTF of the model: geometric defocus x diffraction x residual blur (module docstring)."""
    return (defocus_otf(f_cyc_per_mm, defocus_um, f_number)
            * diffraction_mtf(f_cyc_per_mm, wavelength_nm, f_number)
            * gaussian_mtf(f_cyc_per_mm, residual_blur_um))


@functools.lru_cache(maxsize=128)
def disc_x_at_contrast(level: float) -> float:
    """x in (0, DISC_FIRST_ZERO] where ``2 J1(x)/x = level`` (the monotonic branch).

    As level -> 0 the target drops below the rounding floor of the function near the first zero, where a
    bracket would not change sign: the root is then the zero itself (the contrast is lost entirely there).
    """
    level = float(level)
    if not (level < 1.0):
        return 0.0
    if level <= float(disc_otf(DISC_FIRST_ZERO - 1e-9)):
        return DISC_FIRST_ZERO
    from scipy import optimize  # here, not at import: ~0.1 s of every command's start-up

    return float(optimize.brentq(lambda t: float(disc_otf(t)) - level, 1e-12, DISC_FIRST_ZERO - 1e-9,
                                 xtol=1e-14))


def focus_tolerance_um(criterion: MTFCriterion, f_number: float) -> float:
    """Defocus |dz| (µm) at which MTF(fs) has fallen to ``1 - q`` of its in-focus value.

    Solves ``2 J1(x)/x = 1 - q`` with ``x = pi (dz / N) fs``. Check: fs = 80 cycles/mm, q = 0.05, F/2 gives
    5.08 µm; ray tracing the paper's triplet gives -5.4/+6.1 µm on axis (docs/raytrace.md).
    """
    x = disc_x_at_contrast(1.0 - criterion.q)
    return float(x / (math.pi * criterion.fs_cyc_per_mm) * float(f_number) * 1000.0)


@functools.lru_cache(maxsize=512)
def _pupil_tolerance_um(fs_cyc_per_mm: float, q: float, f_number: float, wavelength_nm: float) -> float:
    from scipy import optimize

    from . import pupil

    lam_um = wavelength_nm * 1e-3
    nu = fs_cyc_per_mm * 1e-3 * lam_um * f_number
    w_per_um = 1.0 / (8.0 * f_number * f_number * lam_um)  # W020 (waves) per µm of defocus
    peak = float(pupil.otf(nu, 0.0))  # aberration-free: the through-focus MTF peaks at W020 = 0 (symmetric)
    level = 1.0 - q

    def f(dz_um):
        return float(pupil.otf(nu, dz_um * w_per_um)) / peak - level

    hi = disc_x_at_contrast(level) / (math.pi * fs_cyc_per_mm * 1e-3) * f_number  # the geometric δ: a lower bound
    lo = 0.0
    for _ in range(60):  # walk out: the main lobe falls monotonically to the first zero
        if f(hi) < 0.0:
            break
        lo, hi = hi, 1.5 * hi
    return float(optimize.brentq(f, lo, hi, xtol=1e-9 * hi, rtol=1e-12))


def pupil_tolerance_um(criterion: MTFCriterion, f_number: float, wavelength_nm: float) -> float:
    """δ(fs, q) of an aberration-free circular pupil with diffraction: defocus |dz| (µm) at which MTF(fs) has
    fallen to ``1 - q`` of its in-focus value, from the exact (Hopkins) OTF of :mod:`fieldcal.optics.pupil`.

    Defocus ``dz`` at image-side F-number N is ``W020 = dz / (8 N^2)`` of wavefront at the pupil's edge, the
    frequency ``nu = fs lambda N`` of the cut-off. Factors that do not change with focus (the pixel aperture, a
    fixed blur) cancel in the ratio to the peak, so the δ of MTF(fs) does not depend on them. As nu -> 0 (low
    F-number, low fs, short wavelength) it tends to the geometric :func:`focus_tolerance_um` (from above); at
    F/8, 80 cycles/mm, 540 nm it is 1.56x that (31.6 against 20.3 µm).

    Raises
    ------
    ParameterError
        naming ``fs_cyc_per_mm`` when fs is at or beyond the diffraction cut-off ``1 / (lambda N)`` (no contrast
        at any focus), or ``f_number`` / ``wavelength_nm`` when not finite and > 0.
    """
    from fieldcal.errors import ParameterError

    n, lam = float(f_number), float(wavelength_nm)
    if not (math.isfinite(n) and n > 0):
        raise ParameterError(f"F-number {f_number!r} must be a finite number > 0", field="f_number",
                             fix="give the lens's image-side F-number (stack.json f_number)")
    if not (math.isfinite(lam) and lam > 0):
        raise ParameterError(f"wavelength {wavelength_nm!r} nm must be a finite number > 0", field="wavelength_nm",
                             fix="give the channel's wavelength in nm (stack.json wavelength_nm)")
    cutoff = 1.0 / (lam * 1e-6 * n)
    if criterion.fs_cyc_per_mm >= 0.999 * cutoff:
        raise ParameterError(f"fs = {criterion.fs_cyc_per_mm:g} cycles/mm is at or beyond the diffraction cut-off "
                             f"{cutoff:.0f} cycles/mm of F/{n:g} at {lam:g} nm: no focus keeps contrast there",
                             field="fs_cyc_per_mm", fix=f"choose fs well below {cutoff:.0f} cycles/mm")
    return _pupil_tolerance_um(float(criterion.fs_cyc_per_mm), float(criterion.q), n, lam)


def model_tolerance_um(criterion: MTFCriterion, f_number: float, channel: str, recorded_wavelength_nm=None) -> float:
    """The tolerance model a profile without measured widths answers with, and the planner's bound on measured
    texture widths: :func:`pupil_tolerance_um` at :func:`tolerance_wavelength_nm` (the recorded wavelength, else
    the channel band's short end, which keeps it at or below the aberration-free truth)."""
    return pupil_tolerance_um(criterion, f_number, tolerance_wavelength_nm(channel, recorded_wavelength_nm))


def model_tolerance_ratio(criterion: MTFCriterion, calibrated_at: MTFCriterion, f_number: float, channel: str,
                          recorded_wavelength_nm=None) -> float:
    """δ(criterion) / δ(calibrated_at) of the aberration-free pupil: how a width measured at one (fs, q)
    converts to another. The geometric law (δ ∝ 1/fs) is its limit at low ``fs lambda N``; with diffraction δ
    changes less with fs (at F/8, 540 nm, halving fs from 80 cycles/mm multiplies δ by ~1.5, not 2). The ratio
    grows with wavelength where fs drops and shrinks where it rises, so it is taken at both ends of the
    channel's band (:func:`tolerance_band_nm`) and the smaller kept: the converted width stays at or below what
    either end gives."""
    if criterion == calibrated_at:
        return 1.0
    return min(pupil_tolerance_um(criterion, f_number, lam) / pupil_tolerance_um(calibrated_at, f_number, lam)
               for lam in tolerance_band_nm(channel, recorded_wavelength_nm))
