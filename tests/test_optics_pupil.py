"""The exact OTF of a circular pupil with defocus and spherical aberration (fieldcal.optics.pupil) against
closed forms and an independent FFT of the pupil."""

import math

import numpy as np
import pytest

from hopkins_util import hopkins_otf as hopkins_defocus_otf
from fieldcal.measure import spherical
from fieldcal.optics import pupil


@pytest.mark.parametrize("nu", [0.02, 0.15, 0.4, 0.8])
@pytest.mark.parametrize("w020", [0.0, 0.5, 2.0, 6.0])
def test_defocus_is_hopkins_closed_form(nu, w020):
    assert float(pupil.otf(nu, w020)) == pytest.approx(hopkins_defocus_otf(nu, w020), abs=1e-9)


def test_geometric_limit_is_the_ray_otf_of_the_skew_model():
    # nu -> 0 at fixed x = -8 pi nu W020, s = 16 pi nu W040: the geometric-optics ray OTF (measure/spherical.py);
    # the difference is the diffraction term, O(nu)
    for x, s in ((1.0, 2.0), (3.0, 5.0), (-2.0, 8.0)):
        ref = float(spherical.sa_otf(x, s)[0])
        errs = [abs(float(pupil.otf(nu, -x / (8 * math.pi * nu), s / (16 * math.pi * nu))) - ref)
                for nu in (1e-2, 1e-3, 1e-4)]
        assert errs[2] < 2e-4 and errs[2] < errs[1] < errs[0]


def _fft_otf(nu: float, w020: float, w040: float, n: int = 256, pad: int = 4) -> float:
    """Radial mean of |FFT(|FFT(P)|^2)| on the ring at nu (the pupil sampled on n x n points, hard edge)."""
    m = n * pad
    y, x = (np.mgrid[0:m, 0:m] - m / 2 + 0.5) / (n / 2)
    r2 = x * x + y * y
    p = (r2 <= 1.0) * np.exp(2j * np.pi * (w020 * r2 + w040 * r2 * r2))
    otf = np.fft.fft2(np.abs(np.fft.fft2(p)) ** 2).real
    otf /= otf[0, 0]
    f = np.fft.fftfreq(m) * m / n  # shift in pupil diameters: the cut-off (nu = 1) at one diameter
    fr = np.hypot(*np.meshgrid(f, f))
    ring = np.abs(fr - nu) < 0.5 / n
    return float(otf[ring].mean())


@pytest.mark.parametrize("nu,w020,w040", [(0.15, -0.4, 0.6), (0.3, 0.2, -0.8), (0.5, -1.0, 1.2)])
def test_spherical_aberration_against_an_fft_of_the_pupil(nu, w020, w040):
    # the FFT's own error is its pupil edge's staircase (~3e-3 at 256 samples across)
    assert float(pupil.otf(nu, w020, w040)) == pytest.approx(_fft_otf(nu, w020, w040), abs=4e-3)


def test_secondary_spherical_is_the_same_integral():
    # W060 rho^6 alone against the FFT too
    m = 512
    y, x = (np.mgrid[0:m, 0:m] - m / 2 + 0.5) / 64
    r2 = x * x + y * y
    p = (r2 <= 1.0) * np.exp(2j * np.pi * 0.7 * r2 ** 3)
    otf = np.fft.fft2(np.abs(np.fft.fft2(p)) ** 2).real
    otf /= otf[0, 0]
    f = np.fft.fftfreq(m) * m / 128
    ring = np.abs(np.hypot(*np.meshgrid(f, f)) - 0.25) < 0.5 / 128
    assert float(pupil.otf(0.25, 0.0, 0.0, 0.7)) == pytest.approx(float(otf[ring].mean()), abs=5e-3)


# ------------------------------------------------------------------------------------- any pupil (otf_2d)
def test_otf_2d_of_a_symmetric_pupil_is_the_radial_otf():
    """No symmetry assumed: in every direction it is the radial OTF (real) of the same wavefront."""
    rng = np.random.default_rng(4)
    nu, th = rng.uniform(0.0, 0.99, 25), rng.uniform(0.0, 2 * np.pi, 25)
    for w2, w4, w6 in ((0.0, 0.0, 0.0), (3.0, 0.5, 0.0), (-8.0, 0.8, 0.2)):
        def wf(u, v):
            r2 = u * u + v * v
            return w2 * r2 + w4 * r2 * r2 + w6 * r2 ** 3
        got = pupil.otf_2d(nu * np.cos(th), nu * np.sin(th), wf, 2 * abs(w2) + 4 * abs(w4) + 6 * abs(w6))
        np.testing.assert_allclose(got, pupil.otf_radial(nu, w2, w4, w6), atol=1e-10)
        np.testing.assert_allclose(pupil.otf_radial(nu, w2, w4, w6),
                                   [float(pupil.otf(v, w2, w4, w6)) for v in nu], atol=1e-10)


def test_otf_2d_is_the_dft_of_the_wave_renderers_sampled_psf():
    """Coma + astigmatism + defocus: the DFT of a finely sampled PSF (the renderer's pupil convention,
    ``exp(-2 pi i W)`` with numpy's FFT) at its own bins, complex, to its pupil edge's sampling error; and the
    node count has converged."""
    from fieldcal.simulate.wave import WaveTerms, monochromatic_psf, wavefront_um

    lam_nm, n_f, n_fft, n_p = 500.0, 2.0, 1024, 256  # lambda N = 1 µm: bin j is nu = j / n_p
    terms = WaveTerms(w040_um=0.15, w131_um=0.25, wast_um=0.2, phi_rad=0.5)
    dz = 6.0

    def wf(u, v):
        return wavefront_um(u, v, dz, n_f, terms) / (lam_nm * 1e-3)

    psf = monochromatic_psf(lam_nm, n_f, n_p / n_fft, n_fft, lambda u, v: wavefront_um(u, v, dz, n_f, terms))
    dft = np.fft.fft2(np.fft.ifftshift(psf))
    slope = (2 * dz / (8 * n_f * n_f) + terms.max_slope_um()) / (lam_nm * 1e-3)
    jy, jx = np.meshgrid(np.arange(-40, 41, 8), np.arange(-40, 41, 8), indexing="ij")
    got = pupil.otf_2d(jx / n_p, jy / n_p, wf, slope)
    assert np.max(np.abs(got.imag)) > 0.05  # coma: a complex OTF, so the sign convention is tested
    # the sampled pupil's anti-aliased edge: ~0.25 % of the value at 256 samples across (2.3e-3 at most)
    np.testing.assert_allclose(got, dft[jy % n_fft, jx % n_fft], atol=3e-3)
    np.testing.assert_allclose(got, pupil.otf_2d(jx / n_p, jy / n_p, wf, slope, n=200), atol=1e-9)
    np.testing.assert_allclose(pupil.otf_2d(-jx / n_p, -jy / n_p, wf, slope), np.conj(got), atol=1e-12)
