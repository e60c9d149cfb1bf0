"""Per-pixel exposure windows of a focal sweep and what a per-pixel-exposure device needs to realise them.

Devices
-------
* ``pixel``: a sensor with per-pixel start/stop registers counting a clock (``clock_ms``); one continuous
  sweep, each pixel integrates exactly ``[start, stop)``. Stored as register values (uint32 ticks).
* ``lcos``: a spatial light modulator in front of the sensor that shows one binary image for at most
  ``max_hold_ms`` (20 ms for the paper's SXGA-3DA) and must then show its complement for as long. The sweep
  is cut into slots of ``slot_ms`` (``pixel_exposure_ms / slot_ms`` an integer); during slot k the camera
  integrates while the stage moves through the slot's part of the range and the LCoS shows mask k; then the
  LCoS shows the complement for ``slot_ms`` with the camera closed and the stage holding. A pixel is open in
  the slots whose centre lies in its window, so it integrates exactly ``pixel_exposure_ms`` and its swept range
  is off-centre by at most half a slot. With ``slot_ms = pixel_exposure_ms`` this is the paper's experiment
  (one sweep of 2α per circular section, V.B). An LCoS modulates every colour together: with several
  channels it needs a Bayer sensor (CFA-aware masks: each pixel follows its own colour's surface).

Masks are stored bit-packed along x (``numpy.packbits``, big-endian bit order) in a ``.npz`` beside the plan.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fieldcal.formats.atomic import atomic_write_bytes
from ..errors import ParameterError, SpecError

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclass(frozen=True)
class Device:
    name: str                       # "pixel" or "lcos"
    slot_ms: float | None = None    # lcos: time one mask is shown
    max_hold_ms: float | None = None
    complement: bool = False
    clock_ms: float | None = None   # pixel: register clock period
    register_bits: int = 32

    def to_dict(self) -> dict:
        return {"name": self.name, "slot_ms": self.slot_ms, "max_hold_ms": self.max_hold_ms,
                "complement": self.complement, "clock_ms": self.clock_ms, "register_bits": self.register_bits}


def make_device(kind: str, pixel_exposure_ms: float, *, slot_ms: float | None = None, max_hold_ms: float = 20.0,
                clock_us: float = 10.0, register_bits: int = 32) -> Device:
    """Validate the device's limits against the requested pixel exposure."""
    if kind == "lcos":
        if not (math.isfinite(max_hold_ms) and max_hold_ms > 0):
            raise ParameterError(f"max hold {max_hold_ms} ms must be > 0", field="max_hold_ms", fix="e.g. 20")
        if slot_ms is None:
            m = max(1, math.ceil(pixel_exposure_ms / max_hold_ms - 1e-9))
            slot_ms = pixel_exposure_ms / m
        if not (math.isfinite(slot_ms) and slot_ms > 0):  # not "exceeds": a negative slot is not too long
            raise ParameterError(f"slot of {slot_ms} ms must be a finite time > 0", field="slot_ms",
                                 fix=f"use a slot in (0, {max_hold_ms}] ms, or leave it out")
        if slot_ms > max_hold_ms + 1e-9:
            raise ParameterError(f"slot of {slot_ms} ms exceeds the LCoS hold limit of {max_hold_ms} ms",
                                 field="slot_ms", fix=f"use a slot <= {max_hold_ms} ms")
        m = pixel_exposure_ms / slot_ms
        if abs(m - round(m)) > 1e-6 or round(m) < 1:
            raise ParameterError(f"pixel exposure {pixel_exposure_ms} ms is not a whole number of {slot_ms} ms slots",
                                 field="slot_ms", fix=f"use a slot of {pixel_exposure_ms}/k ms for a whole k")
        return Device("lcos", slot_ms=float(slot_ms), max_hold_ms=float(max_hold_ms), complement=True)
    if kind == "pixel":
        if not (math.isfinite(clock_us) and clock_us > 0):
            raise ParameterError(f"register clock {clock_us} µs must be > 0", field="clock_us", fix="e.g. 10")
        return Device("pixel", clock_ms=float(clock_us) / 1000.0, register_bits=int(register_bits))
    raise ParameterError(f"device {kind!r} unknown", field="device", fix="use lcos or pixel")


def cfa_index(pattern: str, height: int, width: int, channels) -> np.ndarray:
    """Index into ``channels`` of the colour at each pixel of a Bayer mosaic (-1 where not requested)."""
    if pattern not in CFA_PATTERNS:
        raise ParameterError(f"unknown CFA pattern {pattern!r}", field="cfa", fix=f"use one of {', '.join(CFA_PATTERNS)}")
    lut = np.array([channels.index(c) if c in channels else -1 for c in pattern], dtype=np.int64).reshape(2, 2)
    yy, xx = np.mgrid[0:height, 0:width]
    return lut[yy % 2, xx % 2]


