"""The pylon backend against a fake pypylon that behaves as pypylon and Basler's documents say a camera does.

What the fake reproduces, and where it is written down:
* pypylon's attribute lookup (``pypylon.pylon._LookupParameter``: "GetNode always returns a parameter and does
  not throw"): ``camera.AnyName`` is a parameter object even when the camera has no such node -- ``hasattr`` is
  always True; the object's ``IsValid()`` is False and reading or writing its ``Value`` raises
  ``genicam.LogicalErrorException``.
* Older Basler cameras (ace GigE) name the exposure time ``ExposureTimeAbs`` (µs), newer ones (SFNC 2)
  ``ExposureTime`` (µs) (Basler pylon API, ``PLCamera.ExposureModeEnum.Timed``: "determined by the value of the
  camera's Exposure Time (Abs) parameter"; docs.baslerweb.com/exposure-time-(dart-e): "Set the ExposureTime
  parameter to the desired exposure time in microseconds").
* ``ExposureAuto``/``GainAuto`` = ``Continuous`` keep adjusting while images are acquired; to set the exposure,
  "Set the ExposureAuto parameter to Off" first (docs.baslerweb.com/exposure-time-(dart-e), /gain-auto).
* ``TimeStamp`` counts camera ticks; "on GigE cameras, read the value of the GevTimestampTickFrequency
  parameter to determine the current tick frequency" (docs.baslerweb.com/timestamp).
"""

import sys
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest

from fieldcal.errors import LinkError
from fieldcal.hardware.camera_pylon import PylonCamera


class GenericException(Exception):
    pass


class LogicalErrorException(GenericException):
    pass


class AccessException(GenericException):
    pass


class _Param:
    def __init__(self, cam, name):
        self._cam, self._name = cam, name

    def IsValid(self):
        return self._name in self._cam.nodes

    def IsWritable(self):
        return self.IsValid() and self._cam.writable(self._name)

    def IsReadable(self):
        return self.IsValid()

    @property
    def Value(self):
        if not self.IsValid():
            raise LogicalErrorException(f"Cannot get value of 'Camera/{self._name}'. The parameter is not available.")
        return self._cam.nodes[self._name]

    @Value.setter
    def Value(self, v):
        if not self.IsValid():
            raise LogicalErrorException(f"Cannot set value of 'Camera/{self._name}'. The parameter is not available.")
        if not self._cam.writable(self._name):
            raise AccessException(f"Node '{self._name}' is not writable")
        if self._name in self._cam.enums and v not in self._cam.enums[self._name]:
            raise GenericException(f"Feature '{self._name}' does not have the value '{v}'")
        self._cam.nodes[self._name] = v

    @property
    def Symbolics(self):
        return tuple(self._cam.enums[self._name])


class _Result:
    def __init__(self, cam, ok=True, valid=True):
        self._cam, self._ok, self._valid = cam, ok, valid
        self.released = False
        if valid:
            cam.results.append(self)
        self.Array = np.full((6, 8), 100, np.uint16)
        self.BlockID = len(cam.results)
        self.TimeStamp = cam.ticks

    def IsValid(self):
        return self._valid

    def GrabSucceeded(self):
        return self._ok

    def GetErrorCode(self):
        return 0 if self._ok else 3774873620

    def GetErrorDescription(self):
        return "" if self._ok else "The buffer was incompletely grabbed."

    def Release(self):
        self.released = True


