"""Simulated devices, device strings and plug-ins, and the Basler backend on pylon's camera emulator."""

import math
import os
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import LinkError, ParameterError
from fieldcal.hardware import registry
from fieldcal.hardware.protocols import Camera, DeviceFault, Stage
from fieldcal.hardware.registry import make_device, parse_device_string
from fieldcal.hardware.sim import SimCamera, SimStage


def _stage(**kw):
    s = SimStage(referenced=True, **kw)
    s.connect()
    return s


def test_sim_devices_satisfy_the_protocols(triplet_path):
    assert isinstance(SimStage(), Stage)
    assert isinstance(SimCamera(triplet_path, size=(32, 18)), Camera)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-500, 500, allow_nan=False), min_size=2, max_size=8), st.floats(0.5, 10))
def test_backlash_offset_depends_only_on_the_last_direction(targets, backlash_um):
    s = _stage(backlash_um=backlash_um, noise_um=0.0)
    for z in targets:
        s.move_to_um(z)
        s.wait_on_target(1e9)
        assert s.position_um() == pytest.approx(z)
        if s.moves[-1] != (s.moves[-2] if len(s.moves) > 1 else 0.0):
            d = math.copysign(1.0, z - (s.moves[-2] if len(s.moves) > 1 else 0.0))
            assert s.true_position_um() == pytest.approx(z - d * backlash_um / 2)


def test_settle_time_and_on_target_use_the_virtual_clock():
    s = _stage(velocity_um_per_s=1000.0, settle_ms=20.0)
    s.move_to_um(100.0)
    assert not s.on_target()
    s.wait_on_target(1000)
    # trapezoid: |dz|/v + v/a (100 ms + 1000/50000 s), then the settle time
    assert s.on_target() and s._clock_ms == pytest.approx(100.0 + 1000.0 / 50000.0 * 1000.0 + 20.0)


def test_servo_noise_is_seeded_and_of_the_stated_size():
    a, b = _stage(noise_um=0.5, seed=3), _stage(noise_um=0.5, seed=3)
    err = []
    for z in np.linspace(-100, 100, 200):
        for s in (a, b):
            s.move_to_um(float(z))
            s.wait_on_target(1e9)
        assert a.position_um() == b.position_um()
        err.append(a.position_um() - z)
    assert 0.4 < np.std(err) < 0.6


def test_limits_and_reference_are_enforced():
    s = SimStage(lo_um=-100, hi_um=100)
    s.connect()
    with pytest.raises(DeviceFault) as e:
        s.move_to_um(0.0)
    assert e.value.code == 5
    s.reference()
    with pytest.raises(DeviceFault) as e:
        s.move_to_um(150.0)
    assert e.value.code == 7


@pytest.mark.parametrize("fault,exc", [("motion", DeviceFault), ("timeout", LinkError), ("garbled", LinkError),
                                       ("disconnect", LinkError)])
def test_fail_after_n_moves(fault, exc):
    s = _stage(fail_after=3, fault=fault)
    for z in (1.0, 2.0, 3.0):
        s.move_to_um(z)
        s.wait_on_target(1e9)
    with pytest.raises(exc):
        s.move_to_um(4.0)
        s.wait_on_target(1e9)
        s.position_um()


def test_transient_link_fault_recovers_after_resync():
    s = _stage(fail_after=1, fault="timeout", fail_times=1)
    s.move_to_um(1.0)
    with pytest.raises(LinkError):
        s.move_to_um(2.0)
    s.resync()
    s.move_to_um(2.0)
    s.wait_on_target(1e9)
    assert s.position_um() == pytest.approx(2.0, abs=0.5)


def test_disconnect_survives_resync():
    s = _stage(fail_after=0, fault="disconnect")
    with pytest.raises(LinkError):
        s.move_to_um(1.0)
    with pytest.raises(LinkError):
        s.resync()


def test_sim_camera_renders_at_the_true_stage_position(triplet_path):
    from fieldcal.simulate import Renderer
    cam = SimCamera(triplet_path, size=(48, 27), noise=False)
    stage = _stage(backlash_um=6.0, noise_um=0.0)
    cam.observe_stage(stage)
    cam.connect()
    stage.move_to_um(-150.0)
    stage.wait_on_target(1e9)
    f = cam.snap()
    assert f.image.shape == (27, 48, 3) and f.frame_id == 1
    assert f.meta["z_rendered_um"] == pytest.approx(-147.0)  # moved down: carriage lags 3 um above
    ref = Renderer(cam.spec, cam._scene(), seed=0).render(-147.0, noise=False)
    np.testing.assert_array_equal(f.image, ref.reshape(f.image.shape))
    other = Renderer(cam.spec, cam._scene(), seed=0).render(-150.0, noise=False)
    assert not np.array_equal(f.image, other.reshape(f.image.shape))
    cam.configure(roi=(4, 2, 16, 8))
    assert cam.snap().image.shape == (8, 16, 3)
    with pytest.raises(DeviceFault):
        cam.configure(roi=(40, 0, 16, 8))


