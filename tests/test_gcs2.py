"""The GCS2 client against the bundled C-863 emulator, over a pseudo-terminal and a loopback TCP socket.

The emulator's motion runs on a :class:`ManualClock` that advances with every reading (``tick_s``) or when a
test says so: motion states never depend on how busy the machine is."""

import time

import pytest

from fieldcal.errors import LinkError
from fieldcal.hardware.gcs2 import (GCS2_CONTROLLER_ERRORS, GCS2_FIXES, GCS_DLL_ERRORS, GCS2Client, GCS2Stage,
                                    error_text)
from fieldcal.hardware.gcs2_emulator import HELP_LINES, IDN, GCS2Emulator, ManualClock, PtyServer, TcpServer
from fieldcal.hardware.protocols import DeviceFault

# Reply timeout of the clients under test. 60 ms was too short on a loaded 2-core CI machine (an emulator
# thread starved by the other test worker missed it now and then); tests of late or dropped replies scale with it.
TIMEOUT_MS = 300


@pytest.fixture(params=["pty", "tcp"])
def bench(request):
    emu = GCS2Emulator(settle_ms=2.0, clock=ManualClock(tick_s=0.05))
    srv = PtyServer(emu) if request.param == "pty" else TcpServer(emu)
    port = srv.path if request.param == "pty" else srv.url
    stage = GCS2Stage(port, timeout_ms=TIMEOUT_MS, poll_ms=2)
    stage.connect()
    yield emu, srv, stage, request.param
    stage.close()
    srv.close()


def _referenced(stage):
    stage.reference(timeout_ms=3000)
    return stage


def test_identify_servo_and_limits_in_fieldcal_um(bench):
    emu, _, stage, _ = bench
    assert stage.identify() == IDN
    assert emu.servo  # connect switched the servo on with SVO 1 1 and checked ERR?
    assert "SVO 1 1" in emu.received and "ERR?" in emu.received
    # M-111.1DG: 0..15 mm, zero at 7.5 mm -> +-7500 um
    assert stage.limits_um() == pytest.approx((-7500.0, 7500.0))


def test_move_converts_um_to_mm_at_the_edge(bench):
    emu, _, stage, _ = _referenced(bench[2]) and bench
    stage.move_to_um(250.0)
    assert "MOV 1 7.750000" in emu.received
    stage.wait_on_target(3000)
    assert stage.on_target()
    assert stage.position_um() == pytest.approx(250.0, abs=1e-3)
    assert emu.position() == pytest.approx(7.75)


def test_reversed_axis_sign():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=2, sign=-1, zero_mm=5.0)
        st.connect()
        st.reference(3000)
        assert st.limits_um() == pytest.approx((-10000.0, 5000.0))
        st.move_to_um(1000.0)
        st.wait_on_target(3000)
        assert emu.position() == pytest.approx(4.0)
        assert st.position_um() == pytest.approx(1000.0, abs=1e-3)
        st.close()


def test_move_unreferenced_is_error_5(bench):
    _, _, stage, _ = bench
    with pytest.raises(DeviceFault) as e:
        stage.move_to_um(0.0)
    assert e.value.code == 5 and "unreferenced" in str(e.value)


def test_out_of_limits_is_error_7_and_nothing_moves(bench):
    emu, _, stage, _ = bench
    _referenced(stage)
    before = emu.position()
    with pytest.raises(DeviceFault) as e:
        stage.move_to_um(7600.0)
    assert e.value.code == 7
    assert emu.position() == before


def test_unknown_command_and_syntax_errors(bench):
    _, _, stage, _ = bench
    with pytest.raises(DeviceFault) as e:
        stage.client.command("XYZ 1")
    assert e.value.code == 2
    with pytest.raises(DeviceFault) as e:
        stage.client.command("MOV 1 abc")
    assert e.value.code == 1
    with pytest.raises(DeviceFault) as e:
        stage.client.command("MOV 2 1.0")
    assert e.value.code == 15
    assert stage.client.error_code() == 0  # ERR? cleared them


def test_only_the_last_error_is_latched():
    emu = GCS2Emulator()
    emu.handle("XYZ")        # 2
    emu.handle("MOV 1 1.0")  # 5 (servo off)
    assert emu.handle("ERR?") == "5\n"
    assert emu.handle("ERR?") == "0\n"


def test_multi_line_reply(bench):
    _, _, stage, _ = bench
    lines = stage.client.query("HLP?")
    assert lines == HELP_LINES


