"""Known geometric truth for the registration tests: similarity transforms about the frame centre and frames
warped by them from a margin-padded reference texture (cubic spline)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from fieldcal.composite import register as R


def similarity(scale, angle_deg, tx, ty, w: int, h: int) -> np.ndarray:
    """3x3 reference-to-frame map: scale and rotation about the frame centre, then a shift (px)."""
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    a = np.radians(angle_deg)
    lin = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    m = np.eye(3)
    m[:2, :2] = lin
    m[:2, 2] = c + np.array([tx, ty]) - lin @ c
    return m


def warped(img, ref_to_frame, w: int, h: int, margin: int) -> np.ndarray:
    """w x h frame whose pixel q shows the ``margin``-padded reference ``img`` at ``ref_to_frame^-1 q``."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = R._apply(np.linalg.inv(ref_to_frame), xx, yy)
    return ndimage.map_coordinates(img.astype(np.float64), [py + margin, px + margin], order=3,
                                   mode="reflect").astype(np.float32)
