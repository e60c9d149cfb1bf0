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

from ..errors import ParameterError, SpecError
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


@dataclass(frozen=True)
class LensRecord:
    """What the user states about the optics when the camera does not (``--focal-length-mm``,
    ``--object-distance-mm``); a stated value overrides the camera's. Recorded in stack.json, from where
    calibration copies it into the profile's ``optics`` block (refocusing a plan needs both)."""

    focal_length_mm: float | None = None
    object_distance_mm: float | None = None

    def __post_init__(self):
        for name in ("focal_length_mm", "object_distance_mm"):
            v = getattr(self, name)
            if v is None:
                continue
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and 0 < v <= 1e9
            if not ok:
                raise ParameterError(f"{name} = {v!r} must be a positive finite distance in mm", field=name,
                                     fix="give the lens focal length / the chart distance in mm, e.g. 16 / 500")


def delivered_size_px(cam: dict) -> tuple[int, int] | None:
    """``(width, height)`` of the frames the camera delivers, from its record (:meth:`describe`): the ROI's size
    when one is set, else ``size_px``; None when the camera states neither (then the first frame tells)."""
    roi = cam.get("roi")
    size = roi[2:4] if isinstance(roi, (list, tuple)) and len(roi) == 4 else cam.get("size_px")
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        return None
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
        return None
    return int(size[0]), int(size[1])


def check_plan_size(plan: CapturePlan, size_px: tuple[int, int] | None, camera_name: str = "?") -> None:
    """Refuse a plan made for another image size than the camera delivers (a plan's frames and bands are in
    the profile's pixels: another size would be captured without a word and composited wrongly)."""
    want = plan.image_size_px
    if want is None or size_px is None or tuple(want) == tuple(size_px):
        return
    (w, h), (cw, ch) = want, size_px
    raise SpecError(f"the plan was made for {w}x{h} px images but camera {camera_name} delivers {cw}x{ch} px; "
                    "nothing was moved or written", path=plan.source.get("file"), field="profile.image_size_px",
                    fix=f"set the camera to {w}x{h} px (e.g. size={w}x{h} for a sim camera, or its ROI), or "
                        f"make the plan again from a profile calibrated at {cw}x{ch} px (`fieldcal plan stack "
                        "PROFILE --fs FS --q Q --out PLAN.json`)")


def _stack_header(cam: dict, stage: dict, plan: CapturePlan, lens: LensRecord = LensRecord(),
                  exposure_device=None) -> dict:
    focal = lens.focal_length_mm if lens.focal_length_mm is not None else cam.get("focal_length_mm")
    distance = lens.object_distance_mm if lens.object_distance_mm is not None else cam.get("object_distance_mm")
    size = delivered_size_px(cam)
    keys = {"bit_depth": cam.get("bit_depth"), "black_level": cam.get("black_level"),
            "white_level": cam.get("white_level"), "f_number": cam.get("f_number"), "focal_length_mm": focal,
            "object_distance_mm": distance, "image_size_px": None if size is None else list(size),
            "lens": cam.get("lens")}
    exps = {f.exposure_ms for f in plan.frames}
    if len(exps) == 1 and None not in exps:
        keys["exposure_ms"] = exps.pop()
    keys = {k: v for k, v in keys.items() if v is not None}
    if cam.get("kind") != "sim":
        # a real camera's frames carry the pixel aperture and the pupil's diffraction, fixed at the sensor: a
        # breathing stack's band-pass is corrected for their change (measure/breathing_mtf.py). The simulated
        # camera renders with the geometric path, which has neither.
        keys["sensor_mtf"] = {"pixel_aperture": True, "diffraction": bool(keys.get("f_number"))}
    keys["capture"] = {"stage": stage, "camera": cam, "plan": plan.source, "approach": plan.approach,
                       "overshoot_um": plan.overshoot_um, "z_um": "commanded position; z_measured_um = mean of "
                                                                   "the stage's readings before and after the exposure"}
    if hasattr(plan, "describe"):
        keys["capture"]["sweep"] = plan.describe()
        keys["capture"]["z_um"] = ("middle of the swept range; each frame's sweep.* holds the stage's readings when "
                                   "the exposure opened and closed")
        if exposure_device is not None:
            keys["capture"]["exposure_device"] = exposure_device.describe()
    given = {k: "given" for k in ("focal_length_mm", "object_distance_mm") if getattr(lens, k) is not None}
    if given:
        keys["capture"]["optics_from"] = {**{k: "camera" for k in ("focal_length_mm", "object_distance_mm")
                                             if cam.get(k) is not None}, **given}
    return keys