def test_single_char_commands(bench):
    emu, _, stage, _ = bench
    assert stage.client.query("#7") == ["\xb1"]
    emu.clock = ManualClock(100.0)  # stands still until the test advances it
    emu.set_referenced_at(7.5)
    emu.vel = 0.5
    stage.move_to_um(500.0)  # 1 s of motion
    assert stage.client.query("#5") == ["1"]  # moving, however long the reply took
    emu.clock.advance(0.5)
    assert stage.client.query("#5") == ["1"]
    # on the plateau of the trapezoid: x = v (t - v / 2a)
    x_um = 0.5 * (0.5 - 0.5 / (2 * emu.acc)) * 1000.0
    assert stage.position_um() == pytest.approx(x_um, abs=1e-3)
    stage.stop()
    assert "\x18" in emu.received
    assert emu.error == 0  # stop() read and cleared error 10
    assert not emu.moving()
    assert stage.client.query("#5") == ["0"]
    emu.clock.advance(5.0)
    assert stage.position_um() == pytest.approx(x_um, abs=1e-3)  # stopped where it was


def test_dropped_reply_is_a_link_error_and_resync_recovers(bench):
    emu, _, stage, _ = bench
    _referenced(stage)
    emu.drop_replies(1)
    with pytest.raises(LinkError, match="no reply"):
        stage.position_um()
    stage.resync()
    assert stage.position_um() == pytest.approx(0.0, abs=1e-3)


def test_garbled_reply_is_a_link_error(bench):
    emu, _, stage, _ = bench
    emu.garble_replies(1)
    with pytest.raises(LinkError, match="garbled"):
        stage.limits_um()
    stage.resync()
    assert stage.limits_um() == pytest.approx((-7500.0, 7500.0))


def test_late_reply_is_drained_not_taken_for_the_next_answer(bench):
    emu, _, stage, _ = bench
    _referenced(stage)
    emu.delay_replies(1, 3 * TIMEOUT_MS)
    with pytest.raises(LinkError):
        stage.position_um()  # "1=7.5" arrives after the timeout
    stage.resync()
    # had the stale POS? line been kept, VEL? would read 7.5 instead of the velocity
    assert stage.velocity_um_per_s() == pytest.approx(emu.vel * 1000.0)


@pytest.mark.parametrize("kind", ["pty", "tcp"])
def test_motion_error_is_code_1024_with_meaning_and_fix(kind):
    """A C-863 answers ERR? with 1024 (PI_CNTR_MOTION_ERROR) after a following error, not the DLL's -1024."""
    clock = ManualClock(0.0)
    emu = GCS2Emulator(clock=clock)
    srv = PtyServer(emu) if kind == "pty" else TcpServer(emu)
    with srv:
        st = GCS2Stage(srv.path if kind == "pty" else srv.url, timeout_ms=TIMEOUT_MS, poll_ms=2)
        st.connect()
        emu.set_referenced_at(7.5)
        emu.vel = 2.0
        emu.motion_error_on_next_move()
        st.move_to_um(200.0)  # MOV's own ERR? is 0: the clock has not moved
        clock.advance(1.0)    # past the half-way point where the axis faults
        with pytest.raises(DeviceFault) as e:
            st.wait_on_target(3000)
        assert e.value.code == 1024
        msg = str(e.value)
        assert "position error too large" in msg and "PI_CNTR_MOTION_ERROR" in msg and "obstruction" in msg
        assert not emu.servo and not st.on_target()
        st.close()


def test_error_table_keys_controller_codes_and_keeps_dll_codes_apart():
    assert 1024 in GCS2_CONTROLLER_ERRORS and -1024 not in GCS2_CONTROLLER_ERRORS
    assert GCS2_CONTROLLER_ERRORS[1024][0] == "PI_CNTR_MOTION_ERROR"
    assert GCS_DLL_ERRORS[-1024][0] == "PI_MOTION_ERROR"
    assert all(code >= 0 for code in GCS2_CONTROLLER_ERRORS)
    assert all(code < 0 for code in GCS_DLL_ERRORS)
    assert all(name.startswith("PI_CNTR_") for name, _ in GCS2_CONTROLLER_ERRORS.values())
    assert set(GCS2_FIXES) <= set(GCS2_CONTROLLER_ERRORS) | set(GCS_DLL_ERRORS)
    assert "see the controller manual" in error_text(4242)


