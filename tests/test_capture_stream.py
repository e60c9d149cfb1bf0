"""Plans as message streams: the dry run, the checks and the runner consume one stream; the runner's rewind after
a link error; room for constant-velocity sweeps; the Acquisition's device lifecycle and signals."""

import json
import os
import signal

import numpy as np
import pytest

from fieldcal import Stack
from fieldcal.capture import (JOURNAL, Acquisition, CapturePlan, Checkpoint, CloseExposure, Expose, Interrupted,
                              Move, OpenExposure, PlannedFrame, RunOptions, Runner, Save, Settle, SweepMove, WaitOnTarget,
                              capture, run_capture)
from fieldcal.capture.stream import as_json, check_against_stage, estimate, extent_um
from fieldcal.cli import main
from fieldcal.errors import ParameterError
from fieldcal.hardware.protocols import Frame
from fieldcal.hardware.sim import SimCamera, SimStage

SIZE = (32, 20)


def _devices(lens, **kw):
    stage, cam = SimStage(**kw), SimCamera(lens, size=SIZE, noise=False)
    stage.connect()
    cam.connect()
    cam.observe_stage(stage)
    return stage, cam


def test_the_stream_spells_out_every_action_in_order():
    plan = CapturePlan.from_range(0, 20, 10, exposure_ms=5.0, overshoot_um=15.0)
    got = list(plan.messages(on_target_timeout_ms=1000.0, settle_ms=3.0))
    assert got[:8] == [Checkpoint(0, -15.0), Move(-15.0, "back-off"), WaitOnTarget(1000.0), Move(0.0, "target"),
                       WaitOnTarget(1000.0), Settle(3.0), Expose(0, 5.0), Save(0, 0.0)]
    assert got[8:14] == [Checkpoint(1, -5.0), Move(10.0, "target"), WaitOnTarget(1000.0), Settle(3.0),
                         Expose(1, 5.0), Save(1, 10.0)]  # reached from below already: no back-off
    assert plan.moves() == [(-15.0, False), (0.0, True), (10.0, True), (20.0, True)]
    assert extent_um(got) == plan.motion_range_um() == (-15.0, 20.0)
    # a subset (a resume) backs off before its first frame again: the start position is unknown
    sub = [m for m in plan.messages([2]) if isinstance(m, Move)]
    assert sub == [Move(5.0, "back-off"), Move(20.0, "target")]


def test_the_runner_executes_exactly_the_stream(tmp_path, triplet_path):
    plan = CapturePlan(tuple(PlannedFrame(i, z) for i, z in enumerate([0.0, 30.0, 10.0, 40.0])), approach="+z")
    stage, cam = _devices(triplet_path)
    capture(plan, stage, cam, tmp_path / "S", quiet=True)
    want = [m.z_um for m in plan.messages() if isinstance(m, Move)]
    assert stage.moves == want  # the reference move is not a capture move (SimStage records only MOV targets)
    d = SimStage()
    d.connect()
    acq = Acquisition(d, SimCamera(triplet_path, size=SIZE), handle_signals=False)
    dry = acq.dry_run(plan)
    assert dry["stream"] == as_json(plan.messages())
    assert dry["n_moves"] == len(want) and dry["n_frames"] == 4 and d.moves == []


