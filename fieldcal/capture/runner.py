"""The one runner: executes a message stream on a stage and a camera, committing frames to a sink.

Fault handling is part of the stream's structure, not of the plan generator: every frame's messages begin with a
:class:`~fieldcal.capture.messages.Checkpoint`. On a :class:`~fieldcal.errors.LinkError` (the device's state is
unknown) the runner resyncs the devices, moves to the checkpoint's back-off position (so the frame is approached
from the right side again) and replays the frame's messages, at most ``retries`` times. A
:class:`~fieldcal.errors.DeviceError` (the device reported a fault) or anything else stops the stage and is
raised; committed frames stay committed.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable, Iterable, Protocol

from ..errors import LinkError, ParameterError
from ..progress import status
from .messages import (Checkpoint, CloseExposure, Expose, Message, Move, OpenExposure, Save, Settle, SweepMove,
                       WaitOnTarget)
from .stream import needs_exposure_during_motion


class FrameSink(Protocol):
    """Where :class:`Save` commits a frame (:class:`fieldcal.capture.folder.CaptureFolder`)."""

    def save(self, index: int, z_um: float, image, **frame_meta) -> dict: ...


@dataclass
class Shot:
    """One exposure waiting for its :class:`Save`."""

    frame_index: int
    frame: Any
    z_before_um: float
    z_after_um: float
    time: str
    sweep: dict | None = None


def _stage_ms(stage) -> float | None:
    """The stage's own clock (the simulated stage's virtual time), or None."""
    f = getattr(stage, "now_ms", None)
    return None if f is None else round(float(f()), 6)


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class Runner:
    """Execute a stream on connected devices.

    Parameters
    ----------
    stage, camera : connected :class:`~fieldcal.hardware.protocols.Stage` and ``Camera``.
    sink : what :class:`Save` commits to.
    retries : resync-and-replay attempts per frame after a link error.
    critical : a context manager factory wrapped around each commit (the acquisition defers SIGTERM/SIGINT
        there so a signal never lands between a frame file and its journal line).
    sleep : how :class:`Settle` waits (tests pass a fake).
    """

    def __init__(self, stage, camera, sink: FrameSink, *, retries: int = 2, quiet: bool = True,
                 critical: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
                 sleep: Callable[[float], None] = time.sleep, exposure_device=None, poll_ms: float = 1.0):
        self.stage, self.camera, self.sink = stage, camera, sink
        self.exposure_device = exposure_device
        self.poll_ms = float(poll_ms)
        self._sweep: SweepMove | None = None
        self.retries = int(retries)
        self.quiet = quiet
        self.critical = critical
        self.sleep = sleep
        self.link_retries = 0
        self.saved = 0
        self._shot: Shot | None = None
        self._open: tuple[int, float, str, float | None, float] | None = None
        self._exposure_ms: float | None = None
        self._trigger_set = False
        self._timeout_ms = 30000.0
        self._restore_velocity: float | None = None
        self._trigger_armed = False
        self._msgs: list[Message] = []
        self._k = 0

    # ------------------------------------------------------------------ checks
    def preflight(self, stream: list[Message]) -> None:
        """Refuse, before anything moves, a stream these devices cannot run."""
        if needs_exposure_during_motion(stream) and not hasattr(self.camera, "open_exposure"):
            raise ParameterError(f"camera {getattr(self.camera, 'name', '?')} cannot expose during motion "
                                 "(no open_exposure/close_exposure); nothing was moved", field="camera",
                                 fix="use a camera (or exposure device) that exposes during a sweep")

    # ------------------------------------------------------------------ run
    def run(self, stream: Iterable[Message]) -> int:
        """Execute ``stream``; returns the number of frames saved. Stops the stage on any failure."""
        msgs = list(stream)
        self.preflight(msgs)
        self._msgs = msgs
        k, seg, attempts, recovering = 0, None, 0, False
        try:
            while k < len(msgs):
                m = msgs[k]
                try:
                    if isinstance(m, Checkpoint):
                        if not recovering:
                            seg, attempts = (k, m), 0
                        else:  # the position is unknown after a resync: approach the frame's side again
                            self._do(Move(m.back_off_um, "back-off"))
                            self._do(WaitOnTarget(self._timeout_ms))
                            recovering = False
                    else:
                        self._k = k
                        self._do(m)
                    k += 1
                except LinkError as exc:
                    if seg is None or attempts >= self.retries:
                        raise
                    attempts += 1
                    self.link_retries += 1
                    status(f"capture: link error ({exc.what}); resyncing and retrying frame {seg[1].frame_index}",
                           self.quiet)
                    self._reset_device_state()
                    self.stage.resync()
                    if hasattr(self.camera, "resync"):
                        self.camera.resync()
                    k, recovering = seg[0], True
        except BaseException:
            self.stage.stop()  # a fault, Ctrl-C, SIGTERM or a bug: stop the motion first
            raise
        return self.saved

    def _reset_device_state(self) -> None:
        self._shot, self._open, self._exposure_ms, self._trigger_set = None, None, None, False
        self._sweep = None
        if self.exposure_device is not None:
            self.exposure_device.stop()

    def _arm_trigger(self) -> None:
        """A stage with a position-trigger output is told the exposure's range before the sweep starts."""
        self._trigger_armed = False
        if not hasattr(self.stage, "arm_sweep_trigger"):
            return
        k = self._k + 1  # the OpenExposure/CloseExposure that follow name the range
        at = [getattr(m, "at_um", None) for m in self._msgs[k:k + 2]]
        if len(at) == 2 and None not in at:
            self.stage.arm_sweep_trigger(at[0], at[1])
            self._trigger_armed = True

    def _wait_past(self, z_um: float) -> None:
        """Block until the sweep's move passes ``z_um``: the stage's own wait (exact on the simulated stage),
        else polling its position (what is left on a stage whose position trigger is not wired to the camera)."""
        if hasattr(self.stage, "wait_past_um"):
            self.stage.wait_past_um(z_um, self._timeout_ms)
            return
        from ..errors import DeviceError
        sign = 1.0 if self._sweep is None or self._sweep.z_stop_um >= self._sweep.z_start_um else -1.0
        deadline = time.monotonic() + self._timeout_ms / 1000.0
        while sign * (self.stage.position_um() - z_um) < 0:
            if time.monotonic() > deadline:
                raise DeviceError(f"the stage did not pass {z_um:g} um within {self._timeout_ms:.0f} ms",
                                  path=f"stage {getattr(self.stage, 'name', '?')}",
                                  fix="check the stage moves; raise --on-target-timeout-ms")
            self.sleep(self.poll_ms / 1000.0)

    def _configure_exposure(self, exposure_ms: float | None) -> None:
        if not self._trigger_set:
            self.camera.configure(trigger="software")
            self._trigger_set = True
        if exposure_ms is not None and exposure_ms != self._exposure_ms:
            self.camera.configure(exposure_ms=exposure_ms)
            self._exposure_ms = exposure_ms

    def _do(self, m: Message) -> None:
        if isinstance(m, Move):
            self.stage.move_to_um(m.z_um)
        elif isinstance(m, WaitOnTarget):
            self._timeout_ms = m.timeout_ms
            self.stage.wait_on_target(m.timeout_ms)
            if self._restore_velocity is not None:
                self.stage.set_velocity_um_per_s(self._restore_velocity)
                self._restore_velocity = None
                if self._trigger_armed:
                    self.stage.disarm_sweep_trigger()
                    self._trigger_armed = False
        elif isinstance(m, Settle):
            self.sleep(m.ms / 1000.0)
        elif isinstance(m, Expose):
            self._configure_exposure(m.exposure_ms)
            z0 = self.stage.position_um()
            t = _now_iso()
            frame = self.camera.snap()
            self._shot = Shot(m.frame_index, frame, z0, self.stage.position_um(), t)
        elif isinstance(m, SweepMove):
            if self._restore_velocity is None:  # a replayed sweep (after a link error) keeps the original
                self._restore_velocity = self.stage.velocity_um_per_s()
            self.stage.set_velocity_um_per_s(m.velocity_um_s)
            self._arm_trigger()
            self.stage.move_to_um(m.z_stop_um)
            self._sweep = m
        elif isinstance(m, OpenExposure):
            self._configure_exposure(m.exposure_ms)
            dev = self.exposure_device
            if dev is not None:
                dev.arm()
            if m.at_um is not None:
                self._wait_past(m.at_um)
            z0 = self.stage.position_um()
            t_stage = _stage_ms(self.stage)
            if dev is not None:
                dev.start()
            self.camera.open_exposure()
            self._open = (m.frame_index, z0, _now_iso(), t_stage, time.monotonic())
        elif isinstance(m, CloseExposure):
            if self._open is None or self._open[0] != m.frame_index:
                raise ParameterError(f"CloseExposure({m.frame_index}) without its OpenExposure", field="stream",
                                     fix="open an exposure before closing it")
            if m.at_um is not None:
                self._wait_past(m.at_um)
            frame = self.camera.close_exposure()
            z1, t1_stage, t1_host = self.stage.position_um(), _stage_ms(self.stage), time.monotonic()
            if self.exposure_device is not None:
                self.exposure_device.stop()
            _, z0, t0_iso, t0_stage, t0_host = self._open
            sweep = None
            if self._sweep is not None:
                sweep = {"z_open_measured_um": round(z0, 6), "z_close_measured_um": round(z1, 6),
                         "time_open": t0_iso, "time_close": _now_iso(),
                         "host_duration_ms": round((t1_host - t0_host) * 1000.0, 3),
                         "velocity_um_s": self._sweep.velocity_um_s,
                         "move_um": [self._sweep.z_start_um, self._sweep.z_stop_um]}
                if t0_stage is not None and t1_stage is not None:
                    sweep["stage_clock_ms"] = [t0_stage, t1_stage]
                for key in ("z_open_um", "z_close_um", "sub_exposures"):
                    if key in frame.meta:
                        sweep[f"camera_{key}"] = frame.meta[key]
                if self.exposure_device is not None:
                    sweep["exposure_device"] = getattr(self.exposure_device, "name", "?")
            self._shot = Shot(m.frame_index, frame, z0, z1, t0_iso, sweep)
            self._open = None
        elif isinstance(m, Save):
            self._save(m)
        else:
            raise ParameterError(f"unknown message {m!r}", field="stream",
                                 fix="build streams from fieldcal.capture.messages")

    def _save(self, m: Save) -> None:
        shot = self._shot
        if shot is None or shot.frame_index != m.frame_index:
            raise ParameterError(f"Save({m.frame_index}) without an exposure of that frame", field="stream",
                                 fix="expose a frame before saving it")
        f = shot.frame
        with self.critical():
            self.sink.save(m.frame_index, m.z_um, f.image,
                           z_measured_um=round(0.5 * (shot.z_before_um + shot.z_after_um), 6),
                           z_measured_before_um=round(shot.z_before_um, 6),
                           z_measured_after_um=round(shot.z_after_um, 6), z_commanded_um=m.z_um,
                           exposure_ms=f.exposure_ms, time=shot.time, camera_frame_id=int(f.frame_id),
                           plan_index=m.frame_index, **({} if shot.sweep is None else {"sweep": shot.sweep}))
        self._shot = None
        self.saved += 1
