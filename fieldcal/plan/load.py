"""Load what a plan is made from: a lens profile (``fieldcal-profile/1``) or a lens spec (``fieldcal-lens/1``).

A lens spec is planned from its simulated truth (design studies); the plan's ``profile`` block says so.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ParameterError


def load_profile(path: str | Path, size_px: tuple[int, int] | None = None):
    """Return ``(profile, info)``; ``info`` goes into the plan's ``profile`` block."""
    from fieldcal.profile.lens_profile import load_profile_or_truth
    from fieldcal.simulate.stackgen import check_size

    # the size is an argument, not a field of the file: its errors name no file, so the CLI names its flag
    # (--size; a field 'size_px' of a file is truth.json's); bounded as simulate bounds it
    size_px = check_size(size_px, field="size")
    prof, info = load_profile_or_truth(path, size_px)
    if info["format"].startswith("fieldcal-lens/"):
        info["source"] = "lens spec: planned from the simulated lens's true surfaces (design study)"
    elif size_px is not None:
        raise ParameterError(f"an image size applies to lens specs only, and {path} is a lens profile",
                             field="size", fix="give no size: a profile plans at its own image size")
    return prof, info
