"""Blur levels shared by both image-formation paths: the defocus ladder each pixel interpolates on.

Levels are spaced geometrically in blur-disc diameter above a floor, with an in-focus level at zero, so the
interpolation error is a bounded fraction of the local blur change (docs/simulator.md).
"""

from __future__ import annotations

import math

import numpy as np


def level_diameters_px(max_diameter_px: float, ratio: float, floor_px: float) -> np.ndarray:
    """Blur-level diameters (px): 0, then ``floor * ratio**k`` until ``max_diameter_px`` is covered (plus one
    spare level, so that a diameter exactly on the last level still has an upper neighbour)."""
    n = 0 if max_diameter_px <= floor_px else math.ceil(math.log(max_diameter_px / floor_px) / math.log(ratio))
    return np.concatenate([[0.0], floor_px * ratio ** np.arange(n + 2)])


def fractional_level(diameter_px: np.ndarray, ratio: float, floor_px: float) -> np.ndarray:
    """Continuous level index of each blur diameter: integer at a level, linear in diameter between levels."""
    b = np.asarray(diameter_px, dtype=np.float32)
    safe = np.maximum(b, floor_px)  # the log below is only used above the floor
    k = np.floor(np.log(safe / floor_px) / np.float32(math.log(ratio))).astype(np.float32)
    lo = floor_px * np.power(np.float32(ratio), k)
    frac = (safe - lo) / (lo * np.float32(ratio - 1.0))
    above = 1.0 + k + np.clip(frac, 0.0, 1.0)
    return np.where(b < floor_px, b / np.float32(floor_px), above).astype(np.float32)
