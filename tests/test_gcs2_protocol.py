"""GCS 2.0 behaviour checked against PI's documents, not against the emulator's own habits.

Sources (docs/hardware.md, "GCS2 protocol: what was checked against PI's documents"): PI's C-863.12 manual
MS249E (8.6, ``#5``: "bit-encoded ... 1=First axis in motion, 2=Second axis in motion"; ``#7``: "B0h ... not
ready (e.g., doing a reference move)") and PI's own host library pipython 2.11 (``GCS2Commands.IsMoving``
reads the bit of the axis' index in ``SAI? ALL``; ``pitools.waitonreferencing`` waits for ``#7`` to report
ready, reads ``ERR?``, then ``FRF?``)."""

import pytest

from fieldcal.hardware.gcs2 import GCS2Stage
from fieldcal.hardware.gcs2_emulator import GCS2Emulator, ManualClock, TcpServer
from fieldcal.hardware.protocols import DeviceFault

TIMEOUT_MS = 300


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
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1)
        st.connect()
        try:
            emu.set_referenced_at(7.5)
            st.move_to_um(100.0)
            st.wait_on_target(1500)  # axis 2 keeps moving: the bit of axis 1 alone decides
            assert st.on_target() and st.position_um() == pytest.approx(100.0, abs=1e-3)
            assert "\x18" not in emu.received  # nothing was stopped (#24 would stop axis 2 as well)
        finally:
            st.close()


def test_a_moving_axis_is_still_seen_moving_on_a_multi_axis_controller():
    emu = _TwoAxisController(clock=ManualClock(100.0))  # stands still: axis 1 stays mid-move
    emu.axis2_moving = False
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1)
        st.connect()
        try:
            emu.set_referenced_at(7.5)
            st.move_to_um(500.0)
            with pytest.raises(DeviceFault, match="still moving"):
                st.wait_on_target(50)
        finally:
            st.close()


def test_a_reference_move_that_fails_reports_the_controller_error_at_once():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1)
        st.connect()
        try:
            emu.motion_error_on_next_move()
            with pytest.raises(DeviceFault) as e:
                st.reference(timeout_ms=2000)
            assert e.value.code == 1024  # the controller's error, not a time-out with the error read and lost
            assert not emu.referenced and not st.is_referenced()
        finally:
            st.close()


def test_reference_waits_for_the_controller_to_be_ready_before_reading_frf():
    emu = GCS2Emulator(clock=ManualClock(tick_s=0.05))
    with TcpServer(emu) as srv:
        st = GCS2Stage(srv.url, timeout_ms=TIMEOUT_MS, poll_ms=1)
        st.connect()
        try:
            st.reference(timeout_ms=3000)
            assert st.is_referenced()
            sent = emu.received[emu.received.index("FRF 1"):]
            # after FRF: ERR? (the command's own), then #7 until ready, ERR?, and only then FRF?
            first_frf_q = sent.index("FRF? 1")
            assert "\x07" in sent[:first_frf_q]
            assert sent[first_frf_q - 1] == "ERR?"
        finally:
            st.close()
