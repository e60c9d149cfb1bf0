"""The acquisition: device lifecycle and signals around one plan, dry or real.

:class:`Acquisition` is a context manager that connects the stage and the camera, turns SIGTERM and SIGINT into
a clean stop (the stage is stopped, the folder stays resumable; a signal that arrives during a commit waits for
the commit to finish) and closes the devices whatever happens. Inside it, :meth:`Acquisition.dry_run` and
:meth:`Acquisition.capture` consume the same message stream (:meth:`CapturePlan.messages`).

:func:`run_capture` is the whole ``fieldcal capture`` command as a Python function.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ParameterError
from ..progress import progress, status
from .folder import CaptureFolder
from .plan import CapturePlan
from .runner import Runner
from .stream import as_json, check_against_stage, estimate, extent_um


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; the stage was stopped and the folder is resumable."""


@dataclass(frozen=True)
class RunOptions:
    """How to run a plan (not what to capture: that is the :class:`CapturePlan`).

    Attributes
    ----------
    retries : resync-and-retry attempts per frame after a link error (0..100).
    on_target_timeout_ms : per move, (0, 1 h].
    settle_ms : extra wait after on-target, [0, 10 min].
    readout_ms : per frame, for the dry run's time estimate.
    quiet : no progress output.
    """

    retries: int = 2
    on_target_timeout_ms: float = 30000.0
    settle_ms: float = 0.0
    readout_ms: float = 30.0
    quiet: bool = False

    def __post_init__(self):
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or not 0 <= self.retries <= 100:
            raise ParameterError(f"retries = {self.retries!r} must be an integer in 0..100", field="retries",
                                 fix="e.g. 2")
        for name, lo, hi, lo_open in (("on_target_timeout_ms", 0.0, 3.6e6, True), ("settle_ms", 0.0, 6e5, False),
                                      ("readout_ms", 0.0, 6e5, False)):
            v = getattr(self, name)
            ok = (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
                  and (v > lo if lo_open else v >= lo) and v <= hi)
            if not ok:
                raise ParameterError(f"{name} = {v!r} must be finite, {'>' if lo_open else '>='} {lo:g} and "
                                     f"<= {hi:g}", field=name, fix="give a finite time in ms")


@dataclass
class CaptureResult:
    path: Path
    n_frames: int
    taken: int
    skipped: int
    retaken: int
    link_retries: int = 0


def _frame_bytes(cam: dict) -> int:
    w, h = cam.get("size_px") or (0, 0)
    if cam.get("roi"):
        w, h = cam["roi"][2], cam["roi"][3]
    return int(w) * int(h) * len(cam.get("channels") or ["Y"]) * (1 if (cam.get("bit_depth") or 16) <= 8 else 2)


def _stack_header(cam: dict, stage: dict, plan: CapturePlan) -> dict:
    keys = {"bit_depth": cam.get("bit_depth"), "black_level": cam.get("black_level"),
            "white_level": cam.get("white_level"), "f_number": cam.get("f_number"),
            "object_distance_mm": cam.get("object_distance_mm"), "lens": cam.get("lens")}
    exps = {f.exposure_ms for f in plan.frames}
    if len(exps) == 1 and None not in exps:
        keys["exposure_ms"] = exps.pop()
    keys = {k: v for k, v in keys.items() if v is not None}
    keys["capture"] = {"stage": stage, "camera": cam, "plan": plan.source, "approach": plan.approach,
                       "overshoot_um": plan.overshoot_um, "z_um": "commanded position; z_measured_um = mean of "
                                                                   "the stage's readings before and after the exposure"}
    return keys


class _ProgressSink:
    """Advances a progress bar on each commit."""

    def __init__(self, folder: CaptureFolder, n: int, quiet: bool):
        self.folder = folder
        self._ticks = iter(progress(range(n + 1), total=n, desc="capture", quiet=quiet, unit="frame"))
        next(self._ticks)

    def save(self, index, z_um, image, **meta):
        out = self.folder.save(index, z_um, image, **meta)
        next(self._ticks, None)
        return out


