"""Capturing a focal sweep: one exposure over a constant-velocity move through the plan's range.

A ``fieldcal-plan/1`` sweep plan (``fieldcal plan sweep``) gives the range ``start_um -> stop_um``, the velocity
``v = 2α / t_s`` and the exposure time ``T = |stop - start| / v``; its per-pixel windows are in the device files
``fieldcal plan export-masks`` writes, loaded by the exposure device. :class:`SweepCapturePlan` turns it into a
message stream the one :class:`~fieldcal.capture.runner.Runner` executes::

    Checkpoint -> Move(run-up start) -> WaitOnTarget [-> Settle]
    -> SweepMove(run-up start -> run-out end, v)
    -> OpenExposure(at start_um)      the stage is at v: the exposure device is triggered, the camera opens
    -> CloseExposure(at stop_um)      still at v: the camera closes
    -> WaitOnTarget (the run-out's deceleration) -> Save (the commit point; the old velocity is restored)

The run-up ``v²/2a + v · settle`` (:func:`fieldcal.hardware.motion.run_up_um`) is taken from the stage's own
acceleration, so acceleration and settling happen before the exposure opens (and deceleration after it closes).
The stage's maximum velocity and travel (run-up included) are checked before anything moves.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator

from ..errors import ParameterError, SpecError
from .messages import (Checkpoint, CloseExposure, Message, Move, OpenExposure, Save, Settle, SweepMove,
                       WaitOnTarget)
from .plan import MAX_EXPOSURE_MS, Z_LIMIT_UM, PlannedFrame


@dataclass(frozen=True)
class SweepCapturePlan:
    """What a sweep capture does (µm, µm/s, ms). ``run_up_um`` is None until :meth:`bind` read the stage.

    Attributes
    ----------
    start_um, stop_um : the range the exposure spans (the plan's ``start_um``/``stop_um``).
    velocity_um_s : the constant velocity over it.
    device : the plan's exposure device (``"pixel"``; ``"lcos"`` plans are refused, see :meth:`from_doc`).
    masks_sha256 : the plan's mask sidecar hash; the exposure device's masks must come from it.
    """

    start_um: float
    stop_um: float
    velocity_um_s: float
    device: str = "pixel"
    masks_sha256: str | None = None
    source: dict = field(default_factory=dict)
    image_size_px: tuple[int, int] | None = None
    run_up_um: float | None = None
    accel_um_s2: float | None = None

    def __post_init__(self):
        for name in ("start_um", "stop_um"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and abs(v) <= Z_LIMIT_UM):
                raise ParameterError(f"{name} = {v!r} must be finite within +-{Z_LIMIT_UM:g} um", field=name,
                                     fix="make the sweep plan again")
        if self.start_um == self.stop_um:
            raise ParameterError("the sweep's start and stop are equal", field="stop_um",
                                 fix="make the sweep plan again (a sweep covers a range)")
        v = self.velocity_um_s
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ParameterError(f"velocity {v!r} um/s must be finite and > 0", field="velocity_um_s",
                                 fix="make the sweep plan again")
        if not self.exposure_ms <= MAX_EXPOSURE_MS:
            raise ParameterError(f"the sweep lasts {self.exposure_ms:g} ms (at most {MAX_EXPOSURE_MS:g})",
                                 field="velocity_um_s", fix="plan a faster or shorter sweep")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_doc(cls, doc: dict, path: str | Path | None = None, data: bytes = b"") -> "SweepCapturePlan":
        """From a validated ``fieldcal-plan/1`` sweep document."""
        from ..plan.planfile import plan_image_size_px
        dev = doc["device"]["name"]
        if dev != "pixel":
            raise SpecError(f"the plan is for the {dev!r} device; capture runs sweeps for a pixel-wise exposure "
                            "sensor only (an LCoS holds the stage between slots with the camera closed, which "
                            "one constant-velocity exposure cannot do)", path=path, field="device.name",
                            fix="plan the sweep with --device pixel (`fieldcal plan sweep PROFILE ... --device "
                                "pixel`), or drive the LCoS schedule yourself from the exported slot images")
        return cls(float(doc["start_um"]), float(doc["stop_um"]), float(doc["velocity_um_per_ms"]) * 1000.0,
                   device=dev, masks_sha256=(doc.get("masks") or {}).get("sha256"),
                   source={"kind": "sweep-plan", "file": None if path is None else str(path),
                           "plan_sha256": hashlib.sha256(data).hexdigest() if data else None,
                           "parameters": doc.get("parameters", {})},
                   image_size_px=plan_image_size_px(doc, path))

    # ------------------------------------------------------------------ the CapturePlan interface
    @property
    def direction(self) -> float:
        return 1.0 if self.stop_um > self.start_um else -1.0

    @property
    def approach(self) -> str:
        return "+z" if self.direction > 0 else "-z"

    @property
    def overshoot_um(self) -> float:
        return 0.0 if self.run_up_um is None else self.run_up_um

    @property
    def exposure_ms(self) -> float:
        """The exposure spans the range at constant velocity: ``|stop - start| / v``."""
        return abs(self.stop_um - self.start_um) / self.velocity_um_s * 1000.0

    @property
    def z_um(self) -> float:
        """The frame's nominal z: the middle of the swept range."""
        return round(0.5 * (self.start_um + self.stop_um), 6)

    @property
    def frames(self) -> tuple[PlannedFrame, ...]:
        return (PlannedFrame(0, self.z_um, self.exposure_ms),)

    def fingerprint(self) -> str:
        """sha256 of what decides the image (range, velocity, masks); resume refuses a change."""
        doc = {"kind": "sweep", "start_um": self.start_um, "stop_um": self.stop_um,
               "velocity_um_s": self.velocity_um_s, "masks_sha256": self.masks_sha256}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def describe(self) -> dict:
        """What stack.json records about the sweep (``capture.sweep``)."""
        d = {k: v for k, v in asdict(self).items() if k not in ("source", "image_size_px")}
        d["exposure_ms"] = self.exposure_ms
        if self.run_up_um is not None:
            d["run_up_start_um"] = self.start_um - self.direction * self.run_up_um
            d["run_out_end_um"] = self.stop_um + self.direction * self.run_up_um
        return d

    # ------------------------------------------------------------------ the stage's kinematics
    def bind(self, stage, settle_ms: float = 0.0) -> "SweepCapturePlan":
        """Check the velocity against the stage's maximum (before anything moves) and compute the run-up from
        its acceleration. A stage that cannot say either is refused."""
        from ..hardware.motion import run_up_um
        name = getattr(stage, "name", "?")
        for meth in ("max_velocity_um_per_s", "acceleration_um_per_s2", "set_velocity_um_per_s"):
            if not hasattr(stage, meth):
                raise ParameterError(f"stage {name} cannot run a sweep (no {meth}); nothing was moved",
                                     field="stage", fix="use a stage backend with velocity and acceleration "
                                                        "control (sim, gcs)")
        v_max = float(stage.max_velocity_um_per_s())
        if self.velocity_um_s > v_max * (1 + 1e-9):
            raise ParameterError(f"the plan sweeps at {self.velocity_um_s:g} um/s but stage {name} allows at most "
                                 f"{v_max:g} um/s; nothing was moved", field="velocity_um_s",
                                 fix="plan a slower sweep (a longer --pixel-exposure-ms or a smaller --alpha-um: "
                                     "v = 2 alpha / t_s)")
        a = float(stage.acceleration_um_per_s2())
        if not a > 0:
            raise ParameterError(f"stage {name} reports acceleration {a:g} um/s^2", field="stage",
                                 fix="check the stage's acceleration setting")
        return replace(self, run_up_um=round(run_up_um(self.velocity_um_s, a, settle_ms), 6), accel_um_s2=a)

    def messages(self, indices: Iterable[int] | None = None, *, on_target_timeout_ms: float = 30000.0,
                 settle_ms: float = 0.0) -> Iterator[Message]:
        """The stream (see the module docstring); :meth:`bind` first."""
        from ..hardware.motion import move_duration_s
        if self.run_up_um is None:
            raise ParameterError("the sweep is not bound to a stage", field="stage",
                                 fix="call SweepCapturePlan.bind(stage) before messages()")
        if indices is not None and 0 not in set(indices):
            return
        s, r = self.direction, self.run_up_um
        a_start, a_end = self.start_um - s * r, self.stop_um + s * r
        move_ms = move_duration_s(a_end - a_start, self.velocity_um_s, self.accel_um_s2 or math.inf) * 1000.0
        yield Checkpoint(0, a_start)
        yield Move(a_start, "back-off")
        yield WaitOnTarget(on_target_timeout_ms)
        if settle_ms > 0:
            yield Settle(settle_ms)
        yield SweepMove(a_start, a_end, self.velocity_um_s)
        yield OpenExposure(0, self.exposure_ms, at_um=self.start_um)
        yield CloseExposure(0, at_um=self.stop_um)
        yield WaitOnTarget(on_target_timeout_ms + move_ms)
        yield Save(0, self.z_um)


def check_exposure_device(plan: SweepCapturePlan, device) -> None:
    """Refuse an exposure device whose masks do not belong to the plan (before anything moves)."""
    if device is None:
        raise ParameterError("a sweep plan needs an exposure device for its per-pixel windows; nothing was moved",
                             field="exposure_device",
                             fix="export the plan's masks (`fieldcal plan export-masks PLAN --out MASKS`) and give "
                                 "--exposure-device sim:MASKS (or your device)")
    info = device.describe()
    want = plan.masks_sha256
    got = (info.get("plan") or {}).get("masks_sha256")
    if want and got != want:
        raise SpecError(f"the exposure device's masks were exported from another plan (masks sha256 {got!r:.20}, "
                        f"the plan's {want[:16]}...); nothing was moved", path=info.get("folder"),
                        field="plan.masks_sha256", fix="export the masks of this plan again: `fieldcal plan "
                                                       "export-masks PLAN --out MASKS --overwrite`")
    if info.get("device") not in (None, "pixelwise"):
        raise SpecError(f"the exposure device holds {info.get('device')!r} masks", path=info.get("folder"),
                        field="device", fix="use pixel-wise masks (a plan made with --device pixel)")
    size = info.get("image_size_px")
    if plan.image_size_px is not None and size is not None and tuple(size) != tuple(plan.image_size_px):
        raise SpecError(f"the masks are {size[0]}x{size[1]} px, the plan {plan.image_size_px[0]}x"
                        f"{plan.image_size_px[1]} px", path=info.get("folder"), field="image_size_px",
                        fix="export the masks of this plan again")


__all__ = ["SweepCapturePlan", "check_exposure_device"]
