"""Astigmatism as a field polynomial: lens spec, wave path and truth agree on T - S = A(rho), the astigmatic
triplet follows the traced T - S of docs/raytrace.md, and old scalar documents are unchanged."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fieldcal.errors import FieldcalError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import TruthProfile
from fieldcal.simulate.wave import terms_at

MODELS = Path(__file__).resolve().parents[1] / "models"
# docs/raytrace.md: traced T - S of G at h = 0.45 .. 3.6 mm
TRACE_H_MM = np.arange(1, 9) * 0.45
TRACE_G_UM = np.array([0.5, 2.1, 4.6, 7.8, 11.3, 13.3, 11.3, 5.6])


def _spec_with(astig) -> LensSpec:
    d = LensSpec.load(MODELS / "triplet-uncorrected.json").to_dict()
    for c in d["channels"]:
        c["astigmatism_um"] = astig
    return LensSpec.from_dict(d)


def test_polynomial_splits_tangential_and_sagittal():
    a = [30.0, -12.0, 5.0]
    spec = _spec_with(a)
    h = np.linspace(0.0, spec.image_height_max_mm, 7)
    rho = h / spec.image_height_max_mm
    want = a[0] * rho**2 + a[1] * rho**4 + a[2] * rho**6
    zt = spec.best_focus_um(h, 0.0, "G", "tangential")
    zs = spec.best_focus_um(h, 0.0, "G", "sagittal")
    zm = spec.best_focus_um(h, 0.0, "G")
    np.testing.assert_allclose(zt - zs, want, atol=1e-9)
    np.testing.assert_allclose(0.5 * (zt + zs), zm, atol=1e-9)
    # isotropic equivalent defocus at the mean focus is half the split
    np.testing.assert_allclose(spec.effective_defocus_um(zm, h, 0.0, "G"), 0.5 * np.abs(want), atol=1e-9)


def test_scalar_still_means_rho2_and_round_trips():
    old = LensSpec.load(MODELS / "triplet-uncorrected.json")
    assert old.to_dict()["channels"][0]["astigmatism_um"] == old.channel("R").astigmatism_um  # a number, as before
    assert _spec_with([old.channel("G").astigmatism_um]).channel("G").astigmatism_at(0.7) == pytest.approx(
        old.channel("G").astigmatism_at(0.7))
    poly = _spec_with([30.0, -12.0, 5.0])
    assert poly.to_dict()["channels"][1]["astigmatism_um"] == [30.0, -12.0, 5.0]
    assert LensSpec.from_dict(poly.to_dict()) == poly


def test_bad_astigmatism_is_a_spec_error():
    with pytest.raises(FieldcalError, match="astigmatism_um"):
        _spec_with("lots")
    with pytest.raises(FieldcalError, match="astigmatism_um"):
        _spec_with([])


def test_wave_path_uses_the_polynomial():
    a = [30.0, -12.0, 5.0]
    spec = _spec_with(a)
    for rho in (0.3, 0.75, 1.0):
        t = terms_at(spec, "G", rho, 0.4)
        want = a[0] * rho**2 + a[1] * rho**4 + a[2] * rho**6
        assert t.wast_um == pytest.approx(-want / (16.0 * spec.f_number**2))


def test_truth_gives_tangential_and_sagittal_focus():
    spec = _spec_with([30.0, -12.0, 5.0])
    w, h = 384, 216
    tr = TruthProfile(spec, w, h)
    x = np.array([10.0, 100.0, 300.0, 383.0])
    y = np.array([5.0, 100.0, 150.0, 215.0])
    zt, zs, zm = (tr.best_focus_um(x, y, "G", o) for o in ("tangential", "sagittal", None))
    np.testing.assert_allclose(0.5 * (zt + zs), zm, atol=0.05)
    # with breathing each orientation's focus is the fixed point at its own landing point
    for z, o in ((zt, "tangential"), (zs, "sagittal")):
        xm, ym = tr.spec.pixel_to_mm(*tr.landing_px(x, y, z))  # the truth's spec at its own image size
        np.testing.assert_allclose(z, tr.spec.best_focus_um(xm, ym, "G", o), atol=1e-5)
    xm, ym = tr.spec.pixel_to_mm(x, y)
    assert np.all(np.abs((zt - zs) - spec.channel("G").astigmatism_at(tr.spec.rho(xm, ym))) < 2.0)
    with pytest.raises(FieldcalError, match="orientation"):
        tr.best_focus_um(x, y, "G", "diagonal")


def test_astigmatic_triplet_follows_the_trace():
    spec = LensSpec.load(MODELS / "triplet-astigmatic.json")
    a = spec.best_focus_um(TRACE_H_MM, 0.0, "G", "tangential") - spec.best_focus_um(TRACE_H_MM, 0.0, "G", "sagittal")
    assert np.max(np.abs(a - TRACE_G_UM)) <= 0.6
    # not monotonic: the split peaks inside the field, which a single rho^2 term cannot follow
    assert a.argmax() not in (0, len(a) - 1)
    # the mean surface is the uncorrected triplet's
    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    assert math.isclose(float(spec.best_focus_um(2.0, 1.0, "R")), float(base.best_focus_um(2.0, 1.0, "R")))


def test_fit_follows_a_peaked_astigmatism():
    """T/S rows of the astigmatic triplet (as slanted-edge pairs give them): the surface fit tries the rho^4, rho^6
    astigmatism terms and recovers T - S within 1 µm where one rho^2 term is off by several µm."""
    from fieldcal.fit.select import fit_surfaces
    from fieldcal.fit.synthetic import synthetic_tiles

    spec = LensSpec.load(MODELS / "triplet-astigmatic.json")
    tiles, geom, truth = synthetic_tiles(spec, np.random.default_rng(3), nx=11, ny=7, sigma_um=(0.3, 0.6))
    fit = fit_surfaces(tiles, geom, effort="quick", quiet=True)
    assert fit.model.astig and fit.model.astig_order == 3, fit.model.name
    # over the field the tiles cover (beyond the outermost tile centres the rho^6 term extrapolates)
    x, y = np.meshgrid(np.linspace(tiles.x_px.min(), tiles.x_px.max(), 13),
                       np.linspace(tiles.y_px.min(), tiles.y_px.max(), 7))
    for c in spec.channel_names:
        want = truth.best_focus_um(x, y, c, "tangential") - truth.best_focus_um(x, y, c, "sagittal")
        assert np.max(np.abs(fit.astigmatism_um(x, y, c) - want)) <= 1.0, c


@pytest.mark.parametrize("phi_t, phi_s", [(0.0, 90.0), (20.0, 75.0), (28.0, 62.0)])
def test_pair_of_oblique_edges_gives_tangential_and_sagittal(phi_t, phi_s):
    """An edge at angle phi from the radius peaks at z_mean + (A/2) cos 2 phi: the pair solves back to T and S."""
    from fieldcal.measure.edge_tiles import _ts_from_pair

    zm, a = -120.0, 12.0
    c_t, c_s = math.cos(math.radians(2 * phi_t)), math.cos(math.radians(2 * phi_s))
    z_t, z_s = zm + 0.5 * a * c_t, zm + 0.5 * a * c_s
    got_m, sd, got_t, got_s = _ts_from_pair(z_t, z_s, 1.0, 1.0, c_t, c_s)
    assert got_m == pytest.approx(zm) and got_t == pytest.approx(zm + 0.5 * a) and got_s == pytest.approx(zm - 0.5 * a)
    assert 0.5 * math.sqrt(2.0) - 1e-9 <= sd <= 1.0
