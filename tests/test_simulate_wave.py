"""The wave-optics path against closed forms: diffraction MTF, Hopkins' defocus OTF, the geometric limit, the
ray-error sign, spherical aberration's best focus and asymmetry; the renderer and truth built on it."""

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import special
from scipy.optimize import minimize_scalar

from hopkins_util import hopkins_otf
from fieldcal.errors import SpecError
from fieldcal.simulate import Renderer
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import TruthProfile
from fieldcal.simulate.wave import (ChannelOptics, WaveTerms, best_focus_shift_table, monochromatic_psf,
                                    terms_at, wavefront_um)

REPO = Path(__file__).resolve().parents[1]
LAM_NM, N = 550.0, 2.0


def make_spec(w=64, h=64, pitch_um=2.0, f_number=N, aberrations=None, mono=True, **kw) -> LensSpec:
    """Flat-field, telecentric test lens, float output, no noise; one wavelength unless ``mono=False``."""
    d = {"format": "fieldcal-lens/1", "name": "wave-test", "focal_length_mm": 10.0, "f_number": f_number,
         "image_height_max_mm": math.hypot(w, h) * pitch_um / 2000.0,
         "channels": [{"name": "G", "wavelength_nm": LAM_NM}],
         "sensor": {"width_px": w, "height_px": h, "pixel_pitch_um": pitch_um, "bit_depth": 32,
                    "black_level_dn": 0, "read_noise_e": 0.0, "full_well_e": 10000},
         "residual_blur_um": 0.0}
    ab = dict(aberrations or {})
    if mono:
        ab.setdefault("spectral_response", {"G": [[LAM_NM, 1.0]]})
    d["aberrations"] = ab
    d.update(kw)
    return LensSpec.from_dict(d)


def otf_on_axis(w020_waves: float, n_p: int = 128, n_fft: int = 512, lam_nm=LAM_NM):
    """OTF along fx at the FFT bins s = k / n_p (exact samples of the discrete pupil autocorrelation)."""
    lam_um = lam_nm * 1e-3
    spacing = lam_um * N * n_p / n_fft
    w020 = w020_waves * lam_um
    p = monochromatic_psf(lam_nm, N, spacing, n_fft, lambda u, v: w020 * (u * u + v * v))
    o = np.fft.fft2(np.fft.ifftshift(p))
    k = np.arange(n_p + 1)
    return k / n_p, o[0, k]