@given(st.sampled_from(["sim", "gcs", "pi", "mylab"]),
       st.one_of(st.none(), st.sampled_from(["/dev/ttyUSB0", "COM3", "socket://127.0.0.1:50000", "models/x.json"])),
       st.dictionaries(st.sampled_from(["axis", "size", "fail_after", "zero_mm"]),
                       st.from_regex(r"[A-Za-z0-9_.x-]{1,8}", fullmatch=True), max_size=3))
def test_device_strings_round_trip(kind, arg, options):
    parts = ([arg] if arg else []) + [f"{k}={v}" for k, v in options.items()]
    text = kind + (":" + ",".join(parts) if parts else "")
    assert parse_device_string(text) == (kind, arg, options)


def test_bad_device_strings_name_the_fix(triplet_path):
    with pytest.raises(ParameterError, match="no stage backend called 'nope'"):
        make_device("stage", "nope:x")
    with pytest.raises(ParameterError, match="unknown option"):
        make_device("stage", "sim:fail_aftr=3")
    with pytest.raises(ParameterError, match="not a number"):
        make_device("stage", "sim:fail_after=x")
    with pytest.raises(ParameterError, match="not found"):
        make_device("camera", "sim:missing.json")
    with pytest.raises(ParameterError, match="WIDTHxHEIGHT"):
        make_device("camera", f"sim:{triplet_path},size=big")
    assert make_device("camera", f"sim:{triplet_path},size=40x30").size == (40, 30)


class _LabStage(SimStage):
    pass


def test_a_plug_in_backend_needs_no_core_change(monkeypatch):
    ep = SimpleNamespace(name="lab", value="mylab:LabStage", load=lambda: _LabStage)
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep] if group == "fieldcal.stages" else [])
    dev = make_device("stage", "lab:backlash_um=1")
    assert type(dev) is _LabStage and dev._backlash_um == 1.0
    assert "lab" in registry.available("stage")
    # a plain callable works as well
    ep2 = SimpleNamespace(name="cb", value="mylab:make", load=lambda: lambda arg, **o: ("made", arg, o))
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep2])
    assert make_device("stage", "cb:PORT,k=v") == ("made", "PORT", {"k": "v"})


def test_pylon_camera_replays_images_on_the_emulator(tmp_path):
    os.environ.setdefault("PYLON_CAMEMU", "1")
    pylon = pytest.importorskip("pypylon.pylon")
    import cv2
    if not pylon.TlFactory.GetInstance().EnumerateDevices():
        pytest.skip("no pylon (emulated) camera")
    from fieldcal.hardware.camera_pylon import PylonCamera
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (24, 32), dtype=np.uint8) for _ in range(2)]
    for k, im in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"{k}.png"), im)
    cam = make_device("camera", f"pylon:,pixel_pitch_um=3.45,pixel_format=Mono8,images={tmp_path}")
    assert isinstance(cam, PylonCamera)
    cam.connect()
    try:
        cam.configure(exposure_ms=2.0)
        got = [cam.snap() for _ in range(3)]
    finally:
        cam.close()
    assert [f.exposure_ms for f in got] == [2.0] * 3
    assert len({f.frame_id for f in got}) == 3
    for f in got:
        assert f.image.shape == (24, 32, 1)
        assert any(np.array_equal(f.image[:, :, 0], im) for im in imgs)
    assert not np.array_equal(got[0].image, got[1].image)  # the files are replayed in turn


def test_pylon_needs_the_pixel_pitch():
    with pytest.raises(ParameterError, match="pixel_pitch_um"):
        make_device("camera", "pylon")


@pytest.mark.parametrize("text,field", [("gcs:/dev/x,timeout_ms=nan", "timeout_ms"), ("gcs:/dev/x,zero_mm=inf", "zero_mm"),
                                        ("gcs:/dev/x,poll_ms=0", "poll_ms"), ("gcs:/dev/x,velocity_mm_s=-1", "velocity_mm_s"),
                                        ("gcs:/dev/x,baud=0", "baud"), ("sim:settle_ms=inf", "settle_ms"),
                                        ("sim:velocity_um_per_s=nan", "velocity_um_per_s")])
def test_device_options_must_be_finite_and_in_range(text, field):
    with pytest.raises(ParameterError) as e:
        make_device("stage", text)
    assert e.value.field == field and "fix:" in str(e.value)
