"""PI's own ``pipython`` as an optional stage backend (``pip install fieldcal[pi]``): ``--stage pi:PORT``.

Prefer the built-in :mod:`fieldcal.hardware.gcs2` client; use this one when a lab already relies on pipython.
Two pipython pitfalls are guarded here (checked against pipython 2.11):

* **Error checking left off.** Several pipython calls (``IsControllerReady``, ``ReadGCSCommand``,
  ``GcsCommandset``, referencing waits for some controllers) switch ``errcheck`` off and switch it back on
  only when they return normally: a timeout inside leaves every later command unchecked. Every call here goes
  through :meth:`PipythonStage._call`, which restores ``errcheck = True`` in a ``finally``.
* **A global list that couples controllers.** ``PIGateway._connection_status_changed_callbacks`` is a
  class-level list: every ``GCSDevice`` registers its callback there, and connecting *any* gateway calls
  *all* of them (each device then re-inspects its own controller). Each stage here gets a private gateway
  subclass with its own list, so two controllers never see each other's connection events. The gateway also
  opens the serial port exclusively (pipython does not).

Units as in :class:`fieldcal.hardware.gcs2.GCS2Stage`: ``z_um = sign * (pos_mm - zero_mm) * 1000``.
"""

from __future__ import annotations

import time
from typing import Any

from ..errors import LinkError, ParameterError
from .gcs2 import GCS2_FIXES, GCS2Stage, error_text, param_value
from .protocols import DeviceFault


def _isolated_gateway(port: str, baudrate: int, timeout_ms: float):
    """A pipython gateway on ``port`` with its own callback list and an exclusive serial port."""
    import serial
    from pipython.pidevice.interfaces.piserial import PISerial
    from pipython.pidevice.interfaces.pisocket import PISocket

    def close_once(base):
        def close(self):  # pipython closes a socket twice (CloseConnection, then __del__): the second raises
            if getattr(self, "_fieldcal_closed", False):
                return
            self._fieldcal_closed = True
            base.close(self)
        return close

    if port.startswith("socket://"):
        host, _, p = port[len("socket://"):].rpartition(":")
        cls = type("FieldcalPISocket", (PISocket,), {"_connection_status_changed_callbacks": [],
                                                      "close": close_once(PISocket)})
        gw = cls(host=host, port=int(p))
    else:
        def connect_exclusive(self, port_, baudrate_):
            self._ser = serial.Serial(port=port_, baudrate=baudrate_, timeout=self._timeout / 1000.0, exclusive=True)
            self._connected = True
            self.flush()
            self.call_connection_status_changed_callback(self)

        cls = type("FieldcalPISerial", (PISerial,), {"_connection_status_changed_callbacks": [],
                                                      "ConnectRS232": connect_exclusive,
                                                      "close": close_once(PISerial)})
        gw = cls(port=port, baudrate=baudrate)
    gw.settimeout(timeout_ms)
    return gw


