"""The clean-room truth: where MTF(fs) peaks through focus, and δ(fs, q), per node, channel and orientation.

From the pupil autocorrelation (:func:`otf.otf_quadrature`), not from the rendering FFT, times the pixel
aperture along the frequency's direction. Three curves per node and channel:

* ``T`` — frequency along the radius (tangential edges: the edge lies along the circle about the centre);
* ``S`` — frequency along the circle (sagittal edges);
* ``iso`` — the MTF(fs) averaged over 6 directions 0–150° (what an isotropic texture measures).

Best focus is the curve's maximum (a cubic spline through a fine z grid, to ~0.01 µm); δ is half the length of
the interval where MTF(fs) ≥ (1 − q) · peak. With breathing, the object point that images at the node at z_mid
is followed: its PSF at z is the one at the node's position scaled by m(z) about the frame centre.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from .lens import CleanLens
from .otf import otf_quadrature

ORIENTATIONS = ("T", "S", "iso")


def _curve_fn(lens: CleanLens, x: float, y: float, ch: str, fs_cyc_per_mm: float, z_mid_um: float,
              orientation: str, n_quad: int):
    lam = lens.wavelength_um(ch)
    s = 2.0 * (fs_cyc_per_mm * 1e-3) * lam * lens.f_number       # lag in pupil radii
    f_px = fs_cyc_per_mm * 1e-3 * lens.pitch_um
    cx0, cy0 = 0.5 * (lens.width_px - 1), 0.5 * (lens.height_px - 1)
    if orientation == "T":
        r = lens.radial_unit(x, y)
        dirs = [r]
    elif orientation == "S":
        r = lens.radial_unit(x, y)
        dirs = [(-r[1], r[0])]
    else:
        dirs = [(np.cos(t), np.sin(t)) for t in np.deg2rad(np.arange(6) * 30.0)]
    pix = [abs(np.sinc(f_px * d[0]) * np.sinc(f_px * d[1])) for d in dirs]

    def mtf(z):
        z = np.atleast_1d(np.asarray(z, dtype=np.float64))
        m = 1.0 + lens.breathing_per_um * (z - z_mid_um)
        xs, ys = cx0 + m * (x - cx0), cy0 + m * (y - cy0)
        zt, zs = lens.focus_ts_um(xs, ys, ch)
        k = 1.0 / (8.0 * lens.f_number ** 2 * lam)      # W020 = Δz / (8 N²), as lens.pupil_coefficients_waves
        rh = lens.radial_unit(x, y)
        acc = np.zeros(z.size)
        for d, p in zip(dirs, pix):
            acc += np.abs(otf_quadrature((z - zt) * k, (z - zs) * k, lens.w040_um() / lam, rh, s, d, n=n_quad)) * p
        return acc / len(dirs)
    return mtf


def through_focus_peak(mtf, z_guess: float, half_range_um: float, q: float, coarse_step_um: float) -> dict:
    """Peak and δ of MTF(z): a coarse scan, then a fine grid and a cubic spline around the q-crossings."""
    zc = np.arange(z_guess - half_range_um, z_guess + half_range_um + coarse_step_um, coarse_step_um)
    mc = mtf(zc)
    i = int(np.argmax(mc))
    if i == 0 or i == zc.size - 1:
        raise ValueError(f"truth: MTF peak at the end of the search range ({zc[0]:.1f}..{zc[-1]:.1f} µm)")
    thr = (1.0 - q) * mc[i]
    lo = i
    while lo > 0 and mc[lo] >= thr:
        lo -= 1
    hi = i
    while hi < zc.size - 1 and mc[hi] >= thr:
        hi += 1
    zf = np.linspace(zc[lo] - coarse_step_um, zc[hi] + coarse_step_um, 81)
    sp = CubicSpline(zf, mtf(zf))
    zz = np.linspace(zf[0], zf[-1], 24001)
    v = sp(zz)
    j = int(np.argmax(v))
    peak = float(v[j])
    above = v >= (1.0 - q) * peak
    # the connected run through the peak
    a = j
    while a > 0 and above[a - 1]:
        a -= 1
    b = j
    while b < zz.size - 1 and above[b + 1]:
        b += 1
    return {"z_best_um": float(zz[j]), "mtf_peak": peak, "delta_um": 0.5 * float(zz[b] - zz[a]),
            "z_lo_um": float(zz[a]), "z_hi_um": float(zz[b])}


def node_truth(lens: CleanLens, xs: np.ndarray, ys: np.ndarray, fs_cyc_per_mm: float, q: float,
               z_mid_um: float = 0.0, n_quad: int = 32) -> dict:
    """Truth at every node: ``{ch: {orientation: {"z_best_um": (ny, nx), "delta_um": ..., "mtf_peak": ...}}}``."""
    out = {}
    for ch in lens.channels:
        lam = lens.wavelength_um(ch)
        # geometric δ of a disc blur (MTF ≈ 1 − (π f b)²/8, b = Δz / N): where to look and how finely
        dg = lens.f_number * np.sqrt(8 * q) / (np.pi * fs_cyc_per_mm * 1e-3)
        sa_shift = 8.0 * lens.f_number ** 2 * lens.w040_um()     # focus that balances W040 (W020 = −W040)
        out[ch] = {}
        for o in ORIENTATIONS:
            res = {k: np.zeros((ys.size, xs.size)) for k in ("z_best_um", "delta_um", "mtf_peak")}
            for iy, y in enumerate(ys):
                for ix, x in enumerate(xs):
                    zt, zs = lens.focus_ts_um(x, y, ch)
                    fn = _curve_fn(lens, x, y, ch, fs_cyc_per_mm, z_mid_um, o, n_quad)
                    guess = 0.5 * (zt + zs) - 0.5 * sa_shift
                    half = 6 * dg + abs(zt - zs) + abs(sa_shift) + 8 * lam * lens.f_number ** 2
                    r = through_focus_peak(fn, guess, half, q, dg / 3)
                    for k in res:
                        res[k][iy, ix] = r[k]
            out[ch][o] = res
    return out
