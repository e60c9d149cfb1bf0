"""Focus measures of one plane of one frame, summed into small cells so tiles can be placed anywhere later.

Measures (all float32, computed once per frame and plane with OpenCV):

* **SML** — the sum-modified-Laplacian of Nayar & Nakagawa (1994): ``|I(x-1) - 2I + I(x+1)| +
  |I(y-1) - 2I + I(y+1)|`` per pixel (OpenCV's second-order Sobel with ksize=1 is exactly that kernel).
  Broad-band, dominated by the highest frequencies: a sharp, robust peak. Under focus breathing each frame's
  kernel gets a first-order scale term, so that a patch of the scene gives the same value at every
  magnification whatever its spectrum (:func:`sml` with ``scale``).
* **band-pass energy at fs** — the plane filtered in the Fourier domain (OpenCV's real DFT) by a log-Gabor ring centred on the
  target frequency (cycles/px = fs [cycles/mm] x pitch [mm]), squared. For a texture chart its tile sum is
  ``|OTF(fs, z - z0)|^2 x (texture power at fs) + noise power``: exactly the contrast the planner needs.
* **directional band-pass energy** (optional) — the band-passed image's gradient split into its component
  along the radius from the optical centre and across it. Frequencies along the radius are what the
  tangential MTF sees, across it the sagittal: their peaks give z_tan and z_sag (astigmatism).
* **cell means of I and I^2** (texture and exposure) and the **fraction of saturated pixels**.

Cells are ``cell x cell`` blocks of the plane; a tile at any (fractional) position is summed from the cells'
integral image with bilinear weights at its borders (:func:`box_sums`), which is exact for a density that is
constant inside each cell.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from scipy import fft

# Log-Gabor bandwidth: sigma/f0 = 0.8 in log-frequency, about +-0.8 octave to the e^-1/2 points. Narrow enough
# that the energy follows |OTF(fs)|, wide enough that a 32-64 px tile holds a few hundred frequency samples.
LOG_GABOR_SIGMA_RATIO = 0.8
SATURATION_LEVEL = 0.995  # of white, in normalised units


# Half-length (taps) of the kernels of the SML's scale terms (:func:`_scale_kernels`): its coefficients fall as
# 1/n^2; windowed by Lanczos sigma factors at 8 its response is within 1.4-2.8 % of the exact one up to 0.4
# cycles/px (12 % of the 3-tap SML's at Nyquist, where the exact one is 0).
_DILATION_HALF_TAPS = 8


def _windowed(h: np.ndarray) -> np.ndarray:
    """A truncated kernel (odd length, centred) windowed by Lanczos sigma factors (no Gibbs ripple), with zero
    sum and second moment 2 restored (a x [1, -2, 1] added): the low-frequency response of -(2 pi f)^2."""
    r = h.size // 2
    n = np.arange(-r, r + 1, dtype=np.float64)
    h = h * np.sinc(n / (r + 1))
    h[r] -= h.sum()
    a = 0.5 * (2.0 - float(np.sum(h * n * n)))
    h[r - 1] += a
    h[r + 1] += a
    h[r] -= 2.0 * a
    return h


@functools.lru_cache(maxsize=1)
def _scale_kernels() -> tuple[np.ndarray, np.ndarray]:
    """The first two terms in d = m - 1 of the 3-tap second difference dilated by m, whose response is
    ``-4 sin^2(pi f m) = -4 sin^2(pi f) - d 4 pi f sin(2 pi f) - d^2 4 pi^2 f^2 cos(2 pi f) + ...``:
    kernels with responses ``-2 pi f sin(2 pi f)`` (K1, taken twice) and ``-4 pi^2 f^2 cos(2 pi f)`` (K2),
    float64, 2 _DILATION_HALF_TAPS + 1 taps.

    K1 is the central difference of the band-limited derivative: -1 at 0, 1/4 at +-1, (-1)^n / (n^2 - 1)
    beyond; K2 the band-limited second derivative (-pi^2/3 at 0, 2 (-1)^(n+1) / n^2) averaged over +-1 px.
    Both Fourier series fall as 1/n^2; windowed (:func:`_windowed`) at 8 taps K1 is within 1.4-2.8 % of its
    exact response up to 0.4 cycles/px (12 % of the 3-tap SML's at Nyquist, where the exact one is 0).
    """
    r = _DILATION_HALF_TAPS
    n = np.arange(-r - 1, r + 2, dtype=np.float64)  # one more each side for the +-1 average of K2
    an = np.abs(n)
    safe = np.where(an >= 2, n * n - 1.0, 1.0)
    k1 = np.where(an >= 2, (-1.0) ** an / safe, np.where(an == 1, 0.25, -1.0))[1:-1]
    d2 = np.where(an >= 1, 2.0 * (-1.0) ** (an + 1) / np.where(an >= 1, n * n, 1.0), -np.pi ** 2 / 3.0)
    k2 = 0.5 * (d2[:-2] + d2[2:])
    return _windowed(k1), _windowed(k2)


def sml(plane: np.ndarray, scale: float = 1.0, energy: bool = False) -> np.ndarray:
    """Per-pixel modified Laplacian |d2I/dx2| + |d2I/dy2| (step 1 px), float32.

    ``energy=True``: (d2I/dx2)^2 + (d2I/dy2)^2 instead, the energy of the same two second differences. Its mean
    over a patch does not change when the image moves by a fraction of a pixel (Parseval: for a band-limited
    image the energy of a linear filter's output is the same at every sampling phase), where the absolute
    values' is not: a second difference near Nyquist samples as +-a cos(phase), so |.| rises and falls as the
    content crosses the pixel grid. Calibration's tiles move across it through a scan wherever the image
    breathes (by (m - 1) x the distance from the centre: ~0.5 px at the edge of a 320 px frame over one
    through-focus curve) or drifts (a tilted stage axis); with |.| that biased the edge tiles of breathing
    lenses by -0.6 µm (a random lens at 22 µm steps, F/2.9, exit pupil 30 mm) and tripled their scatter, with
    the energy the bias is gone (docs/measurement.md "Tiles follow the image").

    ``scale``: the image's magnification m in this frame relative to the scale the SML is to be taken at (focus
    breathing). At 1 the 3-tap second difference ``[1, -2, 1]``; otherwise that operator dilated by m, to
    second order in d = m - 1: ``[1, -2, 1] + 2 d K1 + d^2 K2`` (17 taps, :func:`_scale_kernels`). On an image
    magnified by m it gives what the 3-tap operator gives on the image itself, so the per-pixel mean over a
    patch that follows the image is the same at every m whatever the texture's spectrum (to 1e-4 of a
    normalised gain at the 1 % magnification change of a long scan on a breathing lens).

    Why: dilating an image by (1 + e) changes the 3-tap ``L3 I`` by ``-e ((x - c).grad(L3 I) + 2 K I)``
    (``L3[x g] = x L3 g + 2 Dc g``); over a window that follows the image the first part cancels, so the
    patch mean of ``|L3 I|`` scales as ``m^-gamma``, ``gamma = 2 mean(sgn(L3 I) K I) / mean(|L3 I|)``: 2 for a
    continuous second derivative, 0.8-2 for the 3-tap one (set by the texture's spectrum and the blur).
    ``|L3 I + 2 d K1 I| = |L3 I| (1 + gamma_pixel d)`` is that correction to first order, pixel by pixel
    (docs/measurement.md "Tiles follow the image").
    """
    if scale == 1.0:
        dxx = cv2.Sobel(plane, cv2.CV_32F, 2, 0, ksize=1, borderType=cv2.BORDER_REFLECT_101)
        dyy = cv2.Sobel(plane, cv2.CV_32F, 0, 2, ksize=1, borderType=cv2.BORDER_REFLECT_101)
    else:
        d = float(scale) - 1.0
        k1, k2 = _scale_kernels()
        k = 2.0 * d * k1 + d * d * k2
        r = _DILATION_HALF_TAPS
        k[r - 1:r + 2] += (1.0, -2.0, 1.0)
        k = k.astype(np.float32)
        one = np.ones(1, np.float32)
        dxx = cv2.sepFilter2D(plane, cv2.CV_32F, k, one, borderType=cv2.BORDER_REFLECT_101)
        dyy = cv2.sepFilter2D(plane, cv2.CV_32F, one, k, borderType=cv2.BORDER_REFLECT_101)
    if energy:
        cv2.multiply(dxx, dxx, dst=dxx)
        cv2.multiply(dyy, dyy, dst=dyy)
    else:
        # in place: half the memory traffic of cv2.absdiff/add with new arrays
        np.abs(dxx, out=dxx)
        np.abs(dyy, out=dyy)
    dxx += dyy
    return dxx


def _even_fast_len(n: int) -> int:
    """Smallest even size >= n that OpenCV's DFT handles fast (2, 3 and 5 as the only factors)."""
    m = cv2.getOptimalDFTSize(int(n))
    while m % 2:
        m = cv2.getOptimalDFTSize(m + 1)
    return m


@functools.lru_cache(maxsize=4)
def _ccs_log_radius(shape: tuple[int, int]) -> np.ndarray:
    """ln |f| (f in cycles/px) at every slot of OpenCV's packed real spectrum (CCS) of an even ``shape``.

    In CCS a real image's DFT is stored as H x W reals: interior columns hold (Re, Im) pairs of frequencies
    fx = j / W, j = 1 .. W/2 - 1; columns 0 and W - 1 hold the fx = 0 and fx = 1/2 columns packed the same way
    down the rows (Re at row 0, (Re, Im) pairs for fy = i / H, Re of fy = 1/2 in the last row). Multiplying
    every slot by a real, even filter's value at the slot's frequency multiplies the spectrum by the filter.
    DC holds 0 (masked by the ring).
    """
    h, w = shape
    fy_all = fft.fftfreq(h)
    j = (np.arange(1, w - 1) + 1) // 2  # interior columns -> fx index
    fx_int = j / w
    f2 = np.empty((h, w))
    f2[:, 1:w - 1] = fy_all[:, None] ** 2 + fx_int[None, :] ** 2
    i = (np.arange(h) + 1) // 2  # packed column rows -> fy index (0, 1, 1, 2, 2, ..., h/2)
    fy_packed = i / h
    f2[:, 0] = fy_packed ** 2
    f2[:, w - 1] = fy_packed ** 2 + 0.25
    f2[0, 0] = 1.0  # log(0) guard
    lf = (0.5 * np.log(f2)).astype(np.float32)
    lf.setflags(write=False)
    return lf


@functools.lru_cache(maxsize=8)
def log_gabor_ring(shape: tuple[int, int], f0_cyc_per_px: float,
                   sigma_ratio: float = LOG_GABOR_SIGMA_RATIO) -> np.ndarray:
    """Radial log-Gabor transfer function, laid out for OpenCV's packed spectrum (CCS) of ``shape`` (even H, W);
    zero at DC, float32.

    A function of ``f / f0`` only, so the ring at ``f0 / m`` is the ring at ``f0`` for an image magnified by m
    (what lets the band-pass measure follow the scene through focus breathing).
    """
    d = _ccs_log_radius(shape) - np.float32(math.log(f0_cyc_per_px))
    g = np.exp(d * d * np.float32(-1.0 / (2.0 * math.log(sigma_ratio) ** 2)))
    g[0, 0] = 0.0
    g.setflags(write=False)
    return g


def bandpass(plane: np.ndarray, f0_cyc_per_px: float) -> np.ndarray:
    """The plane band-passed around ``f0`` (cycles/px) by a log-Gabor ring, float32 (zero mean).

    OpenCV's real DFT in packed (CCS) form, zero-padded to an even fast size: about 1.5x faster than
    scipy.fft's rfft2/irfft2 pair on float32 1080p planes, and it releases the GIL (planes run in threads).
    """
    return bandpass_many(plane, (f0_cyc_per_px,))[0]


def bandpass_many(plane: np.ndarray, f0s_cyc_per_px) -> list[np.ndarray]:
    """:func:`bandpass` at several frequencies, sharing the plane's forward DFT (one inverse per frequency)."""
    h, w = plane.shape
    hp, wp = _even_fast_len(h), _even_fast_len(w)
    src = np.ascontiguousarray(plane, dtype=np.float32)
    if (hp, wp) != (h, w):
        src = cv2.copyMakeBorder(src, 0, hp - h, 0, wp - w, cv2.BORDER_CONSTANT, value=0.0)
    spec = cv2.dft(src)
    out = []
    f0s = list(f0s_cyc_per_px)
    for i, f0 in enumerate(f0s):
        # the last frequency filters the spectrum in place (one 1080p plane's allocation saved per call)
        ring = log_gabor_ring((hp, wp), float(f0))
        filtered = cv2.multiply(spec, ring, dst=spec) if i == len(f0s) - 1 else cv2.multiply(spec, ring)
        band = cv2.idft(filtered, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
        out.append(band[:h, :w] if (hp, wp) != (h, w) else band)
    return out


def directional_energy(band: np.ndarray, unit_x: np.ndarray, unit_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Band-passed gradient energy along (radial) and across (azimuthal) the unit vectors, float32 each."""
    gx = cv2.Scharr(band, cv2.CV_32F, 1, 0)
    gy = cv2.Scharr(band, cv2.CV_32F, 0, 1)
    along = cv2.add(cv2.multiply(gx, unit_x), cv2.multiply(gy, unit_y))
    across = cv2.subtract(cv2.multiply(gy, unit_x), cv2.multiply(gx, unit_y))
    return cv2.multiply(along, along), cv2.multiply(across, across)


def radial_unit_vectors(shape: tuple[int, int], centre_xy: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors from the optical centre (plane pixel coordinates) at every plane pixel, float32."""
    h, w = shape
    x = np.arange(w, dtype=np.float32)[None, :] - np.float32(centre_xy[0])
    y = np.arange(h, dtype=np.float32)[:, None] - np.float32(centre_xy[1])
    r = np.sqrt(x * x + y * y)
    r = np.maximum(r, np.float32(1e-3))  # the centre pixel: any direction, no 0/0
    return np.broadcast_to(x / r, (h, w)).astype(np.float32), np.broadcast_to(y / r, (h, w)).astype(np.float32)


def cell_grid(shape: tuple[int, int], cell: int) -> tuple[int, int]:
    """(rows, cols) of whole cells in a plane of ``shape``; a partial last row/column is dropped."""
    return shape[0] // cell, shape[1] // cell


def cell_sums(img: np.ndarray, cell: int) -> np.ndarray:
    """Sum of ``img`` over each ``cell x cell`` block (float32, partial border blocks dropped)."""
    hc, wc = cell_grid(img.shape, cell)
    a = img[:hc * cell, :wc * cell]
    if cell == 1:
        return np.ascontiguousarray(a, dtype=np.float32)
    # INTER_AREA with an integer factor is the exact block mean.
    m = cv2.resize(a, (wc, hc), interpolation=cv2.INTER_AREA)
    return m * np.float32(cell * cell)


def saturated_fraction_cells(plane: np.ndarray, cell: int, level: float = SATURATION_LEVEL) -> np.ndarray:
    """Fraction of pixels at or above ``level`` (of white) in each cell, float32."""
    _, sat = cv2.threshold(plane, level, 1.0, cv2.THRESH_BINARY)
    # THRESH_BINARY is strict (>), good enough at 0.995 of white.
    return cell_sums(sat, cell) * np.float32(1.0 / (cell * cell))


def integral(cells: np.ndarray) -> np.ndarray:
    """Integral image of a cell map (float64, one extra leading row and column)."""
    return cv2.integral(np.ascontiguousarray(cells, dtype=np.float32), sdepth=cv2.CV_64F)


def _bilinear(ii: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = ii.shape
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2)
    fx = x - x0
    fy = y - y0
    return ((ii[y0, x0] * (1 - fx) + ii[y0, x0 + 1] * fx) * (1 - fy)
            + (ii[y0 + 1, x0] * (1 - fx) + ii[y0 + 1, x0 + 1] * fx) * fy)


def box_sums(ii: np.ndarray, x0, y0, x1, y1) -> np.ndarray:
    """Sums of the cell density over boxes [x0, x1) x [y0, y1) given in (fractional) cell units.

    Exact for a density that is constant within each cell; boxes are clipped to the map.
    """
    x0, y0, x1, y1 = (np.asarray(v, dtype=np.float64) for v in (x0, y0, x1, y1))
    return _bilinear(ii, x1, y1) - _bilinear(ii, x0, y1) - _bilinear(ii, x1, y0) + _bilinear(ii, x0, y0)


class BoxSampler:
    """:func:`box_sums` over one set of boxes for many integral images of one shape: the corners' cells and
    bilinear weights are found once (a tile table sums ~8 maps per frame over the same boxes), and each image
    then costs four gathers. The same arithmetic as :func:`box_sums`, so the same numbers to the bit."""

    def __init__(self, shape: tuple[int, int], x0, y0, x1, y1):
        h, w = shape
        x0, y0, x1, y1 = (np.asarray(v, dtype=np.float64).ravel() for v in (x0, y0, x1, y1))
        self.n = x0.size
        # the four corners of every box, in box_sums' order: (x1, y1), (x0, y1), (x1, y0), (x0, y0)
        x = np.clip(np.concatenate([x1, x0, x1, x0]), 0.0, w - 1.0)
        y = np.clip(np.concatenate([y1, y1, y0, y0]), 0.0, h - 1.0)
        xi = np.minimum(np.floor(x).astype(np.intp), w - 2)
        yi = np.minimum(np.floor(y).astype(np.intp), h - 2)
        self.fx, self.fy = x - xi, y - yi
        self.gx, self.gy = 1 - self.fx, 1 - self.fy
        self.i00 = yi * w + xi  # flat indices of the 2 x 2 cells around each corner
        self.i01, self.i10, self.i11 = self.i00 + 1, self.i00 + w, self.i00 + w + 1
        self.shape = (h, w)

    def __call__(self, ii: np.ndarray) -> np.ndarray:
        if ii.shape != self.shape:
            raise ValueError(f"integral image of shape {ii.shape}, sampler made for {self.shape}")
        f = ii.ravel()
        v = (f[self.i00] * self.gx + f[self.i01] * self.fx) * self.gy + (f[self.i10] * self.gx
                                                                          + f[self.i11] * self.fx) * self.fy
        n = self.n
        return v[:n] - v[n:2 * n] - v[2 * n:3 * n] + v[3 * n:]
