"""Real ray tracing of a :class:`~fieldcal.raytrace.prescription.Prescription` with optiland (optional extra).

optiland is heavy (vtk, numba; ~1.3 GB), so it is imported only here and only when called; without it,
:func:`require_optiland` raises :class:`RaytraceUnavailable` telling the user to install the ``raytrace``
extra. Everything else in ``fieldcal.raytrace`` (parsing, paraxial checks) works without it.

Choices (docs/raytrace.md says why):

* One monochromatic optic per wavelength, glass indices from fieldcal's model glass
  (:func:`~fieldcal.raytrace.prescription.model_glass_index`) given to optiland as ideal (constant-index)
  materials, so the traced lens and the paraxial check see the same indices. The pitfalls of optiland's Zemax
  glass import (``GLAS MODEL`` read back as a wrong catalogue glass) cannot arise.
* The aperture is the entrance-pupil diameter EFL(d) / N, fixed over wavelength (the stop is physical);
  optiland's ``imageFNO`` aperture recomputes the paraxial solve on every ray batch and is 4x slower.
* Image height h is the *real* chief-ray height on the image plane being evaluated, at the channel's own
  wavelength: a best-focus surface is a surface in image space, and the simulator evaluates a point's
  defocus where it lands on the sensor at that stage position (``Renderer._defocus_at``). Because the image
  space is not telecentric (exit pupil ~19 mm before the image), holding the object angle fixed instead would
  put the traced point at h (1 + dz / 19 mm): 11 µm of focus at the triplet's field edge.
* MTF at exactly ``fs``: optiland's FFT PSF, then a direct Fourier sum of its line-spread functions at fs
  (no interpolation between FFT bins). Tangential = along the meridional plane (pupil y for a field on y);
  the label is checked against ray fans in the tests (optiland's through-focus helper swaps T/S).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import FieldcalError
from .paraxial import paraxial
from .prescription import LINE_D_NM, Prescription


class RaytraceUnavailable(FieldcalError):
    """The optional ray-tracing library is not installed."""

    exit_code = 4


INSTALL_FIX = 'install the optional ray-tracing extra: pip install -e ".[raytrace]" (optiland, ~1.3 GB)'


def require_optiland():
    """Import optiland or raise :class:`RaytraceUnavailable` with the install command."""
    try:
        with _quiet():
            import optiland  # noqa: F401
            from optiland.optic import Optic  # noqa: F401
    except ImportError:
        raise RaytraceUnavailable("ray tracing needs the optional package optiland, which is not installed",
                                  fix=INSTALL_FIX) from None
    return optiland


@contextlib.contextmanager
def _quiet():
    """optiland's numba kernels emit pedantic compiler warnings on first use; they are not ours to fix."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with np.errstate(all="ignore"):
            yield


@dataclass(frozen=True)
class TracedMTF:
    """MTF at one spatial frequency for one field point, wavelength and image-plane position."""

    tangential: float
    sagittal: float

    @property
    def mean(self) -> float:
        return 0.5 * (self.tangential + self.sagittal)


