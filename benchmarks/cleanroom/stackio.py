"""Writes a clean-room stack as a ``fieldcal-stack/1`` folder (docs/stack-format.md), as any program could:
16-bit TIFF frames (12 significant bits) and stack.json with z, pitch, F-number, black and white levels."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import tifffile


def write_stack(out: Path, frames: list[np.ndarray], z_um: list[float], *, pitch_um: float, f_number: float,
                channels: list[str], black_level: float, lens: dict, chart: str) -> Path:
    """Frames (H x W x C uint16) at stage positions z_um into ``out`` (created; a finished stack.json is
    written last, so a folder without it is an interrupted render)."""
    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    entries = []
    for i, (img, z) in enumerate(zip(frames, z_um)):
        name = f"frames/{i:04d}.tiff"
        arr = img if img.shape[-1] > 1 else img[..., 0]
        tifffile.imwrite(out / name, arr, photometric="rgb" if arr.ndim == 3 else "minisblack")
        entries.append({"file": name, "z_um": round(float(z), 6),
                        "sha256": hashlib.sha256((out / name).read_bytes()).hexdigest()})
    h, w = frames[0].shape[:2]
    doc = {"format": "fieldcal-stack/1", "pixel_pitch_um": pitch_um, "channels": list(channels), "bit_depth": 12,
           "black_level": black_level, "white_level": 4095, "f_number": f_number,
           "image_size_px": [int(w), int(h)], "lens": lens, "chart": chart, "frames": entries}
    tmp = out / "stack.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out / "stack.json")
    return out
