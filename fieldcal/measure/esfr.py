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
regions (:func:`esfr_roi` does this when ``vertical=False``). It runs on a batch of regions at once
(:func:`esfr_regions`: every edge of a frame in one pass of array operations, regions zero-padded and masked);
:func:`esfr_roi` and :func:`esfr_vertical` are a batch of one, so a region's result does not depend on its
batch (beyond float rounding: the row centroids' matrix products group a batch's columns alike).
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
        return dict(vars(self))  # the fields in order (a dataclass without slots sets them in __init__)


@dataclass
class SfrResult:
    """e-SFR of one edge, per channel (arrays have a leading channel axis).

    ``x_mid``/``y_mid`` are the edge point at the middle of the rows the e-SFR binned (after phase trimming;
    the point whose MTF it measured) in ROI pixel coordinates (x = column, y = row of the ROI as given, i.e.
    before any transposition), ``angle_deg`` the edge direction from the ROI's +x axis
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


# The core runs on a batch of regions at once (every edge of a frame: one NumPy pass instead of one per edge and
# channel, which cost ~1.5 ms of interpreter overhead per edge). Regions are zero-padded to the batch's largest
# and masked; a batch holds at most this many padded samples (rows x columns x channels), so the per-sample
# temporaries stay small (measured: no faster with larger batches).
_BATCH_SAMPLES = 400_000


def _masked_median(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Median over axis 1 of the ``valid`` entries of ``x`` (B x R x C), as np.median would give; NaN if none."""
    xs = np.sort(np.where(valid, x, np.inf), axis=1)
    n = valid.sum(axis=1)
    lo = np.take_along_axis(xs, np.maximum((n - 1) // 2, 0)[:, None, :], axis=1)[:, 0, :]
    hi = np.take_along_axis(xs, np.minimum(n // 2, x.shape[1] - 1)[:, None, :], axis=1)[:, 0, :]
    return np.where(n > 0, (lo + hi) / 2.0, np.nan)


def _median_1d(x: np.ndarray, in_place: bool = False) -> float:
    """np.median of a 1-D array without its wrapper's overhead (it runs once per edge and channel);
    ``in_place``: reorder ``x`` itself (no copy)."""
    n = x.size
    h = n // 2
    if in_place:
        x.partition(h)
        p = x
    else:
        p = np.partition(x, h)
    if n % 2:
        return float(p[h])
    # the lower middle value is the largest of the h below p[h] (one selection, not two: the same values)
    return float((p[:h].max() + p[h]) / 2.0)


def _window_bounds(cen: np.ndarray, half: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last index ``w`` in 0 .. n-1 with ``|w + 0.5 - cen| <= half`` (the Hamming window of
    :func:`_row_centroids` over the differences), exactly as that test decides (one step either way where the
    rounding of ``cen -+ half`` disagrees with it); ``(n, -1)`` where ``cen`` is not finite."""
    fin = np.isfinite(cen)
    c = np.where(fin, cen, 0.0)

    def inside(w):
        return np.abs((w + 0.5) - c) <= half

    lo = np.ceil(c - half - 0.5)
    lo -= inside(lo - 1.0)
    lo += ~inside(lo)
    hi = np.floor(c + half - 0.5)
    hi += inside(hi + 1.0)
    hi -= ~inside(hi)
    lo = np.where(fin, np.clip(lo, 0, n), n).astype(np.int64)
    hi = np.where(fin, np.clip(hi, -1, n - 1), -1).astype(np.int64)
    return lo, hi


def _row_centroids(d: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Centroid (column) of the row derivative ``d`` (B x C x R x W-1, zero beyond each region's columns) about
    ``centre`` (B x C x R), Hamming-weighted within ``half`` (B,) of it; NaN where ``centre`` is NaN or the
    window holds no signal. The sign of ``d`` (one per region and channel) does not matter: it cancels.

    The weights are separable, ``cos(a - b) = cos a cos b + sin a sin b``, so the windowed sum and first moment
    are six sums per row against per-column functions of ``x`` (one batched matrix product) combined with
    per-row cosines and sines: no weight per element. Columns inside every row's window enter the product
    whole; only the bands at either end where some rows' windows stop are masked.
    """
    B, C, R, Wd = d.shape
    x = np.arange(Wd, dtype=np.float64) + 0.5  # a first difference sits between two pixels
    h = half[:, None, None]
    lo, hi = _window_bounds(centre, h, Wd)
    # rows without a finite centre or without a column in their window are NaN: left out of the bands' extent
    fin = lo <= hi
    k0 = int(lo.max(initial=0, where=fin))  # columns k0 .. k1-1 are inside every (finite) row's window
    k1 = int(hi.min(initial=Wd - 1, where=fin)) + 1
    if k1 <= k0:
        k0 = k1 = Wd  # no common band: mask every column
    ax = np.pi * x[None, :] / half[:, None]
    ca, sa = np.cos(ax), np.sin(ax)
    xb = np.broadcast_to(x, ca.shape)
    basis = np.stack([np.ones_like(ca), xb, ca, xb * ca, sa, xb * sa], axis=2)  # B x W-1 x 6
    dr = d.reshape(B, C * R, Wd)
    s = np.matmul(dr[:, :, k0:k1], basis[:, k0:k1]) if k1 > k0 else np.zeros((B, C * R, 6))
    wi = np.arange(Wd)
    if k0 == Wd:
        m = (wi >= lo.reshape(B, C * R, 1)) & (wi <= hi.reshape(B, C * R, 1))
        s += np.matmul(np.where(m, dr, 0.0), basis)
    else:  # k0 <= hi and lo <= k1 - 1 on every finite row: one bound per band (a row without a centre has none)
        if k0 > 0:
            s += np.matmul(np.where(wi[:k0] >= lo.reshape(B, C * R, 1), dr[:, :, :k0], 0.0), basis[:, :k0])
        if k1 < Wd:
            s += np.matmul(np.where(wi[k1:] <= hi.reshape(B, C * R, 1), dr[:, :, k1:], 0.0), basis[:, k1:])
    s = s.reshape(B, C, R, 6)
    with np.errstate(invalid="ignore", divide="ignore"):
        ac = np.pi * centre / h
        cc, sc = np.cos(ac), np.sin(ac)
        s0 = 0.54 * s[..., 0] + 0.46 * (cc * s[..., 2] + sc * s[..., 4])
        s1 = 0.54 * s[..., 1] + 0.46 * (cc * s[..., 3] + sc * s[..., 5])
        out = s1 / s0
    out[~fin] = np.nan  # no column in the window (a centre off the region, or none): 0 / 0
    return out


def _solve(G: np.ndarray, rhs: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Batched normal equations ``G x = rhs``; NaN where not ``ok`` (too few rows for the fit)."""
    G = G.copy()
    G[~ok] = np.eye(G.shape[-1])
    x = np.linalg.solve(G, rhs)
    x[~ok] = np.nan
    return x


def _fit_edge(cen: np.ndarray, row_ok: np.ndarray, nrows: np.ndarray, degree: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit x(row) per region and channel; refit once without centroids beyond 3 robust sigma.

    ``cen`` (B x R x C) row centroids, ``row_ok`` (B x R) the region's own rows, ``nrows`` (B,) their count.
    All channels of a region share the rows of the first fit (rows with a NaN centroid in any channel are
    dropped). Returns ``(x_edge, slope, rms)``: the fitted edge column and dx/drow at every row (B x R x C), and
    the RMS of the kept centroids about the fit (B x C).
    """
    B, R, C = cen.shape
    good = np.isfinite(cen).all(axis=2) & row_ok
    n_good = good.sum(axis=1)
    shift = (nrows - 1) / 2.0  # mean and std of the row numbers 0 .. n-1: a conditioned abscissa
    scale = np.maximum(np.sqrt((nrows.astype(np.float64) ** 2 - 1.0) / 12.0), 1.0)
    t = np.where(row_ok, (np.arange(R)[None, :] - shift[:, None]) / scale[:, None], 0.0)
    powers = np.arange(degree, -1, -1)  # columns t^deg .. t^0, as np.vander
    tp = [np.ones_like(t), t]  # t^k by products (a float power per element cost as much as the fit)
    for _ in range(degree - 1):
        tp.append(tp[-1] * t)
    A = np.stack(tp[degree::-1], axis=2)
    cz = np.where(good[:, :, None], cen, 0.0)
    Ag = A * good[:, :, None]
    # matmul rather than einsum: these products are tiny (p = degree + 1), where einsum's per-call cost dominates
    AgT = np.swapaxes(Ag, 1, 2)
    coef = _solve(AgT @ A, AgT @ cz, n_good >= degree + 2)
    res = cen - A @ coef
    g3 = np.broadcast_to(good[:, :, None], res.shape)
    med = _masked_median(res, g3)
    mad = 1.4826 * _masked_median(np.abs(res - med[:, None, :]), g3)
    with np.errstate(invalid="ignore"):
        keep = g3 & (np.abs(res) <= np.maximum(3.0 * mad, 0.05)[:, None, :])
    n_keep = keep.sum(axis=1)
    refit = (n_keep >= degree + 2) & (n_keep < n_good[:, None])
    if refit.any():
        kz = keep.astype(np.float64)
        AkT = np.swapaxes(A, 1, 2)[:, None, :, :] * np.swapaxes(kz, 1, 2)[:, :, None, :]  # B x C x p x R
        Gk = AkT @ A[:, None, :, :]
        rk = np.swapaxes(np.swapaxes(A, 1, 2) @ np.where(keep, cen, 0.0), 1, 2)  # B x C x p
        ck = _solve(Gk, rk[..., None], refit)[..., 0]  # B x C x p
        coef = np.where(refit[:, None, :], np.swapaxes(ck, 1, 2), coef)
        res = cen - A @ coef
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(n_keep > 0, np.sqrt(np.where(keep, res * res, 0.0).sum(axis=1) / n_keep), np.nan)
    dA = np.zeros_like(A)
    if degree:
        for j, p in enumerate(powers[:degree]):  # derivative of sum c_j t^p_j
            dA[:, :, j] = p * tp[p - 1]
    return A @ coef, (dA @ coef) / scale[:, None, None], rms


def _check_options(poly_degree: int, oversample: int) -> None:
    if not 1 <= poly_degree <= 3:
        raise ParameterError(f"poly_degree {poly_degree} out of range", field="poly_degree", fix="use 1, 2 or 3")
    if oversample < 1:
        raise ParameterError(f"oversample {oversample} < 1", field="oversample", fix="use 4 (ISO 12233)")


def _as_region(roi) -> np.ndarray:
    a = np.asarray(roi, dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[0] < 4 or a.shape[1] < 6:
        raise ParameterError(f"e-SFR region of shape {a.shape} is too small", field="roi",
                             fix="give at least 4 rows and 6 columns around the edge")
    return a


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
    return esfr_regions([roi], line_init=[x_init], half_width_px=[half_width_px], oversample=oversample,
                        poly_degree=poly_degree, correct_binning=correct_binning, white=white,
                        slant_range_deg=slant_range_deg, min_snr=min_snr, keep_esf=keep_esf,
                        window_half_px=window_half_px)[0]


def esfr_regions(rois, *, vertical=True, line_init=None, half_width_px=None, **kw) -> list[SfrResult]:
    """e-SFR of many regions at once (each as :func:`esfr_roi` would measure it, in one batched pass).

    ``rois``: a sequence of R_i x W_i (x C) arrays (the same channel count); ``vertical``, ``line_init`` and
    ``half_width_px``: one value for all or a sequence with one per region. Other keywords as
    :func:`esfr_vertical`. Returns one :class:`SfrResult` per region, in order.
    """
    n = len(rois)

    def per(v):
        return list(v) if isinstance(v, (list, tuple)) else [v] * n

    vert, inits, hws = per(vertical), per(line_init), per(half_width_px)
    _check_options(kw.get("poly_degree", 1), kw.get("oversample", 4))
    regions = []
    for roi, v in zip(rois, vert):
        a = _as_region(roi)
        regions.append(a if v else np.swapaxes(a, 0, 1))
    if len({a.shape[2] for a in regions}) > 1:
        raise ParameterError("regions with different channel counts", field="rois",
                             fix="give every region the same channels")
    out: list[SfrResult | None] = [None] * n
    order = sorted(range(n), key=lambda i: regions[i].shape[:2])  # similar sizes together: little padding
    i = 0
    while i < n:
        j, rmax, wmax = i, 0, 0
        while j < n:
            r, w, c = regions[order[j]].shape
            r, w = max(rmax, r), max(wmax, w)
            if j > i and (j - i + 1) * r * w * c > _BATCH_SAMPLES:
                break
            rmax, wmax, j = r, w, j + 1
        idx = order[i:j]
        res = _esfr_batch([regions[k] for k in idx], [inits[k] for k in idx], [hws[k] for k in idx], **kw)
        for k, r in zip(idx, res):
            if not vert[k]:  # the edge runs (dx', dy') = (slope, 1) in the transposed frame: (1, slope) here
                r.x_mid, r.y_mid = r.y_mid.copy(), r.x_mid.copy()
                r.angle_deg = (90.0 - r.angle_deg) % 180.0
            out[k] = r
        i = j
    return out


def _esfr_batch(regions: list[np.ndarray], x_inits: list, half_widths: list, *, oversample: int = 4,
                poly_degree: int = 1, correct_binning: bool = True, white: float = 1.0,
                slant_range_deg: tuple[float, float] = SLANT_RANGE_DEG, min_snr: float = 10.0,
                keep_esf: bool = False, window_half_px: float | None = None) -> list[SfrResult]:
    """The e-SFR steps of the module docstring on near-vertical regions (R_i x W_i x C float64), batched."""
    B = len(regions)
    C = regions[0].shape[2]
    nrows = np.array([a.shape[0] for a in regions])
    ncols = np.array([a.shape[1] for a in regions])
    R, W = int(nrows.max()), int(ncols.max())
    # channels before rows: each (region, channel) plane contiguous, for the row sums and the binning
    a = np.zeros((B, C, R, W))
    x0 = np.zeros((B, R))
    hw = np.empty(B)
    for b, (roi, xi, h) in enumerate(zip(regions, x_inits, half_widths)):
        np.copyto(a[b, :, :roi.shape[0], :roi.shape[1]], roi.transpose(2, 0, 1))  # (cheaper than a[...] =)
        x0[b, :roi.shape[0]] = (roi.shape[1] - 1) / 2.0 if xi is None else np.asarray(xi, dtype=np.float64)
        hw[b] = float(h) if h else roi.shape[1] / 2.0
    rows = np.arange(R)
    row_ok = rows[None, :] < nrows[:, None]
    col_ok = np.arange(W)[None, :] < ncols[:, None]
    # rows outside a region get no centroid (NaN, as 0/0 of their zero derivative would give)
    centre0 = np.repeat(np.where(row_ok, x0, np.nan)[:, :, None], C, axis=2)

    # 1-2. Row centroids of the derivative (positive at the edge whichever way the step goes), line fit, again.
    k5 = np.maximum(1, ncols // 5)
    cs = np.concatenate([np.zeros((B, C, 1)), np.cumsum(a.sum(axis=2), axis=2)], axis=2)  # column sums, cumulated
    bi = np.arange(B)
    first = cs[bi, :, k5] / (nrows * k5)[:, None]
    last = (cs[bi, :, ncols] - cs[bi, :, ncols - k5]) / (nrows * k5)[:, None]
    sign = np.sign(last - first)
    sign[sign == 0] = 1.0
    d = np.diff(a, axis=3)  # B x C x R x W-1; its sign per region and channel cancels in the centroids
    for b in np.flatnonzero(ncols < W):
        d[b, :, :, ncols[b] - 1:] = 0.0  # not across the padding
    cen = _row_centroids(d, np.moveaxis(centre0, 2, 1), hw)
    centre, _, _ = _fit_edge(np.moveaxis(cen, 1, 2), row_ok, nrows, 1)
    lost = ~np.where(row_ok[:, :, None], np.isfinite(centre), True).all(axis=(1, 2))
    centre[lost] = centre0[lost]
    centre[~row_ok] = np.nan
    cen = _row_centroids(d, np.moveaxis(centre, 2, 1), hw)
    x_edge, slope_r, edge_rms = _fit_edge(np.moveaxis(cen, 1, 2), row_ok, nrows, poly_degree)
    del d, cen

    # 3. Whole phase cycles: rows * |slope| an integer (mean slope over channels), centred in the ROI.
    sm = slope_r[bi, nrows // 2]  # B x C
    has = np.isfinite(sm).any(axis=1)
    known = ~np.isnan(sm)
    with np.errstate(invalid="ignore", divide="ignore"):  # np.nanmean over the channels, as its sum and count
        slope0 = np.where(has, np.where(known, sm, 0.0).sum(axis=1) / known.sum(axis=1), np.nan)
        s_abs = np.abs(slope0)
        cycles = np.floor(nrows * s_abs)
        trim = has & (s_abs > 1e-6) & (cycles >= 1)
        n = np.minimum(nrows, np.ceil(np.where(trim, cycles / s_abs, 0.0) - 1e-9).astype(np.int64))
    r0 = np.where(trim, (nrows - n) // 2, 0)
    r1 = np.where(trim, r0 + n, nrows)
    Ru = r1 - r0
    row_use = (rows[None, :] >= r0[:, None]) & (rows[None, :] < r1[:, None])

    # 4. Project onto the normal and bin (every region and channel in one bincount).
    nb_half = np.ceil(hw * oversample).astype(np.int64) + 2
    nb = 2 * nb_half
    NB = int(nb.max())
    delta = 1.0 / oversample  # bin width along the normal (px)
    cols = np.arange(W, dtype=np.float64)
    vals = a  # B x C x R x W
    fit_ok = np.where(row_use[:, :, None], np.isfinite(x_edge), True).all(axis=1)  # B x C
    xe = np.moveaxis(np.where(np.isfinite(x_edge), x_edge, 0.0), 2, 1)  # B x C x R
    ct = 1.0 / np.sqrt(1.0 + np.moveaxis(np.where(np.isfinite(slope_r), slope_r, 0.0), 2, 1) ** 2)
    dx = cols[None, None, None, :] - xe[:, :, :, None]  # B x C x R x W
    tb = dx * (ct * oversample)[:, :, :, None]  # distance along the normal in bins
    ib = np.floor(tb)
    tb -= ib  # where in its bin each sample sits (0 .. 1)
    # the bin's index in the one bincount: region and channel's block of NB bins, the edge at nb_half
    ib += (nb_half[:, None] + (np.arange(B * C) * NB).reshape(B, C)).astype(np.float64)[:, :, None, None]
    # |dx| <= hw puts the bin inside 0 .. nb - 1 (|distance along the normal| <= |dx|): no bounds test needed
    use = np.abs(dx) <= hw[:, None, None, None]
    use &= (fit_ok[:, :, None, None] & row_use[:, None, :, None]) & col_ok[:, None, None, :]
    del dx
    # in (region, channel) order: each group contiguous
    gid, v_used, t_used = ib[use].astype(np.int64), vals[use], tb[use]
    del ib, tb, use
    sums = np.bincount(gid, weights=v_used, minlength=B * C * NB).reshape(B * C, NB)
    counts = np.bincount(gid, minlength=B * C * NB).reshape(B * C, NB)
    # mean position of each bin's samples in the bin: with one phase cycle of rows a bin holds 2-3 phases, whose
    # mean sits up to ~1/8 bin off the bin's centre, and which bin a phase on a boundary falls in flips with any
    # sub-0.01 px change of the fitted line (a breathing warp, noise): MTF(fs) jumped by 0.013 at 0.25 cy/px
    bin_pos = np.bincount(gid, weights=t_used, minlength=B * C * NB).reshape(B * C, NB)
    n_used = counts.sum(axis=1)  # every used sample is in one of its group's bins
    # clipped pixels per row; the zero padding beyond a region's columns counts as clipped (<= 0): taken off
    clip = a >= 0.995 * white
    clip |= a <= 0.0
    clip_rows = np.count_nonzero(clip, axis=3) - (W - ncols)[:, None, None]  # B x C x R
    del clip
    clipped = ((clip_rows * row_use[:, None, :]).sum(axis=2) / (Ru * ncols)[:, None]).ravel()  # B*C

    # per (region, channel) rows from here on
    nbr = np.repeat(nb, C)
    filled = counts > 0
    ok = fit_ok.ravel() & (filled.sum(axis=1) >= 8)
    first = np.argmax(filled, axis=1)
    lastb = NB - 1 - np.argmax(filled[:, ::-1], axis=1)
    L = np.where(ok, lastb - first + 1, 0)  # inner span, first to last filled bin
    Lm = max(int(L.max()), 3)
    jj = np.arange(Lm)
    src = np.minimum(first[:, None] + jj[None, :], NB - 1)
    inner = jj[None, :] < L[:, None]
    e_all = sums / np.maximum(counts, 1)
    # each bin's mean moved to the bin's centre along the ESF's local slope (first order): the ESF is then
    # sampled on the regular 1/oversample grid the FFT assumes, whatever phases the rows happened to give
    off = np.where(filled, 0.5 - bin_pos / np.maximum(counts, 1), 0.0)
    both = filled[:, 2:] & filled[:, :-2]
    slope = np.zeros_like(e_all)
    slope[:, 1:-1] = np.where(both, 0.5 * (e_all[:, 2:] - e_all[:, :-2]), 0.0)
    e_all = e_all + off * slope
    E = np.take_along_axis(e_all, src, axis=1)
    fil = np.take_along_axis(filled, src, axis=1) & inner
    hole = inner & ~fil
    if hole.any():  # empty bins (too few rows for the slant): linear interpolation between their neighbours
        pidx = np.maximum.accumulate(np.where(fil, jj[None, :], -1), axis=1)
        nidx = np.minimum.accumulate(np.where(fil, jj[None, :], Lm)[:, ::-1], axis=1)[:, ::-1]
        hr, hc = np.nonzero(hole)
        p, q = pidx[hr, hc], nidx[hr, hc]
        ep, eq = E[hr, p], E[hr, q]
        E[hr, hc] = (eq - ep) / (q - p) * (hc - p) + ep
    E = np.where(inner, E, 0.0)
    esf_out = np.full((B * C, NB), np.nan)
    if keep_esf:  # the binned ESF back on each region's own bins (only kept on request)
        rr, jr = np.nonzero(inner)
        esf_out[rr, src[rr, jr]] = E[rr, jr]

    # 5. LSF, Hamming window centred on its centroid, |FFT| normalised at DC.
    sgn = sign.ravel()  # B*C, region-major like the rows
    n = np.maximum(L - 2, 0)
    jn = np.arange(Lm - 2)
    lsf = (E[:, 2:] - E[:, :-2]) * (0.5 * sgn)[:, None]
    lsf = np.where(jn[None, :] < n[:, None], lsf, 0.0)
    pos = np.clip(lsf, 0.0, None)
    tot = pos.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mid = np.where(tot > 0, (pos * jn[None, :]).sum(axis=1) / tot, (n - 1) / 2.0)
    half = np.maximum(np.maximum(mid, n - 1 - mid), 1.0)
    if window_half_px is not None:
        half = np.minimum(half, max(float(window_half_px) / delta, 4.0))
    win = _hamming(jn[None, :] - mid[:, None], half[:, None]) * (jn[None, :] < n[:, None])
    lw = lsf * win
    nfft_min = 256 * oversample  # spectrum sampled every 1/256 cy/px
    freq = np.fft.rfftfreq(nfft_min, d=delta)
    mtf = np.full((B * C, freq.size), np.nan)
    nfft = np.array([max(nfft_min, 1 << int(math.ceil(math.log2(max(v, 1))))) for v in n])
    for nf in np.unique(nfft[ok]):
        sel = np.flatnonzero(ok & (nfft == nf))
        k = min(int(nf), lw.shape[1])
        spec = np.abs(np.fft.rfft(lw[sel, :k], n=int(nf), axis=1))
        f = np.fft.rfftfreq(int(nf), d=delta)
        with np.errstate(invalid="ignore", divide="ignore"):
            m = np.where(spec[:, :1] > 0, spec / spec[:, :1], np.nan)
        # 6. Transfer of the central difference (and of the binning box).
        corr = np.sinc(2.0 * f * delta)
        if correct_binning:
            corr = corr * np.sinc(f * delta)
        m = m / np.maximum(corr, 0.1)  # sfrmat3 also caps the correction at x10
        if nf != nfft_min:
            m = np.stack([np.interp(freq, f, row) for row in m])
        mtf[sel] = m
    below = mtf < 0.5
    i50 = np.argmax(below, axis=1)
    has50 = below.any(axis=1) & (i50 > 0)
    im = np.maximum(i50 - 1, 0)
    m0, m1 = mtf[np.arange(B * C), im], mtf[np.arange(B * C), i50]
    with np.errstate(invalid="ignore", divide="ignore"):
        f50 = np.where(has50, freq[im] + (m0 - 0.5) / (m0 - m1) * (freq[i50] - freq[im]), np.nan)

    # Quality: plateaus, noise, tails, rise, slant.
    k = np.maximum(2, L // 5)
    ce = np.concatenate([np.zeros((B * C, 1)), np.cumsum(E, axis=1)], axis=1)
    rbc = np.arange(B * C)
    lo_e = ce[rbc, np.minimum(k, L)] / k
    hi_e = (ce[rbc, L] - ce[rbc, np.maximum(L - k, 0)]) / k
    neg = sgn < 0
    lo, hi = np.where(neg, hi_e, lo_e), np.where(neg, lo_e, hi_e)
    step = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        contrast = np.where(hi + lo > 0, step / (hi + lo), np.nan)
    # residual about the pixel's own bin mean (within-bin ESF slope is negligible beside the median)
    resid = v_used - e_all.ravel()[gid]
    starts = np.concatenate([[0], np.cumsum(n_used)])
    noise = np.full(B * C, np.nan)
    for g in np.flatnonzero(ok & (n_used > 0)):
        r_ = resid[starts[g]:starts[g + 1]]  # reordered and overwritten in place: the group's |r - median|
        r_ -= _median_1d(r_, in_place=True)
        noise[g] = 1.4826 * _median_1d(np.abs(r_, out=r_), in_place=True)
    kt = np.maximum(1, (0.15 * n).astype(np.int64))
    cl = np.concatenate([np.zeros((B * C, 1)), np.cumsum(lsf, axis=1)], axis=1)
    lsum = cl[rbc, n]
    head_s, tail_s = cl[rbc, np.minimum(kt, n)], lsum - cl[rbc, np.maximum(n - kt, 0)]
    with np.errstate(invalid="ignore", divide="ignore"):
        # signed sums: noise averages out, a plateau that is still rising (blur wider than the ROI) does not
        tail = np.where(lsum > 0, np.maximum(np.abs(head_s), np.abs(tail_s)) / lsum, np.nan)
    # 10-90 % rise of the ESF (in bins), found outward from the LSF centre
    lo_s, hi_s = lo_e * sgn, hi_e * sgn
    with np.errstate(invalid="ignore", divide="ignore"):
        en = (E * sgn[:, None] - lo_s[:, None]) / (hi_s - lo_s)[:, None]
    cidx = np.clip(np.rint(mid + 1.0), 0, np.maximum(L - 1, 0)).astype(np.int64)
    up = (en >= 0.9) & inner & (jj[None, :] >= cidx[:, None])
    dn = (en <= 0.1) & inner & (jj[None, :] <= cidx[:, None])
    j_up = np.argmax(up, axis=1)
    j_dn = Lm - 1 - np.argmax(dn[:, ::-1], axis=1)
    rise_ok = (hi_s > lo_s) & up.any(axis=1) & dn.any(axis=1)
    width = np.where(rise_ok, (j_up - j_dn).astype(np.float64), np.nan) * delta

    rm = (nrows - 1) // 2  # the middle row (the slope is read there)
    # Where the e-SFR measured: the middle of the rows it binned (phase trimming keeps r0 .. r1 - 1, which for
    # an even count of kept rows or an odd trim sits half a row off the region's middle row). Every kept row
    # weighs alike in the ESF, so its MTF is the mean of the local ones along those rows: on a field whose focus
    # changes along the edge (a sagittal edge lies along the radius, 0.1-0.5 µm/px) the peak belongs there, not
    # to the region's middle row (docs/benchmarks.md bench_edge_bias_s15: half a row at 0.4 µm/px, -0.12 µm).
    y_used = r0 + (Ru - 1) / 2.0
    ylo = np.clip(np.floor(y_used).astype(np.int64), 0, np.maximum(nrows - 1, 0))
    yhi = np.minimum(ylo + 1, np.maximum(nrows - 1, 0))
    fy = (y_used - ylo)[:, None]
    x_used = x_edge[bi, ylo] * (1.0 - fy) + x_edge[bi, yhi] * fy  # B x C (the fitted line between two rows)
    results = []
    mtf = mtf.reshape(B, C, -1)
    f50 = f50.reshape(B, C)
    esf_out = esf_out.reshape(B, C, NB)
    # per-record scalars as Python floats once (float() of each NumPy scalar gives the same values, slower)
    slope_l, x_l = slope_r[bi, rm].ravel().tolist(), x_used.ravel().tolist()
    ok_l, noise_l, step_l, contrast_l = ok.tolist(), noise.tolist(), step.tolist(), contrast.tolist()
    clipped_l, tail_l, width_l, rms_l = clipped.tolist(), tail.tolist(), width.tolist(), edge_rms.ravel().tolist()
    holes_l, ru_l, hw_l, nb_l = hole.sum(axis=1).tolist(), Ru.tolist(), hw.tolist(), nb.tolist()
    for b in range(B):
        qual = []
        x_mid = np.full(C, np.nan)
        angle = np.full(C, np.nan)
        for c in range(C):
            g = b * C + c
            if not ok_l[g]:
                qual.append(EdgeQuality(False, "no edge found in the region", math.nan, math.nan, math.nan,
                                        math.nan, math.nan, clipped_l[g], ru_l[b], hw_l[b], math.nan,
                                        math.nan, math.nan, nb_l[b]))
                continue
            noise_g = noise_l[g]
            st, ctr = step_l[g], contrast_l[g]
            snr = st / noise_g if noise_g > 0 else math.inf
            slope = slope_l[g]
            slant = math.degrees(math.atan(abs(slope)))
            x_mid[c] = x_l[g]
            angle[c] = math.degrees(math.atan2(1.0, slope)) % 180.0  # direction (dx, dy) = (slope, 1)
            tl, er = tail_l[g], rms_l[g]
            reason = "ok"
            if not slant_range_deg[0] <= slant <= slant_range_deg[1]:
                reason = f"slant {slant:.1f} deg outside {slant_range_deg[0]:g}-{slant_range_deg[1]:g} deg"
            elif clipped_l[g] > 0.005:
                reason = f"{100 * clipped_l[g]:.1f} % of the pixels clipped"
            elif not st > 0.02 or not ctr > 0.05:
                reason = f"contrast too low (step {st:.3f}, Michelson {ctr:.2f})"
            elif snr < min_snr:
                reason = f"noisy: SNR {snr:.0f} < {min_snr:g}"
            elif tl > 0.05:
                reason = f"edge blur wider than the region ({100 * tl:.0f} % of the LSF in its outer tails)"
            elif not er < 1.0:
                reason = f"edge not straight or too noisy to locate (row centroids scatter {er:.2f} px)"
            elif ru_l[b] * abs(slope) < 0.999:
                reason = "fewer rows than one phase cycle (bins unevenly sampled)"
            qual.append(EdgeQuality(reason == "ok", reason, slant, ctr, st, noise_g, snr, clipped_l[g],
                                    ru_l[b], hw_l[b], width_l[g], tl, er, holes_l[g]))
        results.append(SfrResult(freq, mtf[b], f50[b], x_mid, np.full(C, float(y_used[b])), angle, qual,
                                 esf_out[b, :, :nbr[b * C]].copy() if keep_esf else None, delta))
    return results


def esfr_roi(roi: np.ndarray, *, vertical: bool = True, line_init: np.ndarray | None = None,
             **kw) -> SfrResult:
    """e-SFR of an edge in ``roi`` either near-vertical (rows) or near-horizontal (columns).

    ``line_init``: initial edge position along the scan lines (per row for a vertical edge, per column for a
    horizontal one). The result's ``x_mid``, ``y_mid`` and ``angle_deg`` are in the ROI's own (x, y) frame.
    """
    hw = kw.pop("half_width_px", None)
    return esfr_regions([roi], vertical=vertical, line_init=[line_init], half_width_px=[hw], **kw)[0]
