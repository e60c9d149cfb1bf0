"""Frames from a clean-room lens: field-varying blur by blending PSFs between grid nodes.

Field variation: the frame is covered by a grid of nodes (``node_px`` apart, corners included); each node has
the exact pupil PSF of its own field position and the sensor position z, and the image is
``Σ_k w_k(x, y) · (chart ⊛ PSF_k)`` with bilinear hat weights w_k — i.e. the PSFs are **blended** between
nodes (at a node the image is that node's exact PSF). Each node's convolution is done in the Fourier domain
over its own support plus a margin: chart spectrum × OTF (interpolated from the pupil's FFT) × pixel aperture
``sinc(fx) sinc(fy)``; the spectrum is then folded (aliased) onto the pixel grid, which samples the blurred
image at the pixel centres exactly as a sensor integrates and samples it. Then photon (Poisson) and read noise
and 12-bit quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from .chart import raster
from .lens import CleanLens
from .otf import interpolation_matrix, otf_native


@dataclass(frozen=True)
class Sensor:
    full_well_e: float = 6000.0
    read_noise_e: float = 4.0
    black_dn: float = 64.0
    white_dn: float = 4000.0      # DN of reflectance 1.0 (12-bit: 4095 is the clip)
    bits: int = 12


def node_grid(width_px: int, height_px: int, node_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Node positions (pixel coordinates) along x and y, the frame's first and last pixel included; an odd
    count on each axis (at most ``node_px`` apart), so every other node also spans the frame."""
    nx = int(np.ceil((width_px - 1) / node_px)) + 1
    ny = int(np.ceil((height_px - 1) / node_px)) + 1
    nx += 1 - nx % 2
    ny += 1 - ny % 2
    return np.linspace(0.0, width_px - 1.0, nx), np.linspace(0.0, height_px - 1.0, ny)


def _hat(pos: np.ndarray, nodes: np.ndarray, a: int) -> np.ndarray:
    d = nodes[1] - nodes[0]
    return np.clip(1.0 - np.abs(pos - nodes[a]) / d, 0.0, 1.0)


