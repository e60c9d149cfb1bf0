"""Load what a plan is made from: a lens profile (``fieldcal-profile/1``) or a lens spec (``fieldcal-lens/1``).

A lens spec is planned from its simulated truth (design studies); the plan's ``profile`` block says so.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import SpecError


def load_profile(path: str | Path, size_px: tuple[int, int] | None = None):
    """Return ``(profile, info)``; ``info`` goes into the plan's ``profile`` block."""
    path = Path(path)
    if not path.exists():
        raise SpecError("profile not found", path=path,
                        fix="give a lens profile from `fieldcal calibrate` or a lens spec such as models/triplet-uncorrected.json")
    try:
        head = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"not valid JSON ({e})", path=path, fix="repair the JSON syntax") from None
    fmt = head.get("format") if isinstance(head, dict) else None
    if fmt == "fieldcal-lens/1":
        from ..lens import LensSpec
        from ..truth import TruthProfile
        spec = LensSpec.from_dict(head, path=path)
        w, h = size_px or (None, None)
        prof = TruthProfile(spec, w, h)
        return prof, {"path": str(path), "format": fmt, "name": spec.name,
                      "source": "lens spec: planned from the simulated lens's true surfaces (design study)",
                      "image_size_px": list(prof.image_size_px)}
    try:
        from ..profile import LensProfile  # written by the calibration issue
    except ImportError:
        raise SpecError(f"cannot read a {fmt!r} file: this fieldcal has no lens-profile reader yet", path=path,
                        field="format", fix="plan from a lens spec (fieldcal-lens/1) until calibration lands") from None
    prof = LensProfile.load(path)
    if size_px is not None:
        raise SpecError("--size applies to lens specs only", path=path, field="size",
                        fix="drop --size: a profile plans at its own image size")
    return prof, {"path": str(path), "format": fmt, "name": getattr(prof, "name", path.stem),
                  "source": "lens profile (calibrated)", "image_size_px": list(prof.image_size_px)}
