"""The best-focus estimator on closed-form flat-field stacks: no piston of its own (issues 13/14, s14).

The band benchmark's fitted-minus-true pistons are positive on ~80 % of lens x channels (median +0.1 µm). A flat
field in focus at exactly z = 0 everywhere, blurred by an exactly known kernel, separates the estimator from
the renderers: whatever mean best focus the tiles report is the estimator's own piston
(benchmarks/bench_piston.py, docs/benchmarks.md ``bench_piston_s14``).
"""

from __future__ import annotations

import numpy as np
import pytest

from fieldcal.formats.frames import ArrayStack
from fieldcal.measure import measure_stack
from fieldcal.measure.sml_gain import exponent_sd
from fieldcal.measure.texture_synth import sinusoid_frame

W, H, PITCH_UM, F_NUMBER, STEP_UM, N_FRAMES = 256, 192, 6.0, 4.0, 20.0, 25
FS = 33.0  # cycles/mm: 0.2 cycles/px


def _flat_stack(z_um, *, breathing_per_um: float = 0.0, pixel_aperture: bool = False) -> ArrayStack:
    """Every point in focus at z = 0 (fieldcal.measure.texture_synth: exact sinusoids, disc blur at the sensor)."""
    frames = [sinusoid_frame(float(z), width=W, height=H, pitch_um=PITCH_UM, f_number=F_NUMBER,
                             breathing_per_um=breathing_per_um, pixel_aperture=pixel_aperture) for z in z_um]
    return ArrayStack(frames, z_um, ["Y"], pixel_pitch_um=PITCH_UM)


def _scan(phase: float, offset_steps: float) -> np.ndarray:
    return (np.arange(N_FRAMES) - (N_FRAMES - 1) / 2.0 + phase + offset_steps) * STEP_UM


@pytest.mark.parametrize("phase,offset_steps", [(0.37, 0.0), (0.13, 2.3)])
@pytest.mark.parametrize("measure", ["sml", "bandpass", "auto"])
def test_flat_closed_form_stack_has_no_estimator_piston(phase, offset_steps, measure):
    """Sampled at a phase that is not symmetric about the peak, and with the scan's centre 2.3 steps from it,
    the tiles' mean best focus is the true 0 to well under 0.002 step (measured: |mean| <= 4e-4 µm).

    Every systematic of the chain moves this mean: a frame's z taken at its exposure's start instead of its
    middle, half a step in the window, a peak model that is not symmetric about its centre, a biased skew
    correction or measure offset."""
    z = _scan(phase, offset_steps)
    t, _ = measure_stack(_flat_stack(z), fs_cyc_per_mm=FS, effort="standard", measure=measure, quiet=True)
    ok = np.asarray(t.ok, dtype=bool)
    assert ok.sum() >= 20
    zb = np.asarray(t.z_best_um)[ok]
    assert abs(float(np.mean(zb))) < 0.002 * STEP_UM, np.mean(zb)
    # and no tile is off by more than a hundredth of a step: the curves are noise-free and identical
    assert float(np.max(np.abs(zb))) < 0.01 * STEP_UM


def test_breathing_with_a_sensor_fixed_mtf_pulls_the_sml_towards_the_larger_image_within_the_stated_sd():
    """The scale-following SML reads a sensor-fixed MTF (here the pixel aperture) at u / m: with m growing with
    z the curve gains m^k and its peak moves up; with m shrinking, down. That error is one draw for the whole
    field, so the band carries it as a field-wide term (fit.tiles.breathing_systematic_sd_um: the exponent's sd
    times the tiles' RMS dz/dk). Measured here: +0.056 / -0.057 µm at b = +-1e-4 /µm against a stated sd of
    0.057-0.058 µm (k = 0.44); without the aperture -0.006 / +0.020 µm (the dilated operator's own); without
    breathing -0.001 µm. A sign error in the scale the SML follows, or a gain taken the wrong way, breaks the
    ordering; an SML that ignored the magnification would be off by ~k_texture x dz/dk, several sds."""
    z = _scan(0.37, 0.3)
    err, stated = {}, {}
    for b in (1e-4, -1e-4):
        t, _ = measure_stack(_flat_stack(z, breathing_per_um=b, pixel_aperture=True), fs_cyc_per_mm=FS,
                             effort="standard", measure="sml", quiet=True)
        ok = np.asarray(t.ok, dtype=bool)
        err[b] = float(np.mean(np.asarray(t.z_best_um)[ok]))
        k = float(t.sml_gain["Y"]["k_max"])
        v = np.asarray(t.z_dgamma_um)[ok]
        stated[b] = exponent_sd(k) * float(np.sqrt(np.mean(v * v)))
        assert 0.2 < k < 0.8  # the pixel aperture's k over the SML's band (h(x) = pi x cot(pi x) - 1 per axis)
    # the sign follows the breathing: the gain rises towards the larger image
    assert err[1e-4] > err[-1e-4]
    # within the band's 90 % (1.645 sd) for the field-wide term
    for b, e in err.items():
        assert abs(e) < 1.645 * stated[b], (b, e, stated[b])