class Renderer:
    """Renders one lens and chart at any z (k working samples per pixel)."""

    def __init__(self, lens: CleanLens, charts: dict, *, z_mid_um: float, k: int = 2, node_px: float = 25.0,
                 margin_px: int = 16, n_pupil: int = 64, sensor: Sensor = Sensor()):
        self.lens, self.charts, self.k, self.z_mid = lens, charts, k, float(z_mid_um)
        self.n_pupil, self.sensor, self.margin = n_pupil, sensor, margin_px
        W, H = lens.width_px, lens.height_px
        self.xs, self.ys = node_grid(W, H, node_px)
        step = max(self.xs[1] - self.xs[0], self.ys[1] - self.ys[0])
        self.R = sfft.next_fast_len(int(np.ceil(2 * step)) + 2 + 2 * margin_px)   # node region, pixels
        self.outer = margin_px + 4
        f = sfft.fftfreq(k * self.R, d=1.0 / k)                                    # cycles/px
        self.FX, self.FY = f[None, :], f[:, None]
        self.pixel = (np.sinc(self.FX) * np.sinc(self.FY)).astype(np.float32)
        f1 = sfft.fftfreq(k * self.R, d=1.0 / k)
        self._interp = {ch: interpolation_matrix(f1, n_pupil, lens.pitch_um / (lens.wavelength_um(ch) * lens.f_number))
                        for ch in lens.channels}
        self._spectra_scale = None
        self._spectra = None
        self._blend_shift = {ch: self._node_shifts(ch) for ch in lens.channels}

    def _node_shifts(self, ch: str) -> np.ndarray:
        """Per node (T, S) focus offset (µm) that removes the blend's mean excess: (κ_x h_x² + κ_y h_y²)/12,
        κ the second differences of the lens's T and S surfaces over one node spacing."""
        L = self.lens
        hx, hy = self.xs[1] - self.xs[0], self.ys[1] - self.ys[0]
        X, Y = np.meshgrid(self.xs, self.ys)
        out = np.zeros(X.shape + (2,))
        for i in range(2):
            f = lambda x, y: L.focus_ts_um(x, y, ch)[i]   # noqa: E731
            kx = (f(X + hx, Y) - 2 * f(X, Y) + f(X - hx, Y))
            ky = (f(X, Y + hy) - 2 * f(X, Y) + f(X, Y - hy))
            out[..., i] = (kx + ky) / 12.0       # κ h² = the second difference over one spacing
        return out

    def _node_origin(self, a: int, b: int) -> tuple[int, int]:
        # region's first pixel (integer, so working sample k·i is pixel i's centre)
        x0 = int(np.floor(self.xs[max(a - 1, 0)])) - self.margin
        y0 = int(np.floor(self.ys[max(b - 1, 0)])) - self.margin
        return x0, y0

    def _chart_spectra(self, scale: float):
        if self._spectra is not None and self._spectra_scale == scale:
            return self._spectra
        self._spectra = {name: self._one_chart_spectra(c, scale) for name, c in self.charts.items()}
        self._spectra_scale = scale
        return self._spectra

    def _one_chart_spectra(self, chart, scale: float):
        L = self.lens
        o = self.outer
        # the whole frame plus room for every node's region, in one raster
        full = raster(chart, (-o, -o), (L.height_px + 2 * o + self.R, L.width_px + 2 * o + self.R), self.k,
                      scale=scale, centre_px=(0.5 * (L.width_px - 1), 0.5 * (L.height_px - 1)))
        k, R = self.k, self.R
        spectra = {}
        for a in range(self.xs.size):
            for b in range(self.ys.size):
                x0, y0 = self._node_origin(a, b)
                sub = full[(y0 + o) * k:(y0 + o + R) * k, (x0 + o) * k:(x0 + o + R) * k]
                spectra[a, b] = sfft.fft2(sub.astype(np.complex64), workers=1)
        return spectra

    def blurred(self, z_um: float, ch: str) -> dict[str, np.ndarray]:
        """The noise-free frame of one channel (reflectance units, H x W) at sensor position z, per chart."""
        L, k, R = self.lens, self.k, self.R
        spectra = self._chart_spectra(L.magnification(z_um, self.z_mid))
        A = self._interp[ch]
        out = {name: np.zeros((L.height_px, L.width_px)) for name in self.charts}
        X = np.arange(L.width_px, dtype=np.float64)
        Y = np.arange(L.height_px, dtype=np.float64)
        for a, xn in enumerate(self.xs):
            wx = _hat(X, self.xs, a)
            xi = np.nonzero(wx)[0]
            for b, yn in enumerate(self.ys):
                wy = _hat(Y, self.ys, b)
                yi = np.nonzero(wy)[0]
                wt, ws, w040 = L.pupil_coefficients_waves(xn, yn, ch, z_um)
                # the blend's focus is the bilinear interpolant of the nodes' foci, above a convex surface by
                # κ h²/12 per axis on average over a cell: each node is rendered that much lower, so the
                # rendered field equals the lens's on average (a zero-mean ripple of ± κ h²/12 remains)
                dt, ds = self._blend_shift[ch][b, a]
                kz = 1.0 / (8.0 * L.f_number ** 2 * L.wavelength_um(ch))
                wt, ws = wt + dt * kz, ws + ds * kz
                nat = otf_native(wt, ws, w040, L.radial_unit(xn, yn), self.n_pupil)
                H = np.asarray((A @ (A @ nat).T).T, dtype=np.float32) * self.pixel   # A_y · nat · A_xᵀ
                x0, y0 = self._node_origin(a, b)
                wxy = np.outer(wy[yi], wx[xi])
                for name in self.charts:
                    spec = spectra[name][a, b] * H
                    folded = spec.reshape(k, R, k, R).sum(axis=(0, 2))
                    img = sfft.ifft2(folded, workers=1).real / (k * k)
                    patch = img[yi[0] - y0:yi[-1] + 1 - y0, xi[0] - x0:xi[-1] + 1 - x0]
                    out[name][yi[0]:yi[-1] + 1, xi[0]:xi[-1] + 1] += patch * wxy
        return out

    def frames(self, z_um: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """One 12-bit RGB frame (H x W x 3, uint16) per chart, with photon and read noise."""
        s = self.sensor
        planes = {name: [] for name in self.charts}
        for ch in self.lens.channels:
            for name, img in self.blurred(z_um, ch).items():
                planes[name].append(expose(img, s, rng))
        return {name: np.stack(p, axis=-1) for name, p in planes.items()}


def expose(reflectance: np.ndarray, s: Sensor, rng: np.random.Generator) -> np.ndarray:
    """Photon (Poisson) and read (Gaussian) noise, gain to DN above the black level, rounding, 12-bit clip."""
    e = np.clip(reflectance, 0.0, None) * s.full_well_e
    e = rng.poisson(e).astype(np.float64) + rng.normal(0.0, s.read_noise_e, e.shape)
    dn = s.black_dn + e * (s.white_dn - s.black_dn) / s.full_well_e
    return np.clip(np.round(dn), 0, 2 ** s.bits - 1).astype(np.uint16)
