"""The capture executor and `fieldcal capture`: crash safety, resume, limits, backlash, faults."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal import Stack
from fieldcal.capture import JOURNAL, CaptureFolder, CapturePlan, PlannedFrame, capture
from fieldcal.cli import main
from fieldcal.errors import LinkError, ParameterError, SpecError, StackError
from fieldcal.hardware.protocols import DeviceFault
from fieldcal.hardware.sim import SimCamera, SimStage

SIZE = (40, 24)


def _devices(lens, **stage_kw):
    stage = SimStage(**stage_kw)
    cam = SimCamera(lens, size=SIZE, noise=False)
    stage.connect()
    cam.connect()
    cam.observe_stage(stage)
    return stage, cam


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _check_complete(folder: Path, plan: CapturePlan):
    s = Stack.open(folder)
    assert sorted(s.z_um.tolist()) == sorted(plan.z_um.tolist())  # every frame exactly once
    assert s.verify_checksums() == []
    for f in s.frames:
        assert f.meta["sha256"] == hashlib.sha256(f.path.read_bytes()).hexdigest()
        assert abs(f.meta["z_measured_um"] - f.z_um) < 1.0
        assert {"z_measured_before_um", "z_measured_after_um", "exposure_ms", "time", "camera_frame_id"} <= set(f.meta)
    return s


@settings(max_examples=50, deadline=None)
@given(st.floats(-300, 300), st.floats(0.5, 50), st.integers(1, 40), st.sampled_from([1.0, -1.0]))
def test_range_plan_and_one_sided_approach(start, step, n, sgn):
    step *= sgn
    plan = CapturePlan.from_range(start, start + step * (n - 1), step)
    assert len(plan.frames) == n and plan.frames[0].z_um == pytest.approx(start, abs=1e-6)  # z rounded to 1e-6 µm
    assert plan.approach == ("+z" if step > 0 else "-z")
    moves = plan.moves()
    for k, (z, is_frame) in enumerate(moves):
        if is_frame:  # every frame position is reached moving in the approach direction
            assert k > 0 and sgn * (z - moves[k - 1][0]) > 0
    lo, hi = plan.motion_range_um()
    assert lo <= min(z for z, _ in moves) and max(z for z, _ in moves) <= hi


def test_plan_rejects_bad_input(tmp_path):
    with pytest.raises(ParameterError):
        CapturePlan.from_range(0, 10, 0)
    with pytest.raises(ParameterError, match="away from stop"):
        CapturePlan.from_range(0, 10, -1)
    p = tmp_path / "plan.json"
    p.write_text(json.dumps({"format": "fieldcal-plan/1", "kind": "sweep"}))
    with pytest.raises(SpecError, match="range_um"):  # the plan reader names the first missing field
        CapturePlan.from_file(p)
    sweep = json.loads((Path(__file__).parent / "data" / "legacy" / "plan-sweep.json").read_text())
    p.write_text(json.dumps(sweep))
    # an LCoS sweep cannot be one constant-velocity exposure (pixel-wise sweeps run: tests/test_capture_sweep.py)
    with pytest.raises(SpecError, match="pixel-wise exposure sensor only"):
        CapturePlan.from_file(p)
    p.write_text(json.dumps({"format": "fieldcal-plan/1", "kind": "stack", "parameters": {}, "direction": "+z",
                             "frames": [{"z_um": 1}, {"z_um": 1}]}))
    with pytest.raises(SpecError, match="distinct z"):
        CapturePlan.from_file(p)


def test_capture_completes_and_rerun_changes_nothing(tmp_path, triplet_path):
    plan = CapturePlan.from_range(-40, 40, 10)
    stage, cam = _devices(triplet_path)
    r = capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert (r.taken, r.skipped) == (9, 0)
    _check_complete(tmp_path / "S", plan)
    before = _snapshot(tmp_path / "S")
    stage2, cam2 = _devices(triplet_path)
    r2 = capture(plan, stage2, cam2, tmp_path / "S", quiet=True)
    assert (r2.taken, r2.skipped) == (0, 9)
    assert stage2.moves == []  # complete: nothing moved
    assert _snapshot(tmp_path / "S") == before


def test_fault_stops_and_resume_keeps_committed_frames(tmp_path, triplet_path):
    plan = CapturePlan.from_range(-40, 40, 10)
    stage, cam = _devices(triplet_path, fail_after=5)
    with pytest.raises(DeviceFault) as e:
        capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert e.value.code == 1024 and "re-run the same command to resume" in str(e.value)
    s = Stack.open(tmp_path / "S")
    assert len(s) == 4  # the back-off move + 4 frames succeeded; the 6th move failed
    kept = {f.file: f.path.read_bytes() for f in s.frames}
    stage2, cam2 = _devices(triplet_path)
    r = capture(plan, stage2, cam2, tmp_path / "S", quiet=True)
    assert (r.taken, r.skipped, r.retaken) == (5, 4, 0)
    s = _check_complete(tmp_path / "S", plan)
    assert all((tmp_path / "S" / f).read_bytes() == b for f, b in kept.items())


def test_torn_frame_is_retaken(tmp_path, triplet_path, monkeypatch):
    plan = CapturePlan.from_range(0, 50, 10)
    stage, cam = _devices(triplet_path)
    calls = {"n": 0}
    real_save = CaptureFolder.save

    def crash_on_third(self, index, z_um, image, **meta):
        calls["n"] += 1
        if calls["n"] == 3:  # after the frame and stack.json, before the commit point
            self._writer.add_frame(image, z_um, file=f"frames/{index:04d}.tiff", **meta)
            raise SystemExit("power cut")
        return real_save(self, index, z_um, image, **meta)

    monkeypatch.setattr(CaptureFolder, "save", crash_on_third)
    with pytest.raises(SystemExit):
        capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert len(Stack.open(tmp_path / "S")) == 3  # stack.json valid, lists the uncommitted frame too
    monkeypatch.setattr(CaptureFolder, "save", real_save)
    # a torn half-line at the end of the journal and a stray temp file, as a crash mid-write leaves them
    with open(tmp_path / "S" / JOURNAL, "ab") as f:
        f.write(b'{"i": 4, "ent')
    (tmp_path / "S" / "frames" / ".0004.tiff.x.tmp").write_bytes(b"partial")
    stage2, cam2 = _devices(triplet_path)
    r = capture(plan, stage2, cam2, tmp_path / "S", quiet=True)
    assert (r.skipped, r.retaken, r.taken) == (2, 1, 4)
    _check_complete(tmp_path / "S", plan)
    assert not list((tmp_path / "S" / "frames").glob(".*"))
    assert len((tmp_path / "S" / JOURNAL).read_text().splitlines()) == 1 + 6


def test_corrupted_committed_frame_is_retaken(tmp_path, triplet_path):
    plan = CapturePlan.from_range(0, 30, 10)
    capture(plan, *_devices(triplet_path), tmp_path / "S", quiet=True)
    victim = tmp_path / "S" / "frames" / "0002.tiff"
    data = bytearray(victim.read_bytes())
    data[-1] ^= 0xFF
    victim.write_bytes(bytes(data))
    r = capture(plan, *_devices(triplet_path), tmp_path / "S", quiet=True)
    assert (r.taken, r.retaken) == (1, 1)
    _check_complete(tmp_path / "S", plan)


def test_changed_plan_is_refused_and_nothing_is_touched(tmp_path, triplet_path):
    capture(CapturePlan.from_range(0, 20, 10), *_devices(triplet_path), tmp_path / "S", quiet=True)
    before = _snapshot(tmp_path / "S")
    stage, cam = _devices(triplet_path)
    with pytest.raises(StackError, match="plan changed"):
        capture(CapturePlan.from_range(0, 30, 10), stage, cam, tmp_path / "S", quiet=True)
    assert stage.moves == [] and _snapshot(tmp_path / "S") == before


def test_plan_outside_travel_is_refused_before_any_motion(tmp_path, triplet_path):
    stage, cam = _devices(triplet_path, lo_um=-100, hi_um=100)
    plan = CapturePlan.from_range(-90, 90, 30)  # the back-off move would go to -110
    with pytest.raises(ParameterError, match="nothing was moved"):
        capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert stage.moves == [] and not stage._referenced and not (tmp_path / "S").exists()


def test_every_frame_sees_the_same_backlash_offset(tmp_path, triplet_path):
    plan = CapturePlan(tuple(PlannedFrame(i, z)
                             for i, z in enumerate([0.0, 30.0, 10.0, 40.0, 20.0])), approach="+z")
    stage, cam = _devices(triplet_path, backlash_um=5.0, noise_um=0.0)
    rendered = []
    real_snap = cam.snap

    def spy():
        f = real_snap()
        rendered.append(f.meta["z_rendered_um"])
        return f

    cam.snap = spy
    capture(plan, stage, cam, tmp_path / "S", quiet=True)
    np.testing.assert_allclose(np.array(rendered) - plan.z_um, -2.5, atol=1e-9)


def test_transient_link_error_is_resynced_and_retried(tmp_path, triplet_path):
    plan = CapturePlan.from_range(0, 40, 10)
    stage, cam = _devices(triplet_path, fail_after=3, fault="timeout", fail_times=1)
    r = capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert r.link_retries == 1 and r.taken == 5
    _check_complete(tmp_path / "S", plan)
    stage, cam = _devices(triplet_path, fail_after=1, fault="timeout")  # persistent: gives up after retries
    with pytest.raises(LinkError):
        capture(plan, stage, cam, tmp_path / "T", quiet=True, retries=2)


def test_ctrl_c_stops_the_stage_and_leaves_a_resumable_folder(tmp_path, triplet_path):
    plan = CapturePlan.from_range(0, 40, 10)
    stage, cam = _devices(triplet_path)
    real_snap, stops, n = cam.snap, [], {"k": 0}

    def snap():
        n["k"] += 1
        if n["k"] == 3:
            raise KeyboardInterrupt
        return real_snap()

    cam.snap = snap
    real_stop = stage.stop
    stage.stop = lambda: (stops.append(1), real_stop())
    with pytest.raises(KeyboardInterrupt):
        capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert stops and len(Stack.open(tmp_path / "S")) == 2
    capture(plan, *_devices(triplet_path), tmp_path / "S", quiet=True)
    _check_complete(tmp_path / "S", plan)


def test_cli_fault_then_resume_then_nothing(tmp_path, triplet_path, capsys):
    out = tmp_path / "S"
    cam = f"sim:{triplet_path},size={SIZE[0]}x{SIZE[1]}"
    argv = ["capture", "--z", "-100", "100", "10", "--camera", cam, "--out", str(out), "--quiet"]
    assert main(argv + ["--stage", "sim:fail_after=7"]) == 3
    err = capsys.readouterr().err
    assert "device error 1024" in err and "resume" in err and "Traceback" not in err
    assert main(argv + ["--stage", "sim"]) == 0
    plan = CapturePlan.from_range(-100, 100, 10)
    s = _check_complete(out, plan)
    assert len(s) == 21 and s.meta["capture"]["camera"]["lens"] == "triplet-uncorrected"
    before = _snapshot(out)
    assert main(argv + ["--stage", "sim"]) == 0
    assert _snapshot(out) == before


def test_cli_dry_run_plan_file_and_errors(tmp_path, triplet_path, capsys):
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"format": "fieldcal-plan/1", "kind": "stack", "direction": "-z", "parameters": {},
                                "frames": [{"z_um": 20.0, "exposure_ms": 5}, {"z_um": 0.0, "exposure_ms": 5}]}))
    cam = f"sim:{triplet_path},size=16x10"
    assert main(["capture", "--plan", str(plan), "--camera", cam, "--out", str(tmp_path / "D"), "--dry-run"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["n_frames"] == 2 and d["approach"] == "-z" and d["disk_bytes"] == 2 * 16 * 10 * 3 * 2
    assert d["motion_range_um"] == [0.0, 40.0] and not (tmp_path / "D").exists()
    assert main(["capture", "--plan", str(plan), "--camera", cam, "--out", str(tmp_path / "E"), "--quiet"]) == 0
    s = Stack.open(tmp_path / "E")
    assert [f.z_um for f in s.frames] == [20.0, 0.0] and s.meta["exposure_ms"] == 5
    rc = main(["capture", "--z", "0", "10", "5", "--stage", "sim:hi_um=5", "--camera", cam, "--out",
               str(tmp_path / "F")])
    assert rc == 2 and "nothing was moved" in capsys.readouterr().err
    (tmp_path / "G").mkdir()
    (tmp_path / "G" / "x.txt").write_text("mine")
    rc = main(["capture", "--z", "0", "10", "5", "--camera", cam, "--out", str(tmp_path / "G")])
    assert rc == 2 and "not a capture folder" in capsys.readouterr().err
    assert (tmp_path / "G" / "x.txt").read_text() == "mine"
