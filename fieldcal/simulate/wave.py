"""Wave-optics image formation (``--optics wave``): PSFs from the pupil function, per channel and field point.

The geometric path (:mod:`fieldcal.simulate.render`) multiplies analytic OTFs (blur disc x diffraction x
Gaussian), which makes every through-focus curve symmetric about the lens's surface. This path computes the
PSF from the pupil: a circular pupil of the image-side F-number N, a wavefront with defocus, astigmatism,
coma and primary spherical aberration, Fraunhofer diffraction, summed over the channel's spectral band,
integrated over the pixel aperture. Kernels and truth share one transfer function, the pupil's exact
autocorrelation (:mod:`fieldcal.optics.pupil`); :func:`monochromatic_psf` (PSF = |FFT(pupil)|^2) remains for
validation. Spherical aberration makes the through-focus
curves asymmetric and moves the sharpest position off the lens's reference surface, as real lenses do.

Conventions (docs/simulator.md, "Wave-optics path")
---------------------------------------------------
Pupil coordinates ``(u, v)`` are normalised to the pupil radius (``rho_p = hypot(u, v) <= 1``), u along the
image x axis, v along y. ``phi`` is the field point's azimuth about the optical centre (tangential direction).
The wavefront (µm of optical path) is::

    W = W020 rho_p^2 + W040 rho_p^4 + W060 rho_p^6 + W131 rho_p^2 t + Wast (t^2 - s^2)
    t = u cos(phi) + v sin(phi),  s = -u sin(phi) + v cos(phi)       (tangential / sagittal pupil components)
    W020 = dz / (8 N^2),   dz = z - z_ref_surface(x, y)   (µm; + = sensor further from the lens)

with the transverse ray error ``eps = -2 N grad W`` (µm on the sensor), so a sensor behind the focus
(dz > 0) sees the marginal ray on the far side of the axis, and W040 > 0 (under-corrected) puts the
marginal focus at ``dz = -16 N^2 W040`` (nearer the lens) and the minimum-RMS focus at ``-8 N^2 W040``
(W020 = -W040). The lens spec's surface ``z_c`` is the *reference* (paraxial, W020 = 0) focus of the wave
path; the sharpest position (peak of MTF at fs) is computed numerically (:func:`best_focus_shift_um`).
The pupil function is ``A exp(-2 pi i W / lambda)``, which with numpy's FFT sign gives exactly ``eps``.

Rendering: blur levels in signed defocus (the geometric path's ladder, centred per field node on that node's
sharpest position) times a coarse grid of field nodes; each (node, level) kernel is a pixel-integrated
polychromatic PSF, cached for the renderer's life; the renderer warps the scene to the sensor first (breathing,
lateral colour), and each sensor pixel blends the images of the two levels that bracket its own defocus and of
the (up to) four nodes around it (bilinear weights).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import fft
from scipy.optimize import minimize_scalar

from fieldcal.errors import ParameterError
from fieldcal.simulate.lens import LensSpec

#: default spectral response per channel: (offset from the channel's wavelength_nm, weight). A three-point
#: (R, G, B) or five-point (mono Y) quadrature of a roughly Gaussian band; FWHM about 2x the outer offset.
DEFAULT_BANDS: dict[str, tuple[tuple[float, float], ...]] = {
    "R": ((-30.0, 0.25), (0.0, 0.5), (30.0, 0.25)),
    "G": ((-25.0, 0.25), (0.0, 0.5), (25.0, 0.25)),
    "B": ((-20.0, 0.25), (0.0, 0.5), (20.0, 0.25)),
    "Y": ((-80.0, 0.1), (-40.0, 0.2), (0.0, 0.4), (40.0, 0.2), (80.0, 0.1)),
}
_OTHER_BAND = ((-25.0, 0.25), (0.0, 0.5), (25.0, 0.25))

_MIN_PUPIL_SAMPLES = 64.0  # pupil diameter in samples, at least (MTF error ~1e-3 at 64 with a soft edge)
# Kernel half-extent beyond the geometric spot, in lambda*N. The energy beyond it is cut off and the kernel
# renormalised, which raises its MTF by that fraction; the fraction jumps whenever the window grows by a pixel
# with defocus. At 8 lambda N (Airy: ~2.5 % outside) MTF(fs) stepped by 0.3 % on a 320 px wave lens with W040 =
# 0.7 waves, and since contrast near the top of a through-focus curve changes by only ~4 % over +-30 µm, that
# step put the kernels' own fs-contrast peak 3.6 µm off the truth (the rendered tiles ~0.9 µm). At 40 lambda N
# (~0.5 % outside) the kernels peak 0.03 µm from it; rendering costs ~1.4x the CPU (docs/simulator.md).
_TAIL_LAMBDA_N = 40.0
# Kernel half-width at least (px). The kernel's DFT is the exact OTF at the grid frequencies j / (K p); between
# them its transfer function is the trigonometric interpolation of those values, off by the PSF energy folded back
# from beyond the window, and that error steps when K does. Small-PSF lenses (F/1.6, 15 µm pixels: K = 7) had
# steps of 1.3e-3 in MTF(fs) and a kernel peak 0.4 µm off the truth's; at K >= 13 (docs/simulator.md).
_MIN_HALF_PX = 6
# integrand evaluations of the exact 2-D OTF block (pupil.otf_2d) at most per kernel (~25 ms); beyond it the
# sampled PSF's DFT (a 1920 x 1080 astigmatic triplet took 5.6x the CPU with the exact block everywhere; at
# this budget every asymmetric kernel of the 320-400 px band-benchmark lenses is exact, and the triplet's
# 1080p kernels near focus (1770 of 6612 within 400 µm))
_EXACT_2D_BUDGET = 1.0e6
# the second image scale at which the renderer's kernels are cached (WaveBlur.kernel: a line through a = 1 and
# 1 + this serves every frame's scale; breathing and lateral colour keep |a - 1| at a few 1e-3 to 2e-2)
_SCALE_STEP = 0.01
# field nodes of the wave renderer at least, for lenses with astigmatism (orientation varies with azimuth)
ASTIG_FIELD_GRID = (11, 7)
_RHO_NODES = 6  # field heights at which the sharpest position is computed (interpolated between)


@dataclass(frozen=True)
class WaveTerms:
    """Wavefront coefficients (µm) at one field point, and the field azimuth (rad)."""

    w040_um: float = 0.0
    w131_um: float = 0.0
    wast_um: float = 0.0
    phi_rad: float = 0.0
    w060_um: float = 0.0

    def max_slope_um(self) -> float:
        """Upper bound of |grad W| (µm per pupil radius) of the non-defocus terms."""
        return (4.0 * abs(self.w040_um) + 6.0 * abs(self.w060_um) + 3.0 * abs(self.w131_um)
                + 2.0 * abs(self.wast_um))


def band(spec: LensSpec, channel: str) -> tuple[tuple[float, float], ...]:
    """Spectral response of a channel: ((wavelength_nm, weight), ...), weights summing to 1."""
    ab = spec.aberrations
    if ab is not None and channel in ab.spectral_response:
        pts = ab.spectral_response[channel]
    else:
        lam = spec.channel(channel).wavelength_nm
        pts = tuple((lam + d, w) for d, w in DEFAULT_BANDS.get(channel, _OTHER_BAND))
    total = sum(w for _, w in pts)
    return tuple((float(l), float(w) / total) for l, w in pts if w > 0)


def terms_at(spec: LensSpec, channel: str, rho: float, phi_rad: float) -> WaveTerms:
    """Wavefront terms of a channel at normalised field height rho and azimuth phi.

    The spec's astigmatism (tangential - sagittal focus, the field polynomial ``A(rho)`` of ``astigmatism_um``)
    becomes ``Wast = -A(rho) / (16 N^2)`` (so the tangential focus lies at ``z_c + A(rho) / 2``, as the geometric
    path and the truth have it); the ``aberrations`` block adds its own terms.
    """
    n = spec.f_number
    wast = -float(spec.channel(channel).astigmatism_at(rho)) / (16.0 * n * n)
    w040 = w060 = w131 = 0.0
    ab = spec.aberrations
    if ab is not None:
        ab = ab.for_channel(channel)
        w040 = float(ab.w040_um(rho))
        w060 = float(ab.w060_um(rho))
        w131 = float(ab.w131_um(rho))
        wast += float(ab.wast_um(rho))
    if w131 == 0.0 and wast == 0.0:
        phi_rad = 0.0  # rotationally symmetric: one PSF serves every azimuth (and one cache entry)
    return WaveTerms(w040, w131, float(wast), float(phi_rad), w060)


def wavefront_um(u, v, dz_um: float, f_number: float, terms: WaveTerms) -> np.ndarray:
    """The wavefront W (µm) at normalised pupil coordinates (module docstring)."""
    r2 = u * u + v * v
    c, s = math.cos(terms.phi_rad), math.sin(terms.phi_rad)
    t = u * c + v * s
    w = (dz_um / (8.0 * f_number * f_number)) * r2
    if terms.w040_um:
        w = w + terms.w040_um * r2 * r2
    if terms.w060_um:
        w = w + terms.w060_um * r2 * r2 * r2
    if terms.w131_um:
        w = w + terms.w131_um * r2 * t
    if terms.wast_um:
        sg = -u * s + v * c
        w = w + terms.wast_um * (t * t - sg * sg)
    return w


def monochromatic_psf(wavelength_nm: float, f_number: float, spacing_um: float, n_fft: int, wavefront,
                      band_cyc_per_um: float | None = None) -> np.ndarray:
    """Intensity PSF (n_fft x n_fft, sum 1) sampled at ``spacing_um``, chief ray at index n_fft // 2.

    ``wavefront(u, v)`` returns W in µm on normalised pupil coordinates. The pupil is sampled with
    ``n_p = n_fft * spacing / (lambda N)`` samples across its diameter (any real number; the edge is
    anti-aliased: transmission = covered fraction across one sample), so the FFT grid step is exactly
    ``spacing_um`` on the sensor. By default needs ``n_p <= n_fft / 2`` (PSF sampled at least at the Nyquist
    rate of its band, 1/(lambda N)): exact at every frequency. With ``band_cyc_per_um`` = f_max, only
    frequencies up to f_max are kept exact (the aliased copies of the OTF at multiples of 1/spacing start beyond
    f_max): ``n_fft >= n_p (1 + lambda N f_max)``, i.e. ``spacing <= 1 / (1/(lambda N) + f_max)``.
    """
    lam_um = wavelength_nm * 1e-3
    n_p = n_fft * spacing_um / (lam_um * f_number)
    f_max = 1.0 / (lam_um * f_number) if band_cyc_per_um is None else float(band_cyc_per_um)
    if n_p * (1.0 + lam_um * f_number * f_max) > n_fft * (1.0 + 1e-9):
        raise ParameterError(f"PSF spacing {spacing_um:.4g} µm is too coarse for frequencies up to {f_max:.4g} "
                             f"cycles/µm at {wavelength_nm:g} nm, F/{f_number:g}", field="spacing_um",
                             fix="sample the PSF more finely")
    m = int(math.ceil(n_p)) + 2
    g = (np.arange(m, dtype=np.float64) - (m - 1) / 2.0) / (n_p / 2.0)
    u, v = g[None, :], g[:, None]
    amp = np.clip(0.5 + (1.0 - np.hypot(u, v)) * (n_p / 2.0), 0.0, 1.0)
    pupil = (amp * np.exp((-2j * np.pi / lam_um) * wavefront(u, v))).astype(np.complex64)
    # the pupil's place in the array only adds a linear phase to E, so |E|^2 is centred on index 0
    e = fft.fft2(pupil, s=(n_fft, n_fft), workers=-1)
    psf = fft.fftshift(e.real * e.real + e.imag * e.imag).astype(np.float64)
    return psf / psf.sum()


class ChannelOptics:
    """The wave optics of one channel: polychromatic PSFs, pixel kernels and through-focus MTF."""

    def __init__(self, spec: LensSpec, channel: str):
        self.spec = spec
        self.channel = channel
        self.f_number = spec.f_number
        self.band = band(spec, channel)
        self.lam_min_um = min(l for l, _ in self.band) * 1e-3
        self.lam_max_um = max(l for l, _ in self.band) * 1e-3
        self.sigma_um = spec.residual_blur_um

    def half_extent_um(self, terms: WaveTerms, dz_um: float) -> float:
        """Radius (µm) holding the PSF: geometric spot + diffraction tail + residual Gaussian."""
        n = self.f_number
        spot = 2.0 * n * (2.0 * abs(dz_um) / (8.0 * n * n) + terms.max_slope_um())
        return spot + _TAIL_LAMBDA_N * self.lam_max_um * n + 4.0 * self.sigma_um

    def psf(self, terms: WaveTerms, dz_um: float, spacing_um: float, n: int,
            band_cyc_per_um: float | None = None) -> np.ndarray:
        """Polychromatic optical PSF on an n x n grid at ``spacing_um`` (n odd: chief ray at the centre sample).

        Each wavelength's PSF is computed on an FFT grid large enough for the spot and at least 64 pupil
        samples, normalised, weighted by the band, then cropped to n x n (so the sum is the energy inside the
        window). ``band_cyc_per_um``: see :func:`monochromatic_psf`. The residual Gaussian is not included
        (:meth:`kernel` and :meth:`mtf` apply it as its OTF).
        """
        n_min = _MIN_PUPIL_SAMPLES * self.lam_max_um * self.f_number / spacing_um
        n_fft = fft.next_fast_len(int(max(n, math.ceil(n_min), 2 * self.half_extent_um(terms, dz_um) / spacing_um)))
        if n_fft % 2:
            n_fft += 1  # even, so the centre index n_fft // 2 is the chief ray
        out = np.zeros((n, n))
        lo = n_fft // 2 - n // 2
        for lam_nm, w in self.band:
            p = monochromatic_psf(lam_nm, self.f_number, spacing_um, n_fft,
                                  lambda u, v: wavefront_um(u, v, dz_um, self.f_number, terms), band_cyc_per_um)
            out += w * p[lo:lo + n, lo:lo + n]
        return out

    def residual_otf(self, f_cyc_per_um):
        """OTF of the residual Gaussian (``residual_blur_um``)."""
        return np.exp(-2.0 * (np.pi * self.sigma_um * np.asarray(f_cyc_per_um)) ** 2)

    def kernel(self, terms: WaveTerms, dz_um: float, pitch_um: float, scale: float = 1.0,
               size: int | None = None) -> np.ndarray:
        """Pixel kernel (K x K, K odd, float32, sum 1): the PSF integrated over each pixel's square aperture,
        band-limited to the pixel grid.

        ``scale`` = a: the kernel is for an image that is then magnified by a (the renderer blurs the scene
        before its breathing / lateral-colour warp), so it is the sensor's pixel PSF shrunk by 1/a: transfer
        function ``OTF(g / (a p)) sinc(g / a)`` at g cycles per (scene) pixel. ``size``: K (odd), instead of
        the window that holds the PSF.

        The kernel is built in the frequency domain on the pixel grid's own frequencies ``j / (K p)``,
        ``|j| <= (K - 1) / 2`` (K from ``half_extent_um``): the optical OTF there times the residual Gaussian's
        OTF and the pixel aperture's OTF ``sinc(fx p) sinc(fy p)`` (100% fill factor), transformed back. So the
        kernel's DFT is ``OTF(f) sinc(f p)`` at those frequencies, with no aliased copies: the scene is itself
        sampled at the pixel grid (as in the geometric path), and aliasing would move the sharpest position
        (high frequencies peak nearer the paraxial focus).

        The optical OTF is exact where it can be: a rotationally symmetric pupil (no coma, no astigmatism) takes
        the pupil's autocorrelation (:func:`fieldcal.optics.pupil.otf_radial`) at each radius of the block, the
        band's OTFs summed as complex values (one polychromatic PSF), as the truth (:meth:`mtf`) does. Why: the
        sampled PSF's DFT carried ~1e-3 of discretisation error that changes with dz (pupil sampling and window
        follow the defocus), which moved the kernels' MTF(fs) peak up to 0.56 µm from the truth's on 15 µm
        pixels at 13 cycles/mm (docs/simulator.md). Other pupils (coma, astigmatism) take the same
        autocorrelation in two dimensions (:func:`fieldcal.optics.pupil.otf_2d`, :meth:`_general_block`) while
        that costs at most ``_EXACT_2D_BUDGET`` integrand values; larger blocks (a big defocused kernel on a
        fine pixel grid) take the DFT of a sampled PSF (:meth:`_sampled_block`), as before session 9.
        """
        scene_px_um = pitch_um * float(scale)  # one scene pixel, in µm at the sensor
        k = size or 2 * int(math.ceil(max(self.half_extent_um(terms, dz_um) / scene_px_um, _MIN_HALF_PX))) + 1
        f_px = fft.fftfreq(k)  # cycles/px, in the DFT's order
        if terms.w131_um == 0.0 and terms.wast_um == 0.0:
            block = self._symmetric_block(terms, dz_um, f_px / scene_px_um)
        elif self._exact_2d_cost(terms, dz_um, scene_px_um, k) <= _EXACT_2D_BUDGET:
            block = self._general_block(terms, dz_um, f_px / scene_px_um)
        else:
            block = self._sampled_block(terms, dz_um, scene_px_um, k)
        pix = np.sinc(f_px / float(scale))
        res = self.residual_otf(np.hypot(f_px[:, None], f_px[None, :]) / scene_px_um)
        block = block * (pix[:, None] * pix[None, :] * res)
        ker = fft.fftshift(fft.ifft2(block, workers=-1).real)
        return (ker / ker.sum()).astype(np.float32)

    def _symmetric_block(self, terms: WaveTerms, dz_um: float, f_cyc_per_um: np.ndarray) -> np.ndarray:
        """Exact polychromatic OTF of a rotationally symmetric pupil on the grid ``f x f`` (cycles/µm, 1-D
        axis in any order), evaluated once per distinct radius."""
        from fieldcal.optics import pupil

        n = self.f_number
        r2 = f_cyc_per_um[:, None] ** 2 + f_cyc_per_um[None, :] ** 2
        radii, inverse = np.unique(np.round(r2, 12), return_inverse=True)
        f = np.sqrt(radii)
        tot = np.zeros_like(f)
        for lam_nm, w in self.band:
            lam = lam_nm * 1e-3
            tot += w * pupil.otf_radial(f * lam * n, dz_um / (8.0 * n * n * lam), terms.w040_um / lam,
                                        terms.w060_um / lam)
        return tot[inverse.reshape(r2.shape)]

    def _exact_2d_cost(self, terms: WaveTerms, dz_um: float, px_um: float, k: int) -> float:
        """Integrand evaluations of :meth:`_general_block` on a K x K block (node rule of ``pupil.otf_2d``)."""
        n = self.f_number
        nu = min(math.sqrt(0.5) / px_um * self.lam_max_um * n, 1.0)
        slope_waves = (2.0 * abs(dz_um) / (8.0 * n * n) + terms.max_slope_um()) / self.lam_min_um
        m = 1.5 * math.pi * nu * slope_waves + 12.0
        return (k * k / 2.0) * m * m * len(self.band)

    def _sampled_block(self, terms: WaveTerms, dz_um: float, px_um: float, k: int) -> np.ndarray:
        """The OTF at the pixel grid's frequencies (K x K, DFT order) from the DFT of a sampled PSF (any pupil):
        the PSF sampled ``os`` times per pixel (os odd; fine enough that the OTF is exact up to the corner of the
        band) on the K x K window, its DFT's central K x K block. Off the exact OTF by the window's truncation
        and the sampled pupil's edge (~1e-3, changing with dz); used only where :meth:`_general_block` is too
        slow (the kernels there span many pixels, and their peak error was <= 0.04 µm in the tests)."""
        f_max = math.sqrt(0.5) / px_um  # the corner of the band, cycles/µm
        spacing = 1.0 / (1.0 / (self.lam_min_um * self.f_number) + f_max)
        os_ = int(math.ceil(px_um / spacing))
        os_ += 1 - os_ % 2
        n = k * os_
        spectrum = fft.fft2(fft.ifftshift(self.psf(terms, dz_um, px_um / os_, n, f_max)), workers=-1)
        h = (k - 1) // 2
        keep = np.r_[0:h + 1, n - h:n]  # frequencies j / (K p), |j| <= h: the pixel grid's band
        return spectrum[np.ix_(keep, keep)]

    def _general_block(self, terms: WaveTerms, dz_um: float, f_cyc_per_um: np.ndarray) -> np.ndarray:
        """Exact polychromatic (complex) OTF of any pupil on the grid ``f x f`` (cycles/µm; rows fy, columns fx;
        a DFT-ordered axis, so ``-f`` of every point is on the grid): the pupil autocorrelation at half the
        points, the rest by ``OTF(-f) = conj(OTF(f))``."""
        fy, fx = np.meshgrid(f_cyc_per_um, f_cyc_per_um, indexing="ij")
        m = f_cyc_per_um.size
        neg = np.r_[0, m - 1:0:-1]  # index of -f along the DFT-ordered axis
        half = (fy > 0) | ((fy == 0) & (fx >= 0))
        tot = np.zeros(fx.shape, dtype=np.complex128)
        tot[half] = self._general_otf(terms, dz_um, fx[half], fy[half])
        rows, cols = np.nonzero(~half)
        tot[rows, cols] = np.conj(tot[neg[rows], neg[cols]])
        return tot

    def mtf(self, terms: WaveTerms, dz_um: float, f_cyc_per_mm: float, n_angles: int = 12) -> float:
        """Optical MTF at f (cycles/mm), averaged over ``n_angles`` orientations (no pixel aperture).

        Exact: the pupil's autocorrelation (:mod:`fieldcal.optics.pupil`), the band's OTFs summed as complex
        values (one polychromatic PSF), then the magnitude. A rotationally symmetric pupil (no coma, no
        astigmatism) has the same OTF in every orientation (:func:`fieldcal.optics.pupil.otf`); others are
        averaged over the orientations (:func:`fieldcal.optics.pupil.otf_2d`). Why exact: the sampled PSF's MTF
        carried ~1e-3 of discretisation error that changes with dz (the pupil's sampling and the PSF window
        follow the defocus), and near the flat top of a low-fs curve that moved the sharpest position by up to
        0.7 µm (docs/simulator.md). The pixel kernels use the same OTF (:meth:`kernel`).
        """
        f_um = f_cyc_per_mm * 1e-3
        if terms.w131_um == 0.0 and terms.wast_um == 0.0:
            return self._symmetric_mtf(terms, dz_um, f_um)
        ang = np.arange(n_angles) * (np.pi / n_angles)
        return float(np.mean(np.abs(self._general_otf(terms, dz_um, f_um * np.cos(ang), f_um * np.sin(ang))))
                     * self.residual_otf(f_um))

    def _general_otf(self, terms: WaveTerms, dz_um: float, fx_cyc_per_um, fy_cyc_per_um) -> np.ndarray:
        """Exact polychromatic complex OTF of any pupil at the frequencies ``(fx, fy)`` (cycles/µm)."""
        from fieldcal.optics import pupil

        n = self.f_number
        slope_um = 2.0 * abs(dz_um) / (8.0 * n * n) + terms.max_slope_um()
        tot = 0.0
        for lam_nm, w in self.band:
            lam = lam_nm * 1e-3
            tot = tot + w * pupil.otf_2d(np.asarray(fx_cyc_per_um) * lam * n, np.asarray(fy_cyc_per_um) * lam * n,
                                         lambda u, v: wavefront_um(u, v, dz_um, n, terms) / lam, slope_um / lam)
        return tot

    def _symmetric_mtf(self, terms: WaveTerms, dz_um: float, f_um: float) -> float:
        """|OTF| at f (cycles/µm) of the channel's band for a rotationally symmetric pupil, exact (module
        :mod:`fieldcal.optics.pupil`): the band's OTFs add (one polychromatic PSF), then the magnitude."""
        from fieldcal.optics import pupil

        n = self.f_number
        tot = 0.0
        for lam_nm, w in self.band:
            lam = lam_nm * 1e-3
            tot += w * float(pupil.otf(f_um * lam * n, dz_um / (8.0 * n * n * lam), terms.w040_um / lam,
                                       terms.w060_um / lam))
        return abs(tot) * float(self.residual_otf(f_um))

    def best_focus_shift_um(self, terms: WaveTerms, fs_cyc_per_mm: float) -> float:
        """dz (µm from the reference surface) where the orientation-averaged MTF at fs peaks.

        A coarse scan (step half the geometric depth ``N / (pi fs)``) over the span of the spherical
        aberration's foci plus margins finds the global maximum (a through-focus curve can have secondary maxima
        after contrast reversal); a bounded Brent search (0.01 µm) refines it on the exact MTF (:meth:`mtf`, no
        sampling noise to smooth away; a quartic fit was needed while it came from a sampled PSF). Without
        spherical aberration and
        with only one of coma or astigmatism the curve is symmetric in dz (W(u, v; -dz) = -W(-u, -v; dz) up to a
        rotation, which leaves the orientation-averaged MTF unchanged), so the shift is exactly 0.
        """
        n = self.f_number
        if terms.w040_um == 0.0 and terms.w060_um == 0.0 and (terms.w131_um == 0.0 or terms.wast_um == 0.0):
            return 0.0
        dof_um = 1000.0 * n / (math.pi * fs_cyc_per_mm)
        # minimum-RMS focus of primary + secondary spherical (W020 = -W040 - 0.9 W060), and their spread
        centre = -8.0 * n * n * (terms.w040_um + 0.9 * terms.w060_um)
        half = 16.0 * n * n * (abs(terms.w040_um) + 1.5 * abs(terms.w060_um)) + 1.5 * dof_um
        step = dof_um / 2.0
        zs = centre + np.arange(-half, half + step / 2, step)
        vals = np.array([self.mtf(terms, float(z), fs_cyc_per_mm) for z in zs])
        i = int(np.argmax(vals))
        res = minimize_scalar(lambda z: -self.mtf(terms, float(z), fs_cyc_per_mm),
                              bounds=(zs[max(i - 1, 0)], zs[min(i + 1, len(zs) - 1)]), method="bounded",
                              options={"xatol": 0.01})
        return float(res.x) if -res.fun >= vals[i] else float(zs[i])  # exact MTF: no sampling noise to smooth


