"""Simulated devices: a stage with settle time, servo noise, backlash, travel limits and injectable faults,
and a camera that renders, through :class:`fieldcal.simulate.Renderer`, what it would see at the stage's
*actual* (not commanded) position. Together they run a whole calibration without hardware.

Time is virtual by default (``realtime=0``): waiting for a move advances the stage's own clock instead of
sleeping, so simulated captures run as fast as the renderer. ``realtime=1`` sleeps for real (demonstrations).

Device strings (see docs/hardware.md)::

    sim                                   defaults: +-7500 um travel, 2 um backlash, 0.05 um servo noise
    sim:fail_after=7                      the 8th move fails with a motion error (GCS2 code 1024)
    sim:fail_after=3,fault=timeout,fail_times=1   one lost reply after 3 moves; resync recovers
    sim:models/triplet-uncorrected.json,size=320x180   (camera) render the lens at 320x180 px
    sim:sweep-masks                       (exposure device) the masks `fieldcal plan export-masks` wrote

A sweep (``open_exposure`` ... ``close_exposure``) is emulated physically by
:func:`fieldcal.simulate.sweep_exposure.render_sweep_exposure`: sub-exposures at the stage's true position
along the move, each gated by the :class:`SimExposureDevice`'s masks, noise applied once to the total.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LinkError, ParameterError
from .motion import move_duration_s, time_at_um, travelled_um
from .protocols import DeviceFault, Frame

FAULT_KINDS = ("motion", "timeout", "garbled", "disconnect")
MOTION_ERROR_CODE = 1024  # PI_CNTR_MOTION_ERROR, what a GCS2 controller's ERR? answers after a following error


def _num(options: dict[str, str], key: str, default: float, *, device: str, positive=False, integer=False):
    """An option value as a number, or a ParameterError naming the option."""
    if key not in options:
        return default
    raw = options[key]
    try:
        v = int(raw) if integer else float(raw)
    except ValueError:
        raise ParameterError(f"option '{key}={raw}' is not a number", path=device, field=key,
                             fix=f"write e.g. {key}={default}") from None
    if not math.isfinite(v) or (positive and v <= 0) or v < 0 and key not in ("lo_um", "hi_um"):
        raise ParameterError(f"option '{key}={raw}' is out of range", path=device, field=key,
                             fix=f"use a {'positive' if positive else 'non-negative'} finite value")
    return v


def _reject_unknown(options: dict[str, str], known: set[str], device: str) -> None:
    bad = sorted(set(options) - known)
    if bad:
        raise ParameterError(f"unknown option(s) {', '.join(bad)}", path=device, field=bad[0],
                             fix=f"known options: {', '.join(sorted(known))}")


class SimStage:
    """A simulated single-axis stage in fieldcal µm.

    Mechanics: the encoder sits on the motor, so :meth:`position_um` reads the servo position
    (target + servo error, ``noise_um`` RMS) while the carriage lags by half the ``backlash_um`` play in the
    direction of the last move: ``true = encoder - sign(last move) * backlash / 2``. Approaching every
    position from the same side makes that offset one constant (absorbed by calibration); mixing directions
    makes it jump by ``backlash_um``. A move follows a trapezoidal velocity profile (``accel_um_per_s2``; see
    :mod:`fieldcal.hardware.motion`): ``|dz| / v + v / a`` for a long move, then ``settle_ms``. Velocities above
    ``max_velocity_um_per_s`` are refused (GCS2 code 8), as a controller refuses them.

    Faults: after ``fail_after`` successful moves the next ``fail_times`` moves (default: all) fail with
    ``fault`` = ``motion`` (:class:`DeviceFault` code 1024 while waiting), ``timeout`` (no reply:
    :class:`LinkError`, the move is lost), ``garbled`` (the position reply is unreadable: :class:`LinkError`)
    or ``disconnect`` (every call fails until reconnected).
    """

    OPTIONS = {"lo_um", "hi_um", "velocity_um_per_s", "max_velocity_um_per_s", "accel_um_per_s2", "settle_ms", "noise_um", "backlash_um", "seed",
               "realtime", "fail_after", "fail_times", "fault", "referenced"}

    def __init__(self, *, lo_um: float = -7500.0, hi_um: float = 7500.0, velocity_um_per_s: float = 1500.0,
                 settle_ms: float = 20.0, noise_um: float = 0.05, backlash_um: float = 2.0, seed: int = 0,
                 realtime: bool = False, fail_after: int | None = None, fail_times: int | None = None,
                 fault: str = "motion", referenced: bool = False, name: str = "sim",
                 max_velocity_um_per_s: float = 5000.0, accel_um_per_s2: float = 50000.0):
        if not lo_um < hi_um:
            raise ParameterError(f"travel lo_um={lo_um} must be below hi_um={hi_um}", path=f"stage {name}",
                                 field="lo_um", fix="give lo_um < hi_um")
        if fault not in FAULT_KINDS:
            raise ParameterError(f"unknown fault '{fault}'", path=f"stage {name}", field="fault",
                                 fix=f"use one of {', '.join(FAULT_KINDS)}")
        self.name = name
        self._lo, self._hi = float(lo_um), float(hi_um)
        self._v = float(velocity_um_per_s)
        self._v_max = float(max_velocity_um_per_s)
        self._accel = float(accel_um_per_s2)
        if not (self._v_max > 0 and self._accel > 0 and 0 < self._v <= self._v_max):
            raise ParameterError(f"velocity {self._v:g} um/s, max velocity {self._v_max:g} um/s and acceleration "
                                 f"{self._accel:g} um/s^2 must be > 0, velocity <= max", path=f"stage {name}",
                                 field="max_velocity_um_per_s", fix="e.g. max_velocity_um_per_s=5000,"
                                                                     "accel_um_per_s2=50000")
        self._v_move = self._v        # the velocity of the move in progress
        self._settle_ms = float(settle_ms)
        self._noise_um = float(noise_um)
        self._backlash_um = float(backlash_um)
        self._rng = np.random.default_rng(seed)
        self._realtime = bool(realtime)
        self._fail_after = fail_after
        self._fail_times = fail_times
        self._fault = fault
        self._seed = seed
        # state
        self._connected = False
        self._referenced = bool(referenced)
        self._clock_ms = 0.0
        self._start_um = 0.0          # servo position when the current move began
        self._target_um = 0.0
        self._t0_ms = 0.0             # move start time
        self._t_arrive_ms = 0.0       # move end time (incl. settle)
        self._servo_err_um = 0.0
        self._direction = 1.0         # sign of the last move: decides which side the backlash play sits on
        self._moves_ok = 0
        self._failures = 0
        self._motion_error = False
        self._disconnected = False
        self._pending_link_fault: str | None = None
        self.moves: list[float] = []  # every accepted target, for tests and logs

    # ------------------------------------------------------------------ construction from a device string
    @classmethod
    def from_spec(cls, arg: str | None, options: dict[str, str]) -> "SimStage":
        device = "stage sim" + (f":{arg}" if arg else "")
        if arg:
            raise ParameterError(f"the simulated stage takes only key=value options, not '{arg}'", path=device,
                                 fix="write e.g. --stage sim:fail_after=7,backlash_um=2")
        _reject_unknown(options, cls.OPTIONS, device)
        kw: dict[str, Any] = {}
        for key in ("lo_um", "hi_um", "settle_ms", "noise_um", "backlash_um"):
            if key in options:
                kw[key] = _num(options, key, 0.0, device=device)
        for key, default in (("velocity_um_per_s", 1500.0), ("max_velocity_um_per_s", 5000.0),
                             ("accel_um_per_s2", 50000.0)):
            if key in options:
                kw[key] = _num(options, key, default, device=device, positive=True)
        for key in ("seed", "fail_after", "fail_times"):
            if key in options:
                kw[key] = int(_num(options, key, 0, device=device, integer=True))
        for key in ("realtime", "referenced"):
            if key in options:
                kw[key] = options[key].lower() in ("1", "true", "yes", "on")
        if "fault" in options:
            kw["fault"] = options["fault"]
        return cls(**kw, name="sim" + ("" if not options else ":" + ",".join(f"{k}={v}" for k, v in options.items())))

    # ------------------------------------------------------------------ clock
    def _now_ms(self) -> float:
        return time.monotonic() * 1000.0 if self._realtime else self._clock_ms

    def _sleep_ms(self, dt_ms: float) -> None:
        if dt_ms <= 0:
            return
        if self._realtime:
            time.sleep(dt_ms / 1000.0)
        else:
            self._clock_ms += dt_ms

    # ------------------------------------------------------------------ link
    def _check_link(self) -> None:
        if not self._connected:
            raise LinkError("the simulated stage is not connected", path=f"stage {self.name}",
                            fix="call connect() first")
        if self._disconnected:
            raise LinkError("the simulated stage does not answer (injected disconnect)", path=f"stage {self.name}",
                            fix="check the cable and power, then re-run: the capture resumes")
        if self._pending_link_fault == "garbled":
            self._pending_link_fault = None
            raise LinkError("garbled reply from the simulated stage (injected fault)", path=f"stage {self.name}",
                            fix="resync() and repeat the command")

    def connect(self) -> None:
        self._connected = True
        self._t0_ms = self._t_arrive_ms = self._now_ms()

    def close(self) -> None:
        self._connected = False

    def identify(self) -> str:
        self._check_link()
        return "fieldcal simulated stage, SimStage, 0, 1"

    def describe(self) -> dict[str, Any]:
        return {"kind": "sim", "name": self.name, "units": "um (fieldcal z; no conversion)",
                "travel_um": [self._lo, self._hi], "backlash_um": self._backlash_um, "noise_um": self._noise_um,
                "velocity_um_per_s": self._v, "max_velocity_um_per_s": self._v_max,
                "accel_um_per_s2": self._accel, "settle_ms": self._settle_ms, "seed": self._seed}

    def resync(self) -> None:
        if not self._connected:
            self.connect()
        if self._disconnected:
            raise LinkError("the simulated stage still does not answer after resync", path=f"stage {self.name}",
                            fix="check the cable and power, then re-run: the capture resumes")
        self._pending_link_fault = None

    # ------------------------------------------------------------------ referencing and limits
    def is_referenced(self) -> bool:
        self._check_link()
        return self._referenced

    def reference(self, timeout_ms: float = 60000.0) -> None:
        self._check_link()
        self._begin_move(0.0)
        self._sleep_ms(self._t_arrive_ms - self._now_ms())
        self._referenced = True

    def limits_um(self) -> tuple[float, float]:
        self._check_link()
        return (self._lo, self._hi)

    def velocity_um_per_s(self) -> float:
        self._check_link()
        return self._v

    def set_velocity_um_per_s(self, v: float) -> None:
        self._check_link()
        if not (math.isfinite(v) and 0 < v <= self._v_max):
            raise DeviceFault(f"velocity {v:g} um/s out of limits (0, {self._v_max:g}]", code=8,
                              device=f"stage {self.name}", fix="lower the velocity below the stage's maximum")
        self._v = float(v)

    def max_velocity_um_per_s(self) -> float:
        """The fastest velocity :meth:`set_velocity_um_per_s` accepts."""
        self._check_link()
        return self._v_max

    def acceleration_um_per_s2(self) -> float:
        """The acceleration (and deceleration) of every move."""
        self._check_link()
        return self._accel

    # ------------------------------------------------------------------ motion
    def _servo_now(self) -> float:
        return self._servo_at(self._now_ms())

    def _servo_at(self, now: float) -> float:
        """Servo (encoder) position at stage time ``now`` (ms) of the current move: the trapezoidal profile,
        then the settled target plus servo error."""
        travel_ms = self._t_arrive_ms - self._settle_ms - self._t0_ms
        if now >= self._t_arrive_ms or travel_ms <= 0:
            if self._motion_error:
                return self._start_um + 0.5 * (self._target_um - self._start_um)
            return self._target_um + self._servo_err_um
        dz = self._target_um - self._start_um
        frac = travelled_um((now - self._t0_ms) / 1000.0, dz, self._v_move, self._accel) / abs(dz)
        if self._motion_error:
            frac = min(frac, 0.5)
        return self._start_um + frac * dz

    def _begin_move(self, z_um: float) -> None:
        start = self._servo_now()
        dz = z_um - start
        if dz != 0.0:
            self._direction = math.copysign(1.0, dz)
        self._start_um, self._target_um = start, float(z_um)
        self._t0_ms = self._now_ms()
        self._v_move = self._v
        self._t_arrive_ms = self._t0_ms + move_duration_s(dz, self._v, self._accel) * 1000.0 + self._settle_ms
        self._servo_err_um = float(self._rng.normal(0.0, self._noise_um)) if self._noise_um > 0 else 0.0

    def _fault_due(self) -> bool:
        if self._fail_after is None or self._moves_ok < self._fail_after:
            return False
        return self._fail_times is None or self._failures < self._fail_times

    def move_to_um(self, z_um: float) -> None:
        self._check_link()
        if not self._referenced:
            raise DeviceFault("unallowable move attempted on unreferenced axis", code=5,
                              device=f"stage {self.name}", fix="reference the stage first")
        if not (math.isfinite(z_um) and self._lo <= z_um <= self._hi):
            raise DeviceFault(f"position {z_um} um out of limits [{self._lo}, {self._hi}] um", code=7,
                              device=f"stage {self.name}", fix="keep the plan inside the stage's travel")
        if self._fault_due():
            self._failures += 1
            if self._fault == "timeout":
                raise LinkError(f"no reply to the move to {z_um} um (injected timeout)", path=f"stage {self.name}",
                                fix="resync() and repeat the command")
            if self._fault == "disconnect":
                self._disconnected = True
                self._check_link()
            if self._fault == "garbled":
                self._pending_link_fault = "garbled"
            if self._fault == "motion":
                self._motion_error = True
        else:
            self._moves_ok += 1
            self._motion_error = False
        self._begin_move(z_um)
        self.moves.append(float(z_um))

    def on_target(self) -> bool:
        self._check_link()
        return not self._motion_error and self._now_ms() >= self._t_arrive_ms

    def wait_on_target(self, timeout_ms: float) -> None:
        self._check_link()
        if self._motion_error:
            self._sleep_ms(min(timeout_ms, max(0.0, (self._t_arrive_ms - self._now_ms()) / 2)))
            raise DeviceFault("motion error: position error too large, servo is switched off automatically",
                              code=MOTION_ERROR_CODE, device=f"stage {self.name}",
                              fix="check the stage for obstruction or overload, then re-run: the capture resumes")
        wait = self._t_arrive_ms - self._now_ms()
        if wait > timeout_ms:
            self._sleep_ms(timeout_ms)
            self.stop()
            raise DeviceFault(f"not on target within {timeout_ms:.0f} ms", code=0, device=f"stage {self.name}",
                              fix="raise the on-target timeout or the velocity")
        self._sleep_ms(wait)

    def position_um(self) -> float:
        self._check_link()
        return float(self._servo_now())

    def true_position_um(self) -> float:
        """Where the carriage (the sensor) really is: what the simulated camera renders. Not on real stages."""
        return float(self._servo_now() - self._direction * self._backlash_um / 2.0)

    # ------------------------------------------------------------------ sweeps (simulation only)
    def now_ms(self) -> float:
        """The stage's clock (virtual unless ``realtime``), ms: what the simulated camera times exposures by."""
        return self._now_ms()

    def true_position_at_ms(self, t_ms: float) -> float:
        """Where the carriage is at stage time ``t_ms`` of the current move (the camera integrates over it)."""
        return float(self._servo_at(float(t_ms)) - self._direction * self._backlash_um / 2.0)

    def wait_past_um(self, z_um: float, timeout_ms: float) -> None:
        """Block until the move in progress reaches ``z_um`` (what a position trigger does on hardware); a
        position the move does not pass is a :class:`DeviceFault`."""
        self._check_link()
        dz = self._target_um - self._start_um
        x = (float(z_um) - self._start_um) * (1.0 if dz >= 0 else -1.0)
        if self._motion_error or not (0.0 <= x <= abs(dz)) or self._now_ms() >= self._t_arrive_ms:
            if self._motion_error:
                self.wait_on_target(timeout_ms)  # raises the motion error
            if abs(self._servo_now() - z_um) < 1e-9:
                return
            raise DeviceFault(f"the move in progress does not pass {z_um:g} um", code=0, device=f"stage {self.name}",
                              fix="start the sweep's move before waiting for its trigger position")
        t_at = self._t0_ms + time_at_um(x, dz, self._v_move, self._accel) * 1000.0
        wait = t_at - self._now_ms()
        if wait > timeout_ms:
            raise DeviceFault(f"{z_um:g} um not reached within {timeout_ms:.0f} ms", code=0,
                              device=f"stage {self.name}", fix="raise the on-target timeout")
        self._sleep_ms(wait)

    def stop(self) -> None:
        if not self._connected or self._disconnected:
            return
        here = self._servo_now()
        self._start_um = self._target_um = here
        self._servo_err_um = 0.0
        self._t0_ms = self._t_arrive_ms = self._now_ms()


