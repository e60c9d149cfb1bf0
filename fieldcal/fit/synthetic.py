"""Simulated calibration data with known truth, for tests and the coverage benchmark.

``random_lens`` draws a :class:`fieldcal.simulate.lens.LensSpec` with random curvature, per-channel focus offsets,
sensor tilt, decentre and astigmatism; ``synthetic_tiles`` measures it the way ``measure.tiles`` would
(noisy best foci with per-tile sigmas that may be underestimated, a few outlier tiles, directional foci and
through-focus widths); ``band_coverage`` scores a fit's credible band against the truth.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fieldcal.simulate.lens import ChannelSpec, LensSpec, SensorSpec
from fieldcal.simulate.truth import TruthProfile
from .data import ImageGeometry, TileData


def base_lens(channels=("R", "G", "B"), width_px: int = 320, height_px: int = 240) -> LensSpec:
    """A plain F/2.8 lens on a 320 x 240 px sensor of 4.8 x 3.6 mm (half-diagonal 3 mm = rho 1)."""
    wl = {"R": 656.3, "G": 546.1, "B": 486.1, "Y": 546.1}
    chans = tuple(ChannelSpec(c, wl.get(c, 550.0)) for c in channels)
    sensor = SensorSpec(width_px=width_px, height_px=height_px, pixel_pitch_um=4800.0 / width_px)
    return LensSpec(name="synthetic", focal_length_mm=16.0, f_number=2.8, image_height_max_mm=3.0,
                    channels=chans, sensor=sensor)


def random_lens(rng: np.random.Generator, channels=("R", "G", "B"), optics: bool = False) -> LensSpec:
    """A lens with random field curvature (rho^2, sometimes rho^4/rho^6), colour, tilt, decentre, astigmatism.

    ``optics=True`` also draws what a real camera adds: F/2-F/4, focus breathing (exit pupil 12-60 mm before
    the sensor, telecentric one time in four) and a stage axis tilted by up to 0.5 mrad. These are drawn after
    everything else, so the same generator gives the same surfaces either way.
    """
    spec = base_lens(channels)
    a1 = rng.uniform(-300.0, 60.0)
    a2 = rng.uniform(-40.0, 40.0) if rng.random() < 0.6 else 0.0
    a3 = rng.uniform(-15.0, 15.0) if rng.random() < 0.2 else 0.0
    astig = rng.uniform(-25.0, 25.0) if rng.random() < 0.5 else 0.0
    chans = []
    for c in spec.channels:
        curv = [a1 * (1.0 + rng.normal(0.0, 0.03)), a2, a3]
        while curv and curv[-1] == 0.0:
            curv.pop()
        chans.append(replace(c, focus_offset_um=rng.uniform(-30.0, 30.0), curvature_um=tuple(curv),
                             astigmatism_um=astig))
    tilt = tuple(rng.uniform(-8.0, 8.0, 2)) if rng.random() < 0.5 else (0.0, 0.0)
    dec = tuple(rng.uniform(-0.3, 0.3, 2)) if rng.random() < 0.5 else (0.0, 0.0)
    spec = replace(spec, channels=tuple(chans), tilt_um_per_mm=tilt, decentre_mm=dec)
    if optics:
        f_number = float(rng.uniform(2.0, 4.0))
        exit_pupil = float("inf") if rng.random() < 0.25 else float(rng.uniform(12.0, 60.0))
        axis = tuple(float(v) for v in rng.uniform(-0.5, 0.5, 2))
        spec = replace(spec, f_number=f_number, exit_pupil_mm=exit_pupil, stage_axis_tilt_mrad=axis)
    return spec


def synthetic_tiles(spec: LensSpec, rng: np.random.Generator, nx: int = 9, ny: int = 7,
                    sigma_um: tuple[float, float] = (0.5, 3.0), underestimate: float = 1.0,
                    outlier_fraction: float = 0.0, directional: bool = True, fs_cyc_per_mm: float = 80.0,
                    q: float = 0.05) -> tuple[TileData, ImageGeometry, TruthProfile]:
    """Tile measurements of ``spec`` on an ``nx`` x ``ny`` grid, per channel.

    True per-tile errors are log-uniform in ``sigma_um`` (larger towards the corners); the *reported*
    sigmas are the true ones divided by ``underestimate``. Outlier tiles are shifted by 20-80 µm.
    """
    s = spec.sensor
    geom = ImageGeometry(s.width_px, s.height_px, s.pixel_pitch_um)
    xs = (np.arange(nx) + 0.5) * s.width_px / nx - 0.5
    ys = (np.arange(ny) + 0.5) * s.height_px / ny - 0.5
    gx, gy = (a.ravel() for a in np.meshgrid(xs, ys))
    truth = TruthProfile(spec)
    cols: dict[str, list] = {k: [] for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um",
                                               "z_tan_um", "z_sag_um", "width_um")}
    for c in spec.channel_names:
        xm, ym = spec.pixel_to_mm(gx, gy)
        r2 = spec.rho(xm, ym) ** 2
        sig = np.exp(rng.uniform(np.log(sigma_um[0]), np.log(sigma_um[1]), gx.size)) * (1.0 + 0.5 * r2)
        z = spec.best_focus_um(xm, ym, c) + sig * rng.standard_normal(gx.size)
        n_out = int(round(outlier_fraction * gx.size))
        if n_out:
            idx = rng.choice(gx.size, n_out, replace=False)
            z[idx] += rng.choice([-1.0, 1.0], n_out) * rng.uniform(20.0, 80.0, n_out)
        if directional:
            zt = spec.best_focus_um(xm, ym, c, "tangential") + 1.2 * sig * rng.standard_normal(gx.size)
            zsg = spec.best_focus_um(xm, ym, c, "sagittal") + 1.2 * sig * rng.standard_normal(gx.size)
        else:
            zt = zsg = np.full(gx.size, np.nan)
        tol = spec.focus_tolerance_um(fs_cyc_per_mm, q, c)
        w = tol * (1.0 + 0.05 * rng.standard_normal(gx.size))
        cols["channel"] += [c] * gx.size
        for k, v in (("x_px", gx), ("y_px", gy), ("z_best_um", z), ("z_sigma_um", sig / underestimate),
                     ("z_tan_um", zt), ("z_sag_um", zsg), ("width_um", w)):
            cols[k].append(v)
    tiles = TileData.from_arrays(np.array(cols["channel"]),
                                 *(np.concatenate(cols[k]) for k in ("x_px", "y_px", "z_best_um", "z_sigma_um",
                                                                     "z_tan_um", "z_sag_um", "width_um")))
    return tiles, geom, truth


def field_points(geometry: ImageGeometry, n: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of pixel coordinates covering the whole image (corners included)."""
    xs = np.linspace(0.0, geometry.width_px - 1.0, n)
    ys = np.linspace(0.0, geometry.height_px - 1.0, n)
    gx, gy = np.meshgrid(xs, ys)
    return gx.ravel(), gy.ravel()


def band_coverage(fit, truth: TruthProfile, level: float = 0.9, n: int = 15) -> float:
    """Fraction of (field point, channel) pairs whose true best focus lies inside the fit's band."""
    x, y = field_points(fit.geometry, n)
    hits = []
    for c in fit.channels:
        lo, hi = fit.interval(x, y, c, level)
        z = truth.best_focus_um(x, y, c)
        hits.append((z >= lo) & (z <= hi))
    return float(np.mean(np.concatenate(hits)))


def surface_rms_error_um(fit, truth: TruthProfile, n: int = 15) -> float:
    """RMS of MAP surface minus truth over the field and channels (µm)."""
    x, y = field_points(fit.geometry, n)
    err = np.concatenate([fit.predict(x, y, c) - truth.best_focus_um(x, y, c) for c in fit.channels])
    return float(np.sqrt(np.mean(err ** 2)))