class TracedLens:
    """A prescription set up in optiland at one wavelength, with movable image plane.

    Parameters
    ----------
    rx : Prescription
    wavelength_nm : float
    f_number : float
        Image-space F-number for an object at infinity: entrance pupil = EFL(d line) / f_number.
    num_rays : int
        Pupil sampling argument of optiland's FFT PSF (64 gives a 45-ray pupil on a 128 grid; enough at
        80 cycles/mm, see docs/raytrace.md for the convergence check).
    """

    def __init__(self, rx: Prescription, wavelength_nm: float, f_number: float, num_rays: int = 64):
        require_optiland()
        self.rx = rx
        self.wavelength_nm = float(wavelength_nm)
        self.f_number = float(f_number)
        self.num_rays = int(num_rays)
        self.epd_mm = paraxial(rx, LINE_D_NM).efl_mm / self.f_number
        self._max_angle_deg = 1.0
        self._angles_deg: list[float] = []
        self._defocus_um = 0.0
        self._chief_fit: dict[float, tuple] = {}
        self.optic = self._build()

    # ------------------------------------------------------------------------------------------- set-up
    def _build(self):
        import optiland.backend as be
        from optiland.materials import IdealMaterial
        from optiland.optic import Optic

        op = Optic(name=self.rx.name)
        op.surfaces.add(index=0, radius=be.inf, thickness=be.inf)
        last = len(self.rx.surfaces) - 1
        for i, s in enumerate(self.rx.surfaces):
            material = IdealMaterial(float(self.rx.index(i, self.wavelength_nm))) if s.is_glass else "air"
            kw = dict(index=i + 1, radius=s.radius_mm if math.isfinite(s.radius_mm) else be.inf,
                      thickness=s.thickness_mm + (self._defocus_um / 1000.0 if i == last else 0.0),
                      material=material, is_stop=s.is_stop)
            if s.kind == "even_asphere":
                # optiland's even asphere coefficients start at r^2; the table's start at r^4.
                kw.update(surface_type="even_asphere", conic=s.conic, coefficients=[0.0, *s.aspheric])
            op.surfaces.add(**kw)
        op.surfaces.add(index=last + 2)
        op.set_aperture(aperture_type="EPD", value=self.epd_mm)
        op.fields.set_type(field_type="angle")
        op.fields.add(y=0.0)
        op.fields.add(y=self._max_angle_deg)
        op.wavelengths.add(value=self.wavelength_nm / 1000.0, is_primary=True)
        return op

    def _ensure_angle(self, angle_deg: float) -> None:
        """optiland takes normalised field coordinates: widen the field when an angle lies beyond it."""
        if abs(angle_deg) > self._max_angle_deg:
            self.set_max_angle_deg(1.3 * abs(angle_deg))

    @property
    def _last_surface(self) -> int:
        return len(self.rx.surfaces)  # optiland index of the last lens surface (object surface is 0)

    def set_defocus_um(self, dz_um: float) -> None:
        """Move the image plane by dz (µm, + away from the lens) from the stated image plane."""
        self._defocus_um = float(dz_um)
        with _quiet():
            self.optic.set_thickness(self.rx.image_distance_mm + self._defocus_um / 1000.0, self._last_surface)

    def set_max_angle_deg(self, angle_deg: float) -> None:
        """Rebuild the field list so normalised field 1 is ``angle_deg`` (must cover every field used)."""
        self._max_angle_deg = max(float(angle_deg), 1e-3)
        self.optic = self._build()  # keeps the current defocus

    # --------------------------------------------------------------------------------------------- rays
    def _chief_rays(self, angles_deg) -> tuple[np.ndarray, np.ndarray]:
        """Chief-ray height on the *stated* image plane and its slope dy/dz, for object angles (deg)."""
        a = np.atleast_1d(np.asarray(angles_deg, dtype=np.float64))
        self._ensure_angle(float(np.max(np.abs(a))))
        with _quiet():
            rays = self.optic.trace_generic(np.zeros_like(a), a / self._max_angle_deg, np.zeros_like(a),
                                            np.zeros_like(a), self.wavelength_nm / 1000.0)
        y = np.asarray(rays.y, dtype=np.float64).ravel()
        slope = (np.asarray(rays.M, dtype=np.float64) / np.asarray(rays.N, dtype=np.float64)).ravel()
        return y - slope * self._defocus_um / 1000.0, slope

    def chief_ray_height_mm(self, angle_deg: float, dz_um: float = 0.0) -> float:
        """Real chief-ray height for an object at ``angle_deg`` on the plane ``dz_um`` from the stated one."""
        y0, t = self._chief_rays([angle_deg])
        return float(y0[0] + t[0] * dz_um / 1000.0)

    def angle_for_height_deg(self, h_mm: float, dz_um: float = 0.0) -> float:
        """Object angle whose real chief ray lands at image height ``h_mm`` on the plane ``dz_um``.

        The chief-ray height and slope are smooth in the angle: a cubic through 7 traced chief rays spanning
        ±15% of the paraxial angle is solved instead of tracing during the root search (cached per height).
        """
        from scipy.optimize import brentq

        if h_mm <= 0.0:
            return 0.0
        fit = self._chief_fit.get(h_mm)
        if fit is None:
            f = paraxial(self.rx, self.wavelength_nm).efl_mm
            a0 = math.degrees(math.atan(h_mm / f))
            if 1.2 * a0 > self._max_angle_deg:
                self.set_max_angle_deg(1.5 * a0)
            angles = a0 * (1.0 + np.linspace(-0.15, 0.15, 7))
            y0, t = self._chief_rays(angles)
            u = (angles - a0) / a0  # normalised abscissa for a well-conditioned fit
            fit = (a0, np.polyfit(u, y0, 3), np.polyfit(u, t, 3))
            self._chief_fit[h_mm] = fit
        a0, py, pt = fit

        def resid(u):
            return np.polyval(py, u) + np.polyval(pt, u) * dz_um / 1000.0 - h_mm

        if resid(-0.15) * resid(0.15) > 0:
            raise ValueError(f"image height {h_mm} mm at defocus {dz_um} µm is outside the chief-ray fit")
        return float(a0 * (1.0 + brentq(resid, -0.15, 0.15, xtol=1e-12)))

    def fan_foci_um(self, angle_deg: float, n: int = 21, pupil: float = 0.7) -> tuple[float, float]:
        """(tangential, sagittal) geometric foci (µm from the stated image plane) from small ray fans.

        A meridional fan (pupil y) and a sagittal fan (pupil x) of half-width ``pupil`` are traced to the
        current image plane and propagated along their directions to the plane of least spread. Used to
        label the MTF's tangential/sagittal axes and as a cheap starting point for the MTF search.
        """
        self._ensure_angle(angle_deg)
        p = np.linspace(-pupil, pupil, n)
        z = np.zeros_like(p)
        hy = angle_deg / self._max_angle_deg
        out = []
        for px, py, coord in ((z, p, "y"), (p, z, "x")):
            with _quiet():
                rays = self.optic.trace_generic(np.zeros_like(p), np.full_like(p, hy), px, py,
                                                self.wavelength_nm / 1000.0)
            pos = np.asarray(getattr(rays, coord), dtype=np.float64).ravel()
            dirc = np.asarray(getattr(rays, "M" if coord == "y" else "L"), dtype=np.float64).ravel()
            nz = np.asarray(rays.N, dtype=np.float64).ravel()
            slope = dirc / nz
            # positions at t mm behind the plane: pos + slope t; least-squares spread is quadratic in t.
            dp = pos - pos.mean()
            ds = slope - slope.mean()
            den = float(np.dot(ds, ds))
            t_mm = -float(np.dot(dp, ds)) / den if den > 0 else 0.0
            out.append(self._defocus_um + t_mm * 1000.0)
        return out[0], out[1]

    # ---------------------------------------------------------------------------------------------- MTF
    def mtf(self, angle_deg: float, freqs_cyc_per_mm) -> list[TracedMTF]:
        """Tangential and sagittal MTF of the field at ``angle_deg`` on the current image plane."""
        from optiland.mtf import FFTMTF

        self._ensure_angle(angle_deg)
        hy = angle_deg / self._max_angle_deg
        with _quiet():
            m = FFTMTF(self.optic, fields=[(0.0, hy)], wavelength=self.wavelength_nm / 1000.0,
                       num_rays=self.num_rays)
            psf = np.asarray(m.psf[0], dtype=np.float64)
            step_t = float(np.asarray(m.freq_tang[0])[1])
            step_s = float(np.asarray(m.freq_sag[0])[1])
        return [TracedMTF(*_mtf_at(psf, step_t, step_s, f)) for f in np.atleast_1d(freqs_cyc_per_mm)]


def _mtf_at(psf: np.ndarray, step_t: float, step_s: float, f: float) -> tuple[float, float]:
    """|OTF| at frequency f along axis 0 (tangential) and axis 1 (sagittal) of an FFT-grid PSF.

    optiland's MTF takes ``fft2(psf)`` slices along axis 0 (tangential) and axis 1 (sagittal) with bin
    widths ``step``; the PSF sample pitch along an axis is therefore ``1 / (grid * step)``. Summing the
    line-spread function against ``exp(-2 pi i f x)`` evaluates the same OTF at f exactly.
    """
    total = float(psf.sum())
    if not total > 0.0:
        return 0.0, 0.0
    g0, g1 = psf.shape
    out = []
    for lsf, g, step in ((psf.sum(axis=1), g0, step_t), (psf.sum(axis=0), g1, step_s)):
        x_mm = (np.arange(g) - g // 2) / (g * step)
        otf = np.sum(lsf * np.exp(-2j * np.pi * f * x_mm)) / total
        out.append(float(min(abs(otf), 1.0)))
    return out[0], out[1]
