"""ISO 12233 e-SFR (slanted-edge) MTF: the measurement core over one region of interest.

The method follows ISO 12233:2017 Annex D / sfrmat3 (Burns), with the steps named as in docs/measurement.md:

1. per-row edge location: centroid of the row derivative, Hamming-weighted about the current estimate
   (two passes: about the initial line, then about the first fit);
2. a straight line (or low-order polynomial) fitted to the centroids, rows with outlying centroids dropped;
3. the rows trimmed to a whole number of phase cycles (``rows * tan(slant)`` an integer) so every 1/4-pixel
   phase is sampled equally;
4. every pixel projected onto the edge normal; the edge-spread function (ESF) binned at ``1/oversample`` px
   along the normal (``np.bincount``, all channels in one call);
5. LSF = central difference of the ESF; Hamming window centred on the LSF centroid; |FFT| (zero-padded, so
   the spectrum is sampled finely), normalised at DC;
6. divided by the transfer of the central difference, ``sinc(2 f Δ)``, and of the binning box, ``sinc(f Δ)``
   (ISO corrects the first only; the second is a known ~2 % loss at 0.5 cy/px that we remove too).

Frequencies are in cycles per pixel *along the edge normal*. The result includes the pixel aperture as seen
along that normal, ``sinc(f cos θ) · sinc(f sin θ)`` for a square pixel and an edge normal at θ to the x axis.

The core works on a near-vertical edge (each row crosses the edge once); callers transpose near-horizontal
regions (:func:`esfr_roi` does this when ``vertical=False``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError

#: slant range (degrees from the nearest pixel axis) the e-SFR accepts as "ok" (ISO 12233 asks for a few degrees)
SLANT_RANGE_DEG = (2.0, 20.0)


@dataclass(frozen=True)
class EdgeQuality:
    """Quality record of one edge in one channel (all in the channel's own pixel units unless named)."""

    ok: bool
    reason: str  # "ok" or why the edge should not be trusted
    slant_deg: float  # angle of the edge from the nearest pixel axis
    contrast: float  # Michelson (hi - lo) / (hi + lo) of the ESF plateaus
    step: float  # hi - lo, in normalised signal units
    noise_rms: float  # robust RMS of the pixel residuals about the binned ESF
    snr: float  # step / noise_rms
    clipped_fraction: float  # fraction of ROI pixels at or beyond the black/white levels
    rows: int  # rows used (after phase trimming)
    half_width_px: float  # pixels within this distance of the edge (across the rows) were used
    rise_px: float  # 10-90 % rise distance of the ESF along the normal (robust to noise, unlike an LSF width)
    tail_fraction: float  # LSF area in the outer 15 % of the window at either end (blur wider than the ROI)
    edge_rms_px: float  # RMS of the row centroids about the fitted edge (straightness / noise)
    empty_bins: int  # ESF bins with no sample (filled by interpolation)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class SfrResult:
    """e-SFR of one edge, per channel (arrays have a leading channel axis).

    ``x_mid``/``y_mid`` are the edge point at the middle row in ROI pixel coordinates (x = column, y = row of
    the ROI as given, i.e. before any transposition), ``angle_deg`` the edge direction from the ROI's +x axis
    in [0, 180) (y down).
    """

    freq_cy_per_px: np.ndarray  # (F,) fine grid of the zero-padded FFT
    mtf: np.ndarray  # (C, F)
    mtf50_cy_per_px: np.ndarray  # (C,)
    x_mid: np.ndarray  # (C,)
    y_mid: np.ndarray  # (C,)
    angle_deg: np.ndarray  # (C,)
    quality: list[EdgeQuality] = field(default_factory=list)
    esf: np.ndarray | None = None  # (C, nbins) binned ESF
    bin_px: float = 0.25

    def mtf_at(self, freq_cy_per_px) -> np.ndarray:
        """MTF of every channel at the given frequencies (linear interpolation of the fine spectrum)."""
        f = np.asarray(freq_cy_per_px, dtype=np.float64)
        return np.stack([np.interp(f, self.freq_cy_per_px, m, right=np.nan) for m in self.mtf])


def mtf50(freq: np.ndarray, mtf: np.ndarray) -> float:
    """First frequency where ``mtf`` falls below 0.5 (linear interpolation); NaN if it never does."""
    below = np.flatnonzero(mtf < 0.5)
    if below.size == 0 or below[0] == 0:
        return math.nan
    i = int(below[0])
    m0, m1 = float(mtf[i - 1]), float(mtf[i])
    return float(freq[i - 1] + (m0 - 0.5) / (m0 - m1) * (freq[i] - freq[i - 1]))


def _hamming(rel: np.ndarray, half: np.ndarray | float) -> np.ndarray:
    """Hamming weights at offsets ``rel`` for a window of half-length ``half`` (zero outside)."""
    x = np.clip(rel / half, -1.0, 1.0)
    return (0.54 + 0.46 * np.cos(np.pi * x)) * (np.abs(rel) <= half)


def _row_centroids(d: np.ndarray, centre: np.ndarray, half: float) -> np.ndarray:
    """Centroid (column) of the signed row derivative ``d`` (R x W-1 x C) about ``centre`` (R x C)."""
    x = np.arange(d.shape[1], dtype=np.float64) + 0.5  # a first difference sits between two pixels
    rel = x[None, :, None] - centre[:, None, :]
    # Hamming weights without a cosine per element: cos(a - b) = cos a cos b + sin a sin b
    ax, ac = np.pi * x / half, np.pi * centre / half
    cosd = np.cos(ax)[None, :, None] * np.cos(ac)[:, None, :] + np.sin(ax)[None, :, None] * np.sin(ac)[:, None, :]
    w = d * (0.54 + 0.46 * cosd) * (np.abs(rel) <= half)
    s = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.einsum("rwc,w->rc", w, x) / s


def _fit_edge(rows: np.ndarray, cen: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit x(row) per channel; refit once without centroids beyond 3 robust sigma.

    All channels in one least-squares solve (rows with a NaN centroid in any channel are dropped).
    Returns ``(x_edge, slope, rms)``: the fitted edge column and dx/drow at every row (R x C), and the RMS of
    the kept centroids about the fit (C,).
    """
    R, C = cen.shape
    good = np.isfinite(cen).all(axis=1)
    if good.sum() < degree + 2:
        nan = np.full((R, C), np.nan)
        return nan, nan.copy(), np.full(C, np.nan)
    shift, scale = rows.mean(), max(rows.std(), 1.0)
    t = (rows - shift) / scale  # conditioned abscissa
    A = np.vander(t, degree + 1)  # columns t^deg .. t^0
    coef = np.linalg.lstsq(A[good], cen[good], rcond=None)[0]
    res = cen - A @ coef
    rg = res[good]
    mad = 1.4826 * np.median(np.abs(rg - np.median(rg, axis=0)), axis=0)
    keep = good[:, None] & (np.abs(res) <= np.maximum(3.0 * mad, 0.05))
    rms = np.full(C, np.nan)
    for c in range(C):
        kc = keep[:, c]
        if degree + 2 <= kc.sum() < good.sum():
            coef[:, c] = np.linalg.lstsq(A[kc], cen[kc, c], rcond=None)[0]
            res[:, c] = cen[:, c] - A @ coef[:, c]
        if kc.any():
            rms[c] = float(np.sqrt(np.mean(res[kc, c] ** 2)))
    powers = np.arange(degree, 0, -1)  # derivative of sum c_j t^p_j
    dA = np.zeros_like(A)
    dA[:, :degree] = powers[None, :] * t[:, None] ** (powers[None, :] - 1)
    return A @ coef, (dA @ coef) / scale, rms


def _rise_10_90(esf: np.ndarray, sign: float, centre: float) -> float:
    """10-90 % rise of a binned ESF (in bins), found outward from ``centre`` (bin index)."""
    k = max(2, esf.size // 5)
    e = esf * sign
    lo, hi = float(e[:k].mean()), float(e[-k:].mean())
    if not hi > lo:
        return math.nan
    en = (e - lo) / (hi - lo)
    c = int(np.clip(round(centre), 0, en.size - 1))
    above = np.flatnonzero(en[c:] >= 0.9)
    below = np.flatnonzero(en[: c + 1] <= 0.1)
    if above.size == 0 or below.size == 0:
        return math.nan
    return float(c + above[0] - below[-1])


def esfr_vertical(roi: np.ndarray, *, x_init: np.ndarray | None = None, half_width_px: float | None = None,
                  oversample: int = 4, poly_degree: int = 1, correct_binning: bool = True,
                  white: float = 1.0, slant_range_deg: tuple[float, float] = SLANT_RANGE_DEG,
                  min_snr: float = 10.0, keep_esf: bool = False,
                  window_half_px: float | None = None) -> SfrResult:
    """e-SFR of a near-vertical edge in ``roi`` (R x W or R x W x C, channels last).

    Parameters
    ----------
    roi : array
        Linear signal (e.g. normalised to [0, 1]); each row crosses the edge once.
    x_init : (R,) array, optional
        Initial edge column per row (e.g. from detection); default the ROI's middle column.
    half_width_px : float, optional
        Only pixels within this horizontal distance of the fitted edge are used (the rest of a rectangular
        ROI may hold other edges); default: the whole ROI.
    oversample : int
        ESF bins per pixel along the normal (ISO: 4).
    poly_degree : int
        Degree of the edge fit x(row): 1 (a straight edge, ISO) to 3 (lens distortion bends long edges).
    correct_binning : bool
        Also divide by the binning box's transfer ``sinc(f / oversample)``.
    white : float
        Saturation level of the signal (for the clipping check).
    slant_range_deg, min_snr : quality thresholds.
    keep_esf : bool
        Keep the binned ESF in the result.

    Returns
    -------
    SfrResult
    """
    a = np.asarray(roi, dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[0] < 4 or a.shape[1] < 6:
        raise ParameterError(f"e-SFR region of shape {a.shape} is too small", field="roi",
                             fix="give at least 4 rows and 6 columns around the edge")
    if not 1 <= poly_degree <= 3:
        raise ParameterError(f"poly_degree {poly_degree} out of range", field="poly_degree", fix="use 1, 2 or 3")
    if oversample < 1:
        raise ParameterError(f"oversample {oversample} < 1", field="oversample", fix="use 4 (ISO 12233)")
    R, W, C = a.shape
    rows_all = np.arange(R, dtype=np.float64)
    hw = float(half_width_px) if half_width_px else W / 2.0
    if x_init is None:
        x_init = np.full(R, (W - 1) / 2.0)
    centre = np.repeat(np.asarray(x_init, dtype=np.float64).reshape(R, 1), C, axis=1)

    # 1-2. Row centroids of the derivative (positive at the edge whichever way the step goes), line fit, again.
    k5 = max(1, W // 5)
    sign = np.sign(a[:, -k5:, :].mean(axis=(0, 1)) - a[:, :k5, :].mean(axis=(0, 1)))
    sign[sign == 0] = 1.0
    d = np.diff(a, axis=1) * sign
    centre, _, _ = _fit_edge(rows_all, _row_centroids(d, centre, hw), 1)
    if not np.isfinite(centre).all():
        centre = np.repeat(np.asarray(x_init, dtype=np.float64).reshape(R, 1), C, axis=1)
    x_edge, slope_r, edge_rms = _fit_edge(rows_all, _row_centroids(d, centre, hw), poly_degree)

    # 3. Whole phase cycles: rows * |slope| an integer (mean slope over channels), centred in the ROI.
    slope0 = float(np.nanmean(slope_r[R // 2])) if np.isfinite(slope_r[R // 2]).any() else math.nan
    r0, r1 = 0, R
    if np.isfinite(slope0) and abs(slope0) > 1e-6:
        cycles = math.floor(R * abs(slope0))
        if cycles >= 1:
            n = min(R, int(math.ceil(cycles / abs(slope0) - 1e-9)))
            r0 = (R - n) // 2
            r1 = r0 + n
    a, x_edge, slope_r = a[r0:r1], x_edge[r0:r1], slope_r[r0:r1]
    Ru = r1 - r0

    # 4. Project onto the normal and bin (all channels in one bincount).
    nb_half = int(math.ceil(hw * oversample)) + 2
    nb = 2 * nb_half
    delta = 1.0 / oversample  # bin width along the normal (px)
    cols = np.arange(W, dtype=np.float64)
    vals = np.moveaxis(a, 2, 0)  # C x R x W
    fit_ok = np.isfinite(x_edge).all(axis=0)
    xe = np.where(np.isfinite(x_edge), x_edge, 0.0).T  # C x R
    ct = 1.0 / np.sqrt(1.0 + np.where(np.isfinite(slope_r), slope_r, 0.0).T ** 2)  # cos of the local slant
    dx = cols[None, None, :] - xe[:, :, None]  # C x R x W
    dist_n = dx * ct[:, :, None]  # distance along the edge normal
    ib = np.floor(dist_n * oversample).astype(np.int64) + nb_half
    use = (np.abs(dx) <= hw) & (ib >= 0) & (ib < nb) & fit_ok[:, None, None]
    ib += (np.arange(C) * nb)[:, None, None]
    sums = np.bincount(ib[use], weights=vals[use], minlength=C * nb).reshape(C, nb)
    counts = np.bincount(ib[use], minlength=C * nb).reshape(C, nb)

    nfft_min = 256 * oversample  # spectrum sampled every 1/256 cy/px
    clipped = np.mean((a >= 0.995 * white) | (a <= 0.0), axis=(0, 1))
    esf_out = np.full((C, nb), np.nan)
    mtf_rows, mtf50s, qual = [], [], []
    freq = np.fft.rfftfreq(nfft_min, d=delta)
    x_mid = np.full(C, np.nan)
    y_mid = np.full(C, (R - 1) / 2.0)
    angle = np.full(C, np.nan)
    rm = (R - 1) // 2 - r0  # the middle row, in the trimmed rows
    for c in range(C):
        filled = counts[c] > 0
        if not fit_ok[c] or filled.sum() < 8:
            mtf_rows.append(np.full(freq.size, np.nan))
            mtf50s.append(math.nan)
            qual.append(EdgeQuality(False, "no edge found in the region", math.nan, math.nan, math.nan, math.nan,
                                    math.nan, float(clipped[c]), Ru, hw, math.nan, math.nan, math.nan, int(nb)))
            continue
        nz = np.flatnonzero(filled)
        inner = slice(nz[0], nz[-1] + 1)
        e = sums[c, inner] / np.maximum(counts[c, inner], 1)
        hole = ~filled[inner]
        if hole.any():  # empty bins (too few rows for the slant): linear interpolation
            x = np.arange(e.size)
            e[hole] = np.interp(x[hole], x[~hole], e[~hole])
        esf_out[c, inner] = e

        # 5. LSF, Hamming window centred on its centroid, |FFT| normalised at DC.
        lsf = (e[2:] - e[:-2]) * (0.5 * sign[c])
        n = lsf.size
        idx = np.arange(n, dtype=np.float64)
        pos = np.clip(lsf, 0.0, None)
        tot = float(pos.sum())
        mid = float(idx @ pos / tot) if tot > 0 else (n - 1) / 2.0
        half = max(mid, n - 1 - mid, 1.0)
        if window_half_px is not None:
            half = min(half, max(float(window_half_px) / delta, 4.0))
        win = _hamming(idx - mid, half)
        nfft = max(nfft_min, 1 << int(math.ceil(math.log2(n))))
        spec = np.abs(np.fft.rfft(lsf * win, n=nfft))
        f = np.fft.rfftfreq(nfft, d=delta)
        m = spec / spec[0] if spec[0] > 0 else np.full_like(spec, np.nan)
        # 6. Transfer of the central difference (and of the binning box).
        corr = np.sinc(2.0 * f * delta)
        if correct_binning:
            corr = corr * np.sinc(f * delta)
        m = m / np.maximum(corr, 0.1)  # sfrmat3 also caps the correction at x10
        if nfft != nfft_min:
            m = np.interp(freq, f, m)
        mtf_rows.append(m)
        mtf50s.append(mtf50(freq, m))

        # Quality.
        k = max(2, e.size // 5)
        lo, hi = float(e[:k].mean()), float(e[-k:].mean())
        if sign[c] < 0:
            lo, hi = hi, lo
        step = hi - lo
        contrast = step / (hi + lo) if hi + lo > 0 else math.nan
        uc = use[c]
        # residual about the pixel's own bin mean (within-bin ESF slope is negligible beside the median)
        resid = vals[c][uc] - esf_out[c][ib[c][uc] - c * nb]
        noise = float(1.4826 * np.median(np.abs(resid - np.median(resid)))) if resid.size else math.nan
        snr = step / noise if noise > 0 else math.inf
        kt = max(1, int(0.15 * n))
        lsum = float(lsf.sum())
        # signed sums: noise averages out, a plateau that is still rising (blur wider than the ROI) does not
        tail = max(abs(float(lsf[:kt].sum())), abs(float(lsf[-kt:].sum()))) / lsum if lsum > 0 else math.nan
        width = _rise_10_90(e, sign[c], mid + 1.0) * delta
        slope = float(slope_r[rm, c])
        slant = math.degrees(math.atan(abs(slope)))
        x_mid[c] = float(x_edge[rm, c])
        angle[c] = math.degrees(math.atan2(1.0, slope)) % 180.0  # direction (dx, dy) = (slope, 1)
        reason = "ok"
        if not slant_range_deg[0] <= slant <= slant_range_deg[1]:
            reason = f"slant {slant:.1f} deg outside {slant_range_deg[0]:g}-{slant_range_deg[1]:g} deg"
        elif clipped[c] > 0.005:
            reason = f"{100 * clipped[c]:.1f} % of the pixels clipped"
        elif not step > 0.02 or not contrast > 0.05:
            reason = f"contrast too low (step {step:.3f}, Michelson {contrast:.2f})"
        elif snr < min_snr:
            reason = f"noisy: SNR {snr:.0f} < {min_snr:g}"
        elif tail > 0.05:
            reason = f"edge blur wider than the region ({100 * tail:.0f} % of the LSF in its outer tails)"
        elif not edge_rms[c] < 1.0:
            reason = f"edge not straight or too noisy to locate (row centroids scatter {edge_rms[c]:.2f} px)"
        elif Ru * abs(slope) < 0.999:
            reason = "fewer rows than one phase cycle (bins unevenly sampled)"
        qual.append(EdgeQuality(reason == "ok", reason, slant, contrast, step, noise, snr, float(clipped[c]), Ru,
                                hw, width, tail, float(edge_rms[c]), int(hole.sum())))
    y_mid[:] = (R - 1) // 2
    return SfrResult(freq, np.stack(mtf_rows), np.asarray(mtf50s), x_mid, y_mid, angle, qual,
                     esf_out if keep_esf else None, delta)


def esfr_roi(roi: np.ndarray, *, vertical: bool = True, line_init: np.ndarray | None = None,
             **kw) -> SfrResult:
    """e-SFR of an edge in ``roi`` either near-vertical (rows) or near-horizontal (columns).

    ``line_init``: initial edge position along the scan lines (per row for a vertical edge, per column for a
    horizontal one). The result's ``x_mid``, ``y_mid`` and ``angle_deg`` are in the ROI's own (x, y) frame.
    """
    a = np.asarray(roi)
    if vertical:
        return esfr_vertical(a, x_init=line_init, **kw)
    t = np.swapaxes(a, 0, 1)
    res = esfr_vertical(t, x_init=line_init, **kw)
    # In the transposed frame the edge runs (dx', dy') = (slope, 1), i.e. (1, slope) in the ROI frame.
    res.x_mid, res.y_mid = res.y_mid.copy(), res.x_mid.copy()
    res.angle_deg = (90.0 - res.angle_deg) % 180.0
    return res