class _ProgressSink:
    """Advances a progress bar on each commit."""

    def __init__(self, folder: CaptureFolder, n: int, quiet: bool, check_size=None):
        self.folder = folder
        self._ticks = iter(progress(range(n + 1), total=n, desc="capture", quiet=quiet, unit="frame"))
        self._check_size = check_size  # the first frame's size, checked before it is saved
        next(self._ticks)

    def save(self, index, z_um, image, **meta):
        if self._check_size is not None and getattr(image, "ndim", 0) >= 2:
            self._check_size((int(image.shape[1]), int(image.shape[0])))
            self._check_size = None
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

    def __init__(self, stage, camera, *, handle_signals: bool = True, exposure_device=None):
        self.stage, self.camera = stage, camera
        self.exposure_device = exposure_device
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
            if self.exposure_device is not None:
                self.exposure_device.connect()
                if hasattr(self.camera, "observe_exposure_device"):
                    self.camera.observe_exposure_device(self.exposure_device)
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
            for dev in (self.exposure_device, self.camera, self.stage):
                if dev is None:
                    continue
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
        plan = self._bind(plan, options)
        stream = list(plan.messages(on_target_timeout_ms=options.on_target_timeout_ms, settle_ms=options.settle_ms))
        cam = self.camera.describe()
        size = delivered_size_px(cam)
        check_plan_size(plan, size, getattr(self.camera, "name", "?"))
        lo, hi = self.stage.limits_um()
        m_lo, m_hi = extent_um(stream)
        est = estimate(stream, velocity_um_s=self.stage.velocity_um_per_s(), readout_ms=options.readout_ms,
                       frame_bytes=_frame_bytes(cam))
        return {**est, "z_um": [f.z_um for f in plan.frames], "approach": plan.approach,
                "motion_range_um": [m_lo, m_hi], "stage_travel_um": [lo, hi],
                "image_size_px": None if size is None else list(size),
                "plan_image_size_px": None if plan.image_size_px is None else list(plan.image_size_px),
                "fits_travel": lo <= m_lo and m_hi <= hi, "stream": as_json(stream),
                **({"sweep": plan.describe()} if hasattr(plan, "describe") else {})}

    def _bind(self, plan, options: RunOptions):
        """A sweep plan learns the stage's kinematics (velocity refused above the maximum, run-up from the
        acceleration) and checks its exposure device; a stack plan with an exposure device is refused."""
        if hasattr(plan, "bind"):
            from .sweep import check_exposure_device
            check_exposure_device(plan, self.exposure_device)
            return plan.bind(self.stage, options.settle_ms)
        if self.exposure_device is not None:
            raise ParameterError("an exposure device gates a sweep's pixels; a stack plan takes frames without one",
                                 field="exposure_device", fix="leave out --exposure-device, or give a sweep plan")
        return plan

    def capture(self, plan: CapturePlan, out: str | Path, options: RunOptions = RunOptions(),
                lens: LensRecord = LensRecord()) -> CaptureResult:
        """Run ``plan`` into the stack folder ``out`` (created, or resumed); see :mod:`fieldcal.capture.folder`.

        Raises
        ------
        ParameterError
            The stream leaves the stage's travel (checked before any motion and before ``out`` is touched).
        SpecError
            The plan was made for another image size than the camera delivers (checked before any motion and
            before ``out`` is touched; a camera that states no size, or a wrong one: at the first frame, before
            it is saved).
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
        plan = self._bind(plan, options)
        kw = dict(on_target_timeout_ms=options.on_target_timeout_ms, settle_ms=options.settle_ms)
        cam = self.camera.describe()
        name = getattr(self.camera, "name", "?")
        size = delivered_size_px(cam)
        check_plan_size(plan, size, name)
        full = list(plan.messages(**kw))
        check_against_stage(full, limits_um=self.stage.limits_um())
        # a camera that cannot expose during motion is refused before the folder is touched
        Runner(self.stage, self.camera, None).preflight(full)
        with CaptureFolder(out) as folder:
            with self.critical():  # a resume's repairs (journal tail, stack.json, leftovers) finish before a signal
                found = folder.prepare(plan_sha256=plan.fingerprint(), n_frames=len(plan.frames),
                                       frame_z_um=[f.z_um for f in plan.frames], camera=cam,
                                       stack_header=_stack_header(cam, self.stage.describe(), plan, lens,
                                                                  self.exposure_device))
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
            # the first frame is checked too: a camera may state no size, or a wrong one (pylon's emulator)
            late_check = None if plan.image_size_px is None else (lambda wh: check_plan_size(plan, wh, name))
            runner = Runner(self.stage, self.camera, _ProgressSink(folder, len(todo), options.quiet, late_check),
                            retries=options.retries, quiet=options.quiet, critical=self.critical,
                            exposure_device=self.exposure_device)
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
            on_target_timeout_ms: float = 30000.0, settle_ms: float = 0.0, quiet: bool = False,
            lens: LensRecord = LensRecord(), exposure_device=None) -> CaptureResult:
    """Run ``plan`` on already connected devices into ``out`` (no signal handling; see :class:`Acquisition`)."""
    from ..errors import DeviceError, LinkError
    acq = Acquisition(stage, camera, handle_signals=False, exposure_device=exposure_device)
    if exposure_device is not None and hasattr(camera, "observe_exposure_device"):
        camera.observe_exposure_device(exposure_device)
    try:
        return acq.capture(plan, out, RunOptions(retries=retries, on_target_timeout_ms=on_target_timeout_ms,
                                                 settle_ms=settle_ms, quiet=quiet), lens)
    except (DeviceError, LinkError) as exc:
        _resumable_hint(exc, Path(out))
        raise


def run_capture(plan: CapturePlan, stage: str | Any, camera: str | Any, out: str | Path | None, *,
                options: RunOptions = RunOptions(), dry_run: bool = False,
                lens: LensRecord = LensRecord(), exposure_device: str | Any | None = None) -> CaptureResult | dict:
    """``fieldcal capture`` as a function: build the devices (device strings or objects), connect them, and
    either describe the run (``dry_run``: the stream and the checks, a dict) or capture into ``out``. ``lens``
    states the focal length and object distance where the camera does not (recorded in stack.json). A sweep plan
    (:class:`~fieldcal.capture.sweep.SweepCapturePlan`) needs ``exposure_device`` (e.g. ``"sim:MASKS"``)."""
    from ..errors import DeviceError, LinkError
    from ..hardware.registry import make_device
    if isinstance(stage, str):
        stage = make_device("stage", stage)
    if isinstance(camera, str):
        camera = make_device("camera", camera)
    if isinstance(exposure_device, str):
        exposure_device = make_device("exposure", exposure_device)
    with Acquisition(stage, camera, exposure_device=exposure_device) as acq:
        if dry_run:
            return acq.dry_run(plan, options)
        try:
            return acq.capture(plan, out, options, lens)
        except (DeviceError, LinkError) as exc:
            _resumable_hint(exc, Path(out))
            raise


__all__ = ["Acquisition", "CaptureResult", "Interrupted", "LensRecord", "RunOptions", "capture",
           "check_plan_size", "delivered_size_px", "run_capture"]
