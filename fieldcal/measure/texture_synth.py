"""Texture stacks whose best focus is known in closed form: the reference for the focus estimators' own bias.

A flat field in focus at z = 0 everywhere: a sum of random sinusoids (scene frequencies ``u_i``, uniformly
spread in orientation and in ``|u|`` up to ``u_max`` cycles/px, amplitudes ``|u|^-1/2``), seen at image scale
``m(z) = exp(b z)`` about the frame's centre (focus breathing: scene frequency u at sensor frequency u / m),
each component multiplied by the OTF at the sensor

    OTF(f) = 2 J1(π d f) / (π d f) · [sinc(f_x) sinc(f_y)],      d = |z| / (N · pitch)   (px),

the uniform defocus disc of diameter |z| / N and, optionally, the 100 % pixel aperture (a sensor-fixed MTF),
then point-sampled at the pixel centres. Every factor is exact: no resampling, no interpolation, no kernel
truncation, so any mean best focus an estimator reports on it is the estimator's own
(``benchmarks/bench_piston.py``, ``tests/test_piston_closed_form.py``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import j1


def sinusoid_frame(z_um: float, *, width: int = 256, height: int = 192, pitch_um: float = 6.0,
                   f_number: float = 4.0, breathing_per_um: float = 0.0, pixel_aperture: bool = False,
                   n_components: int = 300, u_max: float = 0.45, contrast: float = 0.08, seed: int = 5,
                   noise: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """One 16-bit frame (H x W x 1) of the closed-form flat field at stage position ``z_um`` (µm)."""
    g = np.random.default_rng(seed)
    u = u_max * np.sqrt(g.uniform(0.0004, 1.0, n_components))  # uniform over the disc |u| < u_max
    ang = g.uniform(0.0, math.pi, n_components)
    ph = g.uniform(0.0, 2.0 * math.pi, n_components)
    amp = u ** -0.5
    amp = contrast * amp / math.sqrt(0.5 * float(np.sum(amp * amp)))
    m = math.exp(breathing_per_um * z_um)
    fx, fy = u * np.cos(ang) / m, u * np.sin(ang) / m  # sensor frequencies (cycles/px)
    f = np.hypot(fx, fy)
    d_px = abs(z_um) / f_number / pitch_um
    x = math.pi * d_px * f
    otf = np.where(x > 1e-9, 2.0 * j1(x) / np.maximum(x, 1e-300), 1.0)
    if pixel_aperture:
        otf = otf * np.sinc(fx) * np.sinc(fy)
    xs = np.arange(width, dtype=np.float64) - (width - 1) / 2.0
    ys = np.arange(height, dtype=np.float64) - (height - 1) / 2.0
    a = 2.0 * math.pi * fx[:, None] * xs[None, :]           # (n, W)
    b = 2.0 * math.pi * fy[:, None] * ys[None, :] + ph[:, None]  # (n, H)
    w = (amp * otf)[:, None]
    # cos(a + b) = cos a cos b - sin a sin b, summed over the components as two matrix products
    img = 0.5 + (np.cos(b) * w).T @ np.cos(a) - (np.sin(b) * w).T @ np.sin(a)
    if noise:
        img = img + (rng if rng is not None else np.random.default_rng(seed + 1)).normal(0.0, noise, img.shape)
    return np.clip(np.round(img * 65535.0), 0, 65535).astype(np.uint16)[..., None]
