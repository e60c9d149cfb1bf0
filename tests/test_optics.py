"""fieldcal.optics: the MTF criterion, the defocus model, the one integrated sweep OTF/PSF and the LensModel
protocol, against closed forms and independent quadrature."""

import math

import numpy as np
import pytest
from scipy import integrate, special

from fieldcal.errors import ParameterError
from fieldcal.optics import (LensModel, MTFCriterion, defocus_otf, diffraction_mtf, disc_otf, disc_sweep_otf,
                             disc_x_at_contrast, focus_tolerance_um, integrated_otf, sweep_psf_kernel)
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import TruthProfile


# ------------------------------------------------------------------------------------------- criterion
@pytest.mark.parametrize("fs, q, field", [(0.0, 0.05, "fs_cyc_per_mm"), (-3, 0.05, "fs_cyc_per_mm"),
                                          (math.nan, 0.05, "fs_cyc_per_mm"), ("80x", 0.05, "fs_cyc_per_mm"),
                                          (True, 0.05, "fs_cyc_per_mm"), (80.0, 0.0, "q"), (80.0, 1.0, "q"),
                                          (80.0, math.inf, "q"), (80.0, None, "q")])
def test_criterion_rejects_bad_values_naming_the_field(fs, q, field):
    with pytest.raises(ParameterError) as e:
        MTFCriterion(fs, q)
    assert e.value.field == field and e.value.fix


def test_criterion_is_a_frozen_float_value():
    c = MTFCriterion(80, "0.05")
    assert (c.fs_cyc_per_mm, c.q) == (80.0, 0.05) and isinstance(c.fs_cyc_per_mm, float)
    with pytest.raises(AttributeError):
        c.q = 0.1
    assert c == MTFCriterion(80.0, 0.05)
    assert c.nyquist_fraction(5.0) == pytest.approx(0.8)


# --------------------------------------------------------------------------------------------- defocus
def test_focus_tolerance_solves_the_disc_otf():
    for fs, q, n in ((80.0, 0.05, 2.0), (40.0, 0.3, 5.6), (200.0, 0.001, 1.4)):
        t = focus_tolerance_um(MTFCriterion(fs, q), n)
        assert float(defocus_otf(fs, t, n)) == pytest.approx(1.0 - q, abs=1e-10)
        assert float(defocus_otf(fs, 0.999 * t, n)) > 1.0 - q
    # q -> 1: the first zero of J1 (contrast lost entirely)
    assert disc_x_at_contrast(1e-14) == pytest.approx(special.jn_zeros(1, 1)[0])
    # small x: 2 J1(x)/x = 1 - x^2/8 + x^4/192 ...
    x = np.array([1e-6, 1e-5, 0.01])
    np.testing.assert_allclose(disc_otf(x), 1 - x * x / 8 + x ** 4 / 192, rtol=1e-12)


# ------------------------------------------------------------------------------------------ sweep OTF
def test_disc_sweep_otf_closed_form_against_quadrature():
    f = np.array([0.0, 10.0, 80.0, 300.0])
    for a, n in ((3.0, 2.0), (40.0, 2.0), (150.0, 4.0)):
        got = disc_sweep_otf(f, a, n)
        ref = [integrate.quad(lambda dz: float(defocus_otf(fi, dz, n)), -a, a, limit=400)[0] / (2 * a) for fi in f]
        np.testing.assert_allclose(got, ref, atol=1e-9)


@pytest.mark.parametrize("alpha_um", [1.0, 20.0, 60.0, 250.0])
def test_integrated_otf_equals_the_disc_closed_form(alpha_um):
    # the synthetic lens's OTF is the geometric disc alone, so the quadrature must give the closed form,
    # up to the highest frequency a 2 µm pixel passes, also for a wide sweep (many contrast reversals)
    prof = SyntheticProfile(17, 17, f_number=2.0)
    f = np.linspace(0.0, 250.0, 501)
    np.testing.assert_allclose(integrated_otf(prof, f, alpha_um, "G"), disc_sweep_otf(f, alpha_um, 2.0), atol=1e-10)


