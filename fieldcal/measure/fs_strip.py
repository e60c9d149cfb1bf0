"""The band-pass at fs on a strip of the frame: the cheap source of the SML-to-fs offset at quick effort.

``measure="sml@fs"`` moves every tile's SML best focus by one pooled offset per channel, the mean difference
between the band-pass-at-fs peak and the SML peak over the tiles that have both
(:func:`fieldcal.measure.throughfocus.apply_measure_offset`). The offset is one number per channel, so it
does not need the band-pass of every tile: a horizontal strip through the optical centre, a few tile rows
high, crosses every radius out to the frame's half-width (the field positions at which the pupil's
aberrations, and so the offset, change) and costs that fraction of the full-frame band-pass DFT (1.2 s of
42 x 1080p RGB frames; the quick target is 2 s for the whole calibration).

The strip's tiles are its own (one tile row through the middle, at the grid's columns; more rows when the
frame is too narrow for :data:`MIN_TILES` in one, and as many as :data:`BUDGET_PX` pays for on small frames):
their SML and band-pass curves give the offset, which then moves every grid tile's SML best focus.

The strip is band-passed with a margin of :func:`margin_px` rows above and below, then cropped: the log-Gabor
filter's response to the zero padding of the crop's borders stays in the margin, so the strip's cells see the
same filter as a full-frame band-pass would give them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import focus

# Cycles of f0 the log-Gabor kernel's spatial support spans on each side (its envelope is < 1e-3 of the peak
# beyond ~3 periods at the ring's bandwidth); the crop's border response stays inside this margin.
MARGIN_CYCLES = 4.0


@dataclass(frozen=True)
class Strip:
    """Plane rows ``[row0, row1)`` whose band-pass is measured (multiples of the cell size ``cell_px``, in the
    unbinned plane), and the band-pass frequency ``f0_cyc_per_px`` of the unbinned plane."""

    row0: int
    row1: int
    cell_px: int
    f0_cyc_per_px: float


def margin_px(f0_cyc_per_px: float) -> int:
    """Rows band-passed beyond each edge of the strip and then dropped: :data:`MARGIN_CYCLES` periods of f0."""
    return int(math.ceil(MARGIN_CYCLES / max(float(f0_cyc_per_px), 1e-6)))


def centre_strip(plane_rows: int, centre_row: float, height_px: float, cell_px: int,
                 f0_cyc_per_px: float) -> Strip:
    """The strip of ``height_px`` plane rows centred on ``centre_row`` (clipped to the plane, whole cells).

    ``cell_px``: the cell side of the maps in unbinned plane pixels (cell x binning).
    """
    n_cells = plane_rows // cell_px
    want = max(1, int(math.ceil(height_px / cell_px)))
    want = min(want, n_cells)
    first = int(round(centre_row / cell_px - want / 2.0))
    first = min(max(first, 0), n_cells - want)
    return Strip(first * cell_px, (first + want) * cell_px, int(cell_px), float(f0_cyc_per_px))


def strip_bandpass_cells(plane: np.ndarray, strip: Strip, f0_cyc_per_px: float,
                         out: np.ndarray) -> None:
    """Cell sums of the squared band-pass (at ``f0_cyc_per_px`` of this unbinned plane) over the strip,
    written into the strip's rows of ``out`` (a cell map of the whole plane); other cells are set to 0."""
    strip_bands_cells(plane, strip, [f0_cyc_per_px], [out])


def strip_bands_cells(plane: np.ndarray, strip: Strip, f0s_cyc_per_px, outs) -> None:
    """:func:`strip_bandpass_cells` at several frequencies (one forward DFT of the strip, one inverse per
    frequency), each into its own cell map of ``outs``."""
    m = margin_px(min(f0s_cyc_per_px))
    lo, hi = max(strip.row0 - m, 0), min(strip.row1 + m, plane.shape[0])
    c0 = strip.row0 // strip.cell_px
    for band, out in zip(focus.bandpass_many(plane[lo:hi], f0s_cyc_per_px), outs):
        band = band[strip.row0 - lo:strip.row1 - lo]
        cells = focus.cell_sums(band * band, strip.cell_px)
        out[...] = 0.0
        out[c0:c0 + cells.shape[0], :cells.shape[1]] = cells[:, :out.shape[1]]


# The band-pass measure is not a single frequency: its log-Gabor ring weights the band energy by G(f)^2, a
# Gaussian in ln f of variance BAND_LOG_VAR = ln(sigma_ratio)^2 / 2 about f0. Where the sharpest position depends
# on frequency (spherical aberration: dz/dln f of 0.3-10 µm on the benchmark lenses, 0 within noise without it)
# the measure's peak is a weighted mean of the peaks of the frequencies in its band, weighted by G^2 times the
# band energy at the peak times the curve's sharpness (curvature ~ 1 / width^2): for a local power law of that
# product, f^t, the weights are a Gaussian in ln f centred at ln f0 + BAND_LOG_VAR t (:func:`effective_shift_ln`),
# and the peak is off the sharpest position at fs by dz/dln f times that shift.
BAND_LOG_VAR = math.log(focus.LOG_GABOR_SIGMA_RATIO) ** 2 / 2.0
# The two extra frequencies the slope dz/dln f is measured at: one log-Gabor sigma either side of fs (the ring's
# own half-widths in ln f, so the three bands overlap and see the same texture).
SLOPE_FACTORS = (focus.LOG_GABOR_SIGMA_RATIO, 1.0 / focus.LOG_GABOR_SIGMA_RATIO)