def focus_and_band(profile, field, planes, cfa: str | None, confidence: float | None = None,
                   rows_per_chunk: int = 256, sensor_geometry: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Full-frame best focus (refocused) and credible half-width of each pixel of each plane, float32 (P, H, W);
    NaN outside the ROI, or where a CFA site's colour is not planned. The half-width is 0 without a confidence.

    ``sensor_geometry`` (the default): each *sensor* pixel's best focus is that of the scene point it images at
    that stage position, through the profile's geometry (``warp_px``: maps where the profile has them, else its
    scalar magnification and shift; :func:`fieldcal.plan.surfaces.sensor_focus_um`), so windows stay centred on
    the true best focus under strong breathing and distortion. False: the z_ref-geometry surface read at the
    sensor pixel (map-blind; exact only without breathing, shift or distortion).

    The half-width is the profile's band at ``confidence`` (the larger side about the MAP surface, as stack plans
    shrink their tolerances by it: :func:`fieldcal.plan.tolerance.band_halfwidth_um`).
    """
    from .surfaces import sensor_focus_correction
    from .tolerance import band_halfwidth_um

    w_img, h_img = (int(v) for v in profile.image_size_px)
    x0, y0, w, h = field.roi
    z_out = np.full((len(planes), h_img, w_img), np.nan, dtype=np.float32)
    u_out = np.full((len(planes), h_img, w_img), np.nan, dtype=np.float32)
    chans = list(field.channels)
    xs = np.arange(x0, x0 + w, dtype=np.float64)
    corr = {c: sensor_focus_correction(profile, field.roi, c, field.refocus_um) if sensor_geometry else None
            for c in chans}
    for r0 in range(y0, y0 + h, rows_per_chunk):
        r1 = min(r0 + rows_per_chunk, y0 + h)
        gx, gy = np.meshgrid(xs, np.arange(r0, r1, dtype=np.float64))
        zs, us = {}, {}
        for c in chans:
            z = np.asarray(profile.best_focus_um(gx, gy, c), dtype=np.float64)
            if corr[c] is not None:
                z = z + corr[c](gx, gy)
            us[c] = (band_halfwidth_um(profile, gx, gy, c, z, confidence) if confidence is not None
                     else np.zeros_like(z))
            zs[c] = z + field.refocus_um
        if cfa:
            idx = cfa_index(cfa, h_img, w_img, chans)[r0:r1, x0:x0 + w]
            zt, ut = np.full(idx.shape, np.nan), np.full(idx.shape, np.nan)
            for k, c in enumerate(chans):
                zt = np.where(idx == k, zs[c], zt)
                ut = np.where(idx == k, us[c], ut)
            z_out[0, r0:r1, x0:x0 + w], u_out[0, r0:r1, x0:x0 + w] = zt, ut
        else:
            for p, c in enumerate(planes):
                z_out[p, r0:r1, x0:x0 + w], u_out[p, r0:r1, x0:x0 + w] = zs[c], us[c]
    return z_out, u_out


def window_starts(profile, field, planes, cfa: str | None, v_um_per_ms: float, direction: str,
                  rows_per_chunk: int = 256, sensor_geometry: bool = True) -> np.ndarray:
    """Opening time (ms) of each pixel of each plane, full frame, float32, NaN where never exposed.

    +z: the pixel opens when the sensor is α below its best focus, ``(z_p - z_min) / v``; -z: ``(z_max - z_p) / v``;
    z_p the sensor pixel's best focus (:func:`focus_and_band`).
    """
    z, _ = focus_and_band(profile, field, planes, cfa, None, rows_per_chunk, sensor_geometry)
    t = (z - np.float32(field.z_min_um)) if direction == "+z" else (np.float32(field.z_max_um) - z)
    return (t / np.float32(v_um_per_ms)).astype(np.float32)


def widened_windows(z_um: np.ndarray, band_um: np.ndarray, alpha_um: float, v_um_per_ms: float, direction: str,
                    lo_um: float, hi_um: float) -> tuple[np.ndarray, np.ndarray]:
    """(start_ms, stop_ms) of windows spanning ``[z - u - α, z + u + α]`` of a sweep over ``[lo - α, hi + α]``.

    Each pixel stays open while the stage is within α of *any* best focus its credible band allows, so the
    stage passes the true best focus ±α with the band's probability; its exposure is ``t_s (1 + u/α)``.
    """
    if direction == "+z":
        start = (z_um - band_um - np.float32(lo_um)) / np.float32(v_um_per_ms)
    else:
        start = (np.float32(hi_um) - z_um - band_um) / np.float32(v_um_per_ms)
    stop = start + (np.float32(2.0 * alpha_um) + 2.0 * band_um) / np.float32(v_um_per_ms)
    return start.astype(np.float32), stop.astype(np.float32)


def slot_masks(start_ms: np.ndarray, pixel_exposure_ms: float, slot_ms: float, n_slots: int):
    """Yield the boolean mask of each slot: open if the slot's centre lies in ``[start, start + t_s)``."""
    for k in range(n_slots):
        tc = (k + 0.5) * slot_ms
        with np.errstate(invalid="ignore"):
            yield (start_ms <= tc) & (tc < start_ms + pixel_exposure_ms)


def mask_at(start_ms: np.ndarray, stop_ms: np.ndarray, t_ms: float) -> np.ndarray:
    """Which pixels integrate at instant ``t_ms`` (for pictures and for the pixel device)."""
    with np.errstate(invalid="ignore"):
        return (start_ms <= t_ms) & (t_ms < stop_ms)


def pack(mask: np.ndarray) -> np.ndarray:
    return np.packbits(mask.astype(bool), axis=-1)


def unpack(bits: np.ndarray, width: int) -> np.ndarray:
    return np.unpackbits(bits, axis=-1, count=width).astype(bool)


def npz_bytes(arrays: dict) -> tuple[bytes, str]:
    """The compressed .npz file of ``arrays`` in memory and its sha256."""
    import hashlib
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    return data, hashlib.sha256(data).hexdigest()


def write_npz(path: str | Path, arrays: dict) -> str:
    """Write the arrays compressed and atomically; returns the sha256 of the file."""
    data, sha = npz_bytes(arrays)
    atomic_write_bytes(path, data)
    return sha


def load_npz(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise SpecError("the plan's mask file is missing", path=path,
                        fix="keep the .npz beside the plan file, or make the plan again")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise SpecError(f"cannot read the mask file ({e})", path=path, fix="make the plan again") from None
