"""GCS 2.0 behaviour checked against PI's documents, not against the emulator's own habits.

Sources (docs/hardware.md, "GCS2 protocol: what was checked against PI's documents"): PI's C-863.12 manual
MS249E (8.6, ``#5``: "bit-encoded ... 1=First axis in motion, 2=Second axis in motion"; ``#7``: "B0h ... not
ready (e.g., doing a reference move)") and PI's own host library pipython 2.11 (``GCS2Commands.IsMoving``
reads the bit of the axis' index in ``SAI? ALL``; ``pitools.waitonreferencing`` waits for ``#7`` to report
ready, reads ``ERR?``, then ``FRF?``)."""

import contextlib

import pytest

from fieldcal.hardware.gcs2 import GCS2Stage
from fieldcal.hardware.gcs2_emulator import GCS2Emulator, ManualClock, TcpServer
from fieldcal.hardware.protocols import DeviceFault

TIMEOUT_MS = 300


@contextlib.contextmanager
def _stage(emu, cls=GCS2Stage, **kw):
    """A stage of class ``cls`` connected to ``emu`` over TCP, closed after the block."""
    with TcpServer(emu) as srv:
        st = cls(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1, **kw)
        st.connect()
        try:
            yield st
        finally:
            st.close()


class _TwoAxisController(GCS2Emulator):
    """A two-axis controller (axes "1" and "2", e.g. a C-884) whose second axis is in a long motion of its own.
    Axis 1 is the emulator's; axis 2 only shows in ``SAI?`` and in bit 1 (value 2) of the ``#5`` mask."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.axis2_moving = True

    def _handle(self, cmd):
        if cmd == "\x05":
            mask = (1 if self.moving() else 0) | (2 if self.axis2_moving else 0)
            return f"{mask:X}\n"
        if cmd.strip().upper().startswith("SAI?"):
            return "1 \n2\n"
        return super()._handle(cmd)


def test_wait_on_target_reads_only_its_own_axis_bit_of_the_motion_mask():
    emu = _TwoAxisController(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        emu.set_referenced_at(7.5)
        st.move_to_um(100.0)
        st.wait_on_target(1500)  # axis 2 keeps moving: the bit of axis 1 alone decides
        assert st.on_target() and st.position_um() == pytest.approx(100.0, abs=1e-3)
        assert "\x18" not in emu.received  # nothing was stopped (#24 would stop axis 2 as well)


def test_a_moving_axis_is_still_seen_moving_on_a_multi_axis_controller():
    emu = _TwoAxisController(clock=ManualClock(100.0))  # stands still: axis 1 stays mid-move
    emu.axis2_moving = False
    with _stage(emu) as st:
        emu.set_referenced_at(7.5)
        st.move_to_um(500.0)
        with pytest.raises(DeviceFault, match="still moving"):
            st.wait_on_target(50)


def test_a_reference_move_that_fails_reports_the_controller_error_at_once():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        emu.motion_error_on_next_move()
        with pytest.raises(DeviceFault) as e:
            st.reference(timeout_ms=2000)
        assert e.value.code == 1024  # the controller's error, not a time-out with the error read and lost
        assert not emu.referenced and not st.is_referenced()


def test_reference_waits_for_the_controller_to_be_ready_before_reading_frf():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        st.reference(timeout_ms=3000)
        assert st.is_referenced()
        sent = emu.received[emu.received.index("FRF 1"):]
        # after FRF: ERR? (the command's own), then #7 until ready, ERR?, and only then FRF?
        first_frf_q = sent.index("FRF? 1")
        assert "\x07" in sent[:first_frf_q]
        assert sent[first_frf_q - 1] == "ERR?"


def test_the_c863_emulator_takes_one_element_per_command_line():
    # MS249E 8.2: "With the C-863.12 only a single element per command line can be addressed (e. g. axis or
    # parameter)"; "SEP 100 1 0x32 0 1 0x14 1 is not possible"
    emu = GCS2Emulator()
    assert emu.handle("CTO 1 2 1 1 3 0") is None
    assert emu.handle("ERR?") != "0\n" and 1 not in emu.cto
    assert emu.handle("TRO 1 1 2 1") is None and emu.handle("ERR?") != "0\n" and not emu.tro
    for cmd in ("CTO 1 2 1", "CTO 1 3 0", "TRO 1 1"):
        assert emu.handle(cmd) is None and emu.handle("ERR?") == "0\n"
    assert emu.cto[1] == {2: 1.0, 3: 0.0} and emu.tro[1]


def test_the_sweep_trigger_is_configured_one_cto_parameter_per_line():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with _stage(emu, GCS2Stage, trigger_out=2) as st:
        st.arm_sweep_trigger(-100.0, 100.0)  # raises DeviceFault when the controller refuses a line
        assert emu.cto[2] == pytest.approx({2: 1.0, 3: 0.0, 1: 0.2, 8: 7.4, 9: 7.6})
        assert emu.tro[2]
        ctos = [c for c in emu.received if c.startswith("CTO")]
        assert len(ctos) == 5 and all(len(c.split()) == 4 for c in ctos)
        st.disarm_sweep_trigger()
        assert not emu.tro[2]


def test_pipython_backend_arms_the_trigger_one_cto_per_line_and_reads_its_own_axis_bit():
    pytest.importorskip("pipython")
    from fieldcal.hardware.pipython_backend import PipythonStage
    emu = _TwoAxisController(clock=ManualClock(tick_s=0.05))
    with _stage(emu, PipythonStage, trigger_out=1) as st:
        st.arm_sweep_trigger(-100.0, 100.0)
        assert emu.cto[1] == pytest.approx({2: 1.0, 3: 0.0, 1: 0.2, 8: 7.4, 9: 7.6}) and emu.tro[1]
        emu.set_referenced_at(7.5)
        st.move_to_um(100.0)
        st.wait_on_target(1500)  # axis 2 keeps moving (pipython's IsMoving reads axis 1's bit)
        assert st.position_um() == pytest.approx(100.0, abs=1e-3)


def test_resync_on_a_line_that_never_goes_quiet_is_a_link_error_not_a_hang():
    """A controller at another baud rate, or a device that is not a controller, may send without pause: the
    resync's drain must give up (it read until the line was quiet, with no bound)."""
    import socket
    import threading
    import time

    from fieldcal.errors import LinkError
    from fieldcal.hardware.gcs2 import GCS2Client

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    stop = threading.Event()

    def flood():
        conn, _ = srv.accept()
        conn.settimeout(0.2)
        try:
            while not stop.is_set():
                conn.sendall(b"\xa5" * 256)
                time.sleep(0.002)
        except OSError:
            pass
        finally:
            conn.close()

    t = threading.Thread(target=flood, daemon=True)
    t.start()
    c = GCS2Client(f"socket://127.0.0.1:{srv.getsockname()[1]}", timeout_ms=50)
    t0 = time.monotonic()
    try:
        with pytest.raises(LinkError, match="quiet"):
            c.open()
    finally:
        stop.set()
        c.close()
        srv.close()
        t.join(2)
    assert time.monotonic() - t0 < 5.0