def effective_shift_ln(energy_tilt: float, width_tilt: float) -> float:
    """ln(f_eff / f0) of the band-pass measure's peak: ``BAND_LOG_VAR x (energy_tilt - 2 width_tilt)``.

    ``energy_tilt`` = d ln E_peak / d ln f (the band energy at the curves' peaks, measured by the two side bands:
    texture spectrum x MTF^2 there), ``width_tilt`` = d ln(width) / d ln f of the through-focus curves (their
    sharpness, the curvature at the peak, goes as width^-2). Both from the same stack; the peak is moved from
    f_eff to fs by :func:`fieldcal.fit.tiles.band_correction_um`.
    """
    if not (math.isfinite(energy_tilt) and math.isfinite(width_tilt)):
        return 0.0
    return BAND_LOG_VAR * (energy_tilt - 2.0 * width_tilt)


class StripFrames:
    """Per-frame cell maps that are zero outside a strip's rows, stored as those rows only (n x rows x wc).

    Indexing a frame gives the full (hc, wc) map, as a frame of a full cell-map array would (what the tile sums
    read); :meth:`write` keeps the strip's rows of a full map. On 42 x 1080p RGB at standard effort a full
    float32 array per extra band was ~22 MB per plane; the strip is a few percent of it.
    """

    def __init__(self, n_frames: int, shape: tuple[int, int], strip: Strip):
        hc, wc = shape
        self.shape = (int(n_frames), int(hc), int(wc))
        self.r0 = min(strip.row0 // strip.cell_px, hc)
        self.r1 = min(strip.row1 // strip.cell_px, hc)
        self.rows = np.zeros((int(n_frames), self.r1 - self.r0, int(wc)), dtype=np.float32)

    def write(self, k: int, full: np.ndarray) -> None:
        self.rows[k] = full[self.r0:self.r1]

    def __getitem__(self, k: int) -> np.ndarray:
        out = np.zeros(self.shape[1:], dtype=np.float32)
        out[self.r0:self.r1] = self.rows[k]
        return out


def coverage_cells(shape: tuple[int, int], strip: Strip, per_cell: float) -> np.ndarray:
    """A cell map (float32) of ``per_cell`` on the strip's cells and 0 elsewhere. With ``per_cell`` = the
    pixels per cell, its per-pixel mean over a tile is the fraction of the tile the band-pass saw (tiles follow
    the image's breathing and shifts, frame by frame)."""
    out = np.zeros(shape, dtype=np.float32)
    c0, c1 = strip.row0 // strip.cell_px, strip.row1 // strip.cell_px
    out[c0:c1] = per_cell
    return out


# Tiles the strip should hold at least (the offset is their pooled mean: its sd falls as 1/sqrt(n)).
MIN_TILES = 12
# Frame pixels per plane the strip may band-pass: about one tile row of a 1080p frame with its slack and
# margins (1920 x 200). The cost of quick effort is set by its largest frames; a smaller frame gets as many
# rows as this budget pays for, so its offset comes from more tiles (every row on a frame up to ~0.4 MP).
BUDGET_PX = 400_000


def tile_rows(n_columns: int, n_grid_rows: int, width_px: int, tile_px: float) -> int:
    """Rows of tiles in the strip: at least 1 and enough for :data:`MIN_TILES` tiles, more while the band-pass
    stays within :data:`BUDGET_PX`, at most the grid's rows."""
    want = int(math.ceil(MIN_TILES / max(int(n_columns), 1)))
    afford = int(BUDGET_PX // max(float(width_px) * float(tile_px), 1.0))
    return int(min(max(want, afford, 1), max(int(n_grid_rows), 1)))


def tile_centres_y(centre_row: float, n_rows: int, tile_px: float) -> np.ndarray:
    """Centre rows (frame px) of the strip's tile rows, stacked about ``centre_row`` a tile apart."""
    return centre_row + (np.arange(n_rows) - 0.5 * (n_rows - 1)) * float(tile_px)


def slack_px(tile_px: float) -> float:
    """Rows added above and below the strip's row of tiles (centred on the frame's middle), for the tiles'
    motion through the scan (image shift, and breathing, which moves a row near the middle by (m - 1) x its
    distance from the centre); a tile that still leaves the strip in some frame is not used
    (:func:`inside`)."""
    return max(8.0, 0.1 * float(tile_px))


def inside(coverage: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Tiles (rows of a tile x frame coverage curve) that lie inside the strip in every frame."""
    c = np.asarray(coverage, dtype=np.float64)
    return np.all(np.isfinite(c) & (c >= 1.0 - tol), axis=-1)
