"""Device contracts: the :class:`Stage` and :class:`Camera` protocols every backend implements.

Units at this boundary are fieldcal's (DESIGN.md): stage positions in µm of the *fieldcal* z axis
(+z moves the sensor away from the lens), times in ms. A backend converts to its controller's units at its
own edge (the PI GCS2 backend speaks mm to the controller) and says how in :meth:`Stage.describe`.

Two kinds of failure, and what the caller does about each:

* :class:`DeviceFault` (a :class:`~fieldcal.errors.DeviceError`): the device answered and reported an error
  with a code (e.g. GCS2 error 7, "position out of limits"). Its state is known; the operation failed.
* :class:`~fieldcal.errors.LinkError`: no answer, a garbled answer, or the link dropped. The device's state is
  unknown: call :meth:`Stage.resync` (drain the link, re-identify) before going on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..errors import DeviceError, LinkError

__all__ = ["Stage", "SweepStage", "Camera", "SweepCamera", "ExposureDevice", "Frame", "DeviceFault", "LinkError",
           "DeviceError"]


class DeviceFault(DeviceError):
    """A device reported an error code; its state is known.

    Parameters
    ----------
    what : str
        The device's own description of the error.
    code : int
        The device's error code (for PI GCS2 the controller's ``ERR?`` number).
    device : str
        Which device (e.g. ``"stage gcs:/dev/ttyUSB0"``), used as the error's ``path``.
    """

    def __init__(self, what: str, *, code: int, device: str, fix: str | None = None, field: str | None = None):
        self.code = int(code)
        self.device = device
        super().__init__(f"device error {self.code}: {what}", path=device, field=field, fix=fix)


@dataclass(frozen=True)
class Frame:
    """One image from a camera, with what the camera said about it.

    Attributes
    ----------
    image : numpy.ndarray
        ``H x W x C`` (channels last, always 3-D) in the camera's dtype.
    frame_id : int
        The camera's own counter or block id (monotonic within one connection).
    exposure_ms : float
        The exposure actually used.
    timestamp_ms : float
        The camera's timestamp (or host clock when it has none), in ms.
    meta : dict
        Anything else the backend knows (gain, temperature, ...), JSON-serialisable.
    """

    image: np.ndarray
    frame_id: int
    exposure_ms: float
    timestamp_ms: float
    meta: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Stage(Protocol):
    """A single-axis stage that moves the sensor along the optical axis, in fieldcal µm.

    Blocking calls; raise :class:`DeviceFault` or :class:`~fieldcal.errors.LinkError` on failure.
    """

    name: str

    def connect(self) -> None:
        """Open the link (exclusively) and check the device answers."""

    def close(self) -> None:
        """Close the link; never raises."""

    def identify(self) -> str:
        """The device's identity string (``*IDN?`` for GCS2)."""

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable facts for the stack's provenance: identity, units, zero point, options."""

    def is_referenced(self) -> bool:
        """Whether the axis knows its absolute position (after a reference move)."""

    def reference(self, timeout_ms: float = 60000.0) -> None:
        """Run the reference move and wait until it is done. Moves the stage."""

    def limits_um(self) -> tuple[float, float]:
        """Travel limits ``(lo, hi)`` in fieldcal µm; queried, never moves."""

    def velocity_um_per_s(self) -> float: ...

    def set_velocity_um_per_s(self, v: float) -> None: ...

    def move_to_um(self, z_um: float) -> None:
        """Start an absolute move; returns when the controller accepted it (not when it arrived)."""

    def on_target(self) -> bool: ...

    def wait_on_target(self, timeout_ms: float) -> None:
        """Block until on target; :class:`DeviceFault` on a motion error or when the time runs out."""

    def position_um(self) -> float:
        """The controller's measured position (encoder), fieldcal µm."""

    def stop(self) -> None:
        """Stop all motion now (safe to call at any time, also after a link error); never raises."""

    def resync(self) -> None:
        """After a :class:`~fieldcal.errors.LinkError`: drain the link and re-establish a known state."""


@runtime_checkable
class Camera(Protocol):
    """A camera that takes one frame per :meth:`snap`."""

    name: str

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def identify(self) -> str: ...

    def describe(self) -> dict[str, Any]:
        """Provenance and the stack keys this camera fixes: ``pixel_pitch_um``, ``channels``, ``bit_depth``, ..."""

    def configure(self, *, exposure_ms: float | None = None, roi: tuple[int, int, int, int] | None = None,
                  trigger: str | None = None) -> None:
        """Set exposure (ms), ROI ``(x, y, w, h)`` in px and trigger (``"software"`` or ``"free"``)."""

    def snap(self) -> Frame:
        """Trigger (when software-triggered), wait for and return one frame."""


@runtime_checkable
class SweepStage(Stage, Protocol):
    """A stage that can run a focal sweep: its kinematic limits are queried before anything moves.

    Optional: ``wait_past_um(z_um, timeout_ms)`` blocks until the move in progress passes ``z_um`` (the
    simulated stage computes it exactly; without it the runner polls :meth:`position_um`). A backend with a
    hardware position trigger (``configure_position_trigger``) fires the camera's trigger line itself.
    """

    def max_velocity_um_per_s(self) -> float:
        """The fastest velocity the controller accepts."""

    def acceleration_um_per_s2(self) -> float:
        """The acceleration (and deceleration) of a move; decides the sweep's run-up."""


@runtime_checkable
class SweepCamera(Camera, Protocol):
    """A camera with one exposure that spans a motion (open, the stage moves, close)."""

    def open_exposure(self) -> None:
        """Start integrating now (the configured ``exposure_ms`` is the exposure's length)."""

    def close_exposure(self) -> Frame:
        """End the exposure (wait for it) and return its frame."""


@runtime_checkable
class ExposureDevice(Protocol):
    """Per-pixel exposure during a sweep: an LCoS showing a slot sequence in front of the sensor, or a sensor
    with per-pixel start/stop registers.

    Masks come from the device files ``fieldcal plan export-masks`` writes (``masks.json``, format
    ``fieldcal-masks/1``). Time 0 of the masks is the trigger, which the capture gives when the sweep's
    exposure opens (the stage passing the plan's ``start_um``).
    """

    name: str

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def identify(self) -> str: ...

    def describe(self) -> dict[str, Any]:
        """Provenance: the device kind, the masks' manifest (planes, size, hashes, the plan they belong to)."""

    def load_masks(self, folder) -> dict:
        """Load (upload) the masks of an export folder, every file checked against its sha256; returns the
        manifest."""

    def arm(self) -> None:
        """Get ready for the trigger (an LCoS shows its first slot, a sensor latches its registers)."""

    def start(self) -> None:
        """The trigger: the exposure opened now."""

    def stop(self) -> None:
        """The exposure closed; back to idle (never raises)."""