# ------------------------------------------------------------------------------------------ closed forms
def test_ray_error_sign_convention():
    """eps = -2 N grad W: a tilt W = t u moves the PSF to x = -2 N t (the convention docs/simulator.md states)."""
    n, sp, t = 512, 0.2, 1.0
    p = monochromatic_psf(LAM_NM, N, sp, n, lambda u, v: t * u + 0.0 * v)
    x = (np.arange(n) - n // 2) * sp
    assert (p.sum(axis=0) * x).sum() == pytest.approx(-2 * N * t, abs=0.02)
    assert abs((p.sum(axis=1) * x).sum()) < 1e-6
    assert p.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("n_p,tol", [(128, 0.006), (256, 0.003)])
def test_diffraction_limited_mtf_matches_closed_form(n_p, tol):
    s, otf = otf_on_axis(0.0, n_p=n_p, n_fft=4 * n_p)
    ref = (2 / np.pi) * (np.arccos(s) - s * np.sqrt(1 - s * s))
    assert np.max(np.abs(otf.real - ref)) < tol  # measured 0.0047 / 0.0024: the pupil edge's discretisation
    assert np.max(np.abs(otf.imag)) < 1e-6
    assert abs(otf[-1]) < 1e-6  # cut-off at 1 / (lambda N)


@pytest.mark.parametrize("w020_waves", [0.25, 0.5, 1.0, 2.0])
def test_defocus_otf_matches_hopkins(w020_waves):
    s, otf = otf_on_axis(w020_waves)
    ref = np.array([hopkins_otf(float(v), w020_waves) for v in s])
    assert np.max(np.abs(otf.real - ref)) < 0.006  # measured <= 0.0047 (same discretisation as in focus)


def test_large_defocus_approaches_the_geometric_disc():
    """At many waves of defocus the OTF tends to 2 J1(pi b f)/(pi b f), b = |dz| / N (the geometric path)."""
    errs = []
    for w020_waves in (10.0, 20.0):
        s, otf = otf_on_axis(w020_waves, n_p=512, n_fft=2048)
        dz_um = 8 * N * N * w020_waves * LAM_NM * 1e-3
        x = np.pi * (dz_um / N) * s / (LAM_NM * 1e-3 * N)
        geo = 2 * special.j1(np.maximum(x, 1e-9)) / np.maximum(x, 1e-9)
        errs.append(np.max(np.abs(otf.real - geo)[s <= 0.25]))
    assert errs[1] < errs[0] < 0.03  # measured 0.025, 0.015
    assert errs[1] < 0.02


def test_pixel_kernel_energy_and_width():
    """A kernel sums to 1; its variance is the blur disc's b^2/16 plus the pixel box's p^2/12 per axis."""
    spec = make_spec(pitch_um=4.0)
    opt = ChannelOptics(spec, "G")
    for dz in (0.0, 40.0, 120.0):
        k = opt.kernel(WaveTerms(), dz, 4.0).astype(np.float64)
        assert k.sum() == pytest.approx(1.0, abs=1e-6) and k.shape[0] % 2 == 1
        x = (np.arange(k.shape[0]) - k.shape[0] // 2) * 4.0
        b = dz / N
        # the core (disc + pixel + 8 lambda N of diffraction): the Airy tail's second moment grows with radius
        core = np.abs(x) <= b / 2 + 8 * LAM_NM * 1e-3 * N + 4.0
        lsf = k.sum(axis=0)[core]
        var = (lsf * x[core] ** 2).sum() / lsf.sum()
        if dz >= 40:
            assert var == pytest.approx(b * b / 16 + 16.0 / 12, rel=0.06)
    # energy of the sampled PSF inside the kernel window (the Airy tail beyond 40 lambda N is folded into the kernel)
    sp = LAM_NM * 1e-3 * N / 4
    n = 2 * int(math.ceil(opt.half_extent_um(WaveTerms(), 0.0) / sp)) + 1
    assert opt.psf(WaveTerms(), 0.0, sp, n).sum() > 0.99


# -------------------------------------------------------------------------------- spherical aberration
def test_spherical_aberration_best_focus_at_minus_w040():
    """Primary SA: the Strehl (minimum-RMS) focus is at W020 = -W040, i.e. dz = -8 N^2 W040; the MTF(fs) peak
    lies between paraxial (0) and marginal (-16 N^2 W040) focus, on the same side, for either sign."""
    w040 = 0.5 * LAM_NM * 1e-3
    terms = WaveTerms(w040_um=w040)
    sp, n = LAM_NM * 1e-3 * N / 4, 256

    def strehl(dz):
        return monochromatic_psf(LAM_NM, N, sp, n, lambda u, v: wavefront_um(u, v, dz, N, terms)).max()

    r = minimize_scalar(lambda z: -strehl(z), bounds=(-30, 10), method="bounded", options={"xatol": 1e-3})
    assert r.x == pytest.approx(-8 * N * N * w040, rel=0.01)  # measured -8.808 vs -8.800
    opt = ChannelOptics(make_spec(), "G")
    for sign in (1, -1):
        t = WaveTerms(w040_um=sign * w040)
        for fs in (20.0, 80.0):
            z = opt.best_focus_shift_um(t, fs)
            assert 0 < -sign * z < 16 * N * N * w040  # measured -11.3 (20 cy/mm), -10.2 (80)


def test_spherical_aberration_makes_through_focus_asymmetric():
    """W040 > 0 (under-corrected): bright rim on the lens side of best focus, bright core beyond it, and the
    MTF falls more slowly beyond it; W040 < 0 mirrors both."""
    opt = ChannelOptics(make_spec(), "G")
    w040 = 1.0 * LAM_NM * 1e-3
    sp = LAM_NM * 1e-3 * N / 3
    for sign in (1, -1):
        t = WaveTerms(w040_um=sign * w040)
        z0 = opt.best_focus_shift_um(t, 80.0)
        d = 16 * N * N * w040  # the spread of the SA foci (paraxial to marginal)
        lens_side, far_side = opt.mtf(t, z0 - sign * d / 2, 80.0), opt.mtf(t, z0 + sign * d / 2, 80.0)
        assert far_side - lens_side > 0.04  # measured 0.519 vs 0.459
        lens_side, far_side = opt.mtf(t, z0 - sign * 0.75 * d, 80.0), opt.mtf(t, z0 + sign * 0.75 * d, 80.0)
        assert far_side - lens_side > 0.1  # measured 0.285 vs 0.132

        def rim_fraction(dz):
            n = 2 * int(math.ceil(opt.half_extent_um(t, dz) / sp)) + 1
            p = opt.psf(t, dz, sp, n)
            x = (np.arange(n) - n // 2) * sp
            r = np.hypot(x[None, :], x[:, None])
            r_edge = np.sqrt((p * r * r).sum() * 2)  # the uniform disc has <r^2> = R^2 / 2
            return p[(r > 0.7 * r_edge) & (r < 1.2 * r_edge)].sum() / p[r < 0.4 * r_edge].sum()

        rim_lens, rim_far = rim_fraction(z0 - sign * 2 * d), rim_fraction(z0 + sign * 2 * d)
        assert rim_lens - rim_far > 0.2


# ----------------------------------------------------------------------------------- renderer and truth
def test_wave_render_is_the_kernel_convolution_at_a_level():
    """No field dependence (flat field, no aberrations) and a defocus on a ladder level: the frame is the scene
    convolved with that one kernel (the blend of nodes and levels adds nothing)."""
    spec = make_spec(w=48, h=40, pitch_um=4.0)
    rng = np.random.default_rng(1)
    scene = rng.uniform(0.1, 0.9, (40, 48)).astype(np.float32)
    r = Renderer(spec, scene, optics="wave")
    dz = 0.5 * 1.25 ** 3 * N * 4.0  # level 4 of the ladder (floor 0.5 px, ratio 1.25)
    img = r.render_float(dz)[:, :, 0] / np.float32(r.exposure)
    ker = ChannelOptics(spec, "G").kernel(WaveTerms(), dz, 4.0)
    ref = cv2.filter2D(scene, cv2.CV_32F, ker[::-1, ::-1].copy(), borderType=cv2.BORDER_REFLECT)
    assert np.max(np.abs(img - ref)) < 1e-4
    with pytest.raises(Exception, match="optics"):
        Renderer(spec, scene, optics="ray")


def test_rendered_sharpest_position_is_the_truth_best_focus():
    """Frames of a white-noise scene through a lens with spherical aberration: the z where the frame's contrast
    at fs peaks is TruthProfile(optics="wave").best_focus_um, not the lens's (paraxial) surface."""
    w040 = 0.5
    spec = make_spec(w=64, h=64, pitch_um=2.0, aberrations={"unit": "um", "spherical": [w040]})
    fs = 80.0
    truth = TruthProfile(spec, optics="wave", fs_cyc_per_mm=fs)
    z_best = float(truth.best_focus_um(32, 32, "G"))
    z_ref = float(truth.reference_focus_um(32, 32, "G"))
    assert z_ref == pytest.approx(0.0, abs=1e-9)
    assert -16 * N * N * w040 < z_best < -1.0  # the sharpest position is on the marginal side
    scene = np.random.default_rng(0).uniform(0, 1, (64, 64)).astype(np.float32)
    r = Renderer(spec, scene, optics="wave", fs_cyc_per_mm=fs)
    fy, fx = np.meshgrid(np.fft.fftfreq(64), np.fft.fftfreq(64), indexing="ij")
    f = np.hypot(fx, fy) / (2.0e-3)  # cycles/mm
    band = np.abs(f - fs) < 12
    s0 = np.abs(np.fft.fft2(scene - scene.mean())) ** 2

    def contrast(z):
        img = r.render_float(z)[:, :, 0]
        return math.sqrt((np.abs(np.fft.fft2(img - img.mean())) ** 2)[band].sum() / s0[band].sum())

    zs = z_best + np.array([-6.0, -3.0, 0.0, 3.0, 6.0])
    c = np.array([contrast(z) for z in zs])
    assert np.argmax(c) == 2
    a, b, _ = np.polyfit(zs, c, 2)
    assert -b / (2 * a) == pytest.approx(z_best, abs=1.0)
    # and the paraxial surface is clearly less sharp than the truth
    assert contrast(z_ref) < c[2] - 0.02


def test_truth_without_spherical_aberration_is_the_surface():
    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json").with_sensor_size(64, 36)
    t_w = TruthProfile(spec, optics="wave")
    t_g = TruthProfile(spec)
    x, y = np.array([5.0, 32.0, 60.0]), np.array([3.0, 18.0, 30.0])
    for c in spec.channel_names:  # astigmatism alone is symmetric through focus
        assert np.allclose(t_w.best_focus_um(x, y, c), t_g.best_focus_um(x, y, c), atol=1e-9)
    with pytest.raises(ValueError):
        TruthProfile(spec, optics="ray")


def test_field_terms_follow_the_spec():
    spec = make_spec(aberrations={"unit": "waves", "reference_wavelength_nm": 500, "spherical": [1.0],
                                  "coma": [0, 0.2], "astigmatism": [0, 0, 0.4]},
                     channels=[{"name": "G", "wavelength_nm": LAM_NM, "astigmatism_um": 8.0}])
    t = terms_at(spec, "G", 0.5, 0.3)
    assert t.w040_um == pytest.approx(0.5)
    assert t.w131_um == pytest.approx(0.2 * 0.5 * 0.5)
    assert t.wast_um == pytest.approx(0.4 * 0.25 * 0.5 - 8.0 * 0.25 / (16 * N * N))
    assert t.phi_rad == 0.3
    # the astigmatism_um convention: tangential focus at +A rho^2 / 2 (where t-direction defocus cancels)
    a = 8.0 * 0.25
    plain = make_spec(channels=[{"name": "G", "wavelength_nm": LAM_NM, "astigmatism_um": 8.0}])
    tt = terms_at(plain, "G", 0.5, 0.0)
    w = wavefront_um(np.array([1.0]), np.array([0.0]), a / 2, N, tt)  # tangential marginal ray at dz = +A/2
    assert w[0] == pytest.approx(0.0, abs=1e-12)


def test_best_focus_shift_table_over_field():
    spec = make_spec(aberrations={"unit": "um", "spherical": [0.3, 0.0, 0.3]})
    rho, shift = best_focus_shift_table(spec, "G", 80.0)
    assert rho[0] == 0 and rho[-1] >= 0.98  # up to the corner pixel centres
    assert np.all(np.diff(shift) < 0)  # more SA towards the edge -> further towards the lens


# ------------------------------------------------------------------------------------ spec and command
def test_aberrations_block_validation_and_round_trip(tmp_path):
    base = json.loads((REPO / "models" / "triplet-uncorrected.json").read_text())
    assert "aberrations" not in LensSpec.from_dict(base).to_dict()  # older specs load and save unchanged
    for bad, field in [({"unit": "mm"}, "aberrations.unit"), ({"spherical": "big"}, "aberrations.spherical"),
                       ({"sphercal": [1]}, "aberrations.sphercal"),
                       ({"spectral_response": {"Q": [[500, 1]]}}, "aberrations.spectral_response.Q"),
                       ({"spectral_response": {"G": [[500, -1]]}}, "aberrations.spectral_response.G"),
                       ([1, 2], "aberrations")]:
        with pytest.raises(SpecError) as e:
            LensSpec.from_dict({**base, "aberrations": bad}, path=tmp_path / "x.json")
        assert field in str(e.value) and "x.json" in str(e.value)
    good = {**base, "aberrations": {"unit": "um", "spherical": [0.5], "coma": [0, 0.1]}}
    spec = LensSpec.from_dict(good)
    assert LensSpec.from_dict(spec.to_dict()) == spec


def test_meridional_trace_matches_a_single_refracting_sphere():
    """Real-ray axis crossing of one spherical surface against the exact formula: a ray at height h meets the
    sphere at sin i = h / R, leaves at sin i' = sin i / n and crosses the axis R sin i' / sin(i - i') beyond
    the centre of curvature (the paraxial limit is n R / (n - 1))."""
    from fieldcal.raytrace.meridional import axis_crossing_um
    from fieldcal.raytrace.prescription import LINE_D_NM, Prescription, Surface
    r_mm, n, back = 20.0, 1.5168, 58.0
    rx = Prescription((Surface("stop", "standard", math.inf, 0.0, is_stop=True),
                       Surface("1", "standard", r_mm, back, nd=n, vd=64.17)))
    n_d = rx.index(1, LINE_D_NM)
    for h in (0.01, 2.0, 5.0, 8.0):
        i = math.asin(h / r_mm)
        ip = math.asin(math.sin(i) / n_d)
        z_mm = r_mm + r_mm * math.sin(ip) / math.sin(i - ip)
        assert axis_crossing_um(rx, h, LINE_D_NM) == pytest.approx((z_mm - back) * 1000.0, abs=1e-6)


def test_wave_best_focus_against_the_ray_traced_triplet():
    """Independent of optiland: paraxial focus (y-nu trace) + spherical aberration (real meridional rays, numpy)
    + the wave path's MTF peak predict the optiland-traced on-axis best focus of docs/raytrace.md (80 cy/mm);
    models/triplet-wave-sa.json holds those terms and follows the traced G curve over the field."""
    from fieldcal.raytrace.meridional import spherical_aberration
    from fieldcal.raytrace.prescription import load_prescription
    rx = load_prescription(REPO / "models" / "triplet-uncorrected.prescription.csv")
    spec = LensSpec.load(REPO / "models" / "triplet-wave-sa.json")
    traced_axis = {"R": 10.1, "G": -5.7, "B": -6.7}  # docs/raytrace.md, h = 0
    for c in spec.channel_names:
        sa = spherical_aberration(rx, spec.channel(c).wavelength_nm, spec.f_number)
        assert abs(sa.la_um[0]) < 0.05  # the smallest zone converges to the paraxial focus
        t = terms_at(spec, c, 0.0, 0.0)
        assert (t.w040_um, t.w060_um) == pytest.approx((sa.w040_um, sa.w060_um), abs=1e-4)  # the model file's source
        z = sa.paraxial_focus_um + ChannelOptics(spec, c).best_focus_shift_um(t, 80.0)
        assert z == pytest.approx(traced_axis[c], abs=1.5)  # measured +0.74, +0.83, +0.82 µm
    spec0 = LensSpec.from_dict({**spec.to_dict(), "stage_axis_tilt_mrad": [0, 0], "exit_pupil_mm": None})
    t0 = TruthProfile(spec0, optics="wave", fs_cyc_per_mm=80.0)  # no breathing: image height fixed through focus
    cx, cy = spec0.optical_centre_px()
    p = spec0.sensor.pixel_pitch_um / 1000.0
    ang = math.atan2(9, 16)
    plain = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")  # the traced best-focus polynomial
    offsets = []
    for h, z in {0.0: -5.7, 0.9: -24.3, 1.8: -80.5, 2.7: -177.3, 3.6: -321.3}.items():  # traced G
        zb = float(t0.best_focus_um(cx + h * math.cos(ang) / p, cy + h * math.sin(ang) / p, "G"))
        assert zb == pytest.approx(z, abs=3.0)  # measured +0.8 .. +2.7 (the polynomial is 1.7 µm off at the edge)
        offsets.append(zb - float(plain.best_focus_um(h * math.cos(ang), h * math.sin(ang), "G")))
    assert np.ptp(offsets) < 0.5  # the SA shift hardly varies over the field: the spec's surface shape holds
    shift = float(t0.reference_focus_um(cx, cy, "G") - t0.best_focus_um(cx, cy, "G"))
    w = terms_at(spec, "G", 0.0, 0.0)
    assert 8 * N * N * (w.w040_um + 0.9 * w.w060_um) < shift < 16 * N * N * (w.w040_um + w.w060_um)


def test_simulate_command_wave(tmp_path):
    from fieldcal.cli import main
    out = tmp_path / "st"
    rc = main(["simulate", str(REPO / "models" / "triplet-wave-sa.json"), str(out), "--z", "-20", "0", "20",
               "--size", "96x54", "--optics", "wave", "--fs", "10", "--quiet"])
    assert rc == 0
    t = json.loads((out / "truth.json").read_text())
    assert t["optics"] == "wave" and t["renderer"]["optics"] == "wave"
    bf = t["best_focus"]
    assert bf["fs_cyc_per_mm"] == 10.0 and set(bf["shift_um"]) == {"R", "G", "B"}
    assert all(-35 < v < -15 for v in bf["shift_um"]["G"])
    assert "aberrations" in t["lens"]


def test_wave_reuses_the_sensor_chain():
    """Bayer mosaic, noise and quantisation are the geometric path's: same shapes and dtypes, and the noise
    variance of a flat grey frame is g^2 (e + read^2) + 1/12 as in docs/simulator.md."""
    spec = LensSpec.from_dict({**json.loads((REPO / "models" / "triplet-wave-sa.json").read_text()),
                               "relative_illumination_edge": 1.0}).with_sensor_size(96, 54)
    d = spec.to_dict()
    d["sensor"]["cfa"] = "RGGB"
    bayer = LensSpec.from_dict(d)
    scene = np.random.default_rng(0).uniform(0.2, 0.8, (54, 96, 3)).astype(np.float32)
    r = Renderer(bayer, scene, optics="wave", fs_cyc_per_mm=10.0)
    assert r.render(-40.0).shape == (54, 96) and r.truth().shape == (54, 96, 3)
    flat = Renderer(spec, np.full((54, 96), 0.5, np.float32), optics="wave", fs_cyc_per_mm=10.0)
    noisy = flat.render(-40.0).astype(np.float64)
    clean = flat.render(-40.0, noise=False).astype(np.float64)
    s = spec.sensor
    g = (s.white_level_dn - s.black_level_dn) / s.full_well_e
    e = (clean.mean() - s.black_level_dn) / g
    assert np.var(noisy - clean) == pytest.approx(g * g * (e + s.read_noise_e ** 2) + 1 / 12, rel=0.1)


def test_wave_frames_do_not_depend_on_render_order():
    spec = make_spec(w=40, h=32, pitch_um=4.0, aberrations={"unit": "um", "spherical": [0.4], "coma": [0, 0.2]},
                     channels=[{"name": "G", "wavelength_nm": LAM_NM, "curvature_um": [-60.0],
                                "astigmatism_um": 10.0}])
    scene = np.random.default_rng(3).uniform(0, 1, (32, 40)).astype(np.float32)
    a = Renderer(spec, scene, optics="wave", seed=5)
    b = Renderer(spec, scene, optics="wave", seed=5)
    a.render(-120.0)  # fills the caches (kernels, a larger padding) first
    assert np.array_equal(a.render(-10.0), b.render(-10.0))


def _sa_channel(pitch_um: float, fs: float, f_number: float, w040_waves: float):
    """G of a 32 px lens with spherical aberration only: its optics, its on-axis terms and the fs-contrast peak."""
    spec = make_spec(w=32, h=32, pitch_um=pitch_um, f_number=f_number,
                     aberrations={"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [w040_waves]})
    opt = ChannelOptics(spec, "G")
    terms = terms_at(spec, "G", 0.0, 0.0)
    return opt, terms, opt.best_focus_shift_um(terms, fs)


def test_pixel_kernels_keep_the_fs_contrast_peak_of_a_flat_topped_spherical_aberration_curve():
    """Large pixels, low fs, W040 = 0.75 waves: contrast at fs changes by only ~1 % over +-10 µm about its peak,
    so a kernel whose MTF steps when its window grows with defocus moves the rendered peak by microns (the
    8 lambda N window did: 3.6 µm). The kernels' orientation-averaged MTF at fs, divided by the pixel
    aperture, follows the optical MTF smoothly and peaks where the truth says."""
    pitch, fs, n = 15.0, 13.0, 2.85
    opt, terms, z0 = _sa_channel(pitch, fs, n, 0.75)
    dz = z0 + np.arange(-15.0, 15.1, 5.0)
    m = np.array([_kernel_mtf_at(opt, terms, float(d), pitch, fs) for d in dz])
    opt_m = np.array([opt.mtf(terms, float(d), fs) for d in dz])
    # the kernels' DFT is the exact OTF at the grid frequencies; at fs, between them, the kernel's finite window
    # leaves ~4e-4 (measured), flat in dz; the shape must follow the optics (a step of 0.3 % at single defocus
    # steps from the window's growth was the defect; the sampled pupil's edge added ~0.55 % before)
    ratio = m / opt_m
    assert abs(ratio.mean() - 1.0) < 1e-3
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=5e-5)
    c = np.polyfit(dz - z0, m, 2)
    assert abs(-c[1] / (2 * c[0])) < 0.05  # measured 0.009 µm


def test_truth_sharpest_position_is_the_smooth_peak_not_the_noisy_argmax():
    """At low fs the top of the MTF(fs) curve is flat (~2e-3 over +-8 µm) and its computed values carry ~1e-4 of
    sampling noise: the sharpest position is the peak of the smooth curve. Fits over other windows and orders
    agree with it to 0.15 µm (the argmax had wandered 0.6 µm from them)."""
    pitch, fs, n = 15.0, 13.0, 2.1
    opt, terms, z0 = _sa_channel(pitch, fs, n, 0.8)
    dof = 1000.0 * n / (math.pi * fs)
    for half, deg in ((0.3, 2), (0.7, 4), (1.0, 4)):
        d = z0 + dof * np.linspace(-half, half, 21)
        m = np.array([opt.mtf(terms, float(x), fs) for x in d])
        c = np.polyfit(d - z0, m, deg)
        r = np.roots(np.polyder(c))
        r = r[np.abs(r.imag) < 1e-9].real
        assert abs(r[np.argmin(np.abs(r))]) < 0.15, (half, deg)


# ------------------------------------------------------------------------- kernels = the exact OTF
def _kernel_otf(ker: np.ndarray, pitch_um: float, sigma_um: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's DFT with the pixel aperture (sinc) and the residual Gaussian divided out, and the grid's
    frequencies (cycles/µm, rows fy, columns fx)."""
    k = ker.shape[0]
    f = np.fft.fftfreq(k)
    dft = np.fft.fft2(np.fft.ifftshift(ker.astype(np.float64)))
    fr = np.hypot(f[:, None], f[None, :]) / pitch_um
    div = np.sinc(f)[:, None] * np.sinc(f)[None, :] * np.exp(-2.0 * (np.pi * sigma_um * fr) ** 2)
    return dft / div, fr


@pytest.mark.parametrize("w040_waves", [0.0, 0.5])
@pytest.mark.parametrize("dz_um", [-20.0, 0.0, 35.0])
def test_kernel_dft_is_the_exact_polychromatic_otf_at_the_grid_frequencies(w040_waves, dz_um):
    """A rotationally symmetric pupil, a three-wavelength band, a residual Gaussian: the rendered kernel's DFT,
    pixel sinc and Gaussian divided out, is the band's summed pupil OTF (:func:`fieldcal.optics.pupil.otf`, one
    radius at a time) at every frequency of the pixel grid (it was the DFT of a sampled PSF, ~6e-3 off)."""
    from fieldcal.optics import pupil

    pitch, n_f, sigma = 4.0, 2.8, 1.0
    spec = make_spec(pitch_um=pitch, f_number=n_f, mono=False, residual_blur_um=sigma,
                     aberrations={"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [w040_waves]})
    opt = ChannelOptics(spec, "G")
    terms = terms_at(spec, "G", 0.0, 0.0)
    got, fr = _kernel_otf(opt.kernel(terms, dz_um, pitch), pitch, sigma)
    assert len(opt.band) == 3
    exact = np.zeros_like(fr)
    for r in np.unique(fr):
        exact[fr == r] = sum(w * float(pupil.otf(r * l_nm * 1e-3 * n_f, dz_um / (8 * n_f * n_f * l_nm * 1e-3),
                                                 terms.w040_um / (l_nm * 1e-3))) for l_nm, w in opt.band)
    assert np.max(np.abs(got - exact)) < 1e-3
    assert np.max(np.abs(got.imag)) < 1e-5  # symmetric pupil: a real OTF, a symmetric kernel


def test_asymmetric_kernel_dft_is_the_pupil_autocorrelation_and_mirrors_with_the_field():
    """Coma and astigmatism: the kernel's DFT is the band's complex 2-D pupil autocorrelation at the grid
    frequencies; coma's OTF is complex (a one-sided PSF)."""
    pitch, n_f = 4.0, 2.8
    spec = make_spec(pitch_um=pitch, f_number=n_f, mono=False)
    opt = ChannelOptics(spec, "G")
    terms = WaveTerms(w040_um=0.1, w131_um=0.3, wast_um=0.2, phi_rad=0.6)
    ker = opt.kernel(terms, 10.0, pitch)
    got, _ = _kernel_otf(ker, pitch, 0.0)
    f = np.fft.fftfreq(ker.shape[0]) / pitch
    fy, fx = np.meshgrid(f, f, indexing="ij")
    want = opt._general_otf(terms, 10.0, fx, fy)
    assert np.max(np.abs(want.imag)) > 0.02
    assert np.max(np.abs(got - want)) < 1e-3


def _kernel_mtf_at(opt, terms, dz_um: float, pitch_um: float, fs_cyc_per_mm: float, scale: float = 1.0) -> float:
    """Orientation-averaged transfer of a rendered kernel at fs (its DTFT: fs is between grid frequencies),
    pixel aperture divided out."""
    k = opt.kernel(terms, dz_um, pitch_um, scale).astype(np.float64)
    f = fs_cyc_per_mm * pitch_um * scale * 1e-3  # cycles per kernel pixel
    x = np.arange(k.shape[0]) - k.shape[0] // 2
    ang = np.arange(24) * np.pi / 24
    return float(np.mean([abs((k * np.exp(-2j * np.pi * f * (np.cos(a) * x[None, :] + np.sin(a) * x[:, None]))).sum())
                          / (np.sinc(f * np.cos(a) / scale) * np.sinc(f * np.sin(a) / scale)) for a in ang]))


def _smooth_peak(fn, z0: float, width: float) -> float:
    """Peak of a quartic fit to fn over z0 +- width / 2 (17 points)."""
    d = np.linspace(-0.5, 0.5, 17)
    c = np.polyfit(d, [fn(z0 + v * width) for v in d], 4)
    r = np.roots(np.polyder(c))
    r = r[(np.abs(r.imag) < 1e-9) & (np.polyval(np.polyder(c, 2), r.real) < 0)].real
    return float(z0 + r[np.argmin(np.abs(r))] * width)


@pytest.mark.parametrize("f_number,w040_waves,ast_waves", [(2.9, 0.5, 0.0), (1.6, 0.3, 0.6)])
def test_rendered_kernels_peak_where_the_wave_truth_does(f_number, w040_waves, ast_waves):
    """15 µm pixels, fs = 13 cycles/mm, a three-wavelength band: the kernels' MTF(fs) through focus (their DTFT,
    pixel aperture divided out) peaks at TruthProfile(optics="wave")'s sharpest position within 0.05 µm.
    Kernels from the sampled PSF's DFT peaked 0.68 µm (F/2.9, SA) and 0.58 µm (F/1.6, SA + astigmatism) off."""
    pitch, fs = 15.0, 13.0
    ab = {"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [w040_waves]}
    if ast_waves:
        ab["astigmatism"] = [ast_waves]
    spec = make_spec(w=32, h=32, pitch_um=pitch, f_number=f_number, mono=False, aberrations=ab)
    truth = TruthProfile(spec, optics="wave", fs_cyc_per_mm=fs)
    x, y = 20.0, 27.0  # off-axis: the astigmatism's azimuth is not along a pixel axis
    z_best = float(truth.best_focus_um(x, y, "G"))
    opt = ChannelOptics(spec, "G")
    xm, ym = spec.pixel_to_mm(x, y)
    terms = terms_at(spec, "G", float(spec.rho(xm, ym)), math.atan2(y - 15.5, x - 15.5))
    if not ast_waves:
        assert terms.wast_um == 0.0 and terms.w131_um == 0.0
    else:
        assert terms.wast_um != 0.0
    dof = 1000.0 * f_number / (math.pi * fs)
    z_k = _smooth_peak(lambda d: _kernel_mtf_at(opt, terms, d, pitch, fs), z_best, dof)
    assert z_k == pytest.approx(z_best, abs=0.05)


def test_kernel_scale_shrinks_the_psf_for_the_magnifying_warp():
    """The renderer blurs and then magnifies by a: a kernel made with scale a has the transfer function
    OTF(g / (a p)) sinc(g / a) at g cycles per scene pixel, so after the warp the frame has the sensor's own."""
    pitch = 4.0
    spec = make_spec(pitch_um=pitch, f_number=2.8, mono=False,
                     aberrations={"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [0.4]})
    opt = ChannelOptics(spec, "G")
    terms = terms_at(spec, "G", 0.0, 0.0)
    for dz in (-15.0, 10.0):
        for fs in (40.0, 90.0):
            want = opt.mtf(terms, dz, fs)
            assert _kernel_mtf_at(opt, terms, dz, pitch, fs, 1.01) == pytest.approx(want, abs=2e-3)
            # unscaled, the warp would give OTF(1.01 f): measurably different at 90 cycles/mm
    assert abs(_kernel_mtf_at(opt, terms, 10.0, pitch, 90.0 * 1.01) - opt.mtf(terms, 10.0, 90.0)) > 2e-3


def test_renderer_kernels_follow_the_frame_scale():
    """WaveBlur caches kernels at a = 1 and 1.01 and takes the line through them for a frame's scale a: exact at
    a = 1; within 4e-4 of the exact shrunk kernel's transfer function for |a - 1| <= 0.02 (SA, astigmatism and
    coma, nodes mirrored or not)."""
    from fieldcal.simulate.wave import WaveBlur

    ab = {"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [0.3], "astigmatism": [0.5],
          "coma": [0.3]}
    spec = make_spec(w=48, h=40, pitch_um=4.0, f_number=2.8, mono=False, aberrations=ab)
    wb = WaveBlur(spec, np.zeros((40, 48, 1), np.float32), 1.25, 0.5, 60.0)
    for j, i in ((0, 0), (1, 2)):
        terms = wb._node_terms["G", j, i]
        fx, fy = wb._node_flip["G", j, i]
        for k in (-3, 0, 6):
            dz = wb._centre_um("G", j, i) + wb._level_dz_um(k)
            for a in (0.98, 1.0, 1.02):
                got = wb.kernel("G", j, i, k, a).astype(np.float64)
                ref = wb.optics["G"].kernel(terms, dz, 4.0, a, size=got.shape[0]).astype(np.float64)
                ref = ref[::-1 if fy else 1, ::-1 if fx else 1]
                err = np.abs(np.fft.fft2(got) - np.fft.fft2(ref)).max()
                assert err < (1e-6 if a == 1.0 else 4e-4), (j, i, k, a, err)


def test_breathing_frames_warp_the_scene_then_blur_at_the_sensor(monkeypatch):
    """The renderer warps the scene by its frame's scale a = m(z) (1 + lateral colour) and hands the wave blur that
    warped scene with scale 1 (the sensor's own kernels, each sensor pixel at its own defocus); the truth image
    (no breathing) is warped by the lateral colour only (docs/simulator.md "warp, then blur")."""
    from fieldcal.simulate.warp import scale_shift
    from fieldcal.simulate.wave import WaveBlur

    spec = make_spec(w=40, h=32, pitch_um=4.0, exit_pupil_mm=12.0,
                     channels=[{"name": "G", "wavelength_nm": LAM_NM, "lateral_colour": 0.002}])
    seen = []
    orig = WaveBlur.blur

    def spy(self, channel, defocus_um, scale=1.0, scene=None):
        seen.append((scale, scene))
        return orig(self, channel, defocus_um, scale, scene)

    monkeypatch.setattr(WaveBlur, "blur", spy)
    r = Renderer(spec, np.random.default_rng(2).uniform(0, 1, (32, 40)).astype(np.float32), optics="wave")
    cx, cy = r.centre_px
    for z, a in ((-60.0, float(spec.magnification(-60.0)) * 1.002), (45.0, float(spec.magnification(45.0)) * 1.002),
                 (None, 1.002)):
        r.render_float(z) if z is not None else r.truth()
        scale, scene = seen[-1]
        assert scale == 1.0
        sx, sy = (float(v) for v in spec.shift_px(z)) if z is not None else (0.0, 0.0)
        np.testing.assert_allclose(scene, scale_shift(r.scene[:, :, 0], a, cx - a * cx + sx, cy - a * cy + sy),
                                   atol=1e-6)


def test_breathing_stripes_have_the_sensor_otf_at_the_sensor_frequency():
    """As the geometric path's test: stripes of scene frequency g, magnified by a = m(z) = 1.05 and more, reach
    the sensor at g / a, and their contrast there is the wave truth's MTF at g / a times the pixel aperture's
    sinc, not the value of the PSF magnified with the scene (F/8, SA; measured within 2.4e-3, the old order
    0.015-0.025 off)."""
    from tests.test_simulate import stripes

    w, h, pitch, cycles = 128, 64, 5.0, 40  # 0.31 cycles/px of the scene
    spec = make_spec(w=w, h=h, pitch_um=pitch, f_number=8.0, exit_pupil_mm=2.0, mono=False,
                     aberrations={"unit": "waves", "reference_wavelength_nm": LAM_NM, "spherical": [0.5]},
                     channels=[{"name": "G", "wavelength_nm": LAM_NM, "focus_offset_um": 100.0}])
    r = Renderer(spec, stripes(w, h, cycles, lo=0.3, hi=0.7)[:, :, None], optics="wave")
    opt = ChannelOptics(spec, "G")
    terms = terms_at(spec, "G", 0.0, 0.0)
    c = (w - 1) / 2.0
    p = np.arange(24, w - 24)
    for dz in (-30.0, 0.0, 25.0):
        z = 100.0 + dz
        a = float(spec.magnification(z))
        row = r.render_float(z)[:, :, 0].mean(axis=0)[24:w - 24] / r.exposure
        arg = 2 * np.pi * cycles * (c + (p - c) / a) / w
        basis = np.stack([np.ones_like(arg), np.cos(arg), np.sin(arg)], axis=1)
        got = float(np.hypot(*np.linalg.lstsq(basis, row, rcond=None)[0][1:])) / 0.2
        f_px = cycles / w / a
        want = opt.mtf(terms, dz, f_px / (pitch * 1e-3)) * np.sinc(f_px)
        old = opt.mtf(terms, dz, f_px * a / (pitch * 1e-3)) * np.sinc(f_px * a)  # the PSF magnified with the scene
        assert got == pytest.approx(want, abs=0.004), (dz, got, want, old)
        assert abs(old - want) > 0.01
