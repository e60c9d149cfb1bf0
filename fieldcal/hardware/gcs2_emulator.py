"""An emulated PI C-863 (GCS2) with one M-111.1DG axis, served on a pseudo-terminal or a TCP socket.

It is the test bench of :mod:`fieldcal.hardware.gcs2` and a dry-run aid for labs::

    python -m fieldcal.hardware.gcs2_emulator --tcp 50000     # then: --stage gcs:socket://127.0.0.1:50000
    python -m fieldcal.hardware.gcs2_emulator --pty           # prints the pty path: --stage gcs:/dev/pts/N

What it emulates (GCS2 syntax; details we could not check against a real C-863 are listed in docs/hardware.md):
``*IDN?``, ``ERR?``, ``MOV``, ``MOV?``, ``POS?``, ``ONT?``, ``SVO``, ``SVO?``, ``FRF``, ``FRF?``, ``VEL``,
``VEL?``, ``ACC``, ``ACC?``, ``SPA? axis 0xA`` (maximum velocity), ``CTO``, ``CTO?``, ``TRO``, ``TRO?``,
``TMN?``, ``TMX?``, ``CST?``, ``SAI?``, ``HLT``, ``STP``, ``HLP?`` (multi-line), and the single-byte
``#5`` (motion status), ``#7`` (ready; B0h while a reference move runs) and ``#24`` (stop). As the C-863.12
(MS249E 8.2) it takes one element per ``CTO``/``TRO`` line and lists a query's arguments in its reply as given
(``SPA? 1 10`` -> ``1 10=...``). Errors are latched like the controller does: the
last error code is kept until ``ERR?`` reads (and clears) it. Codes: 0 none, 1 syntax, 2 unknown command,
5 move without reference/servo, 7 out of limits, 8 velocity out of limits, 10 stopped, 15 invalid axis,
1024 motion error (PI_CNTR_MOTION_ERROR, as a C-863 answers ERR?; -1024 is the GCS DLL's code, not the
controller's).

Motion: a trapezoidal velocity profile (:mod:`fieldcal.hardware.motion`): a move of d mm takes
``d / VEL + VEL / ACC`` s (a triangle when too short to reach VEL). Every ``VEL``, ``ACC`` and ``MOV`` accepted is
appended to :attr:`GCS2Emulator.motion_log` with its emulated time; with a trigger output enabled (``CTO`` mode
0, ``TRO n 1``) every crossing of a trigger position during a move is appended to :attr:`trigger_log`.

Time: the motion model reads an injectable ``clock`` (seconds). The default is the wall clock; tests pass a
:class:`ManualClock` and advance it themselves, so no test depends on how fast the machine is.

Faults for tests: :meth:`GCS2Emulator.drop_replies`, :meth:`garble_replies`, :meth:`delay_replies`,
:meth:`motion_error_on_next_move`, and ``disconnect()`` on the servers.
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import threading
import time
import tty

from .motion import move_duration_s, time_at_um, travelled_um

IDN = "(c)2015 Physik Instrumente (PI) GmbH & Co. KG, C-863.11, 0115000001, 01.000"
HELP_LINES = ["The following commands are available:", "#5 Request Motion Status", "#7 Request Controller Ready Status",
              "#24 Stop All Axes", "*IDN? Get Device Identification", "ERR? Get Error Number",
              "FRF [{<AxisID>}] Fast Reference Move To Reference Switch", "MOV {<AxisID> <Position>} Set Target Position",
              "POS? [{<AxisID>}] Get Real Position", "end of help"]


class ManualClock:
    """A clock the caller drives: ``clock()`` returns the time (s); :meth:`advance` moves it on. With
    ``tick_s`` every reading also advances it by that much, so motion progresses with the commands sent and
    polling loops end without any wall-clock time passing."""

    def __init__(self, t0_s: float = 0.0, *, tick_s: float = 0.0):
        self.t_s = float(t0_s)
        self.tick_s = float(tick_s)
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            t = self.t_s
            self.t_s += self.tick_s
            return t

    def advance(self, dt_s: float) -> None:
        with self._lock:
            self.t_s += float(dt_s)


MOTION_ERROR = 1024  # PI_CNTR_MOTION_ERROR: what ERR? answers after a following error


class GCS2Emulator:
    """The controller's state machine: feed it command strings, get reply bytes back (or None).

    Parameters
    ----------
    travel_mm : (min, max) soft limits reported by TMN?/TMX?.
    velocity_mm_s : initial velocity (VEL); ``max_velocity_mm_s`` bounds VEL.
    settle_ms : time after the trajectory ends before ONT? reports 1.
    reference_mm : where FRF leaves the axis (the M-111's reference switch sits mid-travel).
    time_scale : emulated seconds per clock second (speeds motion up on the wall clock).
    clock : a callable returning seconds (default ``time.monotonic``); tests pass a :class:`ManualClock`.
    """

    def __init__(self, *, travel_mm=(0.0, 15.0), velocity_mm_s: float = 1.5, max_velocity_mm_s: float = 2.0,
                 settle_ms: float = 5.0, reference_mm: float = 7.5, time_scale: float = 1.0, idn: str = IDN,
                 stage_name: str = "M-111.1DG", clock=None, accel_mm_s2: float = 20.0):
        self.tmn, self.tmx = float(travel_mm[0]), float(travel_mm[1])
        self.vel = float(velocity_mm_s)
        self.max_vel = float(max_velocity_mm_s)
        self.acc = float(accel_mm_s2)
        self._seg_vel = self.vel
        self.motion_log: list[dict] = []   # {"t_s", "cmd", "value"} of every accepted VEL/ACC/MOV
        self.trigger_log: list[dict] = []  # {"t_s", "line", "pos_mm"} of every trigger pulse
        self.cto: dict[int, dict[int, float]] = {}
        self.tro: dict[int, bool] = {}
        self.settle_s = settle_ms / 1000
        self.reference_mm = float(reference_mm)
        self.time_scale = float(time_scale)
        self.clock = clock or time.monotonic
        self.idn = idn
        self.stage_name = stage_name
        self.servo = False
        self.referenced = False
        self.error = 0
        self._lock = threading.RLock()
        self._seg = (0.0, 0.0, 0.0, 0.0)  # (t0, start_mm, target_mm, duration_s) in emulated time
        self._stopped_at: float | None = None
        self._motion_error_armed = False
        self._motion_error = False
        self._referencing = False
        self._drop = 0
        self._garble = 0
        self._delay = (0, 0.0)
        self.received: list[str] = []  # every command, for tests

    # ------------------------------------------------------------------ faults
    def drop_replies(self, n: int = 1) -> None:
        """Swallow the next n replies (a lost answer)."""
        self._drop = n

    def garble_replies(self, n: int = 1) -> None:
        """Corrupt the next n replies (line noise)."""
        self._garble = n

    def delay_replies(self, n: int, delay_ms: float) -> None:
        """Send the next n replies late (after delay_ms)."""
        self._delay = (n, delay_ms / 1000)

    def motion_error_on_next_move(self) -> None:
        """The next MOV (or FRF) stops half-way with error 1024 (PI_CNTR_MOTION_ERROR) and the servo switched off."""
        self._motion_error_armed = True

    def set_referenced_at(self, pos_mm: float) -> None:
        """Test shortcut: the axis is referenced, servo on, at rest at pos_mm (no FRF move needed)."""
        with self._lock:
            self.referenced = self.servo = True
            self._seg = (self._now(), float(pos_mm), float(pos_mm), 0.0)

    # ------------------------------------------------------------------ motion model
    def _now(self) -> float:
        return self.clock() * self.time_scale

    def position(self) -> float:
        t0, a, b, dur = self._seg
        if dur <= 0:
            return b
        x = travelled_um(self._now() - t0, b - a, self._seg_vel, self.acc)
        if self._motion_error:
            x = min(x, 0.5 * abs(b - a))  # a symmetric profile: half the distance at half the time
        return a + (x if b >= a else -x)

    def moving(self) -> bool:
        t0, a, b, dur = self._seg
        end = 0.5 * dur if self._motion_error else dur
        return self._now() < t0 + end

    def _update(self) -> None:
        if self._motion_error and not self.moving() and self.servo:
            self.servo = False
            self.error = MOTION_ERROR
        if self._referencing and not self.moving():
            self._referencing = False
            if not self._motion_error:  # a reference move cut short by a motion error references nothing
                self.referenced = True

    def on_target(self) -> bool:
        t0, a, b, dur = self._seg
        return (not self._motion_error and self.servo and self.referenced
                and self._now() >= t0 + dur + self.settle_s * self.time_scale)

    def _start(self, target: float) -> None:
        here = self.position()
        dur = move_duration_s(target - here, self.vel, self.acc)
        self._seg = (self._now(), here, target, dur)
        self._seg_vel = self.vel
        self._motion_error = False
        self._log_triggers()

    def _log_triggers(self) -> None:
        """Trigger pulses of the move just started (PositionDistance between start and stop thresholds)."""
        t0, a, b, dur = self._seg
        for line, on in self.tro.items():
            cfg = self.cto.get(line, {})
            if not on or cfg.get(3, 0) != 0 or 8 not in cfg or 9 not in cfg:
                continue
            step = abs(cfg.get(1, 0.0))
            lo, hi = cfg[8], cfg[9]
            n = int(abs(hi - lo) / step + 1e-9) + 1 if step > 0 else 1
            for k in range(n):
                p = lo + (k * step if hi >= lo else -k * step)
                if min(a, b) <= p <= max(a, b) and (b - a) * (hi - lo) > 0:
                    t = t0 + time_at_um(abs(p - a), b - a, self._seg_vel, self.acc)
                    self.trigger_log.append({"t_s": t, "line": line, "pos_mm": p})

    def _log(self, cmd: str, value: float) -> None:
        self.motion_log.append({"t_s": self._now(), "cmd": cmd, "value": value})

    def _halt(self) -> None:
        here = self.position()
        self._seg = (self._now(), here, here, 0.0)
        self._referencing = False

    # ------------------------------------------------------------------ command interpreter
    def _set_error(self, code: int) -> None:
        self.error = code  # only the last error is kept, as on the controller

    def _axes(self, args: list[str]) -> list[str] | None:
        axes = args or ["1"]
        if any(a != "1" for a in axes):
            self._set_error(15)
            return None
        return axes

    def handle(self, cmd: str) -> str | None:
        """Execute one command; return the reply text (with its LFs) or None for no reply."""
        with self._lock:
            self.received.append(cmd)
            self._update()
            return self._handle(cmd)

    def _handle(self, cmd: str) -> str | None:
        if cmd == "\x05":  # #5: motion status, hex bit mask of moving axes
            return f"{1 if self.moving() else 0:X}\n"
        if cmd == "\x07":  # #7: ready status, 0xB1 ready / 0xB0 busy
            return "\xb1\n" if not self._referencing else "\xb0\n"
        if cmd == "\x18":  # #24: stop all axes
            self._halt()
            self._set_error(10)
            return None
        parts = cmd.strip().split()
        if not parts:
            return None
        name, args = parts[0].upper(), parts[1:]
        if name == "*IDN?":
            return self.idn + "\n"
        if name == "ERR?":
            code, self.error = self.error, 0
            return f"{code}\n"
        if name == "HLP?":
            return " \n".join(HELP_LINES) + "\n"
        if name == "SPA?":
            if len(args) != 2 or self._axes(args[:1]) is None:
                if len(args) != 2:
                    self._set_error(24)
                return None
            try:
                pid = int(args[1], 0)
            except ValueError:
                self._set_error(1)
                return None
            if pid != 0xA:  # only the maximum closed-loop velocity is emulated
                self._set_error(17)
                return None
            return f"{args[0]} {args[1]}={self.max_vel:.7f}\n"  # the arguments as the query gave them (MS249E 8.2)
        if name in ("CTO", "TRO"):
            return self._trigger_config(name, args)
        if name in ("CTO?", "TRO?"):
            if name == "TRO?":
                return " \n".join(f"{k}={int(v)}" for k, v in sorted(self.tro.items())) + "\n" if self.tro else "\n"
            rows = [f"{line} {pid}={val:g}" for line, cfg in sorted(self.cto.items()) for pid, val in sorted(cfg.items())]
            return " \n".join(rows) + "\n" if rows else "\n"
        if name in ("POS?", "MOV?", "ONT?", "SVO?", "FRF?", "VEL?", "ACC?", "TMN?", "TMX?", "CST?"):
            axes = self._axes(args)
            if axes is None:
                return None
            vals = {"POS?": lambda: f"{self.position():.7f}", "MOV?": lambda: f"{self._seg[2]:.7f}",
                    "ONT?": lambda: str(int(self.on_target())), "SVO?": lambda: str(int(self.servo)),
                    "FRF?": lambda: str(int(self.referenced)), "VEL?": lambda: f"{self.vel:.7f}",
                    "ACC?": lambda: f"{self.acc:.7f}",
                    "TMN?": lambda: f"{self.tmn:.7f}", "TMX?": lambda: f"{self.tmx:.7f}",
                    "CST?": lambda: self.stage_name}[name]
            return " \n".join(f"{a}={vals()}" for a in axes) + "\n"
        if name == "SAI?":
            return "1\n"
        if name in ("STP", "HLT"):
            if name == "HLT" and self._axes(args) is None:
                return None
            self._halt()
            self._set_error(10)
            return None
        if name == "SVO":
            if len(args) != 2 or args[1] not in ("0", "1"):
                self._set_error(1)
            elif self._axes(args[:1]) is not None:
                self.servo = args[1] == "1"
                if not self.servo:
                    self._halt()
            return None
        if name == "FRF":
            if self._axes(args) is None:
                return None
            if not self.servo:
                self._set_error(5)
                return None
            self._referencing = True
            self._start(self.reference_mm)
            if self._motion_error_armed:
                self._motion_error_armed = False
                self._motion_error = True
            return None
        if name in ("MOV", "VEL", "ACC"):
            if len(args) != 2:
                self._set_error(1)
                return None
            if self._axes(args[:1]) is None:
                return None
            try:
                value = float(args[1])
            except ValueError:
                self._set_error(1)
                return None
            if name == "VEL":
                if not (0 < value <= self.max_vel):
                    self._set_error(8)
                else:
                    self.vel = value
                    self._log("VEL", value)
                return None
            if name == "ACC":
                if not (0 < value <= 1e4):
                    self._set_error(17)
                else:
                    self.acc = value
                    self._log("ACC", value)
                return None
            if not (self.servo and self.referenced):
                self._set_error(5)
            elif not (self.tmn <= value <= self.tmx):
                self._set_error(7)
            else:
                self._log("MOV", value)
                self._start(value)
                if self._motion_error_armed:
                    self._motion_error_armed = False
                    self._motion_error = True
            return None
        self._set_error(2)
        return None

    def _trigger_config(self, name: str, args: list[str]) -> None:
        """``CTO {line pid value}`` / ``TRO {line 0|1}`` for digital outputs 1..4 (C-863.12: CTO parameter IDs 1
        TriggerStep, 2 Axis, 3 TriggerMode, 7 Polarity, 8 StartThreshold, 9 StopThreshold, 10 TriggerPosition)."""
        width = 3 if name == "CTO" else 2
        # MS249E 8.2: "With the C-863.12 only a single element per command line can be addressed (e. g. axis or
        # parameter)". Which code the unit sets for a line with more is not in the manual: 24 here (unverified).
        if len(args) != width:
            self._set_error(24)
            return None
        try:
            groups = [[float(v) for v in args[i:i + width]] for i in range(0, len(args), width)]
        except ValueError:
            self._set_error(1)
            return None
        for g in groups:
            line = int(g[0])
            if line not in (1, 2, 3, 4) or (name == "CTO" and int(g[1]) not in (1, 2, 3, 7, 8, 9, 10)) \
                    or (name == "TRO" and g[1] not in (0, 1)):
                self._set_error(17)
                return None
        for g in groups:
            if name == "CTO":
                self.cto.setdefault(int(g[0]), {})[int(g[1])] = g[2]
            else:
                self.tro[int(g[0])] = bool(g[1])
        return None

    # ------------------------------------------------------------------ faults applied on the way out
    def shape_reply(self, reply: str | None) -> tuple[bytes | None, float]:
        """Apply drop/garble/delay faults to a reply: (bytes or None, delay in s)."""
        if reply is None:
            return None, 0.0
        data = reply.encode("latin-1")
        if self._drop > 0:
            self._drop -= 1
            return None, 0.0
        if self._garble > 0:
            self._garble -= 1
            data = bytes(b ^ 0xA5 for b in data[:-1]) + b"\n"
        delay = 0.0
        if self._delay[0] > 0:
            delay = self._delay[1]
            self._delay = (self._delay[0] - 1, delay)
        return data, delay


class _Session:
    """Split a byte stream into GCS2 commands (control bytes stand alone; the rest ends in LF)."""

    def __init__(self, emulator: GCS2Emulator, send):
        self.emu, self.send, self.buf = emulator, send, b""

    def feed(self, data: bytes) -> None:
        for b in data:
            if b in (0x05, 0x07, 0x18) and not self.buf:
                self._reply(chr(b))
            elif b == 0x0A:
                cmd, self.buf = self.buf.decode("latin-1"), b""
                self._reply(cmd)
            else:
                self.buf += bytes([b])

    def _reply(self, cmd: str) -> None:
        data, delay = self.emu.shape_reply(self.emu.handle(cmd))
        if data is None:
            return
        if delay:
            time.sleep(delay)  # the controller answers late; later commands wait behind it
        self.send(data)


class PtyServer:
    """Serve an emulator on a pseudo-terminal; ``path`` is the device a client opens."""

    def __init__(self, emulator: GCS2Emulator):
        self.emulator = emulator
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _send(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except OSError:
            pass

    def _run(self) -> None:
        session = _Session(self.emulator, self._send)
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self._master], [], [], 0.02)
                if r:
                    data = os.read(self._master, 4096)
                    if data:
                        session.feed(data)
            except OSError:
                return

    def disconnect(self) -> None:
        """Pull the cable: the pty goes away; the client sees an I/O error or silence."""
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class TcpServer:
    """Serve an emulator on 127.0.0.1 (one client at a time); ``url`` is a pyserial URL for the client."""

    def __init__(self, emulator: GCS2Emulator, port: int = 0, host: str = "127.0.0.1"):
        self.emulator = emulator
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((host, port))
        self._sock.listen(1)
        self._sock.settimeout(0.01)
        self.host, self.port = self._sock.getsockname()
        self.url = f"socket://{self.host}:{self.port}"
        self._conn: socket.socket | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except (socket.timeout, OSError):
                continue
            self._conn = conn
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # replies go out at once, like a UART
            conn.settimeout(0.01)
            session = _Session(self.emulator, lambda d: self._safe_send(conn, d))
            while not self._stop.is_set():
                try:
                    data = conn.recv(4096)
                except socket.timeout:
                    continue
                except OSError:
                    break
                if not data:
                    break
                session.feed(data)
            try:
                conn.close()
            except OSError:
                pass
            self._conn = None

    @staticmethod
    def _safe_send(conn: socket.socket, data: bytes) -> None:
        try:
            conn.sendall(data)
        except OSError:
            pass

    def disconnect(self) -> None:
        """Drop the current client connection (the server keeps listening)."""
        conn = self._conn
        if conn is not None:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self.disconnect()
        self._thread.join(timeout=1)
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m fieldcal.hardware.gcs2_emulator",
                                description="Emulated PI C-863 + M-111.1DG speaking GCS2 (for dry runs).",
                                epilog="example:\n  python -m fieldcal.hardware.gcs2_emulator --tcp 50000\n"
                                       "  fieldcal capture --z -100 100 10 --stage gcs:socket://127.0.0.1:50000 "
                                       "--camera sim:models/triplet-uncorrected.json --out S",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--tcp", type=int, metavar="PORT", help="listen on 127.0.0.1:PORT")
    g.add_argument("--pty", action="store_true", help="open a pseudo-terminal and print its path")
    p.add_argument("--time-scale", type=float, default=1.0, help="emulated seconds per real second")
    a = p.parse_args(argv)
    emu = GCS2Emulator(time_scale=a.time_scale)
    server = TcpServer(emu, port=a.tcp) if a.tcp is not None else PtyServer(emu)
    print(server.url if a.tcp is not None else server.path, flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        server.close()
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
