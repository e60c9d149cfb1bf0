"""A small client for PI's GCS2 command language (C-863 Mercury and kin) over pyserial, and a Stage on it.

The client is deliberately plain: one command at a time, blocking reads with a timeout, ``ERR?`` after every
command that sets something, and after any link error a resync (drain whatever is still arriving, then
``*IDN?`` until the controller's identity comes back, then ``ERR?``) before anything else is sent.

GCS2 framing (PI's GCS2 manuals): a command is ASCII ending in LF; a reply line ends in LF, and every line of a
multi-line reply except the last ends in a space before the LF (``"1=0.5 \\n"``, ``"2=1.0\\n"``). Single-
character commands (``#5`` motion status, ``#7`` ready, ``#24`` stop) are one control byte with no LF. ``#5``
answers a hex mask with one bit per axis in ``SAI? ALL`` order; the C-863.12 takes one element (axis, parameter,
trigger setting) per command line (MS249E 8.2), so nothing here sends more. docs/hardware.md, "Device protocols
checked against the makers' documents", lists each fact with its source.

Units: the controller speaks mm; :class:`GCS2Stage` speaks fieldcal µm with
``z_um = sign * (pos_mm - zero_mm) * 1000`` (``zero_mm`` is the controller position that fieldcal calls z = 0,
``sign`` = +1 when the controller's + direction moves the sensor away from the lens).

Ports: a device path (``/dev/ttyUSB0``, ``COM3``; opened exclusively) or any pyserial URL
(``socket://127.0.0.1:50000`` for a TCP controller or the bundled emulator).
"""

from __future__ import annotations

import math
import re
import time
from typing import Any

import serial

from ..errors import LinkError, ParameterError
from .protocols import DeviceFault

# Error codes a GCS2 controller answers to ``ERR?`` (PI's controller error list: the C-863.12 manual MS249E,
# section "Error Codes", and PI's PIControllerErrors.h, "Controller Errors"): code -> (PI symbol, meaning).
# docs/hardware.md lists the source of every code. A following (motion) error is 1024, PI_CNTR_MOTION_ERROR;
# -1024 (PI_MOTION_ERROR) is the GCS *DLL*'s own code, which a controller never sends (GCS_DLL_ERRORS).
GCS2_CONTROLLER_ERRORS = {
    0: ("PI_CNTR_NO_ERROR", "no error"),
    1: ("PI_CNTR_PARAM_SYNTAX", "parameter syntax error"),
    2: ("PI_CNTR_UNKNOWN_COMMAND", "unknown command"),
    3: ("PI_CNTR_COMMAND_TOO_LONG", "command length out of limits or command buffer overrun"),
    5: ("PI_CNTR_MOVE_WITHOUT_REF_OR_NO_SERVO",
        "unallowable move attempted on unreferenced axis, or move attempted with servo off"),
    7: ("PI_CNTR_POS_OUT_OF_LIMITS", "position out of limits"),
    8: ("PI_CNTR_VEL_OUT_OF_LIMITS", "velocity out of limits"),
    10: ("PI_CNTR_STOP", "controller was stopped by command"),
    15: ("PI_CNTR_INVALID_AXIS_IDENTIFIER", "invalid axis identifier"),
    17: ("PI_CNTR_PARAM_OUT_OF_RANGE", "parameter out of range"),
    23: ("PI_CNTR_ILLEGAL_AXIS", "illegal axis"),
    24: ("PI_CNTR_PARAM_NR", "incorrect number of parameters"),
    45: ("PI_CNTR_REFERENCING_FAILED", "referencing failed"),
    215: ("PI_CNTR_CONN_POSSIBLY_BROKEN", "the connection between controller and stage may be broken"),
    216: ("PI_CNTR_ON_LIMIT_SWITCH", "the connected stage has driven into a limit switch"),
    1024: ("PI_CNTR_MOTION_ERROR", "motion error: position error too large, servo is switched off automatically"),
}
# Codes of PI's GCS DLL (negative; "DLL Errors" in PIControllerErrors.h): raised by PI's host library (pipython
# over the DLL), never by the controller's ERR?.
GCS_DLL_ERRORS = {
    -1024: ("PI_MOTION_ERROR", "motion error: position error too large, servo is switched off automatically"),
}
GCS2_ERRORS = {code: text for code, (_, text) in GCS2_CONTROLLER_ERRORS.items()}
_MOTION_FIX = "check the stage for obstruction or overload, switch the servo on again, then re-run"
GCS2_FIXES = {
    5: "reference the axis (FRF) with the servo on (SVO) before moving",
    7: "keep the plan inside the stage's travel (TMN?/TMX?)",
    8: "lower the velocity below the stage's maximum",
    10: "the stage was stopped (STP/#24); re-run to resume",
    215: "check the cable between controller and stage, then re-run",
    216: "move the stage off the limit switch (and clear it as the manual says), then re-run",
    1024: _MOTION_FIX,
    -1024: _MOTION_FIX,
}
MOTION_ERROR = 1024
#: After the controller says ready, how long FRF? may still read 0 before the reference move counts as failed (s).
REFERENCE_GRACE_S = 1.0


