"""Prescription tables, model glass and the paraxial check: no ray-tracing library needed."""

import json
import math
import sys

import pytest
from hypothesis import given, settings, strategies as st

from fieldcal.cli import main
from fieldcal.errors import SpecError
from fieldcal.raytrace.build import check_first_order, fit_even_polynomial, parse_sensor, residual_blur_um
from fieldcal.raytrace.paraxial import paraxial
from fieldcal.raytrace.prescription import load_prescription, model_glass_index, parse_rows
from fieldcal.optics import diffraction_mtf, gaussian_mtf

HEADER = "surface,type,radius,thickness,nd,vd,k,a4,a6,a8"


@pytest.fixture
def triplet_rx(models_dir):
    return load_prescription(models_dir / "triplet-uncorrected.prescription.csv")


def write(tmp_path, body, name="t.csv", header=HEADER):
    p = tmp_path / name
    p.write_text(header + "\n" + body + "\n")
    return p


SINGLET = "1,standard,50,5,1.5168,64.17,,,,\nstop,standard,inf,1,,,,,,\n3,standard,-50,45,,,,,,"


# ---------------------------------------------------------------------------------------------- paraxial
def test_triplet_paraxial_matches_the_notes(triplet_rx):
    p = paraxial(triplet_rx)
    assert p.efl_mm == pytest.approx(17.600, abs=5e-4)
    assert p.bfl_mm == pytest.approx(10.511, abs=5e-4)
    assert p.exit_pupil_to_image_mm == pytest.approx(19.031, abs=2e-3)  # models/triplet-uncorrected.json
    assert p.paraxial_focus_shift_um == pytest.approx(21.4, abs=0.2)  # paraxial focus behind the stated plane


def test_triplet_longitudinal_colour_sign(triplet_rx):
    # an undercorrected positive lens: red focuses furthest from the lens
    r, g, b = (paraxial(triplet_rx, w).bfl_mm for w in (656.3, 546.1, 486.1))
    assert r > g > b


@settings(max_examples=60, deadline=None)
@given(r1=st.floats(10, 500), r2=st.floats(-500, -10), d=st.floats(0.5, 8), n=st.floats(1.4, 2.0))
def test_thick_lens_closed_form(r1, r2, d, n):
    """A biconvex thick lens in air: lensmaker's equation for EFL and BFL."""
    rx = parse_rows([dict(surface="stop", type="standard", radius="inf", thickness=0.0),
                     dict(surface="1", type="standard", radius=r1, thickness=d, nd=n, vd=60.0),
                     dict(surface="2", type="standard", radius=r2, thickness=10.0)])
    power = (n - 1) * (1 / r1 - 1 / r2 + (n - 1) * d / (n * r1 * r2))
    f = 1 / power
    bfl = f * (1 - (n - 1) * d / (n * r1))
    p = paraxial(rx)
    assert p.efl_mm == pytest.approx(f, rel=1e-9)
    assert p.bfl_mm == pytest.approx(bfl, rel=1e-9, abs=1e-9)
    # stop at the first vertex: its image by surface 2 (object d before it, in glass): n'/l' - n/l = (n' - n)/R
    l_exit = 1.0 / ((1.0 - n) / r2 + n / -d)
    assert p.exit_pupil_to_image_mm == pytest.approx(10.0 - l_exit, rel=1e-9)


# -------------------------------------------------------------------------------------------- model glass
def test_model_glass_reproduces_n_bk7():
    # Schott N-BK7 datasheet: nC, nd, ne, nF, ng
    for wl, n in ((656.27, 1.51432), (587.56, 1.51680), (546.07, 1.51872), (486.13, 1.52238), (435.83, 1.52668)):
        assert model_glass_index(1.51680, 64.17, wl) == pytest.approx(n, abs=1e-4)


@settings(max_examples=100, deadline=None)
@given(nd=st.floats(1.3, 2.3), vd=st.floats(15, 100))
def test_model_glass_abbe_number_exact_and_normal_dispersion(nd, vd):
    nf, nc = model_glass_index(nd, vd, 486.13), model_glass_index(nd, vd, 656.27)
    assert model_glass_index(nd, vd, 587.56) == pytest.approx(nd, abs=1e-12)
    assert (nd - 1) / (nf - nc) == pytest.approx(vd, rel=1e-9)
    wl = [400, 450, 500, 550, 600, 650, 700]
    ns = [model_glass_index(nd, vd, w) for w in wl]
    assert all(a > b for a, b in zip(ns, ns[1:]))  # index falls with wavelength in the visible


# ------------------------------------------------------------------------------------------------ parsing
def test_triplet_table_parses(triplet_rx):
    s = triplet_rx.surfaces
    assert len(s) == 7 and triplet_rx.stop_index == 4
    assert s[5].kind == "even_asphere" and s[6].aspheric == (1.365e-4, 7.621e-7, 0.0)
    assert s[1].nd == 1.0 and s[2].nd == 2.001 and s[2].vd == 29.13
    assert triplet_rx.meta["efl_mm"] == "17.6"


