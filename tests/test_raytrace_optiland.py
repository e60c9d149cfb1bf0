"""The ray-traced cross-check with optiland (skipped when the optional extra is not installed).

Known truth: the best-focus table of shared/lenses/paper-triplet-uncorrected.md (traced independently with
optiland and rayoptics), the paper's D = 332 µm, and ray-fan geometry for the tangential/sagittal labels.
"""

import json

import numpy as np
import pytest

pytest.importorskip("optiland")

from fieldcal.cli import main  # noqa: E402
from fieldcal.simulate.lens import LensSpec  # noqa: E402
from fieldcal.raytrace.bestfocus import SearchSettings, trace_focus_table  # noqa: E402
from fieldcal.raytrace.build import build_lens_spec, compare_with_spec  # noqa: E402
from fieldcal.raytrace.optiland_backend import TracedLens, _mtf_at  # noqa: E402
from fieldcal.raytrace.paraxial import paraxial  # noqa: E402
from fieldcal.raytrace.prescription import load_prescription  # noqa: E402

NOTES = {  # µm from the stated image plane at h = 0, 1.8, 3.6 mm
    "R": (10.8, -63.8, -301.5),
    "G": (-5.8, -80.6, -319.6),
    "B": (-6.9, -81.8, -321.8),
}


@pytest.fixture(scope="module")
def rx():
    from pathlib import Path
    return load_prescription(Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.prescription.csv")


@pytest.fixture(scope="module")
def table(rx):
    # a narrower coarse scan than the CLI's default keeps this file fast; the scan still moves to the peak
    return trace_focus_table(rx, [0.0, 1.8, 3.6], quiet=True, settings=SearchSettings(coarse_half_width_um=12.0))


def test_notes_table_reproduced(table):
    for ch, zs in NOTES.items():
        for h, want in zip((0.0, 1.8, 3.6), zs):
            assert table.get(ch, h).z_um == pytest.approx(want, abs=3.0), (ch, h)


def test_range_colour_and_peak(table):
    z = np.concatenate([table.column(c) for c in "RGB"])
    assert np.ptp(z) == pytest.approx(332.0, abs=4.0)  # the paper's D
    for h in (0.0, 1.8, 3.6):  # longitudinal colour: R-B spread 18-20 µm in the notes
        assert 15.0 < table.get("R", h).z_um - table.get("B", h).z_um < 22.0
    assert table.get("G", 0.0).peak_mtf == pytest.approx(0.77, abs=0.02)  # the notes' on-axis peak


def test_tangential_sagittal_labels_follow_the_ray_fans(rx, table):
    """optiland's through-focus helper swaps T and S; ours must agree with meridional/sagittal ray fans."""
    edge = table.get("G", 3.6)
    lens = TracedLens(rx, 546.1, 2.0)
    t_fan, s_fan = lens.fan_foci_um(edge.field_angle_deg)
    assert np.sign(edge.z_tangential_um - edge.z_sagittal_um) == np.sign(t_fan - s_fan) != 0
    assert 2.0 < abs(edge.z_tangential_um - edge.z_sagittal_um) < 9.0  # notes: within 6 µm
    on_axis = table.get("G", 0.0)
    assert on_axis.z_tangential_um == pytest.approx(on_axis.z_sagittal_um, abs=0.05)


def test_mtf_at_fs_agrees_with_optilands_fft_bins(rx):
    from optiland.mtf import FFTMTF

    lens = TracedLens(rx, 546.1, 2.0)
    lens.set_max_angle_deg(12.0)
    m = FFTMTF(lens.optic, fields=[(0.0, 0.5)], wavelength=0.5461, num_rays=64)
    psf = np.asarray(m.psf[0])
    ft, fs = np.asarray(m.freq_tang[0]), np.asarray(m.freq_sag[0])
    for k in (3, 6, 9):
        t, s = _mtf_at(psf, ft[1], fs[1], ft[k])
        assert t == pytest.approx(float(np.asarray(m.mtf[0][0])[k]), abs=1e-9)
        t, s = _mtf_at(psf, ft[1], fs[1], fs[k])
        assert s == pytest.approx(float(np.asarray(m.mtf[0][1])[k]), abs=1e-9)


def test_spec_built_from_the_trace_matches_the_hand_model(rx, table, models_dir):
    spec = build_lens_spec(table, paraxial(rx), name="t", image_height_mm=3.6)
    model = LensSpec.load(models_dir / "triplet-uncorrected.json")
    assert spec.exit_pupil_mm == pytest.approx(model.exit_pupil_mm, abs=0.01)
    assert spec.focal_length_mm == pytest.approx(17.6, abs=1e-3)
    assert spec.residual_blur_um == pytest.approx(model.residual_blur_um, abs=0.15)
    assert spec.relative_illumination_edge == pytest.approx(model.relative_illumination_edge, abs=0.005)
    assert spec.sensor.pixel_pitch_um == pytest.approx(model.sensor.pixel_pitch_um, rel=1e-4)
    # 3 heights, 3 coefficients: the fit goes through the traced points
    for row in compare_with_spec(table, spec):
        assert row["diff_um"] == pytest.approx(0.0, abs=1e-2)
    for row in compare_with_spec(table, model):
        assert abs(row["diff_um"]) < 3.0
    spec2 = LensSpec.from_dict(json.loads(json.dumps(spec.to_dict())))  # a valid fieldcal-lens/1
    assert spec2.channel_names == ("R", "G", "B")


def test_cli_from_prescription_end_to_end(models_dir, tmp_path, capsys):
    out = tmp_path / "lens.json"
    rc = main(["lens", "from-prescription", str(models_dir / "triplet-uncorrected.prescription.csv"),
               "--out", str(out), "--channels", "G", "--heights", "2", "--terms", "1", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    spec = LensSpec.load(out)
    assert float(spec.best_focus_um(3.6, 0.0, "G")) == pytest.approx(-319.6, abs=3.0)
    assert float(spec.best_focus_um(0.0, 0.0, "G")) == pytest.approx(-5.8, abs=1.5)
    assert "traced_best_focus" in json.loads(out.read_text())
    assert "optiland" in spec.sources["prescription"]