def rho_nodes(spec: LensSpec) -> np.ndarray:
    """Field heights at which the sharpest position is computed: 0 .. the largest rho on the sensor."""
    s = spec.sensor
    xs, ys = spec.pixel_to_mm(np.array([0, s.width_px - 1, 0, s.width_px - 1]),
                              np.array([0, 0, s.height_px - 1, s.height_px - 1]))
    return np.linspace(0.0, float(np.max(spec.rho(xs, ys))) * 1.0001, _RHO_NODES)


def best_focus_shift_table(spec: LensSpec, channel: str, fs_cyc_per_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(rho, shift_um): the wave path's sharpest position minus the reference surface, over field height.

    The orientation-averaged MTF does not depend on the field azimuth, so the shift is a function of rho only.
    """
    if not (fs_cyc_per_mm > 0 and math.isfinite(fs_cyc_per_mm)):
        raise ParameterError(f"fs must be a positive frequency in cycles/mm, got {fs_cyc_per_mm}", field="fs",
                             fix="e.g. 80")
    opt = ChannelOptics(spec, channel)
    rho = rho_nodes(spec)
    return rho, np.array([opt.best_focus_shift_um(terms_at(spec, channel, float(r), 0.0), fs_cyc_per_mm)
                          for r in rho])


class WaveBlur:
    """Spatially varying wave-optics blur for a :class:`fieldcal.simulate.render.Renderer`.

    Parameters
    ----------
    spec : LensSpec
        Lens at the rendered size.
    scene : ndarray
        H x W x C float32 scene (the renderer's channels).
    level_ratio, level_floor_px : float
        The defocus ladder (as the geometric path's, in blur-disc diameter ``|dz| / N / pitch``), centred per
        node on its sharpest position.
    fs_cyc_per_mm : float
        Frequency whose MTF peak defines the sharpest position (the calibration frequency).
    field_grid : (int, int)
        Field nodes across x and y (corners included).
    """

    def __init__(self, spec: LensSpec, scene: np.ndarray, level_ratio: float, level_floor_px: float,
                 fs_cyc_per_mm: float = 80.0, field_grid: tuple[int, int] = (5, 4)):
        nx, ny = (int(v) for v in field_grid)
        if nx < 2 or ny < 2:
            raise ParameterError(f"field_grid must be at least 2 x 2, got {field_grid}", field="field_grid",
                                 fix="e.g. (5, 4)")
        if any(spec.channel(c).has_astigmatism for c in spec.channel_names):
            # Blending node PSFs of different azimuths mixes orientations: on the astigmatic triplet a 5x4 grid
            # rendered ~0.8 of T - S (slanted-edge T/S 1.1-1.6 µm RMS off); 11x7 brings them to 0.6-1.0 µm for
            # ~20 % more render time (docs/benchmarks.md "bench_edge_calibration")
            nx, ny = max(nx, ASTIG_FIELD_GRID[0]), max(ny, ASTIG_FIELD_GRID[1])
        self.spec = spec
        self.scene = scene
        self.level_ratio = level_ratio
        self.level_floor_px = level_floor_px
        self.fs_cyc_per_mm = float(fs_cyc_per_mm)
        self.field_grid = (nx, ny)
        # the renderer warps the scene to the sensor and then blurs it (True), or blurs and then warps the blurred
        # image (False, up to session 10): docs/simulator.md "Warp, then blur"
        self.warp_first = True
        s = spec.sensor
        self.h, self.w, self.pitch_um = s.height_px, s.width_px, s.pixel_pitch_um
        self.node_x = np.linspace(0.0, self.w - 1.0, nx)
        self.node_y = np.linspace(0.0, self.h - 1.0, ny)
        self.optics = {c: ChannelOptics(spec, c) for c in spec.channel_names}
        self._shift: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._kernels: dict[tuple, np.ndarray] = {}
        self._padded: dict[int, tuple[int, np.ndarray]] = {}
        cx, cy = spec.optical_centre_px()
        # Node terms in a canonical azimuth in [0, pi/2]: W(u, v; pi - phi) = W(-u, v; phi) and
        # W(u, v; -phi) = W(u, -v; phi), so the PSF of a mirrored field point is the mirrored PSF; nodes placed
        # symmetrically about the optical centre share one computation.
        self._node_terms: dict[tuple, WaveTerms] = {}
        self._node_flip: dict[tuple, tuple[bool, bool]] = {}
        for c in spec.channel_names:
            for j, y in enumerate(self.node_y):
                for i, x in enumerate(self.node_x):
                    xm, ym = spec.pixel_to_mm(x, y)
                    dx, dy = x - cx, y - cy
                    phi = math.atan2(abs(dy), abs(dx))
                    self._node_terms[c, j, i] = terms_at(spec, c, round(float(spec.rho(xm, ym)), 9), round(phi, 9))
                    self._node_flip[c, j, i] = (dx < 0, dy < 0)

    # ------------------------------------------------------------------------------ sharpest position
    def shift_table(self, channel: str) -> tuple[np.ndarray, np.ndarray]:
        if channel not in self._shift:
            self._shift[channel] = best_focus_shift_table(self.spec, channel, self.fs_cyc_per_mm)
        return self._shift[channel]

    def best_focus_shift_um(self, channel: str, rho) -> np.ndarray:
        """Sharpest position minus reference surface (µm) at normalised field heights rho."""
        r, s = self.shift_table(channel)
        return np.interp(np.asarray(rho, dtype=np.float64), r, s)

    # ------------------------------------------------------------------------------------ kernels
    def _level_dz_um(self, k: int) -> float:
        """Signed defocus (µm) of ladder level k from the node's centre: level +-k has the blur-disc diameter
        ``level_floor_px * level_ratio**(|k| - 1)`` (the geometric path's levels, render.level_diameters_px)."""
        if k == 0:
            return 0.0
        d_px = self.level_floor_px * self.level_ratio ** (abs(k) - 1)
        return math.copysign(d_px * self.spec.f_number * self.pitch_um, k)

    def kernel(self, channel: str, j: int, i: int, k: int, scale: float = 1.0) -> np.ndarray:
        """Pixel kernel of node (j, i) at ladder level k for a frame that the renderer then magnifies by
        ``scale`` (mirrored per node).

        The renderer blurs the scene and then warps it by the frame's image scale ``a = m(z) lc`` (breathing,
        lateral colour), which magnifies the blur by a: the kernel is the sensor PSF shrunk by 1/a
        (:meth:`ChannelOptics.kernel`). Why: unshrunk kernels magnified the PSF with z, which moved the fs
        contrast peak by up to -0.86 µm on an F/7.5 lens with its exit pupil 15 mm from the sensor
        (docs/simulator.md). a differs from frame to frame, so the cache (keyed by the node's canonical terms
        and the level's defocus) holds the kernels at a = 1 and ``1 + _SCALE_STEP`` and each frame takes the
        line through them: exact at a = 1 (telecentric, no lateral colour), off by ``(a - 1)(a - 1 - step) / 2``
        times the kernel's second derivative in a elsewhere (<= 4e-4 of transfer at |a - 1| <= 0.02, tested).
        """
        terms = self._node_terms[channel, j, i]
        dz = self._centre_um(channel, j, i) + self._level_dz_um(k)
        key = (channel, terms, round(dz, 6))
        if key not in self._kernels:
            self._kernels[key] = [self.optics[channel].kernel(terms, dz, self.pitch_um), None]
        entry = self._kernels[key]
        ker = entry[0]
        if scale != 1.0:
            if entry[1] is None:  # d(kernel)/da, only for lenses whose frames are scaled
                k2 = self.optics[channel].kernel(terms, dz, self.pitch_um, 1.0 + _SCALE_STEP, size=ker.shape[0])
                entry[1] = ((k2.astype(np.float64) - ker) / _SCALE_STEP).astype(np.float32)
            ker = ker + np.float32(scale - 1.0) * entry[1]
        fx, fy = self._node_flip[channel, j, i]
        return ker[::-1 if fy else 1, ::-1 if fx else 1]

    def _centre_um(self, channel: str, j: int, i: int) -> float:
        xm, ym = self.spec.pixel_to_mm(self.node_x[i], self.node_y[j])
        return float(self.best_focus_shift_um(channel, self.spec.rho(xm, ym)))

    def _padded_scene(self, ci: int, pad: int, scene: np.ndarray | None = None) -> tuple[int, np.ndarray]:
        pad = int(16 * 1.5 ** max(0, math.ceil(math.log(max(pad, 1) / 16) / math.log(1.5))))
        if scene is not None:  # a frame's own (warped) scene: not cached
            return pad, np.pad(np.asarray(scene, dtype=np.float32), pad, mode="symmetric")
        if ci not in self._padded or self._padded[ci][0] < pad:
            self._padded[ci] = (pad, np.pad(self.scene[:, :, ci], pad, mode="symmetric"))
        return self._padded[ci]

    # ---------------------------------------------------------------------------------------- blur
    def _signed_level(self, u_um: np.ndarray) -> np.ndarray:
        from .levels import fractional_level
        b = np.abs(u_um).astype(np.float32) / np.float32(self.spec.f_number * self.pitch_um)
        return np.sign(u_um).astype(np.float32) * fractional_level(b, self.level_ratio, self.level_floor_px)

    @staticmethod
    def _hat(coord: np.ndarray, nodes: np.ndarray, i: int) -> np.ndarray:
        """Linear interpolation weight of node i at the coordinates (1 at the node, 0 at its neighbours)."""
        w = np.zeros_like(coord)
        if i > 0:
            m = (coord >= nodes[i - 1]) & (coord <= nodes[i])
            w[m] = (coord[m] - nodes[i - 1]) / (nodes[i] - nodes[i - 1])
        if i < len(nodes) - 1:
            m = (coord >= nodes[i]) & (coord <= nodes[i + 1])
            w[m] = (nodes[i + 1] - coord[m]) / (nodes[i + 1] - nodes[i])
        if i == 0:
            w[coord <= nodes[0]] = 1.0
        return w

    def blur(self, channel: str, defocus_um: np.ndarray, scale: float = 1.0,
             scene: np.ndarray | None = None) -> np.ndarray:
        """The scene channel blurred with the wave PSF of each pixel's signed defocus (µm from the reference
        surface, H x W) and field position: blend of (node, level) kernel images, the kernels shrunk by the
        image scale ``scale`` that the renderer's warp then applies (:meth:`kernel`).

        ``scene``: blur this H x W image instead of the renderer's scene channel; the renderer passes the scene
        already warped to the sensor (``scale`` 1), so every sensor pixel blends the levels of its own defocus
        (docs/simulator.md "Warp, then blur")."""
        ci = self.spec.channel_names.index(channel)
        dz = np.asarray(defocus_um, dtype=np.float64)
        out = np.zeros((self.h, self.w), dtype=np.float32)
        xs = np.arange(self.w, dtype=np.float64)
        ys = np.arange(self.h, dtype=np.float64)
        nx, ny = self.field_grid
        # padding: the largest kernel this frame needs (spot of the largest defocus, plus margins)
        worst = max(self._node_terms[channel, j, i].max_slope_um() for j in range(ny) for i in range(nx))
        big = WaveTerms(w040_um=worst / 4.0)
        max_dz = float(np.max(np.abs(dz))) + max(abs(self._centre_um(channel, j, i)) for j in range(ny)
                                                  for i in range(nx))
        max_dz *= self.level_ratio  # the upper bracketing level
        # kernels are shrunk by the warp's scale a (:meth:`kernel`): in scene pixels their radius is 1/a larger
        half_px = max(self.optics[channel].half_extent_um(big, max_dz) / (self.pitch_um * min(scale, 1.0)),
                      _MIN_HALF_PX)
        pad, padded = self._padded_scene(ci, int(math.ceil(half_px)) + 2 + int(self.level_floor_px), scene)
        for j in range(ny):
            y0 = int(math.ceil(self.node_y[max(j - 1, 0)])); y1 = int(math.floor(self.node_y[min(j + 1, ny - 1)])) + 1
            wy = self._hat(ys[y0:y1], self.node_y, j)
            for i in range(nx):
                x0 = int(math.ceil(self.node_x[max(i - 1, 0)])); x1 = int(math.floor(self.node_x[min(i + 1, nx - 1)])) + 1
                wx = self._hat(xs[x0:x1], self.node_x, i)
                wn = (wy[:, None] * wx[None, :]).astype(np.float32)
                if not wn.any():
                    continue
                idx = self._signed_level(dz[y0:y1, x0:x1] - self._centre_um(channel, j, i)).ravel()
                lo = np.floor(idx).astype(np.int32)
                t = (idx - lo) * wn.ravel()  # weight of the upper level, times the node's
                t0 = wn.ravel() - t  # weight of the lower level
                # group the tile's pixels by their lower level once (stable sort of small ints), so each level
                # touches only the pixels it brackets, as in the geometric path
                order = np.argsort(lo, kind="stable")
                k0, k1 = int(lo[order[0]]), int(lo[order[-1]])
                bounds = np.searchsorted(lo[order], np.arange(k0, k1 + 2))
                tw = x1 - x0
                acc = np.zeros(wn.size, dtype=np.float32)
                for k in range(k0, k1 + 2):
                    below = order[bounds[k - k0 - 1]:bounds[k - k0]] if k > k0 else order[:0]  # lo == k - 1
                    here = order[bounds[k - k0]:bounds[k - k0 + 1]] if k <= k1 else order[:0]  # lo == k
                    ids = np.concatenate([here, below])
                    w = np.concatenate([t0[here], t[below]])
                    keep = w > 0
                    if not keep.any():
                        continue
                    ids, w = ids[keep], w[keep]
                    ker = self.kernel(channel, j, i, k, scale)
                    r = ker.shape[0] // 2
                    if r > pad:
                        raise ParameterError(f"a wave kernel of radius {r} px exceeds the padding {pad} px",
                                             field="z_um", fix="report this: the padding estimate is wrong")
                    # only the bounding box of the pixels that use this level (a band across the node's cells)
                    rr, cc = np.divmod(ids, tw)
                    ra, rb, ca, cb = int(rr.min()), int(rr.max()) + 1, int(cc.min()), int(cc.max()) + 1
                    tile = padded[pad + y0 + ra - r:pad + y0 + rb + r, pad + x0 + ca - r:pad + x0 + cb + r]
                    conv = cv2.filter2D(tile, cv2.CV_32F, ker[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)
                    acc[ids] += w * conv[r + rr - ra, r + cc - ca]
                acc = acc.reshape(wn.shape)
                out[y0:y1, x0:x1] += acc
        return out

    def settings(self) -> dict:
        return {"optics": "wave", "fs_cyc_per_mm": self.fs_cyc_per_mm, "field_grid": list(self.field_grid),
                "bands_nm": {c: [list(p) for p in o.band] for c, o in self.optics.items()},
                "pixel_aperture": "square, 100% fill factor (sinc OTF); kernels band-limited to the pixel grid"}
