"""Files written before the format layer (tests/data/legacy, made at ef2b85d) still load, with the same values.

``expected.json`` holds what the code of that time read from them (record_expected.py); every reader of the
format layer must give the same numbers back, to 1e-9: NumPy releases differ in the last bits of the same
evaluation (2.4 against the recording: 3e-11 relative), which says nothing about the format.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fieldcal.capture.folder import read_journal
from fieldcal.capture.plan import CapturePlan
from fieldcal.formats.stack import Stack
from fieldcal.plan.planfile import read_plan
from fieldcal.profile.lens_profile import LensProfile, load_profile_or_truth
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import load_truth

L = Path(__file__).parent / "data" / "legacy"
EXP = json.loads((L / "expected.json").read_text())
X, Y = [0.0, 60.0, 128.0, 255.0], [0.0, 30.0, 72.0, 143.0]


def close(a, b):
    np.testing.assert_allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float), rtol=1e-9, atol=1e-9)


def test_profile_loads_with_the_same_answers():
    e = EXP["profile"]
    for p in (LensProfile.load(L / "lens.json"), load_profile_or_truth(L / "lens.json")[0]):
        assert p.z_ref_um == e["z_ref_um"] and p.image == e["image"] and p.optics == e["optics"]
        assert list(p.channels) == e["channels"]
        for c in p.channels:
            close(p.best_focus_um(X, Y, c), e["best_focus_um"][c])
            close(p.best_focus_interval_um(X, Y, c, 0.9), e["interval_um"][c])
            close(p.magnification([-300.0, 0.0, 40.0], c), e["magnification"][c])
        close(p.shift_px([-300.0, 0.0, 40.0]), e["shift_px"])
        close(p.focus_tolerance_um(X, Y, "G", 15.0, 0.05), e["tolerance_um"])
        assert int(np.asarray(p.surfaces.samples).shape[0]) == e["n_samples"]
        assert sorted(p.tiles or {}) == e["tiles_keys"]


@pytest.mark.parametrize("name", ["lens-spec.json", "lens-spec-triplet.json"])
def test_lens_specs_load_with_the_same_values(name):
    e = EXP[name]
    assert LensSpec.load(L / name).to_dict() == e["to_dict"]
    truth, info = load_profile_or_truth(L / name, (64, 48))
    assert {**info, "path": None} == {**e["info"], "path": None}  # recorded with a relative path
    for c in truth.channels:
        close(truth.best_focus_um([0.0, 31.5, 63.0], [0.0, 23.5, 47.0], c), e["truth_best_focus_um"][c])


@pytest.mark.parametrize("name", ["plan-stack.json", "plan-sweep.json", "plan-sweep-pixel.json"])
def test_plans_load_unchanged(name):
    assert read_plan(L / name) == EXP[name]


def test_capture_plan_from_a_legacy_plan_file():
    cp = CapturePlan.from_file(L / "plan-stack.json")
    e = EXP["capture_plan"]
    assert cp.z_um.tolist() == e["z_um"] and cp.approach == e["approach"]
    assert [f.exposure_ms for f in cp.frames] == e["exposure_ms"] and cp.fingerprint() == e["fingerprint"]


@pytest.mark.parametrize("name", ["stack", "capture"])
def test_stacks_open_with_the_same_values(name):
    st, e = Stack.open(L / name), EXP[name]
    assert st.z_um.tolist() == e["z_um"] and st.pixel_pitch_um == e["pixel_pitch_um"]
    assert list(st.channels) == e["channels"] and list(st.shape) == e["shape"]
    assert [st.black_level, st.white_level] == e["levels"] and st.meta == e["meta"]
    assert st.verify_checksums() == []


def test_journal_reads_the_same(tmp_path):
    shutil.copytree(L / "capture", tmp_path / "c")  # Journal.read may cut a torn last line: work on a copy
    header, entries = read_journal(tmp_path / "c" / "capture.journal")
    assert header == EXP["journal"]["header"] and entries == EXP["journal"]["entries"]


def test_truth_json_loads_as_the_simulated_lens():
    t = load_truth(L / "stack")
    doc = EXP["truth"]
    assert list(t.image_size_px) == doc["size_px"]
    assert t.spec.to_dict() == LensSpec.from_dict(doc["lens"]).to_dict()
    via_loader, info = load_profile_or_truth(L / "stack" / "truth.json")
    assert info["format"] == "fieldcal-truth/1" and via_loader.image_size_px == t.image_size_px


def test_targets_manifest_is_kept_when_new_charts_are_added(tmp_path):
    from fieldcal.charts.targets import _merge_manifest
    (tmp_path / "targets.json").write_text((L / "targets.json").read_text())
    for e in EXP["targets"]["charts"]:
        for f in e["files"]:
            (tmp_path / f).write_bytes(b"x")
    merged = _merge_manifest(tmp_path / "targets.json", [])
    assert merged["charts"] == EXP["targets"]["charts"]
