"""Sweep capture (issue 17): a pixel-wise sweep plan runs as one exposure over a constant-velocity move, on the
simulated stage + camera + exposure device and on the GCS2 emulator; its masks come from the device files;
the simulated exposure integrates the scene over the sweep with noise counted once."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from fieldcal import Stack
from fieldcal.capture import JOURNAL, CapturePlan, capture
from fieldcal.capture.sweep import SweepCapturePlan
from fieldcal.cli import main
from fieldcal.hardware.exposure import MaskTimeline
from fieldcal.hardware.sim import SimCamera, SimExposureDevice, SimStage
from fieldcal.plan import masks as mk
from fieldcal.simulate import Renderer
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.noise import gain_dn_per_e, to_dn
from fieldcal.simulate.sweep_exposure import render_sweep_exposure, sub_exposure_edges_ms, sweep_signal

SIZE = "64x36"


def _plan(d, triplet_path, name, *extra):
    plan = d / f"{name}.json"
    assert main(["plan", "sweep", str(triplet_path), "--size", SIZE, "--alpha-um", "20", "--out", str(plan),
                 *extra]) == 0
    assert main(["plan", "export-masks", str(plan), "--out", str(d / f"{name}-masks")]) == 0
    return plan, d / f"{name}-masks"


@pytest.fixture(scope="module")
def sweep_files(tmp_path_factory, request):
    from pathlib import Path
    triplet = Path(__file__).resolve().parents[1] / "models" / "triplet-uncorrected.json"
    d = tmp_path_factory.mktemp("sweep")
    fast = _plan(d, triplet, "fast", "--pixel-exposure-ms", "10", "--device", "pixel")   # 4 um/ms
    slow = _plan(d, triplet, "slow", "--pixel-exposure-ms", "40", "--device", "pixel")   # 1 um/ms
    lcos = _plan(d, triplet, "lcos", "--pixel-exposure-ms", "16", "--device", "lcos", "--channels", "G")
    return {"fast": fast, "slow": slow, "lcos": lcos, "triplet": triplet, "dir": d}


def _cam(triplet, step="4"):
    return f"sim:{triplet},size={SIZE},sub_step_um={step}"


def _entries(out):
    return [json.loads(line)["entry"] for line in (out / JOURNAL).read_text().splitlines()[1:]]


# ------------------------------------------------------------------------------------------- end to end
def test_a_sweep_runs_end_to_end_on_the_simulated_devices(sweep_files, tmp_path):
    plan_path, masks = sweep_files["fast"]
    doc = json.loads(plan_path.read_text())
    out = tmp_path / "swept"
    argv = ["capture", "--plan", str(plan_path), "--stage", "sim", "--camera", _cam(sweep_files["triplet"]),
            "--exposure-device", f"sim:{masks}", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    (e,) = _entries(out)
    sw = e["sweep"]
    v_um_s = doc["velocity_um_per_ms"] * 1000.0
    # the exposure opened at the plan's start and closed at its stop, at the plan's velocity (stage clock)
    assert sw["z_open_measured_um"] == pytest.approx(doc["start_um"], abs=1e-6)
    assert sw["z_close_measured_um"] == pytest.approx(doc["stop_um"], abs=1e-6)
    t0, t1 = sw["stage_clock_ms"]
    assert (t1 - t0) == pytest.approx(doc["total_time_ms"], rel=1e-6)
    assert (sw["z_close_measured_um"] - sw["z_open_measured_um"]) / (t1 - t0) * 1000 == pytest.approx(v_um_s,
                                                                                                    rel=1e-3)
    assert e["exposure_ms"] == pytest.approx(doc["total_time_ms"], rel=1e-6)
    # the move began a run-up v^2 / 2a before the range (acceleration outside the exposure) and ran out as far
    meta = json.loads((out / "stack.json").read_text())
    run_up = v_um_s ** 2 / (2 * meta["capture"]["stage"]["accel_um_per_s2"])
    assert meta["capture"]["sweep"]["run_up_um"] == pytest.approx(run_up)
    assert sw["move_um"] == pytest.approx([doc["start_um"] - run_up, doc["stop_um"] + run_up])
    s = Stack.open(out)
    assert len(s.frames) == 1 and s.verify_checksums() == []
    img = s.read(0)
    assert img.shape[:2] == (36, 64) and 0 < img.mean() < 4095
    before = {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main(argv) == 0  # complete: a re-run changes nothing
    assert {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_velocity_and_travel_are_refused_before_anything_moves(sweep_files, tmp_path, capsys):
    plan_path, masks = sweep_files["fast"]  # 4000 um/s
    for stage, msg in (("sim:max_velocity_um_per_s=2000", "allows at most 2000 um/s"),
                       ("sim:lo_um=-400,hi_um=400", "travel is -400..400 um")):
        out = tmp_path / stage.replace(":", "_").replace(",", "_")
        rc = main(["capture", "--plan", str(plan_path), "--stage", stage, "--camera", _cam(sweep_files["triplet"]),
                   "--exposure-device", f"sim:{masks}", "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "nothing was moved" in err and "Traceback" not in err
        assert not out.exists()
    # the same refusal in the API, with the stage's own log showing no move
    plan = CapturePlan.from_file(plan_path)
    stage = SimStage(referenced=True, max_velocity_um_per_s=2000.0)
    stage.connect()
    with pytest.raises(Exception, match="allows at most"):
        plan.bind(stage)
    assert stage.moves == []


def test_what_capture_refuses_about_sweep_plans(sweep_files, tmp_path, capsys):
    fast, fast_masks = sweep_files["fast"]
    cam = _cam(sweep_files["triplet"])
    cases = [
        (["--plan", str(sweep_files["lcos"][0])], "capture runs sweeps for a pixel-wise exposure sensor only"),
        (["--plan", str(fast)], "needs an exposure device"),
        (["--plan", str(fast), "--exposure-device", f"sim:{sweep_files['slow'][1]}"], "exported from another plan"),
        (["--plan", str(fast), "--exposure-device", f"sim:{fast_masks}", "--exposure-ms", "5"], "--exposure-ms"),
        (["--z", "0", "10", "10", "--exposure-device", f"sim:{fast_masks}"], "a stack plan takes frames without"),
    ]
    for extra, msg in cases:
        out = tmp_path / "S"
        rc = main(["capture", *extra, "--stage", "sim", "--camera", cam, "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "Traceback" not in err, (extra, err)
        assert not out.exists()


def test_the_dry_run_shows_the_run_up_and_the_triggered_exposure(sweep_files, capsys):
    plan_path, masks = sweep_files["fast"]
    assert main(["capture", "--plan", str(plan_path), "--stage", "sim", "--camera", _cam(sweep_files["triplet"]),
                 "--exposure-device", f"sim:{masks}", "--out", "unused", "--dry-run"]) == 0
    r = json.loads(capsys.readouterr().out)
    kinds = [m["msg"] for m in r["stream"]]
    assert kinds == ["Checkpoint", "Move", "WaitOnTarget", "SweepMove", "OpenExposure", "CloseExposure",
                     "WaitOnTarget", "Save"]
    doc = json.loads(plan_path.read_text())
    assert r["stream"][4]["at_um"] == doc["start_um"] and r["stream"][5]["at_um"] == doc["stop_um"]
    assert r["stream"][3]["velocity_um_s"] == pytest.approx(doc["velocity_um_per_ms"] * 1000)


# ------------------------------------------------------------------------------------------------ masks
@pytest.mark.parametrize("kind", ["fast", "lcos"])
def test_masks_loaded_from_the_device_files_equal_the_plans_windows(sweep_files, kind):
    plan_path, folder = sweep_files[kind]
    doc = json.loads(plan_path.read_text())
    npz = mk.load_npz(plan_path.with_name(doc["masks"]["file"]))
    dev = SimExposureDevice.from_spec(str(folder), {})
    tl = dev.timeline
    if kind == "lcos":
        assert np.array_equal(dev.arrays["mask_bits"], npz["mask_bits"])
        # every exposed pixel is open for exactly t_s over the sweep (slots whose centre is in its window)
        T = doc["device"]["n_slots"] * doc["device"]["slot_ms"]
    else:
        assert np.array_equal(dev.arrays["start_tick"], npz["start_tick"])
        assert np.array_equal(dev.arrays["stop_tick"], npz["stop_tick"])
        clk = doc["device"]["clock_ms"]
        ok = np.isfinite(npz["window_start_ms"])
        # the sidecar keeps float32 times: half a clock tick plus float32 rounding of the largest time
        tol = clk / 2 + 2 * float(np.spacing(np.float32(np.nanmax(npz["window_stop_ms"]))))
        assert np.abs(tl.start_ms[ok] - npz["window_start_ms"][ok]).max() <= tol
        assert np.abs(tl.stop_ms[ok] - npz["window_stop_ms"][ok]).max() <= tol
        T = doc["total_time_ms"]
    edges = np.linspace(0.0, T, 97)
    open_ms = sum(tl.open_fraction(a, b) * (b - a) for a, b in zip(edges[:-1], edges[1:]))
    exposed = open_ms > 0
    assert exposed.mean() > 0.9
    assert np.allclose(open_ms[exposed], doc["pixel_exposure_ms"], rtol=1e-4)


# ------------------------------------------------------------------------------------------ the physics
@pytest.fixture
def flat_renderer(triplet_path):
    spec = LensSpec.load(triplet_path).with_sensor_size(48, 27)
    spec = dataclasses.replace(spec, sensor=dataclasses.replace(spec.sensor, read_noise_e=40.0))
    return Renderer(spec, np.full((27, 48), 0.5), seed=0)


def test_noise_is_counted_once_for_the_whole_exposure(flat_renderer):
    r, n_sub, T = flat_renderer, 32, 10.0
    z = lambda t: -150.0 + 10.0 * t  # noqa: E731
    clean = render_sweep_exposure(r, z, T, n_sub=n_sub).astype(np.float64)
    a = render_sweep_exposure(r, z, T, n_sub=n_sub, rng=np.random.default_rng(1)).astype(np.float64)
    b = render_sweep_exposure(r, z, T, n_sub=n_sub, rng=np.random.default_rng(2)).astype(np.float64)
    s = r.spec.sensor
    g = gain_dn_per_e(s)
    once = g * (clean - s.black_level_dn) + (g * s.read_noise_e) ** 2 + 1 / 12      # one read-out
    per_sub = g * (clean - s.black_level_dn) + n_sub * (g * s.read_noise_e) ** 2 + 1 / 12  # N read-outs
    ratio_once = np.mean((a - b) ** 2 / (2 * once))
    ratio_sub = np.mean((a - b) ** 2 / (2 * per_sub))
    assert ratio_once == pytest.approx(1.0, abs=0.08)
    assert ratio_sub < 0.15  # N read-outs would have ~10x the variance seen


def test_the_noise_free_sweep_is_the_mean_of_the_masked_frames(flat_renderer, triplet_path):
    r = Renderer(flat_renderer.spec, np.random.default_rng(0).random((27, 48)), seed=0)
    T, n = 12.0, 24
    z = lambda t: -200.0 + 25.0 * t  # noqa: E731
    start = np.random.default_rng(1).uniform(0, 8, size=(1, 27, 48))
    tl = MaskTimeline("pixelwise", ("Y",), T, 48, start_ms=start, stop_ms=start + 4.0)
    w = lambda t0, t1: tl.open_fraction(t0, t1)[0][:, :, None]  # noqa: E731
    got = sweep_signal(r.render_float, z, T, r.spec.sensor.exposure_ms, n_sub=n, weights=w)
    edges = sub_exposure_edges_ms(T, n)
    frames = [r.render_float(z(0.5 * (a + b))) * w(a, b) for a, b in zip(edges[:-1], edges[1:])]
    want = np.mean(frames, axis=0) * (T / r.spec.sensor.exposure_ms)
    assert np.allclose(got, want, rtol=1e-5, atol=1e-7)
    img = render_sweep_exposure(r, z, T, n_sub=n, weights=w)
    assert np.array_equal(img, to_dn(want.astype(np.float32), r.spec.sensor, None))
    # a pixel open for 4 of 12 ms collects a third of the always-open exposure's signal at a static position
    still = sweep_signal(r.render_float, lambda t: -50.0, T, r.spec.sensor.exposure_ms, n_sub=n, weights=w)
    full = sweep_signal(r.render_float, lambda t: -50.0, T, r.spec.sensor.exposure_ms, n_sub=n)
    inside = (start[0] >= 0.5) & (start[0] + 4.0 <= T - 0.5)
    assert np.allclose(still[inside], full[inside] / 3.0, rtol=1e-5)


# ------------------------------------------------------------------------------------------ GCS2 emulator
def test_a_sweep_runs_on_the_gcs2_emulator_with_the_plans_velocity_and_move(sweep_files, tmp_path):
    from fieldcal.hardware.gcs2 import GCS2Stage
    from fieldcal.hardware.gcs2_emulator import GCS2Emulator, ManualClock, TcpServer
    plan_path, masks = sweep_files["slow"]  # 1 mm/s: within the M-111's 2 mm/s
    doc = json.loads(plan_path.read_text())
    emu = GCS2Emulator(settle_ms=2.0, clock=ManualClock(tick_s=0.0005), accel_mm_s2=20.0)
    emu.set_referenced_at(7.5)
    with TcpServer(emu) as srv:
        stage = GCS2Stage(srv.url, timeout_ms=300, poll_ms=1, trigger_out=1)
        cam = SimCamera(sweep_files["triplet"], size=(64, 36), sub_step_um=4.0)
        dev = SimExposureDevice(masks)
        stage.connect()
        cam.connect()
        cam.observe_stage(stage)
        dev.connect()
        try:
            plan = CapturePlan.from_file(plan_path)
            assert isinstance(plan, SweepCapturePlan)
            r = capture(plan, stage, cam, tmp_path / "S", quiet=True, exposure_device=dev)
        finally:
            stage.close()
    assert r.taken == 1
    v_mm_s = doc["velocity_um_per_ms"]  # um/ms = mm/s
    run_up_mm = v_mm_s ** 2 / (2 * 20.0)
    a_mm, b_mm = 7.5 + doc["start_um"] / 1000 - run_up_mm, 7.5 + doc["stop_um"] / 1000 + run_up_mm
    vel = [m for m in emu.motion_log if m["cmd"] == "VEL"]
    mov = [m for m in emu.motion_log if m["cmd"] == "MOV"]
    assert vel[0]["value"] == pytest.approx(v_mm_s, rel=1e-3)          # the plan's velocity ...
    assert mov[0]["value"] == pytest.approx(a_mm, rel=1e-3)             # ... from the run-up start ...
    assert mov[1]["value"] == pytest.approx(b_mm, rel=1e-3)             # ... to the run-out end
    assert mov[1]["value"] - mov[0]["value"] == pytest.approx(b_mm - a_mm, rel=1e-3)
    assert vel[0]["t_s"] <= mov[1]["t_s"] and vel[1]["value"] == pytest.approx(1.5)  # restored after the sweep
    # the emulated move lasted d / v + v / a
    t0, a, b, dur = emu._seg
    assert dur == pytest.approx((b_mm - a_mm) / v_mm_s + v_mm_s / 20.0, rel=1e-6)
    # the trigger output pulsed where the exposure opens and closes
    pulses = [p["pos_mm"] for p in emu.trigger_log]
    assert pulses == pytest.approx([7.5 + doc["start_um"] / 1000, 7.5 + doc["stop_um"] / 1000], abs=1e-6)
    assert "CTO 1 2 1" in emu.received and "CTO 1 3 0" in emu.received and "TRO 1 0" in emu.received
    (e,) = _entries(tmp_path / "S")
    # polled POS?: the exposure opened within a few um of the start (one poll at 1 mm/s)
    assert e["sweep"]["z_open_measured_um"] == pytest.approx(doc["start_um"], abs=5.0)
    assert e["sweep"]["z_close_measured_um"] == pytest.approx(doc["stop_um"], abs=5.0)
    assert math.isfinite(Stack.open(tmp_path / "S").read(0).mean())
