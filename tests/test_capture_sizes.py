"""Simulate and capture record focal length, object distance and image size; capture refuses a plan made for
another image size before anything moves (issue 15)."""

import json
from pathlib import Path

import pytest

from fieldcal import Stack
from fieldcal.capture import CapturePlan, LensRecord, run_capture
from fieldcal.cli import main
from fieldcal.errors import ParameterError, SpecError, StackError
from fieldcal.hardware.sim import SimCamera, SimStage
from fieldcal.simulate.lens import LensSpec

PLAN_SIZE = (320, 180)


def _thin_lens_shift_um(f_mm, u_cal_mm, u_new_mm):
    """Closed form: image distance v = f u / (u - f); the stage follows v(u') - v(u)."""
    v = lambda u: f_mm * u / (u - f_mm)  # noqa: E731
    return (v(u_new_mm) - v(u_cal_mm)) * 1000.0


@pytest.fixture(scope="module")
def size_plan(tmp_path_factory):
    """A stack plan made from the triplet's truth rendered at 320x180."""
    lens = Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json"
    out = tmp_path_factory.mktemp("plan") / "plan.json"
    assert main(["plan", "stack", str(lens), "--fs", "8", "--q", "0.05", "--size", "%dx%d" % PLAN_SIZE,
                 "--out", str(out)]) == 0
    return lens, out


# ------------------------------------------------------------------ simulate -> calibrate -> plan
def test_simulated_stack_records_optics_and_size(small_chart_stack, triplet_path):
    spec = LensSpec.load(triplet_path)
    s = Stack.open(small_chart_stack)
    assert s.meta["focal_length_mm"] == spec.focal_length_mm
    assert s.meta["object_distance_mm"] == spec.object_distance_mm
    assert s.meta["image_size_px"] == [s.shape[1], s.shape[0]] == [256, 144]


def test_profile_from_simulated_stack_refocuses(small_chart_stack, triplet_path, tmp_path, capsys):
    spec = LensSpec.load(triplet_path)
    prof = tmp_path / "P.json"
    assert main(["calibrate", str(small_chart_stack), "--out", str(prof), "--fs", "8", "--effort", "quick",
                 "--z-ref", "0", "-q"]) == 0
    optics = json.loads(prof.read_text())["optics"]
    assert optics["focal_length_mm"] == spec.focal_length_mm
    assert optics["object_distance_mm"] == spec.object_distance_mm
    # failed before ("the profile does not record its calibration object distance and focal length")
    plan = tmp_path / "plan.json"
    assert main(["plan", "stack", str(prof), "--fs", "8", "--q", "0.05", "--object-distance-mm", "500",
                 "--out", str(plan)]) == 0, capsys.readouterr().err
    doc = json.loads(plan.read_text())
    want = _thin_lens_shift_um(spec.focal_length_mm, spec.object_distance_mm, 500.0)
    assert doc["refocus_um"] == pytest.approx(want, abs=1e-3)
    assert doc["profile"]["image_size_px"] == [256, 144]


def test_stack_schema_checks_the_new_keys(small_chart_stack, tmp_path):
    import shutil
    for key, bad in (("focal_length_mm", -16.0), ("focal_length_mm", "16"), ("image_size_px", [320]),
                     ("image_size_px", [320, 0]), ("image_size_px", [320.5, 180])):
        d = tmp_path / f"{key}-{bad!r}".replace("/", "_")
        shutil.copytree(small_chart_stack, d)
        meta = json.loads((d / "stack.json").read_text())
        meta[key] = bad
        (d / "stack.json").write_text(json.dumps(meta))
        with pytest.raises(StackError) as e:
            Stack.open(d, verify=False)
        assert key in str(e.value) and "fix" in str(e.value)


# ------------------------------------------------------------------ capture
def test_capture_refuses_a_plan_for_another_size_before_anything(size_plan, tmp_path, capsys):
    lens, plan = size_plan
    out = tmp_path / "C"
    for extra in (["--dry-run"], []):
        code = main(["capture", "--plan", str(plan), "--camera", f"sim:{lens},size=160x120", "--out", str(out)]
                    + extra)
        err = capsys.readouterr().err
        assert code == 2
        assert str(plan) in err and "profile.image_size_px" in err and "320x180" in err and "160x120" in err
        assert "fix:" in err
        assert not out.exists()
    # through the API: the stage was never moved (nor referenced)
    stage = SimStage()
    with pytest.raises(SpecError):
        run_capture(CapturePlan.from_file(plan), stage, SimCamera(lens, size=(160, 120)), out)
    assert stage.moves == [] and not out.exists()