def error_text(code: int) -> str:
    """The meaning of a GCS error code, with its PI symbol; unknown codes point to the manual."""
    entry = GCS2_CONTROLLER_ERRORS.get(code) or GCS_DLL_ERRORS.get(code)
    if entry is None:
        return "see the controller manual's error list"
    return f"{entry[1]} ({entry[0]})"


SINGLE_CHAR = {"#5": b"\x05", "#7": b"\x07", "#24": b"\x18"}
_AXIS_VALUE = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*(\S+)\s*$")
_PARAM_VALUE = re.compile(r"^\s*([A-Za-z0-9_]+)\s+(0x[0-9A-Fa-f]+|[0-9]+)\s*=\s*(\S+)\s*$")


def param_value(lines: list[str], axis: str, pid: int) -> float | None:
    """The positive finite value of ``<axis> <pid>=<value>`` in a ``SPA?`` reply, the ID hexadecimal (``0xA``, as
    fieldcal asks) or decimal (``10``, as PI's pipython asks); None when no line has it."""
    for line in lines:
        m = _PARAM_VALUE.match(line)
        if not m or m.group(1) != axis:
            continue
        tok = m.group(2)
        if (int(tok, 16) if tok.lower().startswith("0x") else int(tok, 10)) != pid:
            continue
        try:
            v = float(m.group(3))
        except ValueError:
            return None
        return v if math.isfinite(v) and v > 0 else None
    return None


