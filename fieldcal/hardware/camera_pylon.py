"""Basler cameras through pypylon (``pip install fieldcal[basler]``): ``--camera pylon[:SERIAL][,options]``.

Options: ``pixel_pitch_um=3.45`` (required: a camera does not report its pitch), ``pixel_format=Mono12``
(``Mono8``, ``Mono12``, ``Mono16``, ``RGB8Packed``), ``timeout_ms=5000``, ``images=DIR`` (pylon's camera
emulator only: replay the image files in DIR, which makes an end-to-end test without a camera possible; run
with the environment variable ``PYLON_CAMEMU=1`` to get an emulated camera).

Frames are software-triggered (``TriggerMode=On``, ``TriggerSource=Software``) so that each frame starts only
after the stage is on target; the frame id is pylon's ``BlockID``. ``ExposureAuto`` and ``GainAuto`` are switched
``Off`` at connect (a stack needs one fixed exposure and gain; Basler: "Set the ExposureAuto parameter to Off" before
setting the exposure time). The exposure node is ``ExposureTime`` (SFNC 2) or, on older cameras, ``ExposureTimeAbs``
(both µs); pypylon returns a parameter object for *any* attribute name, so a node is looked up by its ``IsValid()``,
never by ``hasattr``. Timestamps are camera ticks, converted with ``GevTimestampTickFrequency`` where the camera
has it (GigE), else 1 tick = 1 ns.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..errors import LinkError, ParameterError
from .protocols import DeviceFault, Frame

_FORMATS = {"Mono8": (["Y"], 8), "Mono10": (["Y"], 10), "Mono12": (["Y"], 12), "Mono16": (["Y"], 16),
            "RGB8Packed": (["R", "G", "B"], 8), "RGB8": (["R", "G", "B"], 8)}
# one format, two names: GenICam PFNC 2.1 (Basler /pixel-format: "RGB8") and the older GigE Vision name
_ALIASES = {"RGB8Packed": "RGB8", "RGB8": "RGB8Packed"}


class PylonCamera:
    OPTIONS = {"pixel_pitch_um", "pixel_format", "timeout_ms", "images"}

    def __init__(self, serial: str | None = None, *, pixel_pitch_um: float, pixel_format: str = "Mono12",
                 timeout_ms: float = 5000.0, images: str | None = None):
        if pixel_format not in _FORMATS:
            raise ParameterError(f"pixel format {pixel_format!r} is not supported", field="pixel_format",
                                 path="camera pylon", fix=f"use one of {', '.join(_FORMATS)}")
        self.serial = serial
        self.pixel_pitch_um = float(pixel_pitch_um)
        self.pixel_format = pixel_format
        self.timeout_ms = float(timeout_ms)
        self.images = images
        self.name = "pylon" + (f":{serial}" if serial else "")
        self.cam = None
        self._exposure_ms: float | None = None
        self._tick_hz: float | None = None
        self._roi = None

    @classmethod
    def from_spec(cls, arg, options):
        device = "camera pylon" + (f":{arg}" if arg else "")
        bad = sorted(set(options) - cls.OPTIONS)
        if bad:
            raise ParameterError(f"unknown option(s) {', '.join(bad)}", path=device, field=bad[0],
                                 fix=f"known options: {', '.join(sorted(cls.OPTIONS))}")
        if "pixel_pitch_um" not in options:
            raise ParameterError("the pixel pitch is not known", path=device, field="pixel_pitch_um",
                                 fix="add pixel_pitch_um=... (from the camera's data sheet), e.g. pylon,pixel_pitch_um=3.45")
        try:
            pitch = float(options["pixel_pitch_um"])
            timeout = float(options.get("timeout_ms", 5000))
        except ValueError as exc:
            raise ParameterError(f"bad option value ({exc})", path=device, fix="options are key=number") from None
        return cls(arg, pixel_pitch_um=pitch, pixel_format=options.get("pixel_format", "Mono12"),
                   timeout_ms=timeout, images=options.get("images"))

    @property
    def _device(self) -> str:
        return f"camera {self.name}"

    def _node(self, *names: str):
        """The first of ``names`` the camera has (pypylon: ``IsValid()``), else None. ``hasattr`` cannot tell:
        pypylon's attribute lookup returns a parameter object for any name ("GetNode always returns a parameter
        and does not throw")."""
        for name in names:
            node = getattr(self.cam, name)
            if node.IsValid():
                return node
        return None

    def _exposure_node(self):
        node = self._node("ExposureTime", "ExposureTimeAbs")
        if node is None:
            raise DeviceFault("the camera has neither ExposureTime nor ExposureTimeAbs", code=0, device=self._device,
                              fix="use a camera with a timed exposure (ExposureMode=Timed)")
        return node

    def _auto_off(self, name: str) -> None:
        """Switch an auto function (``ExposureAuto``, ``GainAuto``) off where the camera has it."""
        node = self._node(name)
        if node is not None and node.IsWritable() and node.Value != "Off":
            node.Value = "Off"

    def connect(self) -> None:
        try:
            from pypylon import genicam, pylon
        except ImportError:
            raise ParameterError("the pylon camera backend needs pypylon", path=self._device,
                                 fix="pip install 'fieldcal[basler]'") from None
        self._pylon, self._genicam = pylon, genicam
        try:
            tl = pylon.TlFactory.GetInstance()
            devices = tl.EnumerateDevices()
            if self.serial:
                devices = [d for d in devices if d.GetSerialNumber() == self.serial]
            if not devices:
                raise LinkError("no Basler camera found" + (f" with serial {self.serial}" if self.serial else ""),
                                path=self._device, fix="check the cable and the serial number (pylon Viewer lists it)")
            self.cam = pylon.InstantCamera(tl.CreateDevice(devices[0]))
            self.cam.Open()
            self._set_pixel_format()
            if self.images:
                self.cam.ImageFilename.Value = str(self.images)
                self.cam.ImageFileMode.Value = "On"
                self.cam.TestImageSelector.Value = "Off"
            # a stack needs one exposure and one gain for all frames: no auto function may change them
            self._auto_off("ExposureAuto")
            self._auto_off("GainAuto")
            # ExposureMode Timed: the exposure time node decides each frame's exposure (Basler,
            # PLCamera.ExposureModeEnum); TriggerWidth would let the (software) trigger's width decide
            mode = self._node("ExposureMode")
            if mode is not None and mode.IsWritable() and mode.Value != "Timed":
                mode.Value = "Timed"
            self.cam.TriggerSelector.Value = "FrameStart"
            self.cam.TriggerMode.Value = "On"
            self.cam.TriggerSource.Value = "Software"
            self.cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except genicam.GenericException as exc:
            raise LinkError(f"pylon: {exc}", path=self._device, fix="check the camera and its settings") from None

    def _set_pixel_format(self) -> None:
        """Set ``PixelFormat``; a format the camera names otherwise (``RGB8``/``RGB8Packed``) is taken under its
        name, one it does not have is a ParameterError that lists the camera's formats."""
        node = self.cam.PixelFormat
        have = tuple(node.Symbolics)
        name = self.pixel_format
        if have and name not in have:
            if _ALIASES.get(name) in have:
                name = _ALIASES[name]
            else:
                self.close()
                usable = [f for f in have if f in _FORMATS]
                raise ParameterError(f"the camera has no pixel format {self.pixel_format!r} (it has: "
                                     f"{', '.join(have)})", path=self._device, field="pixel_format",
                                     fix=f"use one of {', '.join(usable) or ', '.join(_FORMATS)}")
        node.Value = name
        self.pixel_format = name

    def _drop_stale_results(self, limit: int = 64) -> int:
        """Release every result already waiting before a trigger: with GrabStrategy_OneByOne "images are processed
        in the order of their arrival" (Basler, GrabStrategy), so a frame that arrived after its RetrieveResult
        timed out would otherwise be taken for the next position's frame."""
        n = 0
        while n < limit:
            res = self.cam.RetrieveResult(0, self._pylon.TimeoutHandling_Return)
            if res is None or not res.IsValid():
                break
            res.Release()
            n += 1
        return n

    def close(self) -> None:
        try:
            if self.cam is not None:
                self.cam.StopGrabbing()
                self.cam.Close()
        except Exception:  # closing must not hide the error being reported
            pass
        self.cam = None

    def identify(self) -> str:
        info = self.cam.GetDeviceInfo()
        return f"{info.GetModelName()} {info.GetSerialNumber()}"

    def describe(self) -> dict[str, Any]:
        channels, bits = _FORMATS[self.pixel_format]
        d = {"kind": "pylon", "name": self.name, "pixel_pitch_um": self.pixel_pitch_um, "channels": channels,
             "bit_depth": bits, "black_level": 0, "white_level": (1 << bits) - 1, "roi": self._roi,
             "pixel_format": self.pixel_format, "lens": None}
        if self.cam is not None:
            d["identity"] = self.identify()
            d["size_px"] = [int(self.cam.Width.Value), int(self.cam.Height.Value)]
        return d

    def configure(self, *, exposure_ms=None, roi=None, trigger=None) -> None:
        g = self._genicam
        try:
            if exposure_ms is not None:
                node = self._exposure_node()
                node.Value = float(exposure_ms) * 1000.0  # GenICam exposure is in µs
                self._exposure_ms = float(node.Value) / 1000.0
            if roi is not None:
                self.cam.StopGrabbing()
                x, y, w, h = (int(v) for v in roi)
                self.cam.OffsetX.Value, self.cam.OffsetY.Value = 0, 0
                self.cam.Width.Value, self.cam.Height.Value = w, h
                self.cam.OffsetX.Value, self.cam.OffsetY.Value = x, y
                self._roi = [x, y, w, h]
                self.cam.StartGrabbing(self._pylon.GrabStrategy_OneByOne)
            if trigger not in (None, "software"):
                raise DeviceFault(f"trigger {trigger!r} is not supported by this backend", code=0,
                                  device=self._device, fix="use software triggering")
        except g.GenericException as exc:
            raise DeviceFault(f"pylon refused the setting: {exc}", code=0, device=self._device,
                              fix="check the value against the camera's limits") from None

    def snap(self) -> Frame:
        g = self._genicam
        try:
            stale = self._drop_stale_results()
            if not self.cam.WaitForFrameTriggerReady(int(self.timeout_ms), self._pylon.TimeoutHandling_Return):
                raise LinkError("camera not ready for a trigger", path=self._device, fix="check the camera")
            self.cam.ExecuteSoftwareTrigger()
            res = self.cam.RetrieveResult(int(self.timeout_ms), self._pylon.TimeoutHandling_Return)
        except g.GenericException as exc:
            raise LinkError(f"pylon: {exc}", path=self._device, fix="check the camera link") from None
        if res is None or not res.IsValid():
            raise LinkError(f"no frame within {self.timeout_ms:.0f} ms", path=self._device, fix="check the camera link")
        try:
            if not res.GrabSucceeded():
                raise LinkError(f"grab failed: {res.GetErrorDescription()} (pylon error code "
                                f"{int(res.GetErrorCode()) & 0xFFFFFFFF:#010x})", path=self._device,
                                fix="check the camera link")
            img = np.array(res.Array, copy=True)
            frame_id, ticks = int(res.BlockID), int(res.TimeStamp)
        finally:
            res.Release()
        if img.ndim == 2:
            img = img[:, :, None]
        try:
            if self._exposure_ms is None:
                self._exposure_ms = float(self._exposure_node().Value) / 1000.0
            if self._tick_hz is None:
                # docs.baslerweb.com/timestamp: the tick frequency depends on the model; GigE cameras state it
                freq = self._node("GevTimestampTickFrequency")
                self._tick_hz = float(freq.Value) if freq is not None and freq.IsReadable() else 1e9
        except g.GenericException as exc:
            raise LinkError(f"pylon: {exc}", path=self._device, fix="check the camera link") from None
        meta = {"timestamp_ticks": ticks, "timestamp_tick_hz": self._tick_hz}
        if stale:
            meta["stale_frames_dropped"] = stale
        ts_ms = ticks / self._tick_hz * 1000.0 if ticks else time.time() * 1000.0
        return Frame(image=img, frame_id=frame_id, exposure_ms=self._exposure_ms, timestamp_ms=ts_ms, meta=meta)
