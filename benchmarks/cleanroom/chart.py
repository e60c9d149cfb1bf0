"""Charts on the working grid: dead leaves and slanted-edge squares, drawn 8x finer than a pixel and
area-averaged, so the chart seen by the optics has no preferred direction (checked by
:func:`orientation_balance`).

Geometry is in pixel coordinates of the sensor at magnification 1 (pixel centres at integers). The working grid
has ``k`` samples per pixel (sample j at x = x_origin + j / k); the raster has ``m k ≥ 8`` cells per pixel
(``m = ceil(8 / k)``), so every working sample is the mean of an m x m block of raster cells (area averaging). Shapes are scaled about ``centre`` by the
frame's magnification (focus breathing).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SHIFT = 4          # OpenCV fixed-point bits: shapes placed to 1/16 of a raster cell


@dataclass(frozen=True)
class Discs:
    """A dead-leaves chart: discs back to front (later ones occlude earlier ones)."""
    x: np.ndarray
    y: np.ndarray
    r: np.ndarray
    grey: np.ndarray
    background: float


@dataclass(frozen=True)
class Squares:
    """Dark squares on a light ground: centres, side, rotation (rad) of each."""
    x: np.ndarray
    y: np.ndarray
    side: float
    angle: np.ndarray
    dark: float
    light: float


def dead_leaves(width_px: float, height_px: float, seed: int, r_min_px: float = 1.0, r_max_px: float = 40.0,
                coverage: float = 6.0, margin_px: float = 40.0) -> Discs:
    """Discs with radius density ∝ r⁻³ on [r_min, r_max] (scale invariant, Lee et al. 2001), uniform grey in
    [0.1, 0.9], placed uniformly over the frame plus a margin, ``coverage`` times the area on average."""
    rng = np.random.default_rng(seed)
    area = (width_px + 2 * margin_px) * (height_px + 2 * margin_px)
    # E[r²] for p(r) ∝ r⁻³ on [a, b]: 2 ln(b/a) / (1/a² − 1/b²)
    er2 = 2.0 * np.log(r_max_px / r_min_px) / (r_min_px ** -2 - r_max_px ** -2)
    n = int(coverage * area / (np.pi * er2))
    u = rng.random(n)
    r = 1.0 / np.sqrt(r_min_px ** -2 - u * (r_min_px ** -2 - r_max_px ** -2))   # inverse CDF of r⁻³
    x = rng.uniform(-margin_px, width_px + margin_px, n)
    y = rng.uniform(-margin_px, height_px + margin_px, n)
    return Discs(x, y, r, rng.uniform(0.1, 0.9, n), 0.5)


def edge_squares(width_px: float, height_px: float, seed: int, side_px: float = 26.0,
                 pitch_px: float = 44.0) -> Squares:
    """A grid of squares over the frame, each turned by 4–10° (either sign) so every side is a slanted edge."""
    rng = np.random.default_rng(seed)
    xs = np.arange(pitch_px / 2, width_px, pitch_px)
    ys = np.arange(pitch_px / 2, height_px, pitch_px)
    X, Y = np.meshgrid(xs + 0.5 * (width_px - xs[-1] - xs[0]), ys + 0.5 * (height_px - ys[-1] - ys[0]))
    ang = np.deg2rad(rng.uniform(4.0, 10.0, X.size) * rng.choice([-1.0, 1.0], X.size))
    return Squares(X.ravel() - 0.5, Y.ravel() - 0.5, side_px, ang, 0.15, 0.8)


def raster(chart, origin_px: tuple[float, float], shape_px: tuple[int, int], k: int, scale: float = 1.0,
           centre_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The chart on the working grid (k samples per pixel) over ``shape_px`` = (rows, cols) pixels whose first
    sample is at ``origin_px`` = (x, y); float32 reflectance."""
    m = -(-8 // k)
    ss = m * k
    rows, cols = shape_px[0] * k, shape_px[1] * k
    img = np.empty((rows * m, cols * m), np.float32)
    one = float(1 << SHIFT)

    def to_raster(xp, yp):
        # working sample j at x0 + j/k is the mean of raster cells m j … m j + m − 1, whose centres are
        # x0 + j/k + (t − (m − 1)/2) / ss: raster cell t's centre is at x0 + (t − (m − 1)/2) / ss
        xr = (xp - origin_px[0]) * ss + 0.5 * (m - 1)
        yr = (yp - origin_px[1]) * ss + 0.5 * (m - 1)
        return xr, yr

    cx, cy = centre_px
    if isinstance(chart, Discs):
        img[:] = chart.background
        xm = cx + scale * (chart.x - cx)
        ym = cy + scale * (chart.y - cy)
        xr, yr = to_raster(xm, ym)
        rr = chart.r * scale * ss
        keep = (xr + rr > -2) & (xr - rr < img.shape[1] + 2) & (yr + rr > -2) & (yr - rr < img.shape[0] + 2)
        for xi, yi, ri, g in zip(np.round(xr[keep] * one).astype(np.int64), np.round(yr[keep] * one).astype(np.int64),
                                 np.round(rr[keep] * one).astype(np.int64), chart.grey[keep]):
            cv2.circle(img, (int(xi), int(yi)), int(ri), float(g), thickness=-1, lineType=cv2.LINE_8, shift=SHIFT)
    else:
        img[:] = chart.light
        h = 0.5 * chart.side
        corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        for x0, y0, a in zip(chart.x, chart.y, chart.angle):
            c, s = np.cos(a), np.sin(a)
            px = x0 + corners[:, 0] * c - corners[:, 1] * s
            py = y0 + corners[:, 0] * s + corners[:, 1] * c
            xr, yr = to_raster(cx + scale * (px - cx), cy + scale * (py - cy))
            pts = np.round(np.stack([xr, yr], axis=1) * one).astype(np.int32)
            cv2.fillPoly(img, [pts], float(chart.dark), lineType=cv2.LINE_8, shift=SHIFT)
    return img.reshape(rows, m, cols, m).mean(axis=(1, 3))


def orientation_balance(img: np.ndarray, k: int, f_cyc_per_px: float = 0.3, rel_band: float = 0.15) -> dict:
    """Share of the chart's spectral energy in an annulus about f (cycles/px) per 45° sector centred on
    0°, 45°, 90°, 135° (an isotropic chart gives 0.25 each), from a Hann-windowed periodogram."""
    a = np.asarray(img, np.float64)
    a = a - a.mean()
    win = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    p = np.abs(np.fft.fft2(a * win)) ** 2
    fy = np.fft.fftfreq(a.shape[0], d=1.0 / k)[:, None]
    fx = np.fft.fftfreq(a.shape[1], d=1.0 / k)[None, :]
    f = np.hypot(fx, fy)
    ring = np.abs(f - f_cyc_per_px) <= rel_band * f_cyc_per_px
    ang = np.mod(np.degrees(np.arctan2(fy, fx)), 180.0)
    shares = {}
    for c in (0, 45, 90, 135):
        d = np.abs(((ang - c) + 90.0) % 180.0 - 90.0)
        shares[c] = float(p[ring & (d < 22.5)].sum())
    tot = sum(shares.values())
    return {f"{c}deg": v / tot for c, v in shares.items()}
