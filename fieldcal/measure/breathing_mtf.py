"""Band-pass curves of a breathing lens brought back to the sensor frequency of their sensor-fixed MTFs.

The band-pass ring follows the image (:mod:`fieldcal.measure.tiles`): in frame k it is at ``f / s_k`` at the
sensor (``s_k`` the image scale against frame 0), so the scene's texture power at the ring is the same in every
frame and the geometric blur is symmetric on the scale axis. But every MTF that is fixed at the sensor then
changes from frame to frame: the pixel aperture's ``sinc(f p)`` and the pupil's in-focus (diffraction) MTF rise
as ``f / s_k`` falls. That is a tilt ``-2 g ln s(z)`` on ln E (``g = d ln MTF / d ln f`` at f), which moves the
fitted peak towards the magnified side by ~``2 |g| b sigma^2`` (b = 1 / the exit pupil's distance, sigma^2 the
curve's variance in z). On an F/7.5 lens with its exit pupil 15 mm away at 13 cy/mm and 15 µm pixels (g: pixel
-0.13, diffraction -0.07) that is +2.0 µm on the exact pupil MTF x pixel aperture, +2.1 µm measured on rendered
stacks (two seeds; +0.6 µm without breathing); divided out, -0.1 µm.

Both factors are known without the lens: the pitch from the stack, the diffraction-limited MTF from its
F-number and the channel's wavelength (the aberrations' own change of the peak with f is left: W040 0.27
waves at F/7.5 makes g -0.081 where diffraction alone gives -0.073). A 100 % fill factor is assumed (microlenses).

Which factors the frames carry is the stack's to say (``stack.json`` ``"sensor_mtf"``, :func:`declared_factors`):
a camera has both, fieldcal's wave-optics renderer writes both, its geometric renderer neither (a blur disc at
the sensor on a scene sampled at the scene's own scale), and dividing out factors a stack does not have biases
it the other way (-2.7 µm on the geometric renderer's 4 mm exit pupil test stack). Until the geometric renderer
models a pixel aperture, a stack without the key gets no correction; `fieldcal import` declares a camera's
files (formats/importer.py) and a real camera's captures (capture/acquisition.py).
"""
from __future__ import annotations

import math

import numpy as np

from fieldcal.optics.defocus import default_wavelength_nm, diffraction_mtf


def declared_factors(meta: dict | None) -> tuple[bool, float | None] | None:
    """(pixel aperture, F-number for the diffraction factor or None) from a stack's ``"sensor_mtf"`` record
    (``{"pixel_aperture": bool, "diffraction": bool}``; the F-number is the stack's ``f_number``), or None when
    the stack does not say (no correction)."""
    rec = (meta or {}).get("sensor_mtf")
    if not isinstance(rec, dict):
        return None
    f_number = (meta or {}).get("f_number") if rec.get("diffraction") else None
    return bool(rec.get("pixel_aperture")), f_number


def sensor_mtf(f_cyc_per_mm, pixel_pitch_um: float | None, f_number: float | None,
               wavelength_nm: float) -> np.ndarray:
    """Pixel aperture (unless ``pixel_pitch_um`` is None) x aberration-free pupil MTF (unless ``f_number`` is
    None or not finite and positive) at sensor frequencies ``f`` (cycles/mm)."""
    f = np.abs(np.asarray(f_cyc_per_mm, dtype=np.float64))
    out = np.ones_like(f) if pixel_pitch_um is None else np.abs(np.sinc(f * float(pixel_pitch_um) * 1e-3))
    if f_number is not None and math.isfinite(float(f_number)) and float(f_number) > 0:
        out = out * diffraction_mtf(f, wavelength_nm, float(f_number))
    return out


def band_energy_gain(f_cyc_per_mm: float, scale: np.ndarray, pixel_pitch_um: float | None,
                     f_number: float | None, channel: str) -> np.ndarray:
    """Per frame, the factor on a band energy measured at ``f / scale[k]`` at the sensor that puts its
    sensor-fixed MTFs at ``f``: ``(M(f) / M(f / scale))^2`` (1 where ``scale`` is 1 or M vanishes).

    Parameters
    ----------
    f_cyc_per_mm : float
        The band's frequency at frame 0's scale (cycles/mm at the sensor).
    scale : ndarray
        The image scale each frame's band followed (``bp_scale``, 1 at frame 0).
    pixel_pitch_um, f_number : float or None
        The stack's; None where the frames have no such factor (``f_number`` NaN: unknown, none).
    channel : str
        Its name gives the wavelength (:func:`fieldcal.optics.defocus.default_wavelength_nm`).
    """
    s = np.asarray(scale, dtype=np.float64)
    lam = default_wavelength_nm(channel)
    m0 = sensor_mtf(f_cyc_per_mm, pixel_pitch_um, f_number, lam)
    mk = sensor_mtf(f_cyc_per_mm / np.where(s > 0, s, 1.0), pixel_pitch_um, f_number, lam)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.square(m0 / mk)
    return np.where(np.isfinite(g) & (g > 0), g, 1.0)
