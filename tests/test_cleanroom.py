"""The clean-room renderer (benchmarks/cleanroom/) against closed forms, and fieldcal's best focus on it.

The renderer shares no code with fieldcal.simulate/optics/charts; these tests check it against textbook
closed forms (the diffraction-limited MTF of a circular pupil; Hopkins' defocus OTF as a 1-D integral), then
check that fieldcal's calibration lands on the renderer's own truth on a symmetric lens.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import fft as sfft
from scipy.integrate import quad

from benchmarks.cleanroom.chart import dead_leaves, raster
from benchmarks.cleanroom.lens import CleanLens
from benchmarks.cleanroom.otf import otf_native, otf_on_frequencies, otf_quadrature
from benchmarks.cleanroom.render import Renderer, Sensor, expose, node_grid
from benchmarks.cleanroom.truth import node_truth

NU = np.array([0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.9])


def mtf_diffraction(nu):
    """Incoherent MTF of an aberration-free circular pupil (Goodman eq. 6-32), nu = f / f_c."""
    nu = np.clip(nu, 0.0, 1.0)
    return 2.0 / np.pi * (np.arccos(nu) - nu * np.sqrt(1.0 - nu * nu))


def otf_hopkins(nu: float, w020_waves: float) -> float:
    """Hopkins' defocus OTF: the overlap integral with its inner coordinate done in closed form,
    (4 / π a) ∫_0^√(1−ν²) sin(a (√(1−y²) − ν)) dy with a = 8π W020 ν."""
    a = 8.0 * np.pi * w020_waves * nu
    if abs(a) < 1e-12:
        return float(mtf_diffraction(nu))
    return 4.0 / (np.pi * a) * quad(lambda y: np.sin(a * (np.sqrt(1.0 - y * y) - nu)), 0.0,
                                    np.sqrt(1.0 - nu * nu), limit=200)[0]


@pytest.mark.parametrize("n_pupil, tol", [(64, 0.015), (96, 0.01)])
@pytest.mark.parametrize("w020", [0.0, 0.25, 0.7, 1.5])
def test_otf_against_closed_forms(w020, n_pupil, tol):
    hop = np.array([otf_hopkins(n, w020) for n in NU])
    if w020 == 0.0:
        assert np.allclose(hop, mtf_diffraction(NU), atol=1e-9)
    # the rendering path (pupil FFT, interpolated), along x and along an oblique direction
    nat = otf_native(w020, w020, 0.0, (0.6, 0.8), n_pupil=n_pupil)
    for ang in (0.0, 0.7):
        got = otf_on_frequencies(nat, n_pupil, 1.0, NU * np.cos(ang), NU * np.sin(ang))
        assert np.max(np.abs(got - hop)) < tol, (ang, got - hop)
    # the truth path (Gauss–Legendre overlap integral)
    q = np.array([otf_quadrature([w020], [w020], 0.0, (1.0, 0.0), 2 * n, (np.cos(1.1), np.sin(1.1)), n=48)[0]
                  for n in NU])
    assert np.max(np.abs(q - hop)) < 1e-4


def test_astigmatism_and_spherical_paths_agree():
    """T/S astigmatism and W040: the FFT OTF and the quadrature OTF agree along T, S and oblique."""
    r = (0.6, 0.8)
    nat = otf_native(0.4, -0.3, 0.5, r, n_pupil=96)
    for d in (r, (-r[1], r[0]), (np.cos(0.3), np.sin(0.3))):
        for nu in (0.1, 0.25, 0.4):
            a = otf_on_frequencies(nat, 96, 1.0, np.array([nu * d[0]]), np.array([nu * d[1]]))[0]
            b = otf_quadrature([0.4], [-0.3], 0.5, r, 2 * nu, d)[0]
            assert abs(a - b) < 0.01
    # a T-only defocus does not touch the S direction's MTF (frequency along â sees W_S only)
    s_only = otf_quadrature([0.0, 0.8], [0.2, 0.2], 0.0, r, 0.5, (-r[1], r[0]))
    assert abs(s_only[0] - s_only[1]) < 1e-9


def _reference_render(lens, chart, z_um, k, origin, shape):
    """Uniform defocus rendered in one global FFT with the Hopkins closed form (radial table)."""
    fine = raster(chart, origin, shape, k)
    F = sfft.fft2(fine)
    f1y, f1x = sfft.fftfreq(fine.shape[0], 1.0 / k), sfft.fftfreq(fine.shape[1], 1.0 / k)
    fr = np.hypot(f1x[None, :], f1y[:, None])
    fc = lens.pitch_um / (lens.wavelength_um("Y") * lens.f_number)
    w020 = lens.pupil_coefficients_waves(0.0, 0.0, "Y", z_um)[0]
    tab_nu = np.linspace(0.0, 1.0, 401)
    tab = np.array([otf_hopkins(n, w020) if n < 1 else 0.0 for n in tab_nu])
    H = np.interp(fr / fc, tab_nu, tab, right=0.0) * np.sinc(f1x)[None, :] * np.sinc(f1y)[:, None]
    R0, R1 = shape
    folded = (F * H).reshape(k, R0, k, R1).sum(axis=(0, 2))
    return sfft.ifft2(folded).real / k ** 2


def test_renderer_matches_hopkins_end_to_end():
    """Node tiling, PSF blending, pixel aperture and sampling: a uniformly defocused lens renders as the
    chart convolved with the closed-form OTF (one global FFT), to < 0.5 % of full scale."""
    lens = CleanLens("flat", 4.0, width_px=96, height_px=64, c2_um=0.0, channels=("Y",))
    chart = dead_leaves(96, 64, seed=3, r_max_px=20)
    r = Renderer(lens, {"t": chart}, z_mid_um=0.0, k=4, node_px=32, n_pupil=96)
    z = 8.0                        # 1.2 waves of W020 at 540 nm, F/4
    got = r.blurred(z, "Y")["t"]
    m = 40
    ref = _reference_render(lens, chart, z, 4, (-m, -m), (64 + 2 * m, 96 + 2 * m))[m:m + 64, m:m + 96]
    assert np.max(np.abs(got - ref)) < 0.005
    # and the noise model is unbiased with the stated gain
    s = Sensor()
    dn = expose(np.full((64, 64), 0.5), s, np.random.default_rng(0)).astype(float)
    assert abs(dn.mean() - (s.black_dn + 0.5 * (s.white_dn - s.black_dn))) < 2.0


@pytest.fixture(scope="module")
def symmetric_calibration(tmp_path_factory):
    """A symmetric, aberration-free mono lens (192x128, 21 frames, step ≈ 0.5 δ; 2 working samples per pixel
    to stay fast), calibrated at quick effort: (error at the truth nodes in µm, step in µm). The truth is at
    every other render node (exact PSFs), frame corners included."""
    import fieldcal
    from benchmarks.cleanroom.chart import dead_leaves as dl
    from benchmarks.cleanroom.stackio import write_stack

    lens = CleanLens("sym", 4.0, width_px=192, height_px=128, c2_um=20.0, channels=("Y",))
    xs, ys = node_grid(192, 128, 24.0)
    xs, ys = xs[::2], ys[::2]
    truth = node_truth(lens, xs, ys, 80.0, 0.05)["Y"]["iso"]
    step = 0.5 * float(np.median(truth["delta_um"]))
    z = 10.0 + (np.arange(21) - 10) * step
    r = Renderer(lens, {"t": dl(192, 128, seed=5)}, z_mid_um=float(z[10]), k=2, node_px=24.0, n_pupil=64)
    rng = np.random.default_rng(1)
    frames = [r.frames(float(zi), rng)["t"] for zi in z]
    out = tmp_path_factory.mktemp("cleanroom") / "stack"
    write_stack(out, frames, list(z), pitch_um=lens.pitch_um, f_number=lens.f_number,
                channels=["Y"], black_level=Sensor().black_dn, lens={"name": "sym"}, chart="dead-leaves")
    prof = fieldcal.calibrate(str(out), fs_cyc_per_mm=80.0, q=0.05, effort="quick", quiet=True)
    X, Y = np.meshgrid(xs, ys)
    return np.asarray(prof.best_focus_um(X, Y, "Y")) - truth["z_best_um"], step


def test_fieldcal_best_focus_on_cleanroom_symmetric_lens(symmetric_calibration):
    """Over the whole field (corners included), fieldcal's best focus is within 0.1 step (RMS) of the
    clean-room truth and unbiased to 0.05 step."""
    err, step = symmetric_calibration
    assert np.sqrt(np.mean(err ** 2)) <= 0.1 * step, (err / step).round(3)
    assert abs(err.mean()) <= 0.05 * step, (err / step).round(3)