class GCS2Client:
    """GCS2 over one serial port or pyserial URL.

    Parameters
    ----------
    port : str
        ``/dev/ttyUSB0``, ``COM3`` or a pyserial URL such as ``socket://127.0.0.1:50000``.
    baudrate : int
        115200 is the C-863's default.
    timeout_ms : float
        How long to wait for each reply line.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, timeout_ms: float = 500.0):
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_ms = float(timeout_ms)
        self.identity: str | None = None
        self._ser = None
        self._lost = False          # an I/O error hit the port: resync closes and reopens it
        self._resyncing = False
        self._failed: str | None = None
        self.log: list[tuple[str, str]] = []  # (direction, text) of the last exchanges, for error messages

    # ------------------------------------------------------------------ link
    @property
    def device(self) -> str:
        return f"stage gcs:{self.port}"

    def _open_port(self, action: str) -> None:
        try:
            if "://" in self.port:
                self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=self.timeout_ms / 1000)
            else:
                self._ser = serial.Serial(self.port, baudrate=self.baudrate, timeout=self.timeout_ms / 1000,
                                          exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._ser = None
            raise LinkError(f"cannot {action} the port ({exc})" + self._after_failure(), path=self.device,
                            fix="check the port name, cable and power, and that no other program (PIMikroMove, a "
                                "second fieldcal) holds it") from None
        self._lost = False

    def open(self) -> None:
        """Open the port (exclusively for a local device) and identify the controller."""
        self._open_port("open")
        self.resync()

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # closing a dead link must not hide the error that killed it
                pass
            self._ser = None

    def _after_failure(self) -> str:
        return f" while resyncing after {self._failed!r} failed" if self._resyncing and self._failed else ""

    def _link_error(self, what: str, cmd: str) -> LinkError:
        if not self._resyncing:
            self._failed = cmd  # the command whose failure the next resync repairs, named in its errors
        return LinkError(f"{what} (command {cmd!r}){self._after_failure()}", path=self.device,
                         fix="check cable, port and baud rate; the client resyncs before the next command")

    def _port_error(self, what: str, cmd: str) -> LinkError:
        """An I/O error of the port itself: pyserial still says ``is_open``, so remember to reopen it."""
        self._lost = True
        return self._link_error(what, cmd)

    def _write(self, cmd: str) -> None:
        if self._ser is None:
            raise LinkError("the port is not open", path=self.device, fix="call open() first")
        data = SINGLE_CHAR.get(cmd) or (cmd + "\n").encode("ascii")
        try:
            self._ser.write(data)
            self._ser.flush()
        except (serial.SerialException, OSError) as exc:
            raise self._port_error(f"write failed ({exc})", cmd) from None
        self.log = (self.log + [(">", cmd)])[-20:]

    def _set_timeout(self, timeout_ms: float, cmd: str) -> None:
        try:
            self._ser.timeout = timeout_ms / 1000
        except (serial.SerialException, OSError) as exc:  # a vanished port fails even to be reconfigured
            raise self._port_error(f"link lost ({exc})", cmd) from None

    def _read_line(self, cmd: str, timeout_ms: float | None = None) -> str:
        if self._ser is None:
            raise LinkError("the port is not open", path=self.device, fix="call open() first")
        try:
            if timeout_ms is not None:
                self._set_timeout(timeout_ms, cmd)
            try:
                raw = self._ser.read_until(b"\n")
            except (serial.SerialException, OSError) as exc:
                raise self._port_error(f"link lost ({exc})", cmd) from None
        finally:
            if timeout_ms is not None and self._ser is not None:
                try:
                    self._ser.timeout = self.timeout_ms / 1000
                except (serial.SerialException, OSError):
                    pass  # already reported as a link error
        if not raw.endswith(b"\n"):
            raise self._link_error(f"no reply within {timeout_ms or self.timeout_ms:.0f} ms", cmd)
        # '#7' answers with byte 0xB1; everything else must be printable ASCII or TAB (MS249E HPV?: "TAB
        # <PossibleValue> ...")
        text = raw.decode("latin-1")
        if cmd != "#7" and any(not (32 <= ord(ch) < 127 or ch == "\t") for ch in text[:-1]):
            raise self._link_error(f"garbled reply {raw!r}", cmd)
        self.log = (self.log + [("<", text)])[-20:]
        return text[:-1]

    def read_reply(self, cmd: str) -> list[str]:
        """All lines of one reply (a line ending in a space announces another line)."""
        lines = []
        while True:
            line = self._read_line(cmd)
            if line.endswith(" "):
                lines.append(line[:-1])
                continue
            lines.append(line)
            return lines

    def query(self, cmd: str) -> list[str]:
        """Send a query (``POS? 1``, ``#5``, ...) and return its reply lines."""
        self._write(cmd)
        return self.read_reply(cmd)

    def query_axes(self, cmd: str, axis: str) -> str:
        """``CMD? axis`` -> the value string of ``axis=value``; a reply of another shape is a link error."""
        full = f"{cmd} {axis}"
        lines = self.query(full)
        for line in lines:
            m = _AXIS_VALUE.match(line)
            if m and m.group(1) == axis:
                return m.group(2)
        raise self._link_error(f"garbled reply {lines!r} (expected '{axis}=value')", full)

    def query_float(self, cmd: str, axis: str) -> float:
        v = self.query_axes(cmd, axis)
        try:
            x = float(v)
        except ValueError:
            raise self._link_error(f"garbled reply value {v!r}", f"{cmd} {axis}") from None
        if not math.isfinite(x):
            raise self._link_error(f"non-finite reply value {v!r}", f"{cmd} {axis}")
        return x

    def error_code(self) -> int:
        """``ERR?``: the last error (0 = none); reading it clears it on the controller."""
        lines = self.query("ERR?")
        try:
            return int(lines[-1].strip())
        except ValueError:
            raise self._link_error(f"garbled reply {lines!r} to ERR?", "ERR?") from None

    def check_error(self, after: str) -> None:
        code = self.error_code()
        if code != 0:
            raise DeviceFault(f"{error_text(code)} (after {after!r})", code=code,
                              device=self.device, fix=GCS2_FIXES.get(code))

    def command(self, cmd: str) -> None:
        """Send a command that has no reply, then ``ERR?``: a non-zero code raises :class:`DeviceFault`."""
        self._write(cmd)
        self.check_error(cmd)

    def resync(self, drain_ms: float | None = None) -> str:
        """Reopen a lost port, drain the link, re-identify with ``*IDN?`` (skipping stale replies), clear the error.

        Errors name the command whose failure made the resync necessary, not only the resync's own ``*IDN?``.
        """
        self._resyncing = True
        try:
            ident = self._resync(drain_ms)
        finally:
            self._resyncing = False
        self._failed = None
        return ident

    def _resync(self, drain_ms: float | None) -> str:
        if self._ser is None or self._lost or not getattr(self._ser, "is_open", True):
            self.close()
            self._open_port("reopen")
        drain_s = (self.timeout_ms if drain_ms is None else drain_ms) / 1000
        try:
            # a late reply may still be on its way: read until the line has been quiet for drain_s
            self._ser.timeout = drain_s
            give_up = time.monotonic() + max(2.0, 10 * drain_s)  # a line that never goes quiet must not hang us
            while self._ser.read(4096):
                if time.monotonic() > give_up:
                    self._ser.timeout = self.timeout_ms / 1000
                    raise self._link_error("the line does not go quiet (a wrong baud rate, or not a GCS "
                                           "controller?)", "*IDN?")
            self._ser.reset_input_buffer()
            self._ser.timeout = self.timeout_ms / 1000
        except (serial.SerialException, OSError) as exc:
            raise self._port_error(f"link lost while draining ({exc})", "*IDN?") from None
        self._write("*IDN?")
        deadline = time.monotonic() + 4 * self.timeout_ms / 1000
        while True:
            line = self._read_line("*IDN?", timeout_ms=4 * self.timeout_ms)
            if line.strip() and not _AXIS_VALUE.match(line) and not line.strip().lstrip("-").isdigit():
                ident = line.strip()
                break
            if time.monotonic() > deadline:
                raise self._link_error("no identity reply", "*IDN?")
        if self.identity is not None and ident != self.identity:
            raise LinkError(f"a different controller answers now ({ident!r}, was {self.identity!r})",
                            path=self.device, fix="check which controller is on this port")
        self.identity = ident
        self.error_code()  # clear whatever error the lost exchange left behind
        return ident


class GCS2Stage:
    """One axis of a GCS2 controller as a fieldcal :class:`~fieldcal.hardware.protocols.Stage` (µm).

    Device string: ``gcs:PORT[,axis=1][,baud=115200][,zero_mm=7.5][,sign=1][,timeout_ms=500][,poll_ms=10]``
    ``[,max_velocity_mm_s=V][,trigger_out=N]``. ``zero_mm`` defaults to mid-travel of the M-111.1DG (15 mm travel).

    Sweeps (docs/hardware.md, "Focal sweeps"): the velocity limit is ``max_velocity_mm_s`` when given, else the
    controller's parameter 0xA (``SPA? axis 0xA``, "maximum closed-loop velocity"); the acceleration is
    ``ACC?``. With ``trigger_out=N`` the controller's digital output N is configured with ``CTO`` (trigger mode 0,
    PositionDistance, between the sweep's start and stop) and enabled with ``TRO`` for the sweep, so a camera
    wired to it and set to an external trigger opens exactly at ``start_um``.
    """

    OPTIONS = {"axis", "baud", "zero_mm", "sign", "timeout_ms", "poll_ms", "velocity_mm_s", "max_velocity_mm_s",
               "trigger_out"}

    def __init__(self, port: str, *, axis: str = "1", baudrate: int = 115200, zero_mm: float = 7.5,
                 sign: int = 1, timeout_ms: float = 500.0, poll_ms: float = 10.0,
                 velocity_mm_s: float | None = None, max_velocity_mm_s: float | None = None,
                 trigger_out: int | None = None):
        if sign not in (1, -1):
            raise ParameterError(f"sign must be 1 or -1, got {sign}", path=f"stage gcs:{port}", field="sign",
                                 fix="sign=1 when the controller's + moves the sensor away from the lens, else -1")
        self.client = GCS2Client(port, baudrate=baudrate, timeout_ms=timeout_ms)
        self.axis = str(axis)
        self.zero_mm = float(zero_mm)
        self.sign = int(sign)
        self.poll_ms = float(poll_ms)
        self._velocity_mm_s = velocity_mm_s
        self._max_velocity_mm_s = max_velocity_mm_s
        if trigger_out is not None and trigger_out not in (1, 2, 3, 4):
            raise ParameterError(f"trigger_out={trigger_out} is not a digital output line 1..4", path=f"stage gcs:{port}",
                                 field="trigger_out", fix="give the C-863's output line the camera is wired to, e.g. "
                                                          "trigger_out=1")
        self.trigger_out = trigger_out
        self.name = f"gcs:{port}"
        self._axis_bit = 1  # the axis' bit in the #5 mask; connect() reads it from SAI? ALL

    @classmethod
    def from_spec(cls, arg: str | None, options: dict[str, str]) -> "GCS2Stage":
        device = f"stage gcs:{arg or ''}"
        if not arg:
            raise ParameterError("the GCS2 stage needs a port", path=device,
                                 fix="write e.g. --stage gcs:/dev/ttyUSB0 or gcs:socket://127.0.0.1:50000")
        bad = sorted(set(options) - cls.OPTIONS)
        if bad:
            raise ParameterError(f"unknown option(s) {', '.join(bad)}", path=device, field=bad[0],
                                 fix=f"known options: {', '.join(sorted(cls.OPTIONS))}")
        # option -> (low, high, low excluded): finite ranges, so nan/inf/absurd values never reach the controller
        ranges = {"zero_mm": (-1000.0, 1000.0, False), "timeout_ms": (0.0, 600000.0, True),
                  "poll_ms": (0.0, 10000.0, True), "velocity_mm_s": (0.0, 1000.0, True),
                  "max_velocity_mm_s": (0.0, 1000.0, True)}
        try:
            kw: dict[str, Any] = {}
            if "axis" in options:
                kw["axis"] = options["axis"]
            if "baud" in options:
                kw["baudrate"] = int(options["baud"])
                if not 50 <= kw["baudrate"] <= 10_000_000:
                    raise ParameterError(f"baud={options['baud']} is out of range", path=device, field="baud",
                                         fix="use the controller's baud rate, e.g. baud=115200")
            for key, (lo, hi, lo_open) in ranges.items():
                if key in options:
                    v = float(options[key])
                    if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
                        raise ParameterError(f"{key}={options[key]} must be finite and in "
                                             f"{'(' if lo_open else '['}{lo:g}, {hi:g}]", path=device, field=key,
                                             fix=f"give a finite {key}")
                    kw[key] = v
            if "sign" in options:
                kw["sign"] = int(options["sign"])
            if "trigger_out" in options:
                kw["trigger_out"] = int(options["trigger_out"])
        except ValueError as exc:
            raise ParameterError(f"bad option value ({exc})", path=device, fix="options are key=number") from None
        return cls(arg, **kw)

    # ------------------------------------------------------------------ unit conversion at the edge
    def _to_mm(self, z_um: float) -> float:
        return self.zero_mm + self.sign * z_um / 1000.0

    def _to_um(self, pos_mm: float) -> float:
        return self.sign * (pos_mm - self.zero_mm) * 1000.0

    # ------------------------------------------------------------------ Stage protocol
    def connect(self) -> None:
        self.client.open()
        # ``#5`` answers one bit per axis, in the order of ``SAI? ALL`` (MS249E, #5: "1=First axis in motion,
        # 2=Second axis in motion"; pipython's IsMoving reads the same bit): find this axis' bit
        axes = [ln.strip() for ln in self.client.query("SAI? ALL") if ln.strip()]
        if self.axis not in axes:
            self.client.close()
            raise ParameterError(f"axis {self.axis!r} is not an axis of this controller (SAI? ALL: {axes})",
                                 path=f"stage {self.name}", field="axis",
                                 fix=f"give one of its axes, e.g. axis={axes[0] if axes else 1}")
        self._axis_bit = 1 << axes.index(self.axis)
        if self.client.query_axes("SVO?", self.axis) != "1":
            self.client.command(f"SVO {self.axis} 1")
        if self._velocity_mm_s is not None:
            self.client.command(f"VEL {self.axis} {self._velocity_mm_s:.6f}")

    def close(self) -> None:
        self.client.close()

    def identify(self) -> str:
        return self.client.identity or self.client.resync()

    def describe(self) -> dict[str, Any]:
        return {"kind": "gcs", "name": self.name, "identity": self.client.identity, "axis": self.axis,
                "units": "controller mm; z_um = sign * (pos_mm - zero_mm) * 1000",
                "zero_mm": self.zero_mm, "sign": self.sign, "port": self.client.port,
                "max_velocity_mm_s": self._max_velocity_mm_s, "trigger_out": self.trigger_out}

    def resync(self) -> None:
        self.client.resync()

    def is_referenced(self) -> bool:
        return self.client.query_axes("FRF?", self.axis) == "1"

    def reference(self, timeout_ms: float = 60000.0) -> None:
        if self.client.query_axes("SVO?", self.axis) != "1":
            self.client.command(f"SVO {self.axis} 1")
        self.client.command(f"FRF {self.axis}")
        # as PI's pipython (pitools.waitonreferencing): wait for #7 to answer "ready" (MS249E, #7: B0h "not
        # ready (e.g., doing a reference move)"), read ERR? -- a reference move that failed says why here --
        # and only then FRF?
        deadline = time.monotonic() + timeout_ms / 1000
        while not self._ready():
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceFault(f"reference move not done within {timeout_ms:.0f} ms", code=0,
                                  device=self.client.device, fix="check the stage and its reference switch")
            time.sleep(self.poll_ms / 1000)
        self.client.check_error("FRF")
        # pipython (gcs2pitools) keeps polling FRF? after ready: a controller may say ready a moment before the
        # axis counts as referenced; a short grace, not the whole time-out, so a failed reference still ends soon
        grace = min(deadline, time.monotonic() + REFERENCE_GRACE_S)
        while not self.is_referenced():
            if time.monotonic() > grace:
                break
            time.sleep(self.poll_ms / 1000)
        if not self.is_referenced():
            raise DeviceFault("the reference move ended but the axis is not referenced (FRF? 0)", code=0,
                              device=self.client.device, fix="check the stage and its reference switch")

    def _ready(self) -> bool:
        """``#7``: B1h ready, B0h busy (MS249E, #7)."""
        lines = self.client.query("#7")
        if lines[-1] in ("\xb1", "\xb0"):
            return lines[-1] == "\xb1"
        raise self.client._link_error(f"garbled reply {lines!r} (expected B1h or B0h)", "#7")

    def limits_um(self) -> tuple[float, float]:
        a = self._to_um(self.client.query_float("TMN?", self.axis))
        b = self._to_um(self.client.query_float("TMX?", self.axis))
        return (min(a, b), max(a, b))

    def velocity_um_per_s(self) -> float:
        return self.client.query_float("VEL?", self.axis) * 1000.0

    def set_velocity_um_per_s(self, v: float) -> None:
        self.client.command(f"VEL {self.axis} {v / 1000.0:.6f}")

    def max_velocity_um_per_s(self) -> float:
        """``max_velocity_mm_s`` when given, else ``SPA? axis 0xA`` (maximum closed-loop velocity, mm/s)."""
        if self._max_velocity_mm_s is not None:
            return self._max_velocity_mm_s * 1000.0
        cmd = f"SPA? {self.axis} 0xA"
        lines = self.client.query(cmd)  # the reply names axis and parameter: "1 0xA=2.000000"
        v = param_value(lines, self.axis, 0xA)
        if v is not None:
            return v * 1000.0
        raise self.client._link_error(f"garbled reply {lines!r} (expected '{self.axis} 0xA=value')", cmd)

    def acceleration_um_per_s2(self) -> float:
        """``ACC?`` (closed-loop acceleration, mm/s²)."""
        return self.client.query_float("ACC?", self.axis) * 1000.0

    def cto_settings(self, start_um: float, stop_um: float) -> list[tuple[int, str]]:
        """(CTO parameter ID, value) for a PositionDistance trigger that pulses at ``start_um`` and ``stop_um``."""
        a, b = self._to_mm(start_um), self._to_mm(stop_um)
        return [(2, self.axis), (3, "0"), (1, f"{abs(b - a):.6f}"), (8, f"{a:.6f}"), (9, f"{b:.6f}")]

    def arm_sweep_trigger(self, start_um: float, stop_um: float) -> None:
        """With ``trigger_out``: ``CTO`` the line to pulse at ``start_um`` (and at ``stop_um``: TriggerStep is the
        whole range) while the axis moves from start to stop, then ``TRO line 1``. Without it: nothing (the
        runner polls ``POS?`` to open the exposure, which is late by up to one poll)."""
        if self.trigger_out is None:
            return
        n = self.trigger_out
        # CTO parameter IDs of the C-863.12 (MS249E, CTO): 1 TriggerStep, 2 Axis, 3 TriggerMode (0 =
        # PositionDistance), 8 StartThreshold, 9 StopThreshold -- one per command line (MS249E 8.2: "With the
        # C-863.12 only a single element per command line can be addressed")
        for pid, value in self.cto_settings(start_um, stop_um):
            self.client.command(f"CTO {n} {pid} {value}")
        self.client.command(f"TRO {n} 1")

    def disarm_sweep_trigger(self) -> None:
        if self.trigger_out is not None:
            self.client.command(f"TRO {self.trigger_out} 0")

    def move_to_um(self, z_um: float) -> None:
        self.client.command(f"MOV {self.axis} {self._to_mm(z_um):.6f}")

    def on_target(self) -> bool:
        return self.client.query_axes("ONT?", self.axis) == "1"

    def _moving(self) -> bool:
        """``#5``: a hex mask with one bit per axis (MS249E, #5); only this axis' bit counts."""
        lines = self.client.query("#5")
        try:
            return bool(int(lines[-1].strip(), 16) & self._axis_bit)
        except ValueError:
            raise self.client._link_error(f"garbled reply {lines!r}", "#5") from None

    def wait_on_target(self, timeout_ms: float) -> None:
        deadline = time.monotonic() + timeout_ms / 1000
        while self._moving():
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceFault(f"still moving after {timeout_ms:.0f} ms; stopped", code=0,
                                  device=self.client.device, fix="raise the on-target timeout or the velocity")
            time.sleep(self.poll_ms / 1000)
        self.client.check_error("motion")  # a motion error (1024) ends the motion early
        while not self.on_target():
            if time.monotonic() > deadline:
                raise DeviceFault("motion ended off target", code=0, device=self.client.device,
                                  fix="check servo tuning and load; then re-run")
            time.sleep(self.poll_ms / 1000)

    def position_um(self) -> float:
        return self._to_um(self.client.query_float("POS?", self.axis))

    def stop(self) -> None:
        """``#24`` (stop all axes, accepted even mid-command), then clear error 10 it sets. Never raises."""
        try:
            self.client._write("#24")
            self.client.error_code()
        except Exception:  # stop is called while handling another error: never mask that one
            pass