def test_integrated_otf_of_the_full_model_against_adaptive_quadrature(triplet_path):
    # defocus x diffraction x residual blur of a simulated lens, and a sweep centred off best focus
    p = TruthProfile(LensSpec.load(triplet_path))
    f = np.array([0.0, 40.0, 120.0, 250.0])
    for a, off in ((20.0, 0.0), (80.0, 15.0)):
        h = integrated_otf(p, f, a, "G", offset_um=off)
        ref = [integrate.quad(lambda d: float(p.defocus_otf(np.array([fi]), off + d, "G")[0]), -a, a,
                              limit=400)[0] / (2 * a) for fi in f]
        np.testing.assert_allclose(h, ref, atol=1e-9)
    assert integrated_otf(p, f, 20.0, "G")[0] == pytest.approx(1.0)
    np.testing.assert_allclose(integrated_otf(p, f, 1e-6, "G"), p.defocus_otf(f, 0.0, "G"), atol=1e-9)
    # paper Fig. 6: a wider sweep passes less contrast
    assert np.all(np.abs(integrated_otf(p, f[1:], 40.0, "G")) < np.abs(integrated_otf(p, f[1:], 20.0, "G")))


def test_integrated_otf_agrees_with_both_old_definitions(triplet_path):
    """The planner integrated the F-number model (disc x diffraction x residual blur), the compositor the lens's
    MTF with the disc's sign: for every lens model here both are the model's signed OTF, so the one
    implementation reproduces both (the old versions used 48 and 64 fixed nodes, good to ~1e-6 at α <= 60 µm)."""
    from fieldcal.optics import through_focus_otf
    p = TruthProfile(LensSpec.load(triplet_path))
    f = np.linspace(0.0, 250.0, 126)
    dz = np.linspace(-80, 80, 33)[:, None]
    planner = through_focus_otf(f, dz, p.f_number, p.wavelength_nm("G"), p.spec.residual_blur_um)
    compositor = p.defocus_mtf(f, dz, "G") * np.where(np.sign(defocus_otf(f, dz, p.f_number)) == 0, 1.0,
                                                      np.sign(defocus_otf(f, dz, p.f_number)))
    np.testing.assert_allclose(p.defocus_otf(f, dz, "G"), planner, atol=1e-15)
    np.testing.assert_allclose(p.defocus_otf(f, dz, "G"), compositor, atol=1e-15)
    for a in (5.0, 20.0, 60.0):
        for n in (48, 64):  # the old fixed node counts, through the same function
            np.testing.assert_allclose(integrated_otf(p, f, a, "G", n_nodes=n), integrated_otf(p, f, a, "G"),
                                       atol=1e-6)


def test_sweep_psf_kernel_is_normalised_and_widens():
    prof = SyntheticProfile(17, 17, f_number=2.0)
    k0 = sweep_psf_kernel(prof, 0.0, "G", 5.0, 15)
    k1 = sweep_psf_kernel(prof, 30.0, "G", 5.0, 15)
    for k in (k0, k1):
        assert k.shape == (15, 15) and k.min() >= 0 and k.sum() == pytest.approx(1.0)
        np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-12)
    assert k1[7, 7] < k0[7, 7]


# --------------------------------------------------------------------------------------------- model
def test_every_lens_model_implements_the_protocol(triplet_path, tmp_path):
    from fieldcal.profile.lens_profile import LensProfile
    spec = LensSpec.load(triplet_path)
    assert isinstance(TruthProfile(spec, 64, 48), LensModel)
    assert isinstance(SyntheticProfile(), LensModel)
    assert not isinstance(spec, LensModel)  # works in sensor mm: TruthProfile is its lens model
    from fieldcal.composite.register import EstimatedGeometry
    from fieldcal.optics import FrameGeometry
    assert isinstance(EstimatedGeometry(0.0, (1.0, 1.0), 0.0, (0.0, 0.0), 1), FrameGeometry)
    members = [m for cls in (LensModel, FrameGeometry) for m in
               list(cls.__annotations__) + [m for m in vars(cls) if not m.startswith("_")]]
    assert len(members) > 15
    for m in members:
        assert hasattr(LensProfile, m) or m in LensProfile.__dataclass_fields__, m


def test_profile_defocus_model_matches_the_optics():
    prof = SyntheticProfile(f_number=2.8)
    f = np.array([20.0, 80.0])
    np.testing.assert_allclose(prof.defocus_mtf(f, 30.0, "G"), np.abs(defocus_otf(f, 30.0, 2.8)))
    assert float(diffraction_mtf(0.0, 550.0, 2.0)) == pytest.approx(1.0)


def test_integrated_otf_stays_bounded_for_huge_sweeps():
    # past the node cap the rule is approximate, but only where the sweep passes almost nothing
    prof = SyntheticProfile(17, 17, f_number=2.0)
    f = np.linspace(0.0, 250.0, 11)
    for a in (1e4, 1e5):
        exact = disc_sweep_otf(f, a, 2.0)
        np.testing.assert_allclose(integrated_otf(prof, f, a, "G"), exact, atol=2e-3)