class Acquisition:
    """Connected devices for one acquisition; SIGTERM/SIGINT stop it cleanly.

    Examples
    --------
    >>> with Acquisition(make_device("stage", "sim"), make_device("camera", "sim:lens.json")) as acq:  # doctest: +SKIP
    ...     result = acq.capture(CapturePlan.from_range(-100, 100, 10), "S")
    """

    def __init__(self, stage, camera, *, handle_signals: bool = True):
        self.stage, self.camera = stage, camera
        self.handle_signals = handle_signals
        self._old: dict[int, Any] = {}
        self._deferred: int | None = None
        self._in_critical = False

    # ------------------------------------------------------------------ lifecycle
    def _on_signal(self, signum, frame):
        if self._in_critical:
            self._deferred = signum  # raised when the commit is complete
            return
        raise Interrupted(signal.Signals(signum).name)

    @contextlib.contextmanager
    def critical(self):
        """Defer SIGINT/SIGTERM until the block ends (a frame file and its journal line go together)."""
        self._in_critical = True
        try:
            yield
        finally:
            self._in_critical = False
            if self._deferred is not None:
                signum, self._deferred = self._deferred, None
                raise Interrupted(signal.Signals(signum).name)

    def __enter__(self) -> "Acquisition":
        if self.handle_signals and threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.signal(s, self._on_signal)
        try:
            self.stage.connect()
            self.camera.connect()
            if hasattr(self.camera, "observe_stage"):
                self.camera.observe_stage(self.stage)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is not None:
                try:
                    self.stage.stop()
                except Exception:  # stopping must not replace the error being reported
                    pass
            for dev in (self.camera, self.stage):
                try:
                    dev.close()
                except Exception:  # closing must not replace the error being reported
                    pass
        finally:
            for s, old in self._old.items():
                signal.signal(s, old)
            self._old.clear()

    # ------------------------------------------------------------------ the two consumers of the stream
    def dry_run(self, plan: CapturePlan, options: RunOptions = RunOptions()) -> dict[str, Any]:
        """The stream, its extent against the stage's travel, and the time and disk it needs. Moves nothing."""
        stream = list(plan.messages(on_target_timeout_ms=options.on_target_timeout_ms, settle_ms=options.settle_ms))
        cam = self.camera.describe()
        lo, hi = self.stage.limits_um()
        m_lo, m_hi = extent_um(stream)
        est = estimate(stream, velocity_um_s=self.stage.velocity_um_per_s(), readout_ms=options.readout_ms,
                       frame_bytes=_frame_bytes(cam))
        return {**est, "z_um": [f.z_um for f in plan.frames], "approach": plan.approach,
                "motion_range_um": [m_lo, m_hi], "stage_travel_um": [lo, hi],
                "fits_travel": lo <= m_lo and m_hi <= hi, "stream": as_json(stream)}

    def capture(self, plan: CapturePlan, out: str | Path, options: RunOptions = RunOptions()) -> CaptureResult:
        """Run ``plan`` into the stack folder ``out`` (created, or resumed); see :mod:`fieldcal.capture.folder`.

        Raises
        ------
        ParameterError
            The stream leaves the stage's travel (checked before any motion and before ``out`` is touched).
        StackError
            ``out`` holds a different plan or camera, is not a capture folder, or holds links/foreign files.
        ResourceError
            Another capture holds ``out``'s lock; the disk or permissions refused a write.
        DeviceError / LinkError
            A device failed (after ``retries`` resyncs for link errors). The stage is stopped; the folder is
            resumable.
        Interrupted
            SIGINT/SIGTERM, after stopping the stage; the folder is resumable.
        """
        out = Path(out)
        kw = dict(on_target_timeout_ms=options.on_target_timeout_ms, settle_ms=options.settle_ms)
        check_against_stage(list(plan.messages(**kw)), limits_um=self.stage.limits_um())
        cam = self.camera.describe()
        with CaptureFolder(out) as folder:
            with self.critical():  # a resume's repairs (journal tail, stack.json, leftovers) finish before a signal
                found = folder.prepare(plan_sha256=plan.fingerprint(), n_frames=len(plan.frames),
                                       frame_z_um=[f.z_um for f in plan.frames], camera=cam,
                                       stack_header=_stack_header(cam, self.stage.describe(), plan))
            todo = [f.index for f in plan.frames if f.index not in found.committed]
            result = CaptureResult(out, len(plan.frames), 0, len(found.committed), found.torn)
            if not todo:
                status(f"capture: all {len(plan.frames)} frames of {out} are committed and intact; nothing to do",
                       options.quiet)
                return result
            if found.committed:
                status(f"capture: resuming {out}: {len(found.committed)} frames kept, {len(todo)} to take"
                       + (f" ({found.torn} torn)" if found.torn else ""), options.quiet)
            stream = list(plan.messages(todo, **kw))
            runner = Runner(self.stage, self.camera, _ProgressSink(folder, len(todo), options.quiet),
                            retries=options.retries, quiet=options.quiet, critical=self.critical)
            runner.preflight(stream)
            try:
                if not self.stage.is_referenced():
                    self.stage.reference()
                runner.run(stream)
            finally:
                result.taken = runner.saved
                result.link_retries = runner.link_retries
        return result


def _resumable_hint(exc, result_path: Path) -> None:
    """Tell the user a device failure left a resumable folder."""
    exc.fix = ((exc.fix + "; ") if exc.fix else "") + \
        f"committed frames are kept in {result_path}: re-run the same command to resume"
    exc.args = (exc._format(),)


def capture(plan: CapturePlan, stage, camera, out: str | Path, *, retries: int = 2,
            on_target_timeout_ms: float = 30000.0, settle_ms: float = 0.0, quiet: bool = False) -> CaptureResult:
    """Run ``plan`` on already connected devices into ``out`` (no signal handling; see :class:`Acquisition`)."""
    from ..errors import DeviceError, LinkError
    acq = Acquisition(stage, camera, handle_signals=False)
    try:
        return acq.capture(plan, out, RunOptions(retries=retries, on_target_timeout_ms=on_target_timeout_ms,
                                                 settle_ms=settle_ms, quiet=quiet))
    except (DeviceError, LinkError) as exc:
        _resumable_hint(exc, Path(out))
        raise


def run_capture(plan: CapturePlan, stage: str | Any, camera: str | Any, out: str | Path | None, *,
                options: RunOptions = RunOptions(), dry_run: bool = False) -> CaptureResult | dict:
    """``fieldcal capture`` as a function: build the devices (device strings or objects), connect them, and
    either describe the run (``dry_run``: the stream and the checks, a dict) or capture into ``out``."""
    from ..errors import DeviceError, LinkError
    from ..hardware.registry import make_device
    if isinstance(stage, str):
        stage = make_device("stage", stage)
    if isinstance(camera, str):
        camera = make_device("camera", camera)
    with Acquisition(stage, camera) as acq:
        if dry_run:
            return acq.dry_run(plan, options)
        try:
            return acq.capture(plan, out, options)
        except (DeviceError, LinkError) as exc:
            _resumable_hint(exc, Path(out))
            raise


__all__ = ["Acquisition", "CaptureResult", "Interrupted", "RunOptions", "capture", "run_capture"]