def test_dry_run_cli_prints_the_stream(tmp_path, triplet_path, capsys):
    cam = f"sim:{triplet_path},size=16x10"
    assert main(["capture", "--z", "0", "20", "10", "--camera", cam, "--out", str(tmp_path / "D"), "--dry-run",
                 "--settle-ms", "5"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["stream"] == as_json(CapturePlan.from_range(0, 20, 10).messages(settle_ms=5.0))
    assert [m["msg"] for m in d["stream"][:8]] == ["Checkpoint", "Move", "WaitOnTarget", "Move", "WaitOnTarget",
                                                  "Settle", "Expose", "Save"]
    assert not (tmp_path / "D").exists()


def test_estimate_walks_the_stream():
    plan = CapturePlan.from_range(0, 100, 50, exposure_ms=10.0, overshoot_um=20.0)
    e = estimate(plan.messages(settle_ms=5.0), velocity_um_s=100.0, readout_ms=30.0, frame_bytes=7)
    # moves: -20 -> 0 -> 50 -> 100 = 120 um at 100 um/s; 3 x (5 settle + 10 exposure + 30 readout)
    assert e == {"n_frames": 3, "n_moves": 4, "time_s": pytest.approx(1.2 + 3 * 0.045), "disk_bytes": 21}


def test_a_link_error_rewinds_to_the_frames_checkpoint(tmp_path, triplet_path):
    plan = CapturePlan.from_range(0, 40, 10, overshoot_um=20.0)
    stage, cam = _devices(triplet_path, fail_after=3, fault="timeout", fail_times=1, backlash_um=4.0,
                          noise_um=0.0)
    r = capture(plan, stage, cam, tmp_path / "S", quiet=True)
    assert r.link_retries == 1 and r.taken == 5
    # moves 0..2 ok (-20, 0, 10); the 4th (to 20) is lost; the runner backs off to 20 - 20 = 0, then 20 again
    assert stage.moves[:5] == [-20.0, 0.0, 10.0, 0.0, 20.0]
    s = Stack.open(tmp_path / "S")
    assert sorted(s.z_um.tolist()) == [0.0, 10.0, 20.0, 30.0, 40.0]


def test_travel_and_velocity_are_checked_on_the_stream():
    stream = [Checkpoint(0, -10.0), Move(-10.0, "back-off"), WaitOnTarget(1.0), SweepMove(-10.0, 90.0, 500.0)]
    assert extent_um(stream) == (-10.0, 90.0)
    check_against_stage(stream, limits_um=(-100, 100), velocity_limit_um_s=1000.0)
    with pytest.raises(ParameterError, match="nothing was moved"):
        check_against_stage(stream, limits_um=(-5, 100))
    with pytest.raises(ParameterError, match="sweeps at 500 um/s"):
        check_against_stage(stream, limits_um=(-100, 100), velocity_limit_um_s=400.0)


class _ExposingCamera(SimCamera):
    """A camera that integrates while the stage moves: one frame from open_exposure to close_exposure."""

    def open_exposure(self):
        self._opened_at = self._position()

    def close_exposure(self):
        z = self._position()
        img = np.full((SIZE[1], SIZE[0], 3), 100, np.uint16)
        return Frame(img, 1, self._exposure_ms, 0.0, {"z_open_um": self._opened_at, "z_close_um": z})


class _SnapOnlyCamera:
    """A camera that only snaps (the simulated camera also exposes during motion)."""

    def __init__(self, *a, **k):
        self.name = "snap-only"


class _ListSink:
    def __init__(self):
        self.saved = []

    def save(self, index, z_um, image, **meta):
        self.saved.append((index, z_um, meta))
        return meta


def test_room_for_a_constant_velocity_sweep(triplet_path):
    stage = SimStage(referenced=True, noise_um=0.0, backlash_um=0.0, velocity_um_per_s=1500.0)
    cam = _ExposingCamera(triplet_path, size=SIZE, noise=False)
    stage.connect()
    cam.connect()
    cam.observe_stage(stage)
    stream = [Checkpoint(0, -60.0), Move(-60.0, "back-off"), WaitOnTarget(1e4), OpenExposure(0, 50.0),
              SweepMove(-60.0, 60.0, 200.0), WaitOnTarget(1e4), CloseExposure(0), Save(0, 0.0)]
    sink = _ListSink()
    assert Runner(stage, cam, sink).run(stream) == 1
    (i, z, meta), = sink.saved
    assert (i, z) == (0, 0.0)
    assert meta["z_measured_before_um"] == pytest.approx(-60.0) and meta["z_measured_after_um"] == pytest.approx(60.0)
    assert stage.velocity_um_per_s() == 1500.0  # the sweep's velocity was restored after the move
    # 60 um back-off at 1500 um/s + 120 um at the sweep's 200 um/s, each a trapezoid (d/v + v/a) + 20 ms settle
    a = stage.acceleration_um_per_s2()
    assert stage._clock_ms == pytest.approx((60 / 1500 + 1500 / a) * 1e3 + 20.0 + (120 / 200 + 200 / a) * 1e3 + 20.0)
    # a camera that cannot expose during motion is refused before anything moves
    plain = _SnapOnlyCamera(triplet_path, size=SIZE)
    s2 = SimStage(referenced=True)
    s2.connect()
    with pytest.raises(ParameterError, match="cannot expose during motion"):
        Runner(s2, plain, _ListSink()).run(stream)
    assert s2.moves == []


class _Spy(SimStage):
    def __init__(self, **kw):
        super().__init__(**kw)
        self.events = []

    def connect(self):
        self.events.append("connect")
        super().connect()

    def close(self):
        self.events.append("close")
        super().close()

    def stop(self):
        self.events.append("stop")
        super().stop()


def test_acquisition_turns_sigterm_into_a_clean_stop(tmp_path, triplet_path):
    stage = _Spy()
    cam = SimCamera(triplet_path, size=SIZE, noise=False)
    real_snap, n = cam.snap, {"k": 0}

    def snap():
        n["k"] += 1
        if n["k"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return real_snap()

    cam.snap = snap
    before = signal.getsignal(signal.SIGTERM)
    plan = CapturePlan.from_range(0, 40, 10)
    with pytest.raises(Interrupted, match="SIGTERM"):
        run_capture(plan, stage, cam, tmp_path / "S", options=RunOptions(quiet=True))
    assert stage.events[0] == "connect" and "stop" in stage.events and stage.events[-1] == "close"
    assert signal.getsignal(signal.SIGTERM) is before  # handlers restored
    assert len(Stack.open(tmp_path / "S")) == 2
    r = run_capture(plan, "sim", f"sim:{triplet_path},size={SIZE[0]}x{SIZE[1]},noise=0", tmp_path / "S",
                    options=RunOptions(quiet=True))
    assert (r.skipped, r.taken) == (2, 3)


def test_a_signal_during_a_commit_waits_for_the_commit(tmp_path, triplet_path):
    from fieldcal.capture import folder as F
    real = F.CaptureFolder._append_journal
    calls = {"n": 0}

    def append(self, line):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGINT)  # between the frame file and its journal line
        real(self, line)

    F.CaptureFolder._append_journal = append
    try:
        with pytest.raises(Interrupted, match="SIGINT"):
            run_capture(CapturePlan.from_range(0, 40, 10), "sim", f"sim:{triplet_path},size=32x20,noise=0",
                        tmp_path / "S", options=RunOptions(quiet=True))
    finally:
        F.CaptureFolder._append_journal = real
    lines = (tmp_path / "S" / JOURNAL).read_text().splitlines()
    assert len(lines) == 1 + 2 and len(Stack.open(tmp_path / "S")) == 2  # the interrupted commit completed


def test_cli_reports_an_interrupt_with_exit_130(tmp_path, triplet_path, capsys, monkeypatch):
    import fieldcal.capture.runner as R
    real = R.Runner._save

    def save(self, m):
        real(self, m)
        raise Interrupted("SIGTERM")

    monkeypatch.setattr(R.Runner, "_save", save)
    rc = main(["capture", "--z", "0", "20", "10", "--camera", f"sim:{triplet_path},size=16x10", "--out",
               str(tmp_path / "S"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 130 and "resumable" in err and "Traceback" not in err


def test_dry_run_that_leaves_the_travel_exits_2_and_moves_nothing(tmp_path, triplet_path, capsys):
    rc = main(["capture", "--z", "0", "100", "50", "--stage", "sim:lo_um=-10,hi_um=100", "--camera",
               f"sim:{triplet_path},size=16x10", "--out", str(tmp_path / "D"), "--dry-run"])
    d = json.loads(capsys.readouterr().out)
    assert rc == 2 and d["fits_travel"] is False and d["motion_range_um"] == [-20.0, 100.0]
    assert not (tmp_path / "D").exists()


def test_a_real_cameras_stack_declares_its_sensor_fixed_mtfs_and_the_simulated_one_does_not():
    """The breathing correction of the band-pass (measure/breathing_mtf.py) divides out the pixel aperture and the
    pupil's diffraction only where the stack says its frames carry them: a camera's do; fieldcal's simulated
    camera renders with the geometric path, whose frames have neither."""
    from fieldcal.capture.acquisition import _stack_header
    from fieldcal.measure.breathing_mtf import declared_factors

    plan = CapturePlan(tuple(PlannedFrame(i, z) for i, z in enumerate([0.0, 10.0])), approach="+z")
    real = _stack_header({"kind": "pylon", "f_number": 4.0, "pixel_pitch_um": 3.45}, {}, plan)
    assert real["sensor_mtf"] == {"pixel_aperture": True, "diffraction": True}
    assert declared_factors(real) == (True, 4.0)
    no_fnum = _stack_header({"kind": "pylon"}, {}, plan)
    assert declared_factors(no_fnum) == (True, None)
    sim = _stack_header({"kind": "sim", "f_number": 4.0}, {}, plan)
    assert "sensor_mtf" not in sim and declared_factors(sim) is None