class PipythonStage(GCS2Stage):
    """One axis through pipython's ``GCSDevice``; same options and units as ``gcs:``."""

    def __init__(self, port: str, **kw):
        super().__init__(port, **kw)
        self.name = f"pi:{port}"
        self._port, self._baud, self._timeout_ms = port, self.client.baudrate, self.client.timeout_ms
        self.dev = None
        self._gateway = None

    @classmethod
    def from_spec(cls, arg, options):
        try:
            import pipython  # noqa: F401
        except ImportError:
            raise ParameterError("the pi: backend needs PI's pipython", field="stage",
                                 fix="pip install 'fieldcal[pi]', or use the built-in client: stage gcs:PORT") from None
        base = GCS2Stage.from_spec(arg, options)
        return cls(arg, axis=base.axis, baudrate=base.client.baudrate, zero_mm=base.zero_mm, sign=base.sign,
                   timeout_ms=base.client.timeout_ms, poll_ms=base.poll_ms, velocity_mm_s=base._velocity_mm_s,
                   max_velocity_mm_s=base._max_velocity_mm_s, trigger_out=base.trigger_out)

    @property
    def device(self) -> str:
        return f"stage {self.name}"

    def _call(self, fn, *args):
        """Run a pipython call; GCSError -> DeviceFault/LinkError; errcheck is always switched back on."""
        from pipython import GCSError
        try:
            return fn(*args)
        except GCSError as exc:
            code = int(getattr(exc, "val", -1))
            if -1000 < code < 0 or code == -1004:  # interface errors (timeout, unexpected answer): link state unknown
                raise LinkError(f"pipython: {exc}", path=self.device, fix="check cable and port; resync") from None
            raise DeviceFault(f"pipython: {exc}", code=code, device=self.device, fix=GCS2_FIXES.get(code)) from None
        except (OSError, EOFError) as exc:
            raise LinkError(f"pipython: {exc}", path=self.device, fix="check cable and port; resync") from None
        finally:
            if self.dev is not None:
                self.dev.errcheck = True

    def connect(self) -> None:
        from pipython import GCSDevice
        try:
            self._gateway = _isolated_gateway(self._port, self._baud, self._timeout_ms)
        except Exception as exc:  # serial/socket errors of every flavour: report them as a link problem
            raise LinkError(f"cannot open the port ({exc})", path=self.device,
                            fix="check the port name and that no other program holds it") from None
        self.dev = GCSDevice(gateway=self._gateway)
        self.dev.errcheck = True
        self.client.identity = self._call(self.dev.qIDN).strip()
        if not self._call(self.dev.qSVO, self.axis)[self.axis]:
            self._call(self.dev.SVO, self.axis, True)
        if self._velocity_mm_s is not None:
            self._call(self.dev.VEL, self.axis, self._velocity_mm_s)

    def close(self) -> None:
        try:
            if self.dev is not None:
                self.dev.CloseConnection()
        except Exception:  # closing a dead link must not hide the error that killed it
            pass
        try:
            if self._gateway is not None:
                self._gateway.close()
        except Exception:  # as above
            pass
        self.dev = self._gateway = None

    def identify(self) -> str:
        return self.client.identity or self._call(self.dev.qIDN).strip()

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["kind"] = "pi"
        d["backend"] = "pipython"
        return d

    def resync(self) -> None:
        self.close()
        self.connect()
        self._call(self.dev.qERR)

    def is_referenced(self) -> bool:
        return bool(self._call(self.dev.qFRF, self.axis)[self.axis])

    def reference(self, timeout_ms: float = 60000.0) -> None:
        # FRF with the servo off is error 5 (as gcs:, switch it on first: a motion error switches it off)
        if not self._call(self.dev.qSVO, self.axis)[self.axis]:
            self._call(self.dev.SVO, self.axis, True)
        self._call(self.dev.FRF, self.axis)
        deadline = time.monotonic() + timeout_ms / 1000
        while not self.is_referenced():
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceFault(f"reference move not done within {timeout_ms:.0f} ms", code=0, device=self.device)
            time.sleep(self.poll_ms / 1000)

    def limits_um(self) -> tuple[float, float]:
        a = self._to_um(float(self._call(self.dev.qTMN, self.axis)[self.axis]))
        b = self._to_um(float(self._call(self.dev.qTMX, self.axis)[self.axis]))
        return (min(a, b), max(a, b))

    def velocity_um_per_s(self) -> float:
        return float(self._call(self.dev.qVEL, self.axis)[self.axis]) * 1000.0

    def set_velocity_um_per_s(self, v: float) -> None:
        self._call(self.dev.VEL, self.axis, v / 1000.0)

    # sweeps: the same GCS2 commands as gcs:, through pipython's wrappers (untested without pipython installed)
    def max_velocity_um_per_s(self) -> float:
        if self._max_velocity_mm_s is not None:
            return self._max_velocity_mm_s * 1000.0
        # pipython's qSPA first asks HPA? for every parameter's type; read SPA? itself (with its ERR?) and parse
        # it as gcs: does
        cmd = f"SPA? {self.axis} 0xA"
        lines = [ln.rstrip(" ") for ln in str(self._call(self.dev.read, cmd)).split("\n") if ln.strip()]
        v = param_value(lines, self.axis, 0xA)
        if v is None:
            raise LinkError(f"garbled reply {lines!r} to {cmd!r} (expected '{self.axis} 0xA=value')",
                            path=self.device, fix="give max_velocity_mm_s from the stage's data sheet")
        return v * 1000.0

    def acceleration_um_per_s2(self) -> float:
        return float(self._call(self.dev.qACC, self.axis)[self.axis]) * 1000.0

    def arm_sweep_trigger(self, start_um: float, stop_um: float) -> None:
        if self.trigger_out is None:
            return
        n = self.trigger_out
        for pid, value in self.cto_settings(start_um, stop_um):  # one element per line (MS249E 8.2), as gcs:
            self._call(self.dev.CTO, n, pid, value)
        self._call(self.dev.TRO, n, True)

    def disarm_sweep_trigger(self) -> None:
        if self.trigger_out is not None:
            self._call(self.dev.TRO, self.trigger_out, False)

    def move_to_um(self, z_um: float) -> None:
        self._call(self.dev.MOV, self.axis, self._to_mm(z_um))

    def on_target(self) -> bool:
        return bool(self._call(self.dev.qONT, self.axis)[self.axis])

    def wait_on_target(self, timeout_ms: float) -> None:
        deadline = time.monotonic() + timeout_ms / 1000
        while self._call(self.dev.IsMoving, self.axis)[self.axis]:
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceFault(f"still moving after {timeout_ms:.0f} ms; stopped", code=0, device=self.device)
            time.sleep(self.poll_ms / 1000)
        code = int(self._call(self.dev.qERR))
        if code:
            raise DeviceFault(f"pipython: controller error: {error_text(code)}", code=code, device=self.device,
                              fix=GCS2_FIXES.get(code))
        while not self.on_target():
            if time.monotonic() > deadline:
                raise DeviceFault("motion ended off target", code=0, device=self.device)
            time.sleep(self.poll_ms / 1000)

    def position_um(self) -> float:
        return self._to_um(float(self._call(self.dev.qPOS, self.axis)[self.axis]))

    def stop(self) -> None:
        try:
            if self.dev is not None:
                self.dev.errcheck = False  # STP always "fails" with error 10 (stopped by command)
                try:
                    self.dev.STP()
                finally:
                    self.dev.errcheck = True
                self.dev.qERR()
        except Exception:  # stop runs while another error is being handled: never mask it
            pass