def test_json_table_equivalent_to_csv(tmp_path, triplet_rx):
    rows = [dict(surface=s.label, type="even asphere" if s.kind == "even_asphere" else "standard",
                 radius=s.radius_mm if math.isfinite(s.radius_mm) else "inf", thickness=s.thickness_mm,
                 nd=s.nd if s.is_glass else None, vd=s.vd if s.is_glass else None, k=s.conic,
                 a4=s.aspheric[0], a6=s.aspheric[1], a8=s.aspheric[2]) for s in triplet_rx.surfaces]
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"surfaces": rows, "efl_mm": 17.6}))
    rx = load_prescription(p)
    assert paraxial(rx).efl_mm == pytest.approx(paraxial(triplet_rx).efl_mm, rel=1e-12)


def test_glass_by_name(tmp_path):
    rx = load_prescription(write(tmp_path, SINGLET.replace("1.5168,64.17", ",").replace("1,standard,50,5,,",
                                 "1,standard,50,5,,,N-BK7").replace("\n", "\n", 1),
                                 header="surface,type,radius,thickness,nd,vd,glass,k,a4,a6,a8"))
    assert rx.surfaces[0].nd == pytest.approx(1.5168)


BAD = [
    # (row text replacing the first row, column named in the error, words in the message)
    ("1,standard,50,5,1.5168,,,,,", "vd", "row 1"),
    ("1,standard,50,5,,64.17,,,,", "nd", "row 1"),
    ("1,standard,50,5,0.9,64.17,,,,", "nd", "not that of an optical glass"),
    ("1,standard,50,5,64.17,1.5168,,,,", "nd", "column order"),
    ("1,standard,50,5,1.5168,500,,,,", "vd", "Abbe"),
    ("1,standard,fifty,5,1.5168,64.17,,,,", "radius", "not a number"),
    ("1,standard,0,5,1.5168,64.17,,,,", "radius", "radius of 0"),
    ("1,standard,50,-5,1.5168,64.17,,,,", "thickness", "negative"),
    ("1,standard,50,5,1.5168,64.17,0,1e-4,,", "a4", "standard"),
    ("1,toroid,50,5,1.5168,64.17,,,,", "type", "unknown surface type"),
    ("1,standard,50,nan,1.5168,64.17,,,,", "thickness", "finite"),
]


@pytest.mark.parametrize("row,field,words", BAD)
def test_bad_rows_name_row_and_field(tmp_path, row, field, words):
    body = SINGLET.split("\n", 1)
    p = write(tmp_path, row + "\n" + body[1])
    with pytest.raises(SpecError) as e:
        load_prescription(p)
    assert e.value.field == field and e.value.path == str(p)
    assert words in str(e.value) and "fix:" in str(e.value)


def test_unknown_glass_name_refused(tmp_path):
    p = write(tmp_path, "1,standard,50,5,,,UNOBTAINIUM-7,,,,\nstop,standard,inf,1,,,,,,,\n3,standard,-50,45,,,,,,,",
              header="surface,type,radius,thickness,nd,vd,glass,k,a4,a6,a8")
    with pytest.raises(SpecError, match="unknown glass 'UNOBTAINIUM-7'") as e:
        load_prescription(p)
    assert e.value.field == "glass" and "row 1" in str(e.value)


@pytest.mark.parametrize("body,field,words", [
    (SINGLET.replace("stop,", "2,"), "surface", "0 aperture stop"),
    (SINGLET.replace("3,standard", "stop,standard"), "surface", "2 aperture stop"),
    (SINGLET.replace("-50,45,,,", "-50,45,1.5,60,"), "nd", "image side must be air"),
    (SINGLET.replace("1.5168,64.17", ","), "nd", "no lens element"),
    (SINGLET.replace("-50,45", "-50,0"), "thickness", "last thickness"),
])
def test_bad_tables(tmp_path, body, field, words):
    with pytest.raises(SpecError) as e:
        load_prescription(write(tmp_path, body))
    assert e.value.field == field and words in str(e.value)


def test_bad_files(tmp_path):
    with pytest.raises(SpecError, match="not found"):
        load_prescription(tmp_path / "missing.csv")
    with pytest.raises(SpecError) as e:
        load_prescription(write(tmp_path, SINGLET, header="surface,type,radius,thickness,nd,vd,colour"))
    assert e.value.field == "colour"
    with pytest.raises(SpecError) as e:
        load_prescription(write(tmp_path, SINGLET, header="surface,type,radius,nd,vd"))
    assert e.value.field == "thickness"
    p = tmp_path / "t.json"
    p.write_text("{not json")
    with pytest.raises(SpecError, match="not valid JSON"):
        load_prescription(p)
    p.write_text(json.dumps({"surfaces": [{"surface": "1", "radius": 5, "thickness": 1, "colour": 3}]}))
    with pytest.raises(SpecError) as e:
        load_prescription(p)
    assert e.value.field == "colour"


