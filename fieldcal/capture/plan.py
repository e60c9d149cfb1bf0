"""What to capture (:class:`CapturePlan`) and the message stream it becomes (:meth:`CapturePlan.messages`).

The plan is data: positions in capture order, exposures, the side every position is approached from (backlash)
and the back-off distance. :meth:`CapturePlan.messages` turns it into the stream of
:mod:`fieldcal.capture.messages` that the dry run prints, :mod:`fieldcal.capture.stream` checks and
:class:`fieldcal.capture.runner.Runner` executes.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..errors import ParameterError, SpecError
from .messages import Checkpoint, Expose, Message, Move, Save, Settle, WaitOnTarget

# Bounds that keep every later computation finite and meaningful: a focus stage travels millimetres, so a
# position beyond 1 m (1e6 µm) is a typo or an attack (`--z 1e308` would overflow the step count).
Z_LIMIT_UM = 1e6
MAX_FRAMES = 100000
MAX_EXPOSURE_MS = 3.6e6      # one hour
MAX_OVERSHOOT_UM = 1e5
MIN_STEP_UM = 1e-3


def _finite(v, name: str, *, lo: float, hi: float, lo_open: bool = False, fix: str) -> float:
    """``v`` as a float in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), else a ParameterError naming ``name``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ParameterError(f"{name} must be a number, got {v!r}", field=name, fix=fix)
    try:
        x = float(v)
    except OverflowError:  # an int beyond float range
        raise ParameterError(f"{name} = {v} is too large", field=name, fix=fix) from None
    if not math.isfinite(x) or x > hi or x < lo or (lo_open and x == lo):
        bound = f"{'>' if lo_open else '>='} {lo:g} and <= {hi:g}"
        raise ParameterError(f"{name} = {v!r} must be finite, {bound}", field=name, fix=fix)
    return x


@dataclass(frozen=True)
class PlannedFrame:
    """One planned frame: its index in the plan, the commanded position (µm) and its exposure (ms, or None for
    the camera's own)."""

    index: int
    z_um: float
    exposure_ms: float | None = None