class FakeCamera:
    """An older Basler ace GigE as pypylon shows it: ExposureTimeAbs, auto functions left Continuous."""

    def __init__(self, nodes, enums=None):
        object.__setattr__(self, "nodes", dict(nodes))
        object.__setattr__(self, "enums", dict(enums or {"PixelFormat": ("Mono8", "Mono12", "Mono12Packed")}))
        object.__setattr__(self, "results", [])
        object.__setattr__(self, "used_exposure_us", [])
        object.__setattr__(self, "ticks", 0)
        object.__setattr__(self, "fail_next", False)
        object.__setattr__(self, "late_next", False)  # the next frame arrives after RetrieveResult gave up
        object.__setattr__(self, "queue", [])         # pylon's output queue (GrabStrategy_OneByOne: FIFO)
        object.__setattr__(self, "late", [])

    def __getattr__(self, name):  # pypylon: any name gives a parameter object
        return _Param(self, name)

    def writable(self, name):
        if name in ("ExposureTime", "ExposureTimeAbs") and self.nodes.get("ExposureAuto") == "Continuous":
            return False  # the auto function owns the exposure time
        return True

    # camera calls
    def Open(self): pass
    def Close(self): pass
    def StartGrabbing(self, strategy): pass
    def StopGrabbing(self): pass

    def WaitForFrameTriggerReady(self, timeout_ms, handling):
        return True

    def ExecuteSoftwareTrigger(self):
        exp = "ExposureTime" if "ExposureTime" in self.nodes else "ExposureTimeAbs"
        # ExposureMode Timed: "the exposure time ... is determined by the value of the camera's Exposure Time
        # (Abs) parameter"; in TriggerWidth the trigger signal's width decides (a software trigger has none)
        timed = self.nodes.get("ExposureMode", "Timed") == "Timed"
        self.used_exposure_us.append(self.nodes[exp] if timed else None)
        if self.nodes.get("ExposureAuto") == "Continuous":
            self.nodes[exp] *= 1.5  # the auto function adjusts the next exposure
        object.__setattr__(self, "ticks", self.ticks + 250_000_000)
        res = _Result(self, not self.fail_next)
        object.__setattr__(self, "fail_next", False)
        (self.late if self.late_next else self.queue).append(res)
        object.__setattr__(self, "late_next", False)

    def RetrieveResult(self, timeout_ms, handling):
        if self.queue:
            return self.queue.pop(0)
        self.queue.extend(self.late)  # TimeoutHandling_Return: an invalid result; the late frame lands after
        self.late.clear()
        return _Result(self, valid=False)

    def GetDeviceInfo(self):
        return SimpleNamespace(GetModelName=lambda: "acA1300-30gm", GetSerialNumber=lambda: "123")


def _fake_pypylon(monkeypatch, cam):
    pkg = ModuleType("pypylon")
    genicam = ModuleType("pypylon.genicam")
    genicam.GenericException = GenericException
    pylon = ModuleType("pypylon.pylon")
    dev = SimpleNamespace(GetSerialNumber=lambda: "123", GetModelName=lambda: "acA1300-30gm")
    tl = SimpleNamespace(EnumerateDevices=lambda: [dev], CreateDevice=lambda d: d)
    pylon.TlFactory = SimpleNamespace(GetInstance=lambda: tl)
    pylon.InstantCamera = lambda d: cam
    pylon.GrabStrategy_OneByOne = 0
    pylon.TimeoutHandling_Return = 0
    pkg.genicam, pkg.pylon = genicam, pylon
    monkeypatch.setitem(sys.modules, "pypylon", pkg)
    monkeypatch.setitem(sys.modules, "pypylon.genicam", genicam)
    monkeypatch.setitem(sys.modules, "pypylon.pylon", pylon)


_OLD_ACE_GIGE = {"ExposureTimeAbs": 10000.0, "ExposureAuto": "Continuous", "GainAuto": "Continuous",
                 "GainRaw": 192, "ExposureMode": "Timed", "PixelFormat": "Mono8", "TriggerSelector": "FrameStart",
                 "TriggerMode": "Off", "TriggerSource": "Line1", "Width": 8, "Height": 6,
                 "GevTimestampTickFrequency": 125_000_000}


@pytest.fixture
def old_ace(monkeypatch):
    cam = FakeCamera(_OLD_ACE_GIGE)
    _fake_pypylon(monkeypatch, cam)
    pc = PylonCamera(None, pixel_pitch_um=3.75, pixel_format="Mono12")
    pc.connect()
    yield cam, pc
    pc.close()


def test_a_camera_with_exposure_time_abs_only_is_set_through_it(old_ace):
    cam, pc = old_ace
    pc.configure(exposure_ms=2.0)
    assert cam.nodes["ExposureTimeAbs"] == pytest.approx(2000.0)  # µs
    assert "ExposureTime" not in cam.nodes
    f = pc.snap()
    assert f.exposure_ms == pytest.approx(2.0)