def test_capture_of_a_matching_plan_records_size_and_optics(size_plan, tmp_path, capsys):
    lens, plan = size_plan
    spec = LensSpec.load(lens)
    out = tmp_path / "C"
    dry = main(["capture", "--plan", str(plan), "--camera", f"sim:{lens},size=320x180", "--out", str(out),
                "--dry-run"])
    assert dry == 0 and json.loads(capsys.readouterr().out)["image_size_px"] == list(PLAN_SIZE)
    assert main(["capture", "--plan", str(plan), "--camera", f"sim:{lens},size=320x180,noise=0", "--out", str(out),
                 "--object-distance-mm", "750", "--quiet"]) == 0
    s = Stack.open(out)
    assert len(s) == json.loads(plan.read_text())["n_frames"]
    assert s.meta["image_size_px"] == [s.shape[1], s.shape[0]] == list(PLAN_SIZE)
    assert s.meta["focal_length_mm"] == spec.focal_length_mm        # the camera's (its lens spec)
    assert s.meta["object_distance_mm"] == 750.0                      # given: overrides the camera's 1000
    assert s.meta["capture"]["optics_from"] == {"focal_length_mm": "camera", "object_distance_mm": "given"}


class _Mute(SimCamera):
    """A camera (e.g. a plug-in) that states neither its size nor its optics."""

    def describe(self):
        d = super().describe()
        for k in ("size_px", "roi", "focal_length_mm", "object_distance_mm"):
            d.pop(k)
        return d


def test_camera_without_a_size_is_checked_at_the_first_frame(size_plan, tmp_path):
    lens, plan = size_plan
    out = tmp_path / "C"
    with pytest.raises(SpecError) as e:
        run_capture(CapturePlan.from_file(plan), SimStage(), _Mute(lens, size=(160, 120), noise=False), out,
                    options=_quiet())
    assert e.value.field == "profile.image_size_px"
    assert not list((out / "frames").glob("*.tiff"))  # refused before the frame was saved
    out2 = tmp_path / "C2"
    run_capture(CapturePlan.from_file(plan), SimStage(), _Mute(lens, size=PLAN_SIZE, noise=False), out2,
                options=_quiet(), lens=LensRecord(focal_length_mm=17.6, object_distance_mm=400.0))
    s = Stack.open(out2)
    assert (s.meta["focal_length_mm"], s.meta["object_distance_mm"]) == (17.6, 400.0)
    assert "image_size_px" not in s.meta  # not stated by the camera: not claimed


class _Liar(SimCamera):
    """A camera that states the plan's size but delivers another (pylon's emulator states its default size)."""

    def describe(self):
        return dict(super().describe(), size_px=list(PLAN_SIZE))


def test_a_camera_misstating_its_size_is_caught_by_the_first_frame(size_plan, tmp_path):
    lens, plan = size_plan
    with pytest.raises(SpecError):
        run_capture(CapturePlan.from_file(plan), SimStage(), _Liar(lens, size=(160, 120), noise=False),
                    tmp_path / "C", options=_quiet())
    assert not list((tmp_path / "C" / "frames").glob("*.tiff"))
    # without a plan size: captured, and stack.json records the size the frames have, not the stated one
    run_capture(CapturePlan.from_range(-10, 10, 10), SimStage(), _Liar(lens, size=(160, 120), noise=False),
                tmp_path / "R", options=_quiet())
    s = Stack.open(tmp_path / "R")
    assert s.meta["image_size_px"] == [s.shape[1], s.shape[0]] == [160, 120]


def _quiet():
    from fieldcal.capture import RunOptions
    return RunOptions(quiet=True)


def test_plans_without_a_size_still_load_and_bad_sizes_are_named(size_plan, tmp_path):
    lens, plan = size_plan
    doc = json.loads(plan.read_text())
    old = dict(doc, profile={k: v for k, v in doc["profile"].items() if k != "image_size_px"})
    p = tmp_path / "old.json"
    p.write_text(json.dumps(old))
    assert CapturePlan.from_file(p).image_size_px is None  # an old or hand-written plan: nothing to check
    assert CapturePlan.from_file(plan).image_size_px == PLAN_SIZE
    for bad in ([320], [320, 0], [320.0, 180], "320x180", [True, 180]):
        p.write_text(json.dumps(dict(doc, profile=dict(doc["profile"], image_size_px=bad))))
        with pytest.raises(SpecError) as e:
            CapturePlan.from_file(p)
        assert e.value.field == "profile.image_size_px" and e.value.path == str(p)


@pytest.mark.parametrize("flag", ["--focal-length-mm", "--object-distance-mm"])
@pytest.mark.parametrize("value", ["0", "-5", "nan", "inf"])
def test_bad_optics_flags_are_refused(flag, value, triplet_path, tmp_path, capsys):
    out = tmp_path / "C"
    code = main(["capture", "--z", "-10", "10", "10", "--camera", f"sim:{triplet_path},size=40x24", "--out",
                 str(out), f"{flag}={value}"])
    assert code == 2 and flag in capsys.readouterr().err and not out.exists()


def test_lens_record_validates():
    with pytest.raises(ParameterError):
        LensRecord(focal_length_mm=True)
    assert LensRecord(16, 500).focal_length_mm == 16
