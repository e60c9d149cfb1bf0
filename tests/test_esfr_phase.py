"""e-SFR of a short edge (one phase cycle of rows) must not depend on where the edge sits in the pixel grid.

With ``rows * tan(slant)`` ~ 1 each 1/4 px bin holds 2-3 sub-pixel phases whose mean sits off the bin's centre;
read at the nominal centre the ESF was mis-sampled by up to ~1/8 bin, and which bin a phase fell in flipped
with any sub-0.01 px shift of the edge: MTF(0.25 cy/px) moved by 0.01-0.02 with the edge's position (a breathing
warp of a few 1e-5 was enough), and a through-focus curve whose frame at the reference scale was unwarped read
its peak up to 1 µm off (random-4 G of bench_edge_calibration, issue 13).
"""

import numpy as np
import pytest

from fieldcal.measure.esfr import esfr_vertical
from fieldcal.measure.esfr_synth import analytic_mtf, render_edge


@pytest.mark.parametrize("normal_deg", [5.0, 8.0])
@pytest.mark.parametrize("defocus_d_px", [0.0, 0.9])
def test_short_edge_mtf_does_not_depend_on_subpixel_position(normal_deg, defocus_d_px):
    rows = int(np.ceil(1.0 / np.tan(np.radians(normal_deg))))  # one phase cycle, the fewest e-SFR accepts
    truth = float(analytic_mtf(np.array([0.25]), sigma_px=0.3, defocus_d_px=defocus_d_px, normal_deg=normal_deg)[0])
    vals = []
    for phase_px in np.linspace(0.0, 0.2, 21):
        img = render_edge(rows, 27, normal_deg=normal_deg, point_px=(13.0 + phase_px, (rows - 1) / 2.0),
                          sigma_px=0.3, defocus_d_px=defocus_d_px)
        r = esfr_vertical(img, half_width_px=12)
        vals.append(float(np.interp(0.25, r.freq_cy_per_px, r.mtf[0])))
    vals = np.array(vals)
    assert np.ptp(vals) < 0.006, f"MTF(0.25) over sub-pixel positions {vals.min():.4f}-{vals.max():.4f}"
    assert np.max(np.abs(vals - truth)) < 0.006, f"closed form {truth:.4f}, measured {vals.min():.4f}-{vals.max():.4f}"
