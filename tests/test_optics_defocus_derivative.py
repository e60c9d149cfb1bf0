"""The disc OTF's derivative (the curve fits' Jacobian) against SciPy's J2 and a finite difference."""

import numpy as np
from scipy import special

from fieldcal.optics.defocus import disc_otf, disc_otf_derivative


def test_disc_otf_derivative_is_minus_two_j2_over_x_everywhere():
    x = np.concatenate([[0.0, 1e-9, -1e-5, 0.05, -0.0999, 0.1, 0.2, -3.0], np.linspace(-40, 40, 20001)])
    ref = np.where(x == 0, 0.0, -2.0 * special.jv(2, np.where(x == 0, 1.0, x)) / np.where(x == 0, 1.0, x))
    assert np.max(np.abs(disc_otf_derivative(x) - ref)) < 1e-11
    h = 1e-5
    xx = np.linspace(-25, 25, 2001)
    fd = (disc_otf(xx + h) - disc_otf(xx - h)) / (2 * h)
    assert np.max(np.abs(fd - disc_otf_derivative(xx))) < 1e-8