@pytest.mark.parametrize("kind", ["gcs", "pi"])
def test_reference_switches_the_servo_on_first_on_both_backends(kind):
    # after a motion error the controller has switched the servo off (error 1024's text); FRF with the servo off
    # is error 5 ("... or move attempted with servo off", pipython gcserror)
    if kind == "pi":
        pytest.importorskip("pipython")
    from fieldcal.hardware.pipython_backend import PipythonStage
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with _stage(emu, PipythonStage if kind == "pi" else GCS2Stage) as st:
        emu.servo = False
        st.reference(timeout_ms=3000)
        assert emu.referenced and emu.servo and st.is_referenced()


def test_an_axis_the_controller_does_not_have_is_a_clear_parameter_error():
    from fieldcal.errors import ParameterError
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1, axis="2")
        with pytest.raises(ParameterError) as e:
            st.connect()
        assert e.value.field == "axis" and "'1'" in str(e.value) and "fix:" in str(e.value)
        st.close()


class _SignedZeroPaddedController(GCS2Emulator):
    """Answers values as MS249E 8.2's example does ("1=+0000.0000"): sign, zero padding, four decimals."""

    def _handle(self, cmd):
        reply = super()._handle(cmd)
        name = cmd.strip().split()[0].upper() if cmd.strip() else ""
        if reply and name in ("POS?", "TMN?", "TMX?", "VEL?", "ACC?"):
            ax, val = reply.strip().split("=")
            return f"{ax}={float(val):+010.4f}\n"
        return reply