def test_every_emulated_error_code_has_a_meaning():
    emu = GCS2Emulator(clock=ManualClock(0.0))
    codes = set()
    for cmd in ("XYZ", "MOV 1 abc", "MOV 2 1", "MOV 1 1.0", "VEL 1 99"):
        emu.handle(cmd)
        codes.add(int(emu.handle("ERR?")))
    emu.set_referenced_at(7.5)
    for cmd in ("MOV 1 99", "STP"):
        emu.handle(cmd)
        codes.add(int(emu.handle("ERR?")))
    assert codes == {1, 2, 5, 7, 8, 10, 15}
    assert codes <= set(GCS2_CONTROLLER_ERRORS)


def test_disconnect_is_a_link_error(bench):
    _, srv, stage, kind = bench
    srv.disconnect()
    time.sleep(0.05)
    with pytest.raises(LinkError):
        stage.position_um()
    if kind == "pty":  # the port itself is gone: resync tries to reopen it and says so
        with pytest.raises(LinkError, match="cannot reopen the port"):
            stage.resync()
    else:  # the server still listens: resync reopens the lost connection
        stage.resync()
        assert stage.limits_um() == pytest.approx((-7500.0, 7500.0))


def test_a_lost_port_is_reopened_on_resync():
    """pyserial keeps is_open True after an I/O error: the client must remember the loss and reopen."""
    emu = GCS2Emulator(clock=ManualClock(0.0))
    with TcpServer(emu) as srv:
        c = GCS2Client(srv.url, timeout_ms=TIMEOUT_MS)
        c.open()
        first = c._ser
        srv.disconnect()
        with pytest.raises(LinkError) as e:
            for _ in range(5):  # the first write may still be buffered; a read then sees the closed socket
                c.query("POS? 1")
        assert "POS? 1" in str(e.value)
        assert first.is_open  # what pyserial reports: not a sign the port works
        c.resync()
        assert c._ser is not first and c.query_float("TMX?", "1") == pytest.approx(15.0)
        c.close()


def test_a_failed_resync_names_the_command_that_failed(bench):
    emu, _, stage, _ = bench
    emu.drop_replies(2)  # POS? is lost, and so is the resync's *IDN?
    with pytest.raises(LinkError, match="POS\\? 1"):
        stage.position_um()
    with pytest.raises(LinkError) as e:
        stage.resync()
    assert "'*IDN?'" in str(e.value) and "while resyncing after 'POS? 1' failed" in str(e.value)
    stage.resync()  # the next one succeeds, and forgets the failed command
    assert stage.position_um() == pytest.approx(-7500.0, abs=1e-3)  # unreferenced: at 0 mm
    assert stage.client._failed is None


def test_port_is_opened_exclusively():
    emu = GCS2Emulator()
    with PtyServer(emu) as srv:
        a = GCS2Client(srv.path, timeout_ms=TIMEOUT_MS)
        a.open()
        b = GCS2Client(srv.path, timeout_ms=TIMEOUT_MS)
        with pytest.raises(LinkError, match="cannot open"):
            b.open()
        a.close()


def test_missing_port_is_a_clear_error():
    with pytest.raises(LinkError) as e:
        GCS2Client("/dev/does-not-exist-fieldcal", timeout_ms=TIMEOUT_MS).open()
    assert "does-not-exist" in str(e.value) and "fix:" in str(e.value)


def test_pipython_backend_against_the_emulator():
    pytest.importorskip("pipython")
    from fieldcal.hardware.pipython_backend import PipythonStage
    from pipython.pidevice.interfaces.pigateway import PIGateway
    emu1, emu2 = GCS2Emulator(clock=ManualClock(tick_s=0.05)), GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with PtyServer(emu1) as s1, TcpServer(emu2) as s2:
        a = PipythonStage(s1.path, timeout_ms=200, poll_ms=2)
        b = PipythonStage(s2.url, timeout_ms=200, poll_ms=2)
        a.connect()
        b.connect()
        # guard 2: the gateways keep their callbacks to themselves, the global list stays empty
        assert PIGateway._connection_status_changed_callbacks == []
        assert type(a._gateway)._connection_status_changed_callbacks is not \
            type(b._gateway)._connection_status_changed_callbacks
        a.reference(3000)
        a.move_to_um(50.0)
        a.wait_on_target(3000)
        assert emu1.position() == pytest.approx(7.55) and emu2.position() == pytest.approx(0.0)
        with pytest.raises(DeviceFault) as e:
            a.move_to_um(9000.0)
        assert e.value.code == 7
        # guard 1: a timeout inside a call that switches errcheck off leaves it on afterwards
        emu1.drop_replies(1)
        with pytest.raises(LinkError):
            a._call(a.dev.ReadGCSCommand, "POS? 1")
        assert a.dev.errcheck is True
        a.resync()
        assert a.position_um() == pytest.approx(50.0, abs=1e-3)
        a.close()
        b.close()
