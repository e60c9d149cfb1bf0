"""Focal-sweep plans (paper IV.C): sweep range, velocity, total time, per-pixel windows, device masks, IPSF trade.

The sensor sweeps ``[z_min - α, z_max + α]`` at ``v = 2α / t_s``; each pixel integrates while the sensor is within
α of its own best focus (per channel, or per Bayer site), so every pixel sees ``t_s`` and the whole sweep takes
``T = (D + 2α) / v = (D / 2α + 1) t_s`` (eq. 3) with D the range of best focus over the ROI and channels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..formats.atomic import atomic_write_bytes
from ..optics import LensModel, valid_fs_cyc_per_mm
from ..optics.sweep import integrated_otf
from . import ipsf as ip
from . import masks as mk
from .planfile import PLAN_FORMAT
from .scene import Scene
from .surfaces import SampledField, sample_field
from .tolerance import check_confidence

DEFAULT_ALPHAS_UM = (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0)
# Every LCoS slot is a full-frame mask in the sidecar; beyond this (α -> 0 makes T = (D/2α + 1) t_s explode)
# the mask file and the capture would never finish.
MAX_SLOTS = 10_000


@dataclass(frozen=True)
class SweepRequest:
    alpha_um: float = 20.0
    pixel_exposure_ms: float = 16.0
    device: str = "pixel"
    slot_ms: float | None = None
    max_hold_ms: float = 20.0
    clock_us: float = 10.0
    cfa: str | None = None
    scene: Scene = field(default_factory=Scene)
    direction: str = "+z"
    grid_step_px: int = 8
    fs_cyc_per_mm: float = 80.0
    wiener_nsr: float = 0.01
    trade_alphas_um: tuple[float, ...] = DEFAULT_ALPHAS_UM
    confidence: float | None = None   # widen each pixel's window by its credible band at this level


@dataclass
class SweepPlan:
    request: SweepRequest
    field: SampledField
    device: mk.Device
    planes: list[str]
    cfa: str | None
    start_um: float
    stop_um: float
    velocity_um_per_ms: float
    total_time_ms: float
    n_slots: int | None
    window_start_ms: np.ndarray  # (P, H, W) float32, NaN where never exposed
    trade: list[dict]
    ipsf_summary: dict[str, Any]
    warnings: list[str]
    widen_um: np.ndarray | None = None  # (P, H, W) float32: each pixel's credible half-width (None: no confidence)


    @property
    def range_um(self) -> float:
        """D of eq. 3: the range of best focus, widened by the credible bands when the plan has a confidence."""
        return abs(self.stop_um - self.start_um) - 2.0 * self.request.alpha_um

    @property
    def window_stop_ms(self) -> np.ndarray:
        """Closing time (ms): ``t_s`` after opening, plus the time the stage takes to cross twice the pixel's
        credible half-width when the plan has a confidence."""
        stop = self.window_start_ms + np.float32(self.request.pixel_exposure_ms)
        if self.widen_um is not None:
            stop = stop + np.float32(2.0 / self.velocity_um_per_ms) * self.widen_um
        return stop

    def band_summary(self) -> dict:
        return band_summary_of(self.widen_um, self.request.alpha_um, self.request.confidence)

    def slot_z_edges_um(self) -> list[float]:
        if self.n_slots is None:
            return []
        s = 1.0 if self.request.direction == "+z" else -1.0
        dz = self.velocity_um_per_ms * self.device.slot_ms
        return [self.start_um + s * k * dz for k in range(self.n_slots + 1)]

    def mask_arrays(self) -> dict[str, np.ndarray]:
        """What the ``.npz`` holds (see docs/planning.md)."""
        r = self.request
        arrays: dict[str, np.ndarray] = {
            "planes": np.asarray(self.planes, dtype="<U8"),
            "window_start_ms": self.window_start_ms,
            "window_stop_ms": self.window_stop_ms,
        }
        p, h, w = self.window_start_ms.shape
        if self.device.name == "lcos":
            bits = np.stack([mk.pack(m) for m in mk.slot_masks(self.window_start_ms,
                                                                 self.window_stop_ms - self.window_start_ms,
                                                                 self.device.slot_ms, self.n_slots)])
            arrays["mask_bits"] = bits
            arrays["mask_shape"] = np.asarray([self.n_slots, p, h, w], dtype=np.int64)
            arrays["slot_ms"] = np.asarray(self.device.slot_ms)
        else:
            clk = self.device.clock_ms
            ok = np.isfinite(self.window_start_ms)
            start = np.where(ok, np.rint(np.nan_to_num(self.window_start_ms) / clk), 0).astype(np.uint32)
            ticks = np.rint(np.nan_to_num(self.window_stop_ms - self.window_start_ms) / clk)
            stop = np.where(ok, start + ticks.astype(np.uint32), 0).astype(np.uint32)
            arrays["start_tick"] = start
            arrays["stop_tick"] = stop
            arrays["clock_ms"] = np.asarray(clk)
        if self.widen_um is not None:
            arrays["widen_um"] = self.widen_um
        return arrays

    def to_dict(self, masks_file: str | None = None, masks_sha256: str | None = None,
                profile_info: dict | None = None) -> dict:
        r = self.request
        x, y, w, h = self.field.roi
        dev = self.device.to_dict()
        if self.device.name == "lcos":
            dev.update({"n_slots": self.n_slots, "slot_z_edges_um": [round(v, 4) for v in self.slot_z_edges_um()],
                        "wall_time_ms": round(2.0 * self.n_slots * self.device.slot_ms, 4),
                        "schedule": "for each slot k: LCoS shows mask k and the camera integrates while the stage "
                                    "moves from slot_z_edges_um[k] to [k+1]; then the LCoS shows the complement "
                                    "for slot_ms with the camera closed and the stage holding"})
        else:
            dev.update({"wall_time_ms": round(self.total_time_ms, 4)})
        return {
            "format": PLAN_FORMAT,
            "kind": "sweep",
            "profile": profile_info or {},
            "parameters": {
                "alpha_um": r.alpha_um, "pixel_exposure_ms": r.pixel_exposure_ms, "device": r.device,
                "slot_ms": r.slot_ms, "max_hold_ms": r.max_hold_ms, "clock_us": r.clock_us, "cfa": self.cfa,
                "roi": [x, y, w, h], "channels": list(self.field.channels),
                "object_distance_mm": r.scene.object_distance_mm, "direction": r.direction,
                "grid_step_px": r.grid_step_px, "fs_cyc_per_mm": r.fs_cyc_per_mm, "wiener_nsr": r.wiener_nsr,
                "confidence": r.confidence,
            },
            "band_widening": self.band_summary(),
            "direction": r.direction,
            "refocus_um": round(self.field.refocus_um, 4),
            "range_um": round(self.range_um, 4),
            "best_focus_range_um": [round(self.field.z_min_um, 4), round(self.field.z_max_um, 4)],
            "start_um": round(self.start_um, 4),
            "stop_um": round(self.stop_um, 4),
            "alpha_um": r.alpha_um,
            "pixel_exposure_ms": r.pixel_exposure_ms,
            "velocity_um_per_ms": self.velocity_um_per_ms,
            "total_time_ms": round(self.total_time_ms, 6),
            "device": dev,
            "masks": {"file": masks_file, "sha256": masks_sha256, "planes": self.planes,
                      "encoding": "npz: planes, window_start_ms/window_stop_ms (P,H,W) float32 NaN = never; "
                                  + ("widen_um (P,H,W) float32 credible half-width added to α each side; "
                                     if self.widen_um is not None else "")
                                  + ("mask_bits (n_slots,P,H,ceil(W/8)) uint8 numpy.packbits along x, mask_shape"
                                     if self.device.name == "lcos" else "start_tick/stop_tick (P,H,W) uint32, clock_ms")},
            "ipsf": self.ipsf_summary,
            "alpha_trade": self.trade,
            "warnings": self.warnings,
        }


def band_summary_of(widen_um: np.ndarray | None, alpha_um: float, confidence: float | None) -> dict:
    """What the plan document records about the windows' widening by the profile's credible band."""
    if widen_um is None:
        return {"confidence": None, "rule": "no widening: every pixel integrates ±α about its MAP best focus"}
    u = widen_um[np.isfinite(widen_um)]
    return {"confidence": confidence,
            "rule": "each pixel integrates while the stage is within α + u of its MAP best focus, u its credible "
                    "half-width at the confidence; its exposure is t_s (1 + u/α)",
            "half_width_um": {"min": round(float(u.min(initial=0.0)), 4), "mean": round(float(u.mean()) if u.size else 0.0, 4),
                              "max": round(float(u.max(initial=0.0)), 4)}}


def _check(r: SweepRequest):
    for name, v in (("alpha_um", r.alpha_um), ("pixel_exposure_ms", r.pixel_exposure_ms)):
        try:
            ok = math.isfinite(float(v)) and float(v) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ParameterError(f"{name} = {v!r} must be a finite number > 0", field=name,
                                 fix="e.g. --alpha-um 20 --pixel-exposure-ms 16")
    if float(r.alpha_um) > 1e6:  # a half-range beyond 1 m is no stage's sweep (plan files cap positions at 1e9 µm)
        raise ParameterError(f"alpha_um = {r.alpha_um!r} µm is more than a stage travels (1 m)", field="alpha_um",
                             fix="give the sweep's half-range in µm, e.g. --alpha-um 20")
    if r.direction not in ("+z", "-z"):
        raise ParameterError(f"direction {r.direction!r} unknown", field="direction", fix="use +z or -z")
    if not (math.isfinite(r.wiener_nsr) and r.wiener_nsr > 0):
        raise ParameterError(f"Wiener NSR {r.wiener_nsr} must be > 0", field="wiener_nsr", fix="e.g. 0.01")
    valid_fs_cyc_per_mm(r.fs_cyc_per_mm)
    check_confidence(r.confidence)


def plan_sweep(profile: LensModel, request: SweepRequest) -> SweepPlan:
    r = request
    _check(r)
    device = mk.make_device(r.device, r.pixel_exposure_ms, slot_ms=r.slot_ms, max_hold_ms=r.max_hold_ms,
                            clock_us=r.clock_us)
    fieldd = sample_field(profile, r.scene, r.grid_step_px, sensor_geometry=True)  # windows are per sensor pixel
    cfa = r.cfa if r.cfa is not None else profile.cfa
    if cfa is not None and cfa not in mk.CFA_PATTERNS:
        raise ParameterError(f"unknown CFA pattern {cfa!r}", field="cfa", fix=f"use one of {', '.join(mk.CFA_PATTERNS)}")
    chans = list(fieldd.channels)
    if cfa:
        planes = [f"CFA:{cfa}"]
    elif device.name == "lcos" and len(chans) > 1:
        raise ParameterError("an LCoS modulates all colours together, so one mask cannot follow several channels' "
                             "surfaces on a sensor without a colour mosaic", field="channels",
                             fix="give --cfa RGGB (or the sensor's pattern) for a Bayer sensor, or plan one channel "
                                 "(--channels G)")
    else:
        planes = chans
    alpha, ts = float(r.alpha_um), float(r.pixel_exposure_ms)
    v = 2.0 * alpha / ts
    lo, hi = fieldd.z_min_um, fieldd.z_max_um
    z_map = band = None
    if r.confidence is not None:
        # the sweep must reach α beyond the farthest edge of any pixel's credible band
        z_map, band = mk.focus_and_band(profile, fieldd, planes, cfa, r.confidence)
        if np.isfinite(band).any():
            lo = min(lo, float(np.nanmin(z_map - band)))
            hi = max(hi, float(np.nanmax(z_map + band)))
    D = hi - lo
    T = ip.sweep_total_time_ms(D, alpha, ts)
    if r.direction == "+z":
        start, stop = lo - alpha, hi + alpha
    else:
        start, stop = hi + alpha, lo - alpha
    n_slots = None
    warnings: list[str] = []
    if device.name == "lcos":
        slots = T / device.slot_ms
        alpha_min = D / (2.0 * max(MAX_SLOTS * device.slot_ms / ts - 1.0, 1e-12))
        if not slots <= MAX_SLOTS:
            raise ParameterError(f"a sweep with α = {alpha:g} µm over D = {D:.1f} µm lasts {T:.4g} ms, i.e. "
                                 f"{slots:.3g} LCoS slots of {device.slot_ms:g} ms (at most {MAX_SLOTS})",
                                 field="alpha_um", fix=f"use --alpha-um {1.01 * alpha_min:.3g} or more "
                                                       "(T = (D/2α + 1) t_s)")
        n_slots = max(1, int(math.ceil(slots - 1e-9)))
    else:
        ticks = T / device.clock_ms
        if ticks >= 2 ** device.register_bits:
            raise ParameterError(f"the sweep lasts {ticks:.0f} register clocks, more than {device.register_bits} bits hold",
                                 field="clock_us", fix="use a slower register clock (--clock-us)")
    if band is None:
        starts = mk.window_starts(profile, fieldd, planes, cfa, v, r.direction)
    else:
        starts, _ = mk.widened_windows(z_map, band, alpha, v, r.direction, lo, hi)
    ref = "G" if "G" in chans else chans[0]
    trade = ip.alpha_trade(profile, D, ts, sorted(set(r.trade_alphas_um) | {alpha}), ref, r.fs_cyc_per_mm,
                           r.wiener_nsr)
    row = next(t for t in trade if t["alpha_um"] == alpha)
    summary = {"channel": ref, "fs_cyc_per_mm": r.fs_cyc_per_mm, "mtf_at_fs": row["mtf_at_fs"],
               "noise_gain": row["noise_gain"], "wiener_nsr": r.wiener_nsr,
               "in_focus_mtf_at_fs": float(abs(integrated_otf(profile, np.array([r.fs_cyc_per_mm]), 0.0, ref)[0]))}
    if device.name == "lcos" and device.slot_ms < ts:
        warnings.append(f"each pixel's 2α range is off-centre by up to {v * device.slot_ms / 2:.2f} µm (half a slot)")
    return SweepPlan(r, fieldd, device, planes, cfa, float(start), float(stop), v, T, n_slots, starts, trade,
                     summary, warnings, band)


def write_sweep_plan(plan: SweepPlan, out: str | Path, profile_info: dict | None = None,
                     extra_parameters: dict | None = None) -> dict:
    """Write the mask sidecar (atomically) and then the plan (atomically); returns the plan document.

    The document is built and validated before either file is written, so a plan the schema refuses leaves no
    orphan ``.masks.npz`` behind."""
    from .planfile import validate_plan, write_plan
    out = Path(out)
    npz = out.with_name(out.stem + ".masks.npz")
    data, sha = mk.npz_bytes(plan.mask_arrays())
    doc = plan.to_dict(masks_file=npz.name, masks_sha256=sha, profile_info=profile_info)
    doc["parameters"].update(extra_parameters or {})
    validate_plan(doc, out, check_files=False)
    atomic_write_bytes(npz, data)
    write_plan(out, doc)
    return doc