def _parse_size(text: str, device: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParameterError(f"size '{text}' is not WIDTHxHEIGHT", path=device, field="size",
                             fix="write e.g. size=320x180") from None
    if not (8 <= w <= 20000 and 8 <= h <= 20000):
        raise ParameterError(f"size {w}x{h} is out of range", path=device, field="size",
                             fix="use 8..20000 px per side, e.g. size=320x180")
    return w, h


class SimCamera:
    """A camera on a simulated lens: renders the scene at the stage's actual position.

    Bind it to a stage with :meth:`observe_stage` (the capture command does): it then renders at
    ``stage.true_position_um()`` when the stage has one (simulated stage: backlash and servo error show up in
    the frames exactly as on hardware), else at the stage's measured position.

    Parameters
    ----------
    lens_path : path to a ``fieldcal-lens/1`` spec.
    size : (W, H) rendered size; the sensor area is kept (``LensSpec.with_sensor_size``).
    scene : ``"chart"`` (the calibration texture), ``"charuco"``, ``"slanted-edge"`` or an image file
        (:func:`fieldcal.simulate.scene.load_scene`).
    """

    OPTIONS = {"size", "seed", "scene", "noise", "sub_step_um"}
    DEFAULT_SIZE = (320, 180)

    def __init__(self, lens_path: str | Path, *, size: tuple[int, int] = DEFAULT_SIZE, seed: int = 0,
                 scene: str = "chart", noise: bool = True, sub_step_um: float = 1.0):
        from fieldcal.simulate.lens import LensSpec
        self.lens_path = Path(lens_path)
        self.spec = LensSpec.load(self.lens_path).with_sensor_size(*size)
        self.size = (int(size[0]), int(size[1]))
        self.seed = int(seed)
        self.scene_kind = scene
        self.noise = bool(noise)
        self.name = f"sim:{self.lens_path}"
        self._renderer = None
        self._connected = False
        self._frame_id = 0
        self._exposure_ms = float(self.spec.sensor.exposure_ms)
        self._roi: tuple[int, int, int, int] | None = None
        self._trigger = "software"
        self._position = lambda: 0.0
        self._stage = None
        self._exposure_device = None
        self._open: tuple[float | None, float] | None = None  # (stage time ms or None, position um) at open
        if not (math.isfinite(sub_step_um) and sub_step_um > 0):
            raise ParameterError(f"sub_step_um = {sub_step_um} must be > 0", path=f"camera sim:{lens_path}",
                                 field="sub_step_um", fix="e.g. sub_step_um=1 (um of travel per sub-exposure)")
        self.sub_step_um = float(sub_step_um)

    @classmethod
    def from_spec(cls, arg: str | None, options: dict[str, str]) -> "SimCamera":
        device = "camera sim" + (f":{arg}" if arg else "")
        if not arg:
            raise ParameterError("the simulated camera needs a lens spec", path=device,
                                 fix="write e.g. --camera sim:models/triplet-uncorrected.json,size=320x180")
        _reject_unknown(options, cls.OPTIONS, device)
        if not Path(arg).is_file():
            raise ParameterError(f"lens spec '{arg}' not found", path=arg,
                                 fix="give the path of a fieldcal-lens/1 JSON file, e.g. models/triplet-uncorrected.json")
        size = _parse_size(options["size"], device) if "size" in options else cls.DEFAULT_SIZE
        seed = int(_num(options, "seed", 0, device=device, integer=True))
        noise = options.get("noise", "1").lower() in ("1", "true", "yes", "on")
        step = _num(options, "sub_step_um", 1.0, device=device, positive=True)
        return cls(arg, size=size, seed=seed, scene=options.get("scene", "chart"), noise=noise, sub_step_um=step)

    def observe_stage(self, stage) -> None:
        """Render at this stage's actual position (true position when simulated, else measured)."""
        self._position = getattr(stage, "true_position_um", None) or stage.position_um
        self._stage = stage

    def observe_exposure_device(self, device) -> None:
        """Gate sweep exposures by this device's masks (a :class:`SimExposureDevice`)."""
        self._exposure_device = device

    def connect(self) -> None:
        if self._renderer is None:
            from ..simulate import Renderer
            self._renderer = Renderer(self.spec, self._scene(), seed=self.seed)
        self._connected = True

    def _scene(self):
        from ..simulate.scene import load_scene
        image, _ = load_scene(self.scene_kind, self.size[0], self.size[1], seed=self.seed)
        return image

    def close(self) -> None:
        self._connected = False

    def identify(self) -> str:
        return f"fieldcal simulated camera, lens {self.spec.name}, {self.size[0]}x{self.size[1]}"

    def describe(self) -> dict[str, Any]:
        s = self.spec.sensor
        return {"kind": "sim", "name": self.name, "lens": self.spec.name, "lens_file": str(self.lens_path),
                "size_px": list(self.size), "seed": self.seed, "scene": self.scene_kind,
                "pixel_pitch_um": s.pixel_pitch_um, "channels": list(self.spec.channel_names),
                "bit_depth": s.bit_depth, "black_level": s.black_level_dn, "white_level": s.white_level_dn,
                "f_number": self.spec.f_number, "focal_length_mm": self.spec.focal_length_mm,
                "object_distance_mm": self.spec.object_distance_mm,
                "roi": None if self._roi is None else list(self._roi), "sub_step_um": self.sub_step_um}

    def configure(self, *, exposure_ms: float | None = None, roi: tuple[int, int, int, int] | None = None,
                  trigger: str | None = None) -> None:
        if exposure_ms is not None:
            if not (math.isfinite(exposure_ms) and exposure_ms > 0):
                raise DeviceFault(f"exposure {exposure_ms} ms out of range", code=1, device=f"camera {self.name}",
                                  fix="use a positive exposure in ms")
            self._exposure_ms = float(exposure_ms)
        if roi is not None:
            x, y, w, h = (int(v) for v in roi)
            if x < 0 or y < 0 or w < 1 or h < 1 or x + w > self.size[0] or y + h > self.size[1]:
                raise DeviceFault(f"ROI {roi} outside the {self.size[0]}x{self.size[1]} sensor", code=1,
                                  device=f"camera {self.name}", fix="give x, y, w, h inside the sensor")
            self._roi = (x, y, w, h)
        if trigger is not None:
            if trigger not in ("software", "free"):
                raise DeviceFault(f"unknown trigger '{trigger}'", code=1, device=f"camera {self.name}",
                                  fix="use 'software' or 'free'")
            self._trigger = trigger

    def snap(self) -> Frame:
        if not self._connected:
            raise LinkError("the simulated camera is not connected", path=f"camera {self.name}",
                            fix="call connect() first")
        z_um = float(self._position())
        img = self._renderer.render(z_um, noise=self.noise)
        # exposure scales the signal around the spec's nominal exposure (clipped by the sensor's white level)
        nominal = float(self.spec.sensor.exposure_ms)
        if abs(self._exposure_ms - nominal) > 1e-9:
            black = float(self.spec.sensor.black_level_dn)
            white = float(self.spec.sensor.white_level_dn)
            scaled = black + (img.astype(np.float32) - black) * np.float32(self._exposure_ms / nominal)
            img = np.clip(np.rint(scaled), 0, white).astype(img.dtype)
        if img.ndim == 2:
            img = img[:, :, None]
        if self._roi is not None:
            x, y, w, h = self._roi
            img = img[y:y + h, x:x + w]
        self._frame_id += 1
        return Frame(image=np.ascontiguousarray(img), frame_id=self._frame_id, exposure_ms=self._exposure_ms,
                     timestamp_ms=time.time() * 1000.0, meta={"z_rendered_um": z_um})

    # ------------------------------------------------------------------ sweeps: one exposure over a motion
    def _stage_clock(self):
        st = self._stage
        if st is not None and hasattr(st, "now_ms") and hasattr(st, "true_position_at_ms"):
            return st
        return None

    def open_exposure(self) -> None:
        """Start integrating: remember when (the stage's clock) and where the sensor is."""
        if not self._connected:
            raise LinkError("the simulated camera is not connected", path=f"camera {self.name}",
                            fix="call connect() first")
        st = self._stage_clock()
        self._open = (None if st is None else float(st.now_ms()), float(self._position()))

    def _z_of_t(self):
        """Sensor position over the exposure: the simulated stage's exact trajectory, else (another stage) the
        readings at open and close joined at constant velocity."""
        t_open, z_open = self._open
        st = self._stage_clock()
        if st is not None and t_open is not None:
            return lambda t: st.true_position_at_ms(t_open + t)
        z_close = float(self._position())
        T = self._exposure_ms
        return lambda t: z_open + (z_close - z_open) * (t / T)

    def close_exposure(self) -> Frame:
        """End the exposure: integrate the scene over the motion, gated by the exposure device, noise once."""
        from ..simulate.noise import frame_rng
        from ..simulate.sweep_exposure import n_sub_for, render_sweep_exposure
        from .exposure import frame_weights
        if self._open is None:
            raise DeviceFault("close_exposure without open_exposure", code=1, device=f"camera {self.name}",
                              fix="open the exposure before closing it")
        z_of_t = self._z_of_t()
        T = self._exposure_ms
        n = n_sub_for(z_of_t(T) - z_of_t(0.0), self.sub_step_um)
        weights = None
        dev = self._exposure_device
        if dev is not None:
            tl = dev.timeline
            if tuple(tl.shape[1:]) != (self.size[1], self.size[0]):
                raise DeviceFault(f"the exposure device's masks are {tl.shape[2]}x{tl.shape[1]} px, the camera "
                                  f"{self.size[0]}x{self.size[1]} px", code=1, device=f"camera {self.name}",
                                  fix="export masks of a plan made for this camera's size")
            mosaic = bool(self.spec.sensor.cfa)
            weights = lambda t0, t1: frame_weights(tl.open_fraction(t0, t1), tl.planes, self.spec.channel_names,  # noqa: E731
                                                   mosaic, dev.folder)
        self._frame_id += 1
        rng = frame_rng(self.seed + self._frame_id, self._open[1]) if self.noise else None
        img = render_sweep_exposure(self._renderer, z_of_t, T, n_sub=n, weights=weights, rng=rng)
        if img.ndim == 2:
            img = img[:, :, None]
        if self._roi is not None:
            x, y, w, h = self._roi
            img = img[y:y + h, x:x + w]
        meta = {"z_open_um": float(z_of_t(0.0)), "z_close_um": float(z_of_t(T)), "sub_exposures": n,
                "noise": "once, on the total exposure"}
        self._open = None
        return Frame(image=np.ascontiguousarray(img), frame_id=self._frame_id, exposure_ms=T,
                     timestamp_ms=time.time() * 1000.0, meta=meta)


class SimExposureDevice:
    """A simulated per-pixel exposure device (LCoS or pixel-wise sensor) holding the masks of an export folder.

    Device string: ``sim:FOLDER`` (the folder ``fieldcal plan export-masks`` wrote). The simulated camera reads
    :attr:`timeline` while it integrates; :meth:`start`/:meth:`stop` record the trigger as hardware would.
    """

    OPTIONS: set[str] = set()

    def __init__(self, folder: str | Path | None = None, *, name: str = "sim"):
        self.name = name if folder is None else f"sim:{folder}"
        self.folder: Path | None = None
        self.manifest: dict | None = None
        self.timeline = None
        self.arrays: dict | None = None
        self.state = "idle"
        self.triggers = 0
        if folder is not None:
            self.load_masks(folder)

    @classmethod
    def from_spec(cls, arg: str | None, options: dict[str, str]) -> "SimExposureDevice":
        device = "exposure device sim" + (f":{arg}" if arg else "")
        _reject_unknown(options, cls.OPTIONS, device)
        if not arg:
            raise ParameterError("the simulated exposure device needs a masks folder", path=device,
                                 fix="write e.g. --exposure-device sim:sweep-masks (from `fieldcal plan "
                                     "export-masks PLAN --out sweep-masks`)")
        return cls(arg)

    def load_masks(self, folder) -> dict:
        from ..plan.device_masks import load_device_masks
        from .exposure import MaskTimeline
        dm = load_device_masks(folder)
        self.folder = Path(folder)
        self.manifest, self.arrays = dm.manifest, dm.arrays
        self.timeline = MaskTimeline.from_device_masks(dm)
        return dm.manifest

    def connect(self) -> None:
        if self.manifest is None:
            raise ParameterError("no masks loaded", path=f"exposure device {self.name}", field="masks",
                                 fix="give the masks folder: --exposure-device sim:FOLDER")

    def close(self) -> None:
        self.state = "idle"

    def identify(self) -> str:
        return f"fieldcal simulated exposure device ({self.manifest['device'] if self.manifest else 'no masks'})"

    def describe(self) -> dict[str, Any]:
        m = self.manifest or {}
        return {"kind": "sim", "name": self.name, "device": m.get("device"), "planes": m.get("planes"),
                "image_size_px": m.get("image_size_px"), "total_time_ms": m.get("total_time_ms"),
                "pixel_exposure_ms": m.get("pixel_exposure_ms"), "plan": m.get("plan"),
                "folder": None if self.folder is None else str(self.folder)}

    def arm(self) -> None:
        self.state = "armed"

    def start(self) -> None:
        if self.state != "armed":
            raise DeviceFault("triggered while not armed", code=1, device=f"exposure device {self.name}",
                              fix="arm() before the exposure opens")
        self.state = "running"
        self.triggers += 1

    def stop(self) -> None:
        self.state = "idle"