# ----------------------------------------------------------------------------------------- first order
def test_efl_bfl_check(triplet_rx):
    p = paraxial(triplet_rx)
    check_first_order(p, 17.6, 10.49, 0.005)  # the table's stated BFL (10.49) is within 0.5% of 10.511
    with pytest.raises(SpecError) as e:
        check_first_order(p, 17.0, None, 0.005, path="t.csv")
    assert e.value.field == "efl_mm" and "17.6000" in str(e.value)
    with pytest.raises(SpecError) as e:
        check_first_order(p, None, 9.9, 0.005)
    assert e.value.field == "bfl_mm"


def test_a_mistyped_radius_is_caught_by_the_efl_check(tmp_path, models_dir):
    text = (models_dir / "triplet-uncorrected.prescription.csv").read_text().replace("11.5163", "12.5163")
    p = tmp_path / "typo.csv"
    p.write_text(text)
    assert main(["lens", "check", str(p)]) == 2  # '# efl_mm: 17.6' in the table


def test_fit_even_polynomial_exact_and_normalised():
    h = [0.0, 1.0, 2.0, 3.0, 4.0]
    z = [5.0 - 100.0 * (x / 4) ** 2 - 20.0 * (x / 4) ** 4 for x in h]
    a0, curv, rms = fit_even_polynomial(h, z, 4.0, 2)
    assert a0 == pytest.approx(5.0) and curv == pytest.approx((-100.0, -20.0)) and rms < 1e-9


def test_residual_blur_inverts_the_model_mtf():
    # the triplet's sources: diffraction 0.889 at 546 nm F/2, traced peak 0.77 -> 1.066 µm
    s = residual_blur_um(0.77, 80.0, 546.1, 2.0)
    assert s == pytest.approx(1.066, abs=2e-3)
    assert float(diffraction_mtf(80.0, 546.1, 2.0) * gaussian_mtf(80.0, s)) == pytest.approx(0.77, abs=1e-9)
    assert residual_blur_um(0.95, 80.0, 546.1, 2.0) == 0.0  # above the diffraction limit: no blur


def test_parse_sensor():
    assert parse_sensor("3840x2160@1.6342", None) == (3840, 2160, 1.6342)
    assert parse_sensor("640x480", 3.6) == (640, 480, None)
    for bad in ("3840", "4x4@1", "100x100@-1", "100x100@abc"):
        with pytest.raises(Exception):
            parse_sensor(bad, None)


# ------------------------------------------------------------------------------------------------- CLI
def test_cli_check(models_dir, capsys):
    assert main(["lens", "check", str(models_dir / "triplet-uncorrected.prescription.csv")]) == 0
    out = capsys.readouterr().out
    assert "EFL 17.6000 mm" in out and "BFL 10.5114 mm" in out and "19.031" in out


def test_cli_bad_table_is_a_message_not_a_traceback(tmp_path, capsys):
    p = write(tmp_path, SINGLET.replace("1.5168,64.17", "1.5168,"))
    out = tmp_path / "lens.json"
    assert main(["lens", "from-prescription", str(p), "--out", str(out), "--f-number", "4",
                 "--image-height", "3"]) == 2
    err = capsys.readouterr().err
    assert "row 1" in err and "'vd'" in err and "Traceback" not in err
    assert not out.exists()


def test_cli_without_optiland_says_how_to_install(tmp_path, models_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "optiland", None)  # import optiland -> ImportError
    out = tmp_path / "lens.json"
    rc = main(["lens", "from-prescription", str(models_dir / "triplet-uncorrected.prescription.csv"),
               "--out", str(out), "--quiet"])
    assert rc == 4
    assert 'pip install -e ".[raytrace]"' in capsys.readouterr().err
    assert not out.exists()


def test_cli_refuses_to_overwrite(tmp_path, models_dir, capsys):
    out = tmp_path / "lens.json"
    out.write_text("{}")
    assert main(["lens", "from-prescription", str(models_dir / "triplet-uncorrected.prescription.csv"),
                 "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.read_text() == "{}"


def test_cli_option_errors(models_dir, tmp_path, capsys):
    t = str(models_dir / "triplet-uncorrected.prescription.csv")
    o = str(tmp_path / "l.json")
    for extra, field in ((["--channels", "R=10000"], "--channels"), (["--heights", "1"], "--heights"),
                         (["--terms", "5"], "--terms"), (["--sensor", "9000x9000@5"], "--sensor"),
                         (["--efl", "-3"], "--efl")):
        assert main(["lens", "from-prescription", t, "--out", o, *extra]) == 2, extra
        assert field in capsys.readouterr().err