@dataclass(frozen=True)
class CapturePlan:
    """What to capture: positions (µm) in capture order and how to approach them.

    Attributes
    ----------
    frames : PlannedFrame per position, in capture order.
    approach : ``"+z"`` (every position is reached moving +z, i.e. from below) or ``"-z"``.
    overshoot_um : how far past a position the stage backs off before approaching it (must exceed the backlash).
    source : where the plan came from (plan-file parameters or the ``--z`` range), stored in the stack.
    image_size_px : ``(width, height)`` the plan was made for (its profile's image size), or None when it does
        not say (a ``--z`` range, a hand-written plan); capture refuses a camera that delivers another size.
    """

    frames: tuple[PlannedFrame, ...]
    approach: str = "+z"
    overshoot_um: float = 20.0
    source: dict = field(default_factory=dict)
    image_size_px: tuple[int, int] | None = None

    def __post_init__(self):
        if not self.frames:
            raise ParameterError("the plan has no frames", field="frames", fix="give at least one position")
        if len(self.frames) > MAX_FRAMES:
            raise ParameterError(f"the plan has {len(self.frames)} frames (at most {MAX_FRAMES})", field="frames",
                                 fix="use fewer positions (a larger step)")
        if [f.index for f in self.frames] != list(range(len(self.frames))):
            raise ParameterError("frame indices must be 0, 1, 2, ... in capture order", field="frames[].index",
                                 fix="number the frames in capture order")
        for f in self.frames:
            _finite(f.z_um, f"frames[{f.index}].z_um", lo=-Z_LIMIT_UM, hi=Z_LIMIT_UM,
                    fix=f"keep positions within +-{Z_LIMIT_UM:g} um")
            if f.exposure_ms is not None:
                _finite(f.exposure_ms, f"frames[{f.index}].exposure_ms", lo=0.0, hi=MAX_EXPOSURE_MS, lo_open=True,
                        fix="use a positive exposure in ms")
        z = [f.z_um for f in self.frames]
        if len(set(z)) != len(z):
            raise ParameterError("plan positions repeat; a stack needs distinct z", field="frames[].z_um",
                                 fix="remove repeated positions")
        if self.approach not in ("+z", "-z"):
            raise ParameterError(f"approach must be '+z' or '-z', got {self.approach!r}", field="approach",
                                 fix="use '+z' or '-z'")
        _finite(self.overshoot_um, "overshoot_um", lo=0.0, hi=MAX_OVERSHOOT_UM,
                fix="use e.g. 20 um (more than the stage's backlash)")
        size = self.image_size_px
        if size is not None and not (len(size) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                            and v > 0 for v in size)):
            raise ParameterError(f"image_size_px = {size!r} must be (width, height) in whole pixels or None",
                                 field="image_size_px", fix="e.g. (320, 180)")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_range(cls, start_um: float, stop_um: float, step_um: float, *, exposure_ms: float | None = None,
                   approach: str | None = None, overshoot_um: float = 20.0) -> "CapturePlan":
        """``start, start+step, ...`` up to and including ``stop`` when it falls on the grid."""
        fix = f"give start, stop and step in um within +-{Z_LIMIT_UM:g}, e.g. -100 100 10"
        start = _finite(start_um, "start_um", lo=-Z_LIMIT_UM, hi=Z_LIMIT_UM, fix=fix)
        stop = _finite(stop_um, "stop_um", lo=-Z_LIMIT_UM, hi=Z_LIMIT_UM, fix=fix)
        step = _finite(step_um, "step_um", lo=-2 * Z_LIMIT_UM, hi=2 * Z_LIMIT_UM, fix=fix)
        if abs(step) < MIN_STEP_UM:
            raise ParameterError(f"step {step_um} um is below {MIN_STEP_UM} um", field="step_um",
                                 fix="use a step of at least 0.001 um (e.g. 10)")
        if (stop - start) * step < 0:
            raise ParameterError(f"z {start_um:g} {stop_um:g} {step_um:g}: the step goes away from stop",
                                 field="step_um", fix="use a negative step to go down, e.g. 100 -100 -10")
        n = int(math.floor((stop - start) / step + 1e-9)) + 1
        if n > MAX_FRAMES:
            raise ParameterError(f"the range gives {n} frames (at most {MAX_FRAMES})", field="step_um",
                                 fix="use a larger step")
        if exposure_ms is not None:
            exposure_ms = _finite(exposure_ms, "exposure_ms", lo=0.0, hi=MAX_EXPOSURE_MS, lo_open=True,
                                  fix="use a positive exposure in ms")
        zs = start + step * np.arange(n)
        frames = tuple(PlannedFrame(i, round(float(v), 6), exposure_ms) for i, v in enumerate(zs))
        approach = approach or ("+z" if step > 0 else "-z")
        return cls(frames, approach, overshoot_um,
                   {"kind": "range", "z_um": [start, stop, step], "exposure_ms": exposure_ms})

    @classmethod
    def from_file(cls, path: str | Path, *, exposure_ms: float | None = None, approach: str | None = None,
                  overshoot_um: float = 20.0) -> "CapturePlan":
        """A ``fieldcal-plan/1`` stack plan (frames in capture order), read by :func:`fieldcal.plan.read_plan`;
        a sweep plan gives a :class:`fieldcal.capture.sweep.SweepCapturePlan` instead."""
        from fieldcal.plan import read_plan
        from fieldcal.plan.planfile import plan_image_size_px

        path = Path(path)
        try:
            doc = read_plan(path, check_files=False)
            data = path.read_bytes()
        except (OSError, RecursionError, ValueError, OverflowError) as exc:  # a folder, unreadable, deep JSON, 10**400
            raise SpecError(f"cannot read the plan ({type(exc).__name__}: {exc})", path=path,
                            fix="give the path of a plan made by `fieldcal plan`") from None
        if doc.get("kind") == "sweep":
            from .sweep import SweepCapturePlan
            if exposure_ms is not None or approach is not None:
                raise ParameterError("a sweep's exposure is its plan's sweep time and its direction the plan's",
                                     field="exposure_ms" if exposure_ms is not None else "approach",
                                     fix="leave out --exposure-ms and --approach for a sweep plan (plan the sweep "
                                         "again to change them)")
            return SweepCapturePlan.from_doc(doc, path, data)
        if doc.get("kind") != "stack":
            raise SpecError(f"kind {doc.get('kind')!r} cannot be captured", path=path, field="kind",
                            fix="give a stack or sweep plan made by `fieldcal plan`")
        if exposure_ms is not None:
            exposure_ms = _finite(exposure_ms, "exposure_ms", lo=0.0, hi=MAX_EXPOSURE_MS, lo_open=True,
                                  fix="use a positive exposure in ms")
        frames = []
        for k, e in enumerate(doc["frames"]):
            exp = exposure_ms if exposure_ms is not None else e.get("exposure_ms")
            frames.append(PlannedFrame(k, e["z_um"], exp))
        try:
            # a hand-written plan may leave out its direction: approach every frame from below (+z)
            return cls(tuple(frames), approach or doc.get("direction", "+z"), overshoot_um,
                       {"kind": "plan", "file": str(path), "plan_sha256": hashlib.sha256(data).hexdigest(),
                        "parameters": doc.get("parameters", {})}, plan_image_size_px(doc, path))
        except ParameterError as exc:
            if exc.field in ("overshoot_um", "approach"):
                raise
            raise SpecError(exc.what, path=path, field=exc.field, fix=exc.fix) from None

    # ------------------------------------------------------------------ inspection
    @property
    def z_um(self) -> np.ndarray:
        return np.array([f.z_um for f in self.frames], dtype=np.float64)

    @property
    def sign(self) -> float:
        """+1 when positions are approached moving +z, else -1."""
        return 1.0 if self.approach == "+z" else -1.0

    def back_off_um(self, frame: PlannedFrame) -> float:
        """Where the stage goes before approaching ``frame`` from the plan's side."""
        return frame.z_um - self.sign * self.overshoot_um

    def fingerprint(self) -> str:
        """sha256 of what decides the frames (positions, order, exposures, approach); resume refuses a change."""
        doc = {"z_um": [f.z_um for f in self.frames], "exposure_ms": [f.exposure_ms for f in self.frames],
               "approach": self.approach, "overshoot_um": self.overshoot_um}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def messages(self, indices: Iterable[int] | None = None, *, on_target_timeout_ms: float = 30000.0,
                 settle_ms: float = 0.0) -> Iterator[Message]:
        """The acquisition stream for the frames ``indices`` (default all), in plan order.

        Per frame: :class:`Checkpoint`; a back-off :class:`Move` wherever the position would otherwise be
        reached from the wrong side (always before the first frame, as the start position is unknown);
        the target :class:`Move`; :class:`WaitOnTarget`; :class:`Settle` (when ``settle_ms`` > 0);
        :class:`Expose`; :class:`Save` (the commit point).
        """
        wanted = None if indices is None else set(indices)
        last: float | None = None
        for f in self.frames:
            if wanted is not None and f.index not in wanted:
                continue
            back = self.back_off_um(f)
            yield Checkpoint(f.index, back)
            if last is None or self.sign * (f.z_um - last) <= 0:
                yield Move(back, "back-off")
                yield WaitOnTarget(on_target_timeout_ms)
            yield Move(f.z_um, "target")
            yield WaitOnTarget(on_target_timeout_ms)
            if settle_ms > 0:
                yield Settle(settle_ms)
            yield Expose(f.index, f.exposure_ms)
            yield Save(f.index, f.z_um)
            last = f.z_um

    def moves(self) -> list[tuple[float, bool]]:
        """The motion sequence ``[(z_um, is_frame)]`` of the whole stream (a view of :meth:`messages`)."""
        return [(m.z_um, m.purpose == "target") for m in self.messages() if isinstance(m, Move)]

    def motion_range_um(self) -> tuple[float, float]:
        """Every position the stream can send the stage to (back-off positions of rewinds included)."""
        from .stream import extent_um
        return extent_um(self.messages())
