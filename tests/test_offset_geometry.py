"""The sml@fs offset compares the band-pass and the SML at one point with one window (s14-offset).

On a curved field of a lens without aberration every point's through-focus curve is symmetric, so the SML and the
band-pass at fs peak together at every point and the channel's offset must be 0. A tile's best focus is its
texture's energy-weighted average of the local best foci, and the two measures weigh the points differently
(their centroids and their responses to the window term ``L s^2 / 24`` differ), so the raw per-tile differences
pool to an offset of the curvature's sign (docs/benchmarks.md ``bench_piston_s14``, ``bench_offset_s14``).
"""

from __future__ import annotations

import numpy as np
import pytest

from fieldcal.formats.frames import ArrayStack
from fieldcal.measure import measure_stack
from fieldcal.measure.texture_synth import curved_frame
from fieldcal.measure.tiles import TileRules

STEP_UM, N_FRAMES, PITCH_UM, FS = 20.0, 21, 6.0, 33.0


@pytest.mark.parametrize("curvature", [6e-4, -6e-4])
def test_offset_is_zero_on_a_symmetric_curved_field(curvature):
    """Closed form (texture_synth.curved_frame: exact sinusoids, each pixel blurred by the disc of its own defocus
    from z0 = c r^2; the window term L s^2 / 24 is 4 c 32^2 / 24 = 0.10 µm here): the raw pooled difference has
    the curvature's sign (measured +0.045 / -0.034 µm) and the corrected one is 0 within 0.01 µm (5e-4 step;
    measured +0.001 / -0.007). (At 2.5x this curvature the correction leaves +0.03 µm of either sign's 0.09:
    the window response is not exactly quadratic in the tile side there, docs/benchmarks.md bench_offset_s14.)"""
    z = (np.arange(N_FRAMES) - (N_FRAMES - 1) / 2.0 + 0.37) * STEP_UM
    st = ArrayStack([curved_frame(float(v), curvature) for v in z], z, ["Y"], pixel_pitch_um=PITCH_UM)
    t, _ = measure_stack(st, fs_cyc_per_mm=FS, effort="standard", quiet=True)
    rec = t.skew["Y"]
    assert rec["offset_geometry_n"] >= 20
    raw, new = rec["offset_raw_um"], rec["offset_um"]
    assert np.sign(raw) == np.sign(curvature) and abs(raw) > 0.025, raw  # what the old code pooled
    assert abs(new) < 0.01 and abs(new) < 0.4 * abs(raw), (raw, new)
    assert rec["offset_weight"] < 0.1  # and no evidence for an offset is left
    # switched off, the offset is the raw one (the behaviour before)
    t0, _ = measure_stack(st, fs_cyc_per_mm=FS, effort="standard", quiet=True, rules=TileRules(offset_geometry=False))
    assert t0.skew["Y"]["offset_um"] == pytest.approx(raw, abs=1e-9)
    assert "offset_geometry_n" not in t0.skew["Y"]


def test_the_correction_on_a_subset_of_tiles(monkeypatch):
    """Large grids measure the quadrants of OFFSET_GEOMETRY_TILES tiles spread over the grid (8 curve fits each):
    the offset is then pooled over those tiles alone and is still corrected (here 14 of the 24 tiles)."""
    import fieldcal.measure.tiles as tiles_mod
    monkeypatch.setattr(tiles_mod, "OFFSET_GEOMETRY_TILES", 14)
    z = (np.arange(N_FRAMES) - (N_FRAMES - 1) / 2.0 + 0.37) * STEP_UM
    st = ArrayStack([curved_frame(float(v), 6e-4) for v in z], z, ["Y"], pixel_pitch_um=PITCH_UM)
    t, _ = measure_stack(st, fs_cyc_per_mm=FS, effort="standard", quiet=True)
    rec = t.skew["Y"]
    assert rec["offset_geometry_n"] == 14 and rec["n_tiles"] >= 20
    assert rec["offset_raw_um"] > 0.025 and abs(rec["offset_um"]) < 0.4 * rec["offset_raw_um"], rec