def test_values_are_parsed_in_the_manuals_signed_zero_padded_form():
    emu = _SignedZeroPaddedController(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        assert st.client.query("POS? 1") == ["1=+0000.0000"]
        assert st.limits_um() == pytest.approx((-7500.0, 7500.0))
        st.reference(3000)
        assert st.position_um() == pytest.approx(0.0, abs=0.1)
        assert st.velocity_um_per_s() == pytest.approx(1500.0)


class _DecimalParamController(GCS2Emulator):
    """Echoes a parameter ID in decimal (pipython itself sends IDs in decimal: ``SPA? 1 10``)."""

    def _handle(self, cmd):
        reply = super()._handle(cmd)
        if reply and cmd.strip().upper().startswith("SPA?"):
            head, val = reply.strip().split("=")
            ax, pid = head.split()
            return f"{ax} {int(pid, 0)}={val}\n"
        return reply


@pytest.mark.parametrize("kind", ["gcs", "pi"])
@pytest.mark.parametrize("controller", [GCS2Emulator, _DecimalParamController])
def test_the_maximum_velocity_is_read_from_parameter_0xa_on_both_backends(kind, controller):
    # MS249E VEL (p. 204): the maximum VEL is the Maximum Closed-Loop Velocity parameter, ID 0xA
    if kind == "pi":
        pytest.importorskip("pipython")
    from fieldcal.hardware.pipython_backend import PipythonStage
    emu = controller(clock=ManualClock(tick_s=0.05), max_velocity_mm_s=2.5)
    with _stage(emu, PipythonStage if kind == "pi" else GCS2Stage) as st:
        assert st.max_velocity_um_per_s() == pytest.approx(2500.0)
        assert st.acceleration_um_per_s2() == pytest.approx(emu.acc * 1000.0)


class _HpvController(GCS2Emulator):
    """Answers HPV? in MS249E's documented shape, whose lines carry TABs ("{<PamID> <ItemID> "=" <ListType>
    [ {TAB <PossibleValue> "=" <ValueDescription>} ] }", MS249E HPV?, p. 161)."""

    LINES = ["#Possible parameter values are:", "0x3C 1=1\t0=off\t1=on", "end of help"]

    def _handle(self, cmd):
        if cmd.strip().upper() == "HPV?":
            return " \n".join(self.LINES) + "\n"
        return super()._handle(cmd)


def test_a_reply_with_tabs_is_not_taken_for_line_noise():
    emu = _HpvController(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        assert st.client.query("HPV?") == _HpvController.LINES


class _LateReferenceFlagController(GCS2Emulator):
    """Says ready (#7) a moment before FRF? reports the axis referenced: its first two FRF? after the reference
    move answer 0 (pipython's gcs2pitools keeps polling FRF? after ready for this)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.late_answers = 2

    def _handle(self, cmd):
        if cmd.strip().upper() == "FRF? 1" and self.referenced and self.late_answers > 0:
            self.late_answers -= 1
            return "1=0\n"
        return super()._handle(cmd)


def test_a_reference_flag_that_lags_ready_by_a_few_polls_is_waited_for():
    """Review finding: after #7 said ready, one FRF? reading 0 failed the reference at once."""
    emu = _LateReferenceFlagController(clock=ManualClock(tick_s=0.05))
    with _stage(emu) as st:
        st.reference(timeout_ms=3000)
        assert st.is_referenced() and emu.late_answers == 0
