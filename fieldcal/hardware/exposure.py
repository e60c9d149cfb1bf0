"""Per-pixel exposure devices: what their masks mean in time, from the files ``fieldcal plan export-masks`` writes.

A device folder (``fieldcal-masks/1``, :mod:`fieldcal.plan.device_masks`) is what a device loads: 1-bit slot
images for an LCoS, 16-bit start/stop register maps for a pixel-wise exposure sensor. :class:`MaskTimeline`
turns it into the fraction of any time interval each pixel integrates — time counted in ms from the moment the
device is triggered, which is the moment the sweep's exposure opens (the stage passing the plan's
``start_um``).

* ``pixelwise``: pixel p integrates ``[start_tick, stop_tick) * clock_ms``; start = stop = 0 is never.
* ``lcos``: slot k is shown during ``[k, k + 1) * slot_ms`` of integration time; a pixel integrates in the
  slots whose image is 1 there. (The DC-balancing complement the LCoS shows between slots, camera closed, is
  not integration time: see docs/hardware.md for why capture runs only pixel-wise sweeps.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SpecError
from ..plan import masks as mk


@dataclass(frozen=True)
class MaskTimeline:
    """When each pixel of each plane integrates, in ms from the trigger.

    Attributes
    ----------
    kind : ``"pixelwise"`` or ``"lcos"``.
    planes : plane names (channels, or ``CFA:RGGB`` for one plane following a Bayer mosaic).
    start_ms, stop_ms : (P, H, W) float64 windows (pixelwise; None for lcos).
    slot_bits : (n_slots, P, H, ceil(W/8)) packed slot images (lcos; None for pixelwise).
    slot_ms : slot time (lcos).
    width_px : W (to unpack slot images).
    duration_ms : the sweep's exposure time (the manifest's ``total_time_ms``).
    """

    kind: str
    planes: tuple[str, ...]
    duration_ms: float
    width_px: int
    start_ms: np.ndarray | None = None
    stop_ms: np.ndarray | None = None
    slot_bits: np.ndarray | None = None
    slot_ms: float | None = None

    @classmethod
    def from_device_masks(cls, dm) -> "MaskTimeline":
        """From :func:`fieldcal.plan.device_masks.load_device_masks`'s result (manifest + arrays)."""
        man, arr = dm.manifest, dm.arrays
        w = int(man["image_size_px"][0])
        planes = tuple(str(p) for p in man["planes"])
        if man["device"] == "pixelwise":
            clk = float(man["pixelwise"]["clock_ms"])
            return cls("pixelwise", planes, float(man["total_time_ms"]), w,
                       start_ms=arr["start_tick"].astype(np.float64) * clk,
                       stop_ms=arr["stop_tick"].astype(np.float64) * clk)
        return cls("lcos", planes, float(man["total_time_ms"]), w, slot_bits=arr["mask_bits"],
                   slot_ms=float(man["lcos"]["slot_ms"]))

    @property
    def shape(self) -> tuple[int, int, int]:
        """(P, H, W)."""
        if self.start_ms is not None:
            return tuple(self.start_ms.shape)  # type: ignore[return-value]
        n, p, h, _ = self.slot_bits.shape
        return (p, h, self.width_px)

    def open_fraction(self, t0_ms: float, t1_ms: float) -> np.ndarray:
        """(P, H, W) float32: the fraction of ``[t0, t1)`` each pixel integrates."""
        dt = float(t1_ms) - float(t0_ms)
        if not dt > 0:
            raise ValueError("t1_ms must be after t0_ms")
        if self.kind == "pixelwise":
            ov = np.minimum(self.stop_ms, t1_ms) - np.maximum(self.start_ms, t0_ms)
            return (np.clip(ov, 0.0, None) / dt).astype(np.float32)
        out = np.zeros(self.shape, dtype=np.float32)
        n = self.slot_bits.shape[0]
        k0 = max(0, int(np.floor(t0_ms / self.slot_ms)))
        k1 = min(n - 1, int(np.floor(t1_ms / self.slot_ms)))
        for k in range(k0, k1 + 1):
            ov = min(t1_ms, (k + 1) * self.slot_ms) - max(t0_ms, k * self.slot_ms)
            if ov > 0:
                out += np.float32(ov / dt) * mk.unpack(self.slot_bits[k], self.width_px)
        return out


def frame_weights(fraction: np.ndarray, planes: tuple[str, ...], channels: tuple[str, ...], mosaic: bool,
                  source: str | Path | None = None) -> np.ndarray:
    """(P, H, W) open fractions -> weights for the camera's frame: H x W for a mosaic, H x W x C otherwise.

    One plane gates every colour of its pixel (a pixel-wise sensor, or a CFA plane on a demosaicked frame);
    one plane per channel gates that channel.
    """
    if len(planes) == 1:
        w = fraction[0]
        return w if mosaic else w[:, :, None]
    if not mosaic and list(planes) == list(channels):
        return np.moveaxis(fraction, 0, -1)
    raise SpecError(f"the masks have planes {list(planes)} but the camera delivers channels {list(channels)}"
                    + (" as a mosaic" if mosaic else ""), path=source, field="planes",
                    fix="plan the sweep for the camera's channels (--channels, --cfa) and export the masks again")