def test_auto_exposure_and_auto_gain_are_switched_off_so_every_frame_has_the_set_exposure(old_ace):
    cam, pc = old_ace
    assert cam.nodes["ExposureAuto"] == "Off" and cam.nodes["GainAuto"] == "Off"
    pc.configure(exposure_ms=3.5)
    frames = [pc.snap() for _ in range(3)]
    assert cam.used_exposure_us == pytest.approx([3500.0] * 3)  # what the sensor really integrated
    assert [f.exposure_ms for f in frames] == pytest.approx([3.5] * 3)
    assert cam.nodes["TriggerMode"] == "On" and cam.nodes["TriggerSource"] == "Software"
    assert cam.nodes["TriggerSelector"] == "FrameStart"


def test_an_exposure_the_camera_never_stated_is_read_from_the_node_it_has(old_ace):
    cam, pc = old_ace
    f = pc.snap()  # no configure(): the camera's own setting is recorded
    assert f.exposure_ms == pytest.approx(10.0)


def test_timestamps_are_converted_with_the_camera_tick_frequency(old_ace):
    cam, pc = old_ace
    a, b = pc.snap(), pc.snap()
    # 250e6 ticks per frame at 125 MHz = 2 s
    assert b.timestamp_ms - a.timestamp_ms == pytest.approx(2000.0)
    assert a.timestamp_ms == pytest.approx(2000.0)


def test_a_failed_grab_names_pylon_error_code_and_description_and_releases_the_buffer(old_ace):
    cam, pc = old_ace
    cam.fail_next = True
    with pytest.raises(LinkError) as e:
        pc.snap()
    assert "incompletely grabbed" in str(e.value) and "0xe1000014" in str(e.value)
    assert cam.results[-1].released


def test_the_pfnc_and_the_older_gige_name_of_a_pixel_format_are_one_format(monkeypatch):
    # Basler /pixel-format: "Set the PixelFormat parameter to one of the following values (if available): ...
    # RGB8, BGR8" (GenICam PFNC 2.1 names); older GigE cameras name the same format RGB8Packed
    cam = FakeCamera(_OLD_ACE_GIGE, enums={"PixelFormat": ("Mono8", "RGB8", "BGR8")})
    _fake_pypylon(monkeypatch, cam)
    pc = PylonCamera(None, pixel_pitch_um=3.45, pixel_format="RGB8Packed")
    pc.connect()
    try:
        assert cam.nodes["PixelFormat"] == "RGB8"
        assert pc.describe()["pixel_format"] == "RGB8" and pc.describe()["channels"] == ["R", "G", "B"]
    finally:
        pc.close()


def test_a_pixel_format_the_camera_lacks_is_a_clear_error_listing_its_formats(monkeypatch):
    from fieldcal.errors import ParameterError
    cam = FakeCamera(_OLD_ACE_GIGE, enums={"PixelFormat": ("Mono8", "RGB8")})
    _fake_pypylon(monkeypatch, cam)
    pc = PylonCamera(None, pixel_pitch_um=3.45, pixel_format="Mono12")
    with pytest.raises(ParameterError) as e:
        pc.connect()
    assert e.value.field == "pixel_format" and "Mono8" in str(e.value) and "fix:" in str(e.value)


def test_the_exposure_mode_is_set_to_timed(monkeypatch):
    cam = FakeCamera({**_OLD_ACE_GIGE, "ExposureMode": "TriggerWidth"})
    _fake_pypylon(monkeypatch, cam)
    pc = PylonCamera(None, pixel_pitch_um=3.75, pixel_format="Mono8")
    pc.connect()
    try:
        pc.configure(exposure_ms=1.25)
        pc.snap()
        assert cam.nodes["ExposureMode"] == "Timed" and cam.used_exposure_us == pytest.approx([1250.0])
    finally:
        pc.close()


def test_a_frame_that_arrives_after_its_time_out_is_not_taken_for_the_next_position(old_ace):
    # Basler GrabStrategy: OneByOne -- "Images are processed in the order of their arrival": a frame that came
    # late is the first in the queue at the next RetrieveResult, though it was exposed at the previous position
    cam, pc = old_ace
    cam.late_next = True
    with pytest.raises(LinkError, match="no frame"):
        pc.snap()
    f = pc.snap()
    assert f.frame_id == 2  # the frame of this trigger, not the late one (BlockID 1)
    assert cam.results[0].released and cam.results[1].released
