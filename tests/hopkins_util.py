"""Hopkins (1955) defocus OTF as a 1-D integral: the tests' independent reference for fieldcal.optics.pupil.

The overlap of two unit pupils shifted by +-s has |x| <= sqrt(1 - y^2) - s; W020 rho^2 differs between them by
4 W020 s x, so OTF = (4 / (pi a)) int_0^sqrt(1-s^2) sin(a (sqrt(1-y^2) - s)) dy, a = 8 pi W020 s (scipy quad;
independent of the library's 2-D Gauss-Legendre rule).
"""

from __future__ import annotations

import numpy as np
from scipy import integrate


def hopkins_otf(s: float, w020_waves: float) -> float:
    """OTF of a circular pupil defocused by ``w020_waves`` at ``s`` = frequency / cut-off (0 beyond it)."""
    if s >= 1.0:
        return 0.0
    if w020_waves == 0.0 or s == 0.0:
        return (2.0 / np.pi) * (np.arccos(s) - s * np.sqrt(1.0 - s * s))
    a = 8.0 * np.pi * w020_waves * s
    val, _ = integrate.quad(lambda y: np.sin(a * (np.sqrt(1.0 - y * y) - s)), 0.0, np.sqrt(1.0 - s * s),
                            limit=400, epsabs=1e-13)
    return 4.0 / (np.pi * a) * val
