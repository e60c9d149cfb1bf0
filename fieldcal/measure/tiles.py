"""Per-tile through-focus measurement over a chart stack: the :class:`TileTable`.

One streaming pass over the frames in z order (a few frames in memory at a time, float32 only) computes, per
frame and colour plane, small *cell maps* of each focus measure (:mod:`.focus`) and, when no geometry is
given, registers the frame to its neighbour (:mod:`.geometry`). The next frame is read in a background
thread, and the colour planes are measured in a 2-thread pool while the main thread reads and registers the
next frame (OpenCV releases the GIL); registration comes first so the band-pass can follow the image's
magnification (focus breathing). After the pass the tile grid is laid out in
the geometry of the reference frame, each tile is placed in every frame where the measured geometry says
the image has moved (focus breathing moves a corner by tens of pixels over a scan), its measures are
summed from the cell maps, and each through-focus curve is fitted (:mod:`.throughfocus`).
"""

from __future__ import annotations

import contextlib
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..errors import ParameterError
from ..optics import MTFCriterion
from ..progress import progress, status
from . import focus, fs_strip
from .breathing_mtf import band_energy_gain, declared_factors
from .bayer import PlaneLayout, extract_plane, plane_layouts, plane_shape
from .geometry import (GeometryMeasurements, StepFit, compose_steps, downsample,
                       lateral_colour_scales, register_step, registration_plane)
from .throughfocus import (CurveFit, CurveRules, analyse_curves, apply_measure_offset, apply_pooled_skew,
                           band_frequency_terms, pooled_skew_shift, shift_by_offset, skew_model_sd_um)

# Focus breathing: the image of a scene patch is magnified by m(z) through the scan. The 3-tap SML's mean over a
# patch that follows the image scales as m^-gamma with gamma 0.8-2 set by the texture's spectrum and the blur
# (a constant 2 left an exponent error of sd 0.61 across simulated lenses); each frame's SML is therefore taken
# with a scale term in its kernel (focus.sml(plane, scale)), which removes that for any spectrum, and the
# curves are fitted on the scale axis where the blur seen at the scene's scale is symmetric (_ScaleAxis).
# What remains is carried as an exponent sd times each tile's sensitivity dz/d(exponent) measured on the
# stack: the breathing systematic of the band (docs/fitting.md "Breathing systematic"). 0.45 (was 0.61): the
# remaining per-channel errors of the 14 breathing lenses of the band-coverage benchmark (s6) amount to an RMS
# exponent of 0.31-0.33, against 0.03-0.13 on the closed-form textures (tests/test_measure_maps.py); at 0.3
# the bands were too narrow on average (mean coverage 0.83, the end-to-end test in tests/test_calibrate.py
# 0.79), because part of those errors is not breathing-shaped; 0.45 gives 0.87-0.88 there. Since session 7 a
# tile's SML curve is its RMS second difference (the root of the energy's mean, focus.sml(energy=True)): an
# amplitude like the absolute values' mean, so k keeps its meaning and the sd is kept. Not re-tuned, and not
# derived either: one stack cannot identify k (its sensitivity varies by only 5-10 % over the field). Evidence
# (s7, docs/benchmarks.md): per-channel pistons less the stage frames' share (from the true frame errors) over
# dz/dk give k of 0.12-1.8 on 15 channels of 8 breathing lenses (0.16 on the widest-curve one, where the
# absolute-value SML's term claimed 1.2 µm); the pistons are not breathing-shaped enough to fit k from them.
# Since session 10 the sd is the stack's own (measure.sml_gain: k bounded by the sensor-fixed MTFs the stack
# declares, or a camera's, TileTable.sml_gain); SML_SCALE_RESIDUAL_SD is kept for tables without that record.
MIN_TILE_PX = 32
SML_SCALE_RESIDUAL_SD = 0.45
_DGAMMA = 0.5  # exponent step of the sensitivity (one-sided difference; the bias is linear in it)

EFFORTS = {
    # tile_div: default tile = min(W, H) / tile_div; geo_ds: downsampling for registration, keeping at least
    # geo_min_px on the short side; geo_all: register every channel through focus (else G, copied to all:
    # m(z) and s(z) are the same for every channel, lateral colour is measured at the reference frame); bp_all:
    # band-pass measure (hence widths) on every channel, else none unless it gives z_best; focus_bin: 2x2
    # binning before the SML when there is no band-pass (quick), only if the binned short side keeps bin_min_px
    # (binning halves the SML's top frequency and so doubles its curves' width: on a 240 px frame a quarter of
    # the tiles then failed the peak-at-edge test, the centre among them); directional: z_tan/z_sag; cell size.
    "quick": {"tile_div": 8, "geo_ds": 8, "geo_min_px": 128, "geo_all": False, "bp_all": False, "focus_bin": 2,
              "bin_min_px": 512, "directional": False, "cell": 4, "bp_strip": True},
    "standard": {"tile_div": 12, "geo_ds": 4, "geo_min_px": 256, "geo_all": False, "bp_all": True, "focus_bin": 1,
                 "directional": False, "cell": 4},
    "thorough": {"tile_div": 16, "geo_ds": 2, "geo_min_px": 256, "geo_all": True, "bp_all": True, "focus_bin": 1,
                 "directional": True, "cell": 4},
}
SML_AT_FS = "sml@fs"
MEASURES = ("auto", "sml", "bandpass", SML_AT_FS)
_SML_BASED = ("sml", SML_AT_FS)  # measures whose tile curve (and breathing sensitivity) is the SML's
# Highest band-pass frequency a plane resolves (cycles per plane pixel): the log-Gabor ring reaches ~1.6 f0 at
# 2 sigma, so above 0.4 it would pass aliased energy (Nyquist 0.5).
MAX_BANDPASS_CYC_PER_PX = 0.4


@dataclass(frozen=True)
class TileRules:
    """Per-tile rejection thresholds applied before the curve tests (:class:`CurveRules`).

    saturated_max : fraction of a tile's pixels at >= 0.995 of white (in any frame) above which it is rejected.
    dark_min : mean level (fraction of white) below which a tile is too dark to measure.
    texture_min : RMS contrast of the tile's cell means (std / mean, at its most contrasted frame) below
        which the tile has too little texture; averaging over cells keeps sensor noise (1-2 % per pixel at
        typical exposures) well below this.
    """

    saturated_max: float = 0.002
    dark_min: float = 0.01
    texture_min: float = 0.03
    curve: CurveRules = field(default_factory=CurveRules)
    # the stage's 1-sigma repeatability (µm; None: the stack's stage record, :func:`measure_stack`): every tile's curve
    # is sampled at the same frames, so the frames' errors enter the pooled skew shift and sml@fs offset coherently
    # (throughfocus.pooled_skew, apply_measure_offset: in their sd and evidence)
    stage_repeatability_um: float | None = None


@dataclass
class TileTable:
    """One row per tile and channel (docs/architecture.md). Columns are 1-D arrays of equal length.

    ``x_px, y_px``: tile centre in the geometry of the reference frame. ``z_best_um, z_sigma_um``: best
    focus and its 1-sigma (NaN when rejected). ``width_um``: half-width where the contrast at ``fs`` falls by
    ``q`` (from the band-pass curve; NaN if that curve was rejected). ``peak``: fitted height of the focus
    measure above its floor, per pixel. ``status``: "ok" or the rejection reason. ``z_tan_um, z_sag_um``:
    best foci of the directional measures (NaN unless effort="thorough"). ``curves``: the per-frame curves
    (``"sml"``, ``"bandpass"``; rows as the table, columns as ``z_um``) for plots and diagnostics.
    """

    channel: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    z_best_um: np.ndarray
    z_sigma_um: np.ndarray
    width_um: np.ndarray
    peak: np.ndarray
    status: np.ndarray
    z_tan_um: np.ndarray
    z_sag_um: np.ndarray
    z_um: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tile_px: int = 0
    fs_cyc_per_mm: float = math.nan
    q: float = math.nan
    measure: str = "sml"
    image_size_px: tuple[int, int] = (0, 0)
    pixel_pitch_um: float = math.nan
    curves: dict[str, np.ndarray] = field(default_factory=dict)
    # d z_best / d (exponent of a residual gain m^k on the SML curve) per row (µm per unit exponent; 0 without
    # breathing, NaN when the best focus is not the SML's or the row is rejected): the breathing systematic's
    # sensitivity
    z_dgamma_um: np.ndarray | None = None
    # best-focus sd per unit of independent per-frame stage-position noise (dimensionless; NaN when rejected):
    # the stage-repeatability term of the band (docs/fitting.md "Stage errors")
    stage_gain: np.ndarray | None = None
    # per channel: the pooled skew correction applied to every tile's symmetric centre (shift_um, sd_um,
    # weight; throughfocus.pooled_skew_shift)
    skew: dict = field(default_factory=dict)
    # per channel: the SML's sensor-fixed gain exponent on a breathing stack (measure.sml_gain): its in-focus
    # bound "k_max" (of the factors the stack declares, "declared"; else of a camera's) and the sd the band
    # carries ("k_sd"); empty without breathing or SML
    sml_gain: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.channel.size)

    @property
    def ok(self) -> np.ndarray:
        return self.status == "ok"

    def counts(self) -> dict[str, int]:
        """Number of rows per status."""
        names, n = np.unique(self.status, return_counts=True)
        return {str(a): int(b) for a, b in zip(names, n)}

    def rows(self, channel: str) -> np.ndarray:
        return np.flatnonzero(self.channel == channel)

    def to_dict(self) -> dict:
        """JSON-ready columns (NaN -> None)."""
        def col(a):
            a = np.asarray(a)
            if a.dtype.kind == "f":
                return [None if not math.isfinite(v) else float(v) for v in a]
            return a.tolist()
        return {"tile_px": self.tile_px, "fs_cyc_per_mm": self.fs_cyc_per_mm, "q": self.q,
                "measure": self.measure, "image_size_px": list(self.image_size_px),
                "pixel_pitch_um": self.pixel_pitch_um,
                **{k: col(getattr(self, k)) for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um",
                                                        "width_um", "peak", "status", "z_tan_um", "z_sag_um")},
                **({"z_dgamma_um": col(self.z_dgamma_um)} if self.z_dgamma_um is not None else {}),
                **({"stage_gain": col(self.stage_gain)} if self.stage_gain is not None else {}),
                **({"skew": self.skew} if self.skew else {}),
                **({"sml_gain": self.sml_gain} if self.sml_gain else {})}


# ---------------------------------------------------------------------------------------------- helpers
def _effort(effort: str) -> dict:
    if effort not in EFFORTS:
        raise ParameterError(f"unknown effort {effort!r}", field="effort", fix=f"use one of {', '.join(EFFORTS)}")
    return EFFORTS[effort]


def default_tile_px(shape: tuple[int, int], effort: str = "standard") -> int:
    """Tile size (px) for an image of ``shape`` (H, W): about 1/8 (quick) to 1/16 (thorough) of its short side."""
    n = min(shape) / _effort(effort)["tile_div"]
    return int(max(MIN_TILE_PX, 8 * round(n / 8)))


def _check_params(stack, fs_cyc_per_mm, q, tile_px, measure):
    MTFCriterion(fs_cyc_per_mm, q)
    if measure not in MEASURES:
        raise ParameterError(f"unknown focus measure {measure!r}", field="measure",
                             fix=f"use one of {', '.join(MEASURES)}")
    h, w = stack.shape
    if tile_px is not None and not (isinstance(tile_px, (int, np.integer)) and 16 <= tile_px <= min(h, w) // 2):
        raise ParameterError(f"tile_px must be an integer from 16 to half the short image side "
                             f"({min(h, w) // 2} px), got {tile_px!r}", field="tile_px",
                             fix="use a tile of 32-128 px, or leave it unset for the default")
    stack.require_frames(CurveRules().min_frames, "through-focus measurement")
    pitch = stack.pixel_pitch_um
    if pitch is None or not (math.isfinite(pitch) and pitch > 0):  # an ArrayStack made without one
        raise ParameterError(f"the stack's pixel pitch is {pitch!r}: fs in cycles/mm needs it",
                             path=stack.path, field="pixel_pitch_um",
                             fix="give the sensor's pixel pitch in µm (ArrayStack(..., pixel_pitch_um=3.45))")


def resolve_measure(stack, fs_cyc_per_mm: float, measure: str, effort: str = "standard") -> str:
    """The focus measure ``measure="auto"`` uses: ``"sml@fs"`` when every plane resolves fs
    (``fs x pitch x stride <= MAX_BANDPASS_CYC_PER_PX``), else the SML.

    At ``effort="quick"`` (``EFFORTS[...]["bp_strip"]``) the band-pass runs on the central tile row only
    (:mod:`fieldcal.measure.fs_strip`): the full-resolution DFT of every plane of every frame took 42 frames of
    1080p RGB from 2.1 to 3.3 s (the quick target is 2 s), and the offset is one number per channel, which
    that row's tiles give; without it a quick profile read the SML's peak, 2-10 µm from the fs-contrast peak
    on lenses with strong spherical aberration (docs/measurement.md "Asymmetric curves").

    ``"sml@fs"``: each tile's SML best focus moved by the channel's pooled offset to the band-pass at fs
    (:func:`fieldcal.measure.throughfocus.apply_measure_offset`). Why: the paper's best focus is where contrast
    at fs peaks, and where the through-focus curves are skewed (spherical aberration) the broad-band SML peaks
    elsewhere (docs/measurement.md "Asymmetric curves"); where they are symmetric both peak together and the
    SML, which sums every frequency, scatters less from tile to tile (0.18-0.25 vs 0.34-0.63 µm on the triplet
    at 384x216, 1.0 vs 0.35 µm on its RGGB sub-lattices).
    """
    if measure != "auto":
        return measure
    if not _effort(effort).get("auto_at_fs", True):
        return "sml"
    stride = max(lay.stride for lay in plane_layouts(stack.channels, stack.cfa))
    f0 = fs_cyc_per_mm * float(stack.pixel_pitch_um) * 1e-3 * stride
    return SML_AT_FS if f0 <= MAX_BANDPASS_CYC_PER_PX else "sml"


def _reference_index(z_sorted: np.ndarray, z_ref_um: float | None) -> int:
    if z_ref_um is None:
        return int(z_sorted.size // 2)
    return int(np.argmin(np.abs(z_sorted - z_ref_um)))


def _geometry_channels(stack, layouts: list[PlaneLayout], all_channels: bool) -> list[int]:
    """Indices into ``layouts`` of the plane registered for each measured channel (first site of a colour)."""
    first: dict[str, int] = {}
    for i, lay in enumerate(layouts):
        first.setdefault(lay.name, i)
    if all_channels:
        return [first[c] for c in stack.channels]
    pick = "G" if "G" in first else stack.channels[0]
    return [first[pick]]


@dataclass
class _Maps:
    """Cell maps of one plane over all frames (frames in z order)."""

    layout: PlaneLayout
    cell: int
    f0_cyc_per_px: float
    maps: dict[str, np.ndarray]
    strip: fs_strip.Strip | None = None  # band-pass on this strip only (quick's sml@fs offset)
    slope: fs_strip.Strip | None = None  # band-pass either side of fs on this strip (dz/dln f, fs_strip.SLOPE_FACTORS)


# ------------------------------------------------------------------------------------------------ the pass
def _read_ahead(stack, order: np.ndarray):
    """Frames of ``stack`` in ``order``, the next one read in a background thread while this one is used.

    Decoding a frame (memory-mapped copy or tifffile) releases the GIL, so reading overlaps the measurement;
    two raw frames are in memory at a time.
    """
    if len(order) == 0:
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="fieldcal-read") as pool:
        nxt = pool.submit(stack.read, int(order[0]))
        for j in range(len(order)):
            frame = nxt.result()
            if j + 1 < len(order):
                nxt = pool.submit(stack.read, int(order[j + 1]))
            yield frame
            del frame


@contextlib.contextmanager
def _opencv_threads(n: int):
    """OpenCV's own thread count set to ``n`` for the block (process-wide), then restored.

    The pass runs planes in parallel itself; OpenCV's internal threads on top of that only added overhead
    (~1 s CPU of 12 at 1080p standard effort, measured).
    """
    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _normalised(raw: np.ndarray, black: float, gain: float) -> np.ndarray:
    """``(raw - black) * gain`` as a new contiguous float32 plane, in one pass where OpenCV supports the dtype."""
    raw = np.ascontiguousarray(raw)
    if raw.dtype in (np.uint8, np.uint16, np.int16, np.float32, np.float64):
        return cv2.addWeighted(raw, gain, raw, 0.0, -black * gain, dtype=cv2.CV_32F)
    plane = raw.astype(np.float32)
    plane -= np.float32(black)
    plane *= np.float32(gain)
    return plane


def _focus_maps(m: _Maps, k: int, plane, fbin: int, scale: float, units) -> None:
    """Fill frame ``k`` of every cell map of one plane (runs in a worker thread: OpenCV releases the GIL).

    ``plane``: the normalised float32 plane, or ``(raw, black, gain)`` to normalise here. ``scale``: the
    image's magnification in this frame (relative to frame 0), so the band-pass and the SML follow the scene.
    """
    if isinstance(plane, tuple):
        plane = _normalised(*plane)
    side = None
    if m.slope is not None:  # the band-pass either side of fs on the slope strip (kept as its rows only)
        side = [np.empty(m.maps["bp_lo"].shape[1:], np.float32) for _ in range(2)]
    if m.strip is not None:  # before binning: the strip's band-pass is of the full-resolution plane
        f0 = m.strip.f0_cyc_per_px / scale
        if side is not None:  # the same strip: one DFT for the three frequencies
            fs_strip.strip_bands_cells(plane, m.strip, [f0] + [f0 * r for r in fs_strip.SLOPE_FACTORS],
                                       [m.maps["bandpass"][k]] + side)
        else:
            fs_strip.strip_bandpass_cells(plane, m.strip, f0, m.maps["bandpass"][k])
    elif side is not None:
        fs_strip.strip_bands_cells(plane, m.slope, [m.slope.f0_cyc_per_px * r / scale for r in fs_strip.SLOPE_FACTORS],
                                   side)
    if side is not None:
        m.maps["bp_lo"].write(k, side[0])
        m.maps["bp_hi"].write(k, side[1])
    if fbin > 1:
        plane = downsample(plane, fbin)
    c = m.cell
    # the SML at frame 0's scale: its mean over a tile that follows the image is then invariant to breathing; as
    # an energy, also to the sub-pixel motion of the image across the pixel grid (focus.sml)
    m.maps["sml"][k] = focus.cell_sums(focus.sml(plane, scale, energy=True), c)
    m.maps["sum"][k] = focus.cell_sums(plane, c)
    if "bandpass" in m.maps and m.strip is None:
        band = focus.bandpass(plane, m.f0_cyc_per_px / scale)
        m.maps["bandpass"][k] = focus.cell_sums(cv2.multiply(band, band), c)
        if "along" in m.maps:
            along, across = focus.directional_energy(band, *units)
            # The band energy (scale-invariant: the ring follows the image) split by each cell's fraction of
            # gradient energy along the radius. The gradient energy itself is not invariant: Scharr's response
            # at f0 / scale goes as ~(f0 / scale)^0.8-1 (not the ideal f^2), which biased z_tan/z_sag by -2 um
            # (x scale^2: +1.9 um) at a 4 mm exit pupil; the fraction is a ratio of two such energies.
            a_c, x_c = focus.cell_sums(along, c), focus.cell_sums(across, c)
            tot = a_c + x_c
            frac = np.divide(a_c, tot, out=np.full_like(tot, 0.5), where=tot > 0)
            e = m.maps["bandpass"][k]
            m.maps["along"][k] = e * frac
            m.maps["across"][k] = e - m.maps["along"][k]
    if cv2.minMaxLoc(plane)[1] >= focus.SATURATION_LEVEL:
        m.maps["sat"][k] = focus.saturated_fraction_cells(plane, c)
    else:
        m.maps["sat"][k] = 0.0


def _scan(stack, *, want_focus: bool, want_geometry: bool, fs_cyc_per_mm: float, effort: str,
          centre_px: tuple[float, float] | None, z_ref_um: float | None, quiet: bool, bp_all: bool = False,
          known_geometry: GeometryMeasurements | None = None, bp_strip: tuple[float, float] | None = None,
          slope_strip: tuple[float, float] | None = None):
    """The one pass over the frames in z order: cell maps of the focus measures and the per-frame geometry.

    Per frame, the registration plane(s) are registered to the previous frame first (main thread), so the
    image's magnification in this frame is known before its band-pass is taken; the focus measures of each
    plane then run in a small thread pool while the next frame is read and registered.

    Returns (z sorted, order, maps, geometry or None, scale) with ``scale[k]`` the magnification the band-pass
    of frame k followed, relative to frame 0 (measured here, or from ``known_geometry``).
    ``bp_strip = (centre row, height)`` (frame px): the band-pass on that strip only (:mod:`.fs_strip`).
    ``slope_strip``: the same for the band-pass either side of fs (maps ``bp_lo``, ``bp_hi``, ``slope_cover``), from
    which the sharpest position's change with frequency is measured (:func:`_frequency_slope`).
    """
    cfg = _effort(effort)
    layouts = plane_layouts(stack.channels, stack.cfa)
    h, w = stack.shape
    order = np.asarray(stack.order_by_z)
    z = np.asarray(stack.z_um, dtype=np.float64)[order]
    n = z.size
    centre = centre_px if centre_px is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
    pitch_mm = stack.pixel_pitch_um * 1e-3
    black = float(stack.black_level)
    gain = 1.0 / (float(stack.white_level) - black)  # white > black: checked when the stack was opened

    maps: list[_Maps] = []
    with_bp = bool(bp_all or cfg["bp_all"])
    fbin = 1 if with_bp and bp_strip is None else int(cfg["focus_bin"])
    if fbin > 1 and min(h, w) // fbin < cfg.get("bin_min_px", 0):
        fbin = 1
    if want_focus:
        for li, lay0 in enumerate(layouts):
            # 2x2 binning (quick): a plane pixel then covers fbin x fbin plane pixels of the frame
            lay = lay0 if fbin == 1 else PlaneLayout(lay0.name, lay0.channel_index, lay0.stride * fbin,
                                                     lay0.offset_x + lay0.stride * (fbin - 1) / 2.0,
                                                     lay0.offset_y + lay0.stride * (fbin - 1) / 2.0)
            f0 = fs_cyc_per_mm * pitch_mm * (lay.stride if bp_strip is None else lay0.stride)
            if with_bp and f0 > MAX_BANDPASS_CYC_PER_PX:
                raise ParameterError(
                    f"fs = {fs_cyc_per_mm:g} cycles/mm is {f0:.2f} cycles per pixel of the {lay.name} "
                    f"{'sub-lattice' if lay.stride > 1 else 'plane'}: above what the pixels resolve "
                    f"({MAX_BANDPASS_CYC_PER_PX})",
                    field="fs_cyc_per_mm",
                    fix=f"use fs <= {MAX_BANDPASS_CYC_PER_PX / (pitch_mm * lay.stride):.0f} cycles/mm for "
                        "this stack, or measure='sml'")
            cell = max(2, cfg["cell"] // lay0.stride)
            ph, pw = plane_shape((h, w), lay0)
            hc, wc = focus.cell_grid((ph // fbin, pw // fbin), cell)
            names = ["sml", "sum", "sat"]
            if with_bp:
                names += ["bandpass"] + (["along", "across"] if cfg["directional"] else [])
            strip = None
            if with_bp and bp_strip is not None:
                strip = fs_strip.centre_strip(ph, (bp_strip[0] - lay0.offset_y) / lay0.stride,
                                              bp_strip[1] / lay0.stride, cell * fbin, f0)
                names.append("bp_cover")
            slope = None
            if with_bp and slope_strip is not None and f0 * fs_strip.SLOPE_FACTORS[1] <= MAX_BANDPASS_CYC_PER_PX:
                slope = (strip if bp_strip == slope_strip and strip is not None else
                         fs_strip.centre_strip(ph, (slope_strip[0] - lay0.offset_y) / lay0.stride,
                                               slope_strip[1] / lay0.stride, cell * fbin, f0))
            maps.append(_Maps(lay, cell, f0, {k: np.empty((n, hc, wc), np.float32) for k in names}, strip, slope))
            if strip is not None:
                maps[-1].maps["bp_cover"][:] = fs_strip.coverage_cells((hc, wc), strip, float(cell * cell))
            if slope is not None:  # the strip's rows only, and one coverage map for every frame
                maps[-1].maps.update(
                    bp_lo=fs_strip.StripFrames(n, (hc, wc), slope), bp_hi=fs_strip.StripFrames(n, (hc, wc), slope),
                    slope_cover=np.broadcast_to(fs_strip.coverage_cells((hc, wc), slope, float(cell * cell)),
                                                (n, hc, wc)))
    units = {}
    if want_focus and cfg["directional"]:
        for li, m in enumerate(maps):
            cxp, cyp = m.layout.to_plane(*centre)
            units[li] = focus.radial_unit_vectors(plane_shape((h, w), layouts[li]), (float(cxp), float(cyp)))

    geo_idx = _geometry_channels(stack, layouts, cfg["geo_all"]) if want_geometry else []
    # Downsample for speed, but keep enough pixels on the short side for the registration to lock onto.
    ds = int(max(1, min(cfg["geo_ds"], min(h, w) // cfg["geo_min_px"])))
    prev: dict[int, np.ndarray] = {}
    steps: dict[int, list] = {i: [] for i in geo_idx}
    ref_k = _reference_index(z, z_ref_um)
    ref_small: dict[str, np.ndarray] = {}  # each colour's plane in the reference frame, for lateral colour
    first_of: dict[str, int] = {}
    for i, lay in enumerate(layouts):
        first_of.setdefault(lay.name, i)
    # Magnification of each frame, followed by the band-pass filter: a fixed frequency in cycles/px of an
    # image magnified by m is a different scene frequency in every frame, and the texture's power there
    # changes as ~m^-1.4 (dead leaves, measured), biasing best focus by -0.5 um on the triplet's breathing.
    scale = np.ones(n)
    rates: list[float] = []  # ln(step scale ratio) per µm of each registered step
    scale_ci = None if known_geometry is None else [known_geometry.channel_index(lay.name) for lay in layouts]
    n_workers = max(1, min(len(layouts), os.cpu_count() or 1, 2))
    pending: list = []
    with ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="fieldcal-measure") as pool, \
            contextlib.closing(_read_ahead(stack, order)) as frames, _opencv_threads(1):
        for k in progress(range(n), total=n, desc="measuring frames", quiet=quiet, unit="frame"):
            frame = next(frames)
            mosaic = not (stack.cfa is None and frame.ndim == 3)
            planes: dict = {}  # li -> normalised plane, or (raw, black, gain) left to the worker
            for li, lay in enumerate(layouts):
                lateral_here = want_geometry and k == ref_k and len(first_of) > 1 and first_of.get(lay.name) == li
                raw = extract_plane(frame, lay) if mosaic else frame[:, :, lay.channel_index]
                if li in steps or lateral_here:
                    planes[li] = _normalised(raw, black, gain)
                elif want_focus:
                    planes[li] = (raw, black, gain)
                if lateral_here:
                    ref_small[lay.name] = registration_plane(planes[li], ds)
                if li in steps:
                    small = registration_plane(planes[li], ds)  # the one registration (also compositing's)
                    # Centre in the small grid: x_full = S x_small + O.
                    S, O = lay.stride * ds, lay.stride * (ds - 1) / 2.0
                    cs = ((centre[0] - lay.offset_x - O) / S, (centre[1] - lay.offset_y - O) / S)
                    if k > 0:
                        last = next((q for q in reversed(steps[li]) if q is not None), None)
                        init = None if last is None else (last.r, last.tx / S, last.ty / S)  # steps vary slowly
                        st = register_step(prev[li], small, cs, init=init)
                        if st is not None:  # back to full-frame pixels: r unchanged, t scaled by S
                            d = np.diag([1.0, S, S])
                            st = StepFit(st.r, st.tx * S, st.ty * S, d @ st.cov @ d, st.n_patches)
                        steps[li].append(st)
                    prev[li] = small
            del frame
            if not want_focus:
                continue
            if geo_idx and k > 0:
                # ln m is linear in z to ~1e-4 over a scan; the median rate of the steps so far keeps one bad
                # registration (a textureless or clipped frame) from detuning the ring for the rest of the scan
                st = steps[geo_idx[0]][-1]
                if st is not None and math.isfinite(st.r) and st.r > 0:
                    rates.append(math.log(st.r) / (z[k] - z[k - 1]))
                if rates:
                    scale[k] = math.exp(float(np.median(rates)) * (z[k] - z[0]))
            # Frame k-2's measures must be done (at most three frames of planes in memory); frame k-1's may still
            # run, so the workers always have queued planes while this thread reads and registers.
            while len(pending) > len(maps):
                pending.pop(0).result()
            for li, m in enumerate(maps):
                s_k = scale[k] if scale_ci is None else float(known_geometry.magnification[k, scale_ci[li]]
                                                              / known_geometry.magnification[0, scale_ci[li]])
                if scale_ci is not None:
                    scale[k] = s_k
                pending.append(pool.submit(_focus_maps, m, k, planes[li], fbin, s_k, units.get(li)))
            del planes
        for f in pending:
            f.result()

    geometry = None
    if want_geometry:
        ref = _reference_index(z, z_ref_um)
        C = len(stack.channels)
        cols = [compose_steps(steps[li], ref) for li in geo_idx]
        if len(cols) == 1 and C > 1:
            cols = cols * C
        m_, ms, sx, sy, ss = (np.stack([c[j] for c in cols], axis=1) for j in range(5))
        lateral = None
        if len(ref_small) > 1 and len({p.shape for p in ref_small.values()}) == 1:
            lay_ref = layouts[geo_idx[0]]
            S, O = lay_ref.stride * ds, lay_ref.stride * (ds - 1) / 2.0
            cs = ((centre[0] - lay_ref.offset_x - O) / S, (centre[1] - lay_ref.offset_y - O) / S)
            reference = "G" if "G" in ref_small else stack.channels[0]
            lateral = lateral_colour_scales(ref_small, cs, reference)
        geometry = GeometryMeasurements(z, tuple(stack.channels), m_, ms, sx, sy, ss, ref,
                                        (float(centre[0]), float(centre[1])), (int(w), int(h)), order.copy(),
                                        lateral)
    return z, order, maps, geometry, scale


# ------------------------------------------------------------------------------------------ tile layout
def tile_centres(geometry: GeometryMeasurements, tile_px: int, margin_px: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """Tile centres (reference-frame px) on a grid of pitch ``tile_px`` whose tiles stay inside every frame.

    A tile moves and scales with the image (``c + m (p - c) + s``); the grid covers the part of the
    reference frame that every frame still sees, minus ``margin_px``.
    """
    w, h = geometry.image_size_px
    cx, cy = geometry.centre_px
    lo_x, lo_y, hi_x, hi_y = -math.inf, -math.inf, math.inf, math.inf
    half = tile_px / 2.0
    for k in range(geometry.z_um.size):
        for c in range(len(geometry.channels)):
            m = geometry.magnification[k, c]
            sx, sy = geometry.shift_x_px[k, c], geometry.shift_y_px[k, c]
            lo_x = max(lo_x, cx + (-0.5 + margin_px + m * half - sx - cx) / m)
            hi_x = min(hi_x, cx + (w - 0.5 - margin_px - m * half - sx - cx) / m)
            lo_y = max(lo_y, cy + (-0.5 + margin_px + m * half - sy - cy) / m)
            hi_y = min(hi_y, cy + (h - 0.5 - margin_px - m * half - sy - cy) / m)

    def axis(lo, hi):
        if hi < lo:
            return np.zeros(0)
        nt = int(math.floor((hi - lo) / tile_px)) + 1
        start = 0.5 * (lo + hi) - 0.5 * (nt - 1) * tile_px
        return start + tile_px * np.arange(nt)

    xs, ys = np.meshgrid(axis(lo_x, hi_x), axis(lo_y, hi_y))
    return xs.ravel(), ys.ravel()


def _tile_curves(m: _Maps, geometry: GeometryMeasurements, xs: np.ndarray, ys: np.ndarray, tile_px: int,
                 moments_of: str = "sml"):
    """Per-pixel mean of every map over each tile in each frame: dict name -> (n_tiles, n_frames).

    Also ``"mx", "my"``: first moments (full-frame px, frame k's geometry) of the ``moments_of`` map, and
    ``"cx", "cy"``: the box centres, so the measure-weighted position of each tile can be found later.
    """
    lay = m.layout
    n = geometry.z_um.size
    out = {k: np.empty((xs.size, n)) for k in list(m.maps) + ["sum2", "area", "mx", "my", "cx", "cy"]}
    c = m.cell
    hc, wc = m.maps[moments_of].shape[1:]
    # cell centres in full-frame px
    xcell, ycell = lay.to_full(np.arange(wc) * c + (c - 1) / 2.0, np.arange(hc) * c + (c - 1) / 2.0)
    for k in range(n):
        xk, yk = geometry.map_points(k, lay.name, xs, ys)
        half = 0.5 * tile_px * geometry.magnification[k, geometry.channel_index(lay.name)]
        # full-frame continuous coords -> plane coords -> cell units (cell j spans plane [j c - 0.5, (j+1) c - 0.5])
        x0, y0 = lay.to_plane(xk - half, yk - half)
        x1, y1 = lay.to_plane(xk + half, yk + half)
        bx0, by0, bx1, by1 = (x0 + 0.5) / c, (y0 + 0.5) / c, (x1 + 0.5) / c, (y1 + 0.5) / c
        area = (bx1 - bx0) * (by1 - by0) * c * c  # plane pixels
        out["area"][:, k] = area
        out["cx"][:, k], out["cy"][:, k] = xk, yk
        boxes = focus.BoxSampler((hc + 1, wc + 1), bx0, by0, bx1, by1)  # every map of this frame: the same boxes
        for name, stackmap in m.maps.items():
            s = boxes(focus.integral(stackmap[k]))
            out[name][:, k] = s / area
            if name == moments_of:
                e = stackmap[k]
                out["mx"][:, k] = boxes(focus.integral(e * xcell[None, :].astype(np.float32))) / area
                out["my"][:, k] = boxes(focus.integral(e * ycell[:, None].astype(np.float32))) / area
        # The window grows with the image (area ~ m^2) and keeps the same scene content; the SML maps were taken
        # with the frame's scale term (_focus_maps, focus.sml), so their per-pixel mean over it needs nothing more.
        out["sat"][:, k] *= c * c  # sat cells hold fractions, not sums: back to a fraction of the tile
        # mean of the squared cell means: with "sum" it gives the texture contrast between cells (cell
        # averaging keeps sensor noise out of it)
        cm = m.maps["sum"][k] * np.float32(1.0 / (c * c))
        out["sum2"][:, k] = boxes(focus.integral(cm * cm)) * (c * c) / area
    return out


def _weighted_positions(cc: dict[str, np.ndarray], geometry: GeometryMeasurements, channel: str,
                        measure_key: str, tile_px: int, z: np.ndarray,
                        z_best_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each tile's focus-measure-weighted centre (reference-frame px): where its best focus belongs.

    A tile's best focus is an average of the local best foci inside it, weighted by where its texture is; across
    a steep field-curvature gradient that is not the geometric centre. The weights are each pixel's energy above
    the curve's floor summed over the scan's frames (window below): a pixel whose energy goes as ``a(u) f(z - s(u))``
    (texture strength a, local best focus s) weighs ``a(u) sum_k f(z_k - s(u))``, which is ``a(u)`` times the
    curve's area over the step wherever the curve spans more than a step, whatever s(u) and wherever the frames
    fall. Weights taken around the fitted best focus (interpolated between the two frames about it, or a kernel
    a step wide) follow the strip that is sharp there, and so where the scan's frames fall: on the 256x144
    triplet (~1.5 µm of best focus per px, 20 µm steps) two scans of one lens then differed by a rho² mode of
    1.4-2.8 µm in the tiles' errors, which ``profile diff`` flagged; with the scan's sum the mode is gone
    (docs/measurement.md "Reported position"). The geometric centre instead put tiles 2.6 µm RMS off there.

    The sum runs over the frames within the same distance of the tile's fitted best focus ``z_best_um`` on both
    sides (the largest window the scan holds around it): a pixel whose curve the scan's end cuts off would
    otherwise weigh less than its neighbours on the other side of best focus, pulling the position inwards
    (the 256x144 triplet at 10 µm steps: surface RMS 0.67 -> 1.5 µm, 6.8 µm at the corners).
    """
    v = cc[measure_key]
    nt, n = v.shape
    floor = np.min(v, axis=1)
    ci = geometry.channel_index(channel)
    cx, cy = geometry.centre_px
    half = 0.5 * tile_px
    kbest = np.argmax(v, axis=1)
    zb = np.where(np.isfinite(z_best_um), z_best_um, z[kbest])
    reach = np.maximum(np.minimum(zb - z[0], z[-1] - zb), 0.0)
    nearest = np.argmin(np.abs(z[None, :] - zb[:, None]), axis=1)
    sw, sx, sy = np.zeros(nt), np.zeros(nt), np.zeros(nt)
    for k in range(n):
        e = v[:, k] - floor
        bx, by = cc["cx"][:, k], cc["cy"][:, k]
        with np.errstate(divide="ignore", invalid="ignore"):
            xk = (cc["mx"][:, k] - floor * bx) / e
            yk = (cc["my"][:, k] - floor * by) / e
        bad = ~(e > 0) | ~np.isfinite(xk) | ~np.isfinite(yk)
        # a frame's weighted centre stays inside its tile (noise-only weights could push it anywhere)
        xk = np.where(bad, bx, np.clip(xk, bx - half, bx + half))
        yk = np.where(bad, by, np.clip(yk, by - half, by + half))
        m = geometry.magnification[k, ci]
        inside = (np.abs(z[k] - zb) <= reach) | (k == nearest)
        w = np.where(bad | ~inside, 0.0, e)
        sw += w
        sx += w * (cx + (xk - cx - geometry.shift_x_px[k, ci]) / m)
        sy += w * (cy + (yk - cy - geometry.shift_y_px[k, ci]) / m)
    # no weight anywhere (a flat curve): the geometric centre, frame 0's box mapped back
    x0 = cx + (cc["cx"][:, 0] - cx - geometry.shift_x_px[0, ci]) / geometry.magnification[0, ci]
    y0 = cy + (cc["cy"][:, 0] - cy - geometry.shift_y_px[0, ci]) / geometry.magnification[0, ci]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sw > 0, sx / sw, x0), np.where(sw > 0, sy / sw, y0)


def _exponent_sensitivity(cc, geometry: GeometryMeasurements, channel: str, z: np.ndarray, res: dict,
                          measure: str, q: float, rules: TileRules) -> np.ndarray:
    """d z_best / d(exponent of a residual gain m^k on the SML curve) of each accepted tile (µm per unit
    exponent), by refitting its SML curve scaled by m^_DGAMMA. 0 when the image does not breathe."""
    out = np.full(res["z_best_um"].size, np.nan)
    if measure not in _SML_BASED:
        return out
    ok = np.flatnonzero(res["status"] == "ok")
    m = geometry.magnification[:, geometry.channel_index(channel)]
    if ok.size == 0 or np.allclose(m, 1.0, rtol=0.0, atol=1e-12):
        out[ok] = 0.0
        return out
    fits = analyse_curves(z, cc["sml"][ok] * (m ** _DGAMMA)[None, :], "peak", None, q, rules.curve)
    if rules.curve.skew:
        fits = apply_pooled_skew(fits, apply=False)[0]
    base = res.get("z_sml_um", res["z_best_um"])
    for t, f in zip(ok, fits):
        if f.status == "ok":
            out[t] = (f.z_best_um - base[t]) / _DGAMMA
    return out


@dataclass(frozen=True)
class _ScaleAxis:
    """The focus axis on which a breathing lens's curves are symmetric, and the way back to z.

    With the image scale ``m(z) = 1 + b (z - z_r)`` (b = 1 / the exit pupil's distance) the geometric blur
    disc at the sensor is ``|z - z0| / N``; a measure taken at the scene's scale (the SML with its scale term,
    the band-pass that follows the image) sees it divided by m(z), and ``|z - z0| / m(z)`` is proportional to
    ``|y - y0|`` with ``y = z_r + (z - z_r) / m(z)`` (the sensor's distance from the exit pupil, inverted).
    In z the curve's flanks are therefore skewed, by ~b x its width squared (2.5 µm on an F/6.7 lens with a
    16 mm exit pupil at 320 px, where the curves span ~200 µm); in y it is symmetric, so curves are fitted in
    y and their positions mapped back. ``b`` is the least-squares slope of the measured m(z) (linear to ~1e-4
    over a scan); b = 0 (telecentric) is the identity.
    """

    z_ref_um: float
    b_per_um: float

    def y(self, z):
        return self.z_ref_um + (np.asarray(z, dtype=np.float64) - self.z_ref_um) / (
            1.0 + self.b_per_um * (np.asarray(z, dtype=np.float64) - self.z_ref_um))

    def z(self, y):
        d = np.asarray(y, dtype=np.float64) - self.z_ref_um
        return self.z_ref_um + d / (1.0 - self.b_per_um * d)

    def dz_dy(self, y):
        return 1.0 / np.square(1.0 - self.b_per_um * (np.asarray(y, dtype=np.float64) - self.z_ref_um))


def _scale_axis(geometry: GeometryMeasurements, channel: str) -> _ScaleAxis:
    """:class:`_ScaleAxis` of one channel from the measured magnification (relative to the reference frame)."""
    ci = geometry.channel_index(channel)
    z = np.asarray(geometry.z_um, dtype=np.float64)
    m = geometry.magnification[:, ci] / geometry.magnification[geometry.ref_index, ci]
    dz = z - geometry.z_ref_um
    ok = np.isfinite(m)
    den = float(np.sum(dz[ok] ** 2))
    b = float(np.sum((m[ok] - 1.0) * dz[ok]) / den) if den > 0 else 0.0
    if not math.isfinite(b) or abs(b) < 1e-12:
        b = 0.0
    return _ScaleAxis(geometry.z_ref_um, b)


def _to_z(res: dict, axis: _ScaleAxis) -> None:
    """Map one channel's results from the axis y back to z, in place (positions; sds and widths by dz/dy)."""
    if axis.b_per_um == 0.0:
        return
    gain = axis.dz_dy(res["z_best_um"])
    res["z_sigma_um"] = res["z_sigma_um"] * gain
    res["width_um"] = res["width_um"] * gain
    for key in ("z_best_um", "z_tan_um", "z_sag_um", "z_sml_um"):
        if key in res:
            res[key] = axis.z(res[key])


def _strip_widths_on_grid(width_um: np.ndarray, sx: np.ndarray, sy: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                          tile: int) -> np.ndarray:
    """Quick effort's strip widths as a grid column: each strip tile's width goes to the grid tile of its column
    whose centre is nearest, if within half a tile (the mean where two land on one); NaN elsewhere.

    Why: quick band-passes only the strip (:mod:`.fs_strip`), whose tiles are its own, so its widths are the
    only measured δ a quick profile can have; the tolerance fit (fit/tolerance.py) is over tile positions, and
    half a tile moves a smooth width field by far less than the width's noise. The fit is then of what a strip
    spans (a constant and rho^2, not a tilt across it: fit/tolerance.py ``_spanned``)."""
    out = np.zeros(xs.size)
    n = np.zeros(xs.size)
    for w, x, y in zip(width_um, sx, sy):
        if not np.isfinite(w):
            continue
        d = np.where(np.abs(xs - x) < 0.5, np.abs(ys - y), np.inf)
        j = int(np.argmin(d)) if d.size else -1
        if j >= 0 and d[j] <= 0.5 * tile:
            out[j] += w
            n[j] += 1
    return np.where(n > 0, out / np.maximum(n, 1), np.nan)


def _analyse(channel_curves: dict[str, np.ndarray], z: np.ndarray, *, fs_cyc_per_mm: float, q: float,
             measure: str, rules: TileRules, bp_scale: np.ndarray | None = None,
             offset_from: dict | None = None, bp_skew_weight: float | None = None) -> dict[str, np.ndarray]:
    """Tile tests (saturation, texture) then the batched curve fits of one channel's tiles.

    ``bp_scale[k]``: the magnification the band-pass filter followed in frame k (its frequency was
    ``fs / bp_scale[k]`` at the sensor), used to give the width at ``fs`` itself. ``offset_from``: the
    ``"sml@fs"`` offset record measured on other tiles (quick's strip, :mod:`.fs_strip`), applied here.
    ``bp_skew_weight``: the evidence weight for the band-pass curves' pooled skew shift to use instead of this
    channel's own (:func:`_analyse_channels`: the largest over the channels).
    """
    nt = channel_curves["sml"].shape[0]
    res = {k: np.full(nt, np.nan) for k in ("z_best_um", "z_sigma_um", "width_um", "peak", "z_tan_um", "z_sag_um",
                                            "stage_gain")}
    stat = np.full(nt, "ok", dtype=object)
    mean = channel_curves["sum"]
    var = np.maximum(channel_curves["sum2"] - mean * mean, 0.0)
    safe_mean = np.where(mean > 0, mean, 1.0)
    contrast = np.where(mean > 0, np.sqrt(var) / safe_mean, 0.0)
    low = (np.max(mean, axis=1) < rules.dark_min) | (np.max(contrast, axis=1) < rules.texture_min)
    sat = np.max(channel_curves["sat"], axis=1) > rules.saturated_max
    stat[low] = "low_texture"
    stat[sat] = "saturated"
    todo = np.flatnonzero(~(low | sat))
    if todo.size:
        if "bandpass" in channel_curves:
            # Band energy / mean level^2 = (contrast at fs)^2 x the texture's power there: invariant to the
            # illumination and exposure of each frame (a 1 % flicker would otherwise move a broad peak by a
            # large fraction of a step); the tile mean is averaged over thousands of pixels, so it adds no noise.
            e_bp = channel_curves["bandpass"][todo] / np.square(safe_mean[todo])
            if "bp_cover" in channel_curves:  # band-pass on a strip only (quick): its tiles give the offset
                seen = fs_strip.inside(channel_curves["bp_cover"])
                channel_curves["bandpass"][~seen] = np.nan
                seen = np.flatnonzero(seen[todo])
                bp = [CurveFit.rejected("not_measured")] * todo.size
                fits = analyse_curves(z, e_bp[seen], "otf", fs_cyc_per_mm, q, rules.curve) if seen.size else []
                for i, f in zip(seen, fits):
                    bp[i] = f
            else:
                bp = analyse_curves(z, e_bp, "otf", fs_cyc_per_mm, q, rules.curve)
        else:  # quick effort: no band-pass on this channel, so no width
            bp = [CurveFit.rejected("not_measured")] * todo.size
        main = bp if measure == "bandpass" else analyse_curves(z, channel_curves["sml"][todo], "peak", None, q,
                                                                rules.curve)
        if rules.curve.skew:
            # One skew correction for the channel, applied where the curve is contrast at fs (the paper's best
            # focus is where it peaks); an SML's peak is not that point on a skewed lens, so the SML keeps its
            # centre and the shift is only recorded (docs/measurement.md "Asymmetric curves").
            main, res["skew"] = apply_pooled_skew(main, apply=measure == "bandpass",
                                                  repeatability_um=rules.stage_repeatability_um)
        if measure == SML_AT_FS:
            bp_skew = None
            if rules.curve.skew:
                # (NaN with < 2 fitted curves: nothing measured to share, nothing to redo)
                rep_um = rules.stage_repeatability_um
                own = pooled_skew_shift(bp, rep_um)[2] if sum(f.status == "ok" for f in bp) >= 2 else math.nan
                bp, bp_skew = apply_pooled_skew(bp, apply=True, weight=bp_skew_weight, repeatability_um=rep_um)
                res["skew"] = {**res.get("skew", {}), "bp_shift_um": bp_skew["shift_um"],
                               "bp_shift_sd_um": bp_skew["sd_um"], "bp_shift_model_sd_um": bp_skew["model_sd_um"],
                               "bp_skew_weight": bp_skew["weight"], "bp_shift_frames_sd_um": bp_skew["frames_sd_um"],
                               "bp_own_weight": own}
            # the SML's own best foci: the breathing sensitivity is of the SML curve (_exponent_sensitivity)
            res["z_sml_um"] = np.full(nt, np.nan)
            res["z_sml_um"][todo] = [f.z_best_um for f in main]
            # the tiles' distance from the middle of the tiles (the frame's centre, strip or grid alike), for the
            # offset's zone jackknife
            radius = None
            if "cx" in channel_curves and "cy" in channel_curves:
                cx, cy = (np.mean(channel_curves[k][todo], axis=1) for k in ("cx", "cy"))
                radius = np.hypot(cx - np.mean(cx), cy - np.mean(cy))
            main, offset = (apply_measure_offset(main, bp, radius, bp_skew, rules.stage_repeatability_um)
                            if offset_from is None
                            else (shift_by_offset(main, offset_from), {**offset_from, "from": "strip"}))
            res["skew"] = {**res.get("skew", {}), **offset}
        for t, fb, fm in zip(todo, bp, main):
            stat[t] = fm.status
            if fm.status == "ok":
                res["z_best_um"][t], res["z_sigma_um"][t], res["peak"][t] = fm.z_best_um, fm.z_sigma_um, fm.peak
                res["stage_gain"][t] = fm.stage_gain
            if fb.status == "ok":  # (on quick's strip: its tiles' widths, put on the grid by _strip_widths_on_grid)
                # the curve's peak saw the sensor frequency fs / s(z0); the width scales as 1 / frequency
                s0 = 1.0 if bp_scale is None else float(np.interp(fb.z_best_um, z, bp_scale))
                res["width_um"][t] = fb.width_um / s0
        if "along" in channel_curves:
            for key, col in (("along", "z_tan_um"), ("across", "z_sag_um")):
                e_dir = channel_curves[key][todo] / np.square(safe_mean[todo])  # as the band energy above
                for t, d in zip(todo, analyse_curves(z, e_dir, "otf", fs_cyc_per_mm, q, rules.curve)):
                    if d.status == "ok":
                        res[col][t] = d.z_best_um
    res["status"] = stat.astype(str)
    return res


def _analyse_channels(run, channels) -> dict[str, dict]:
    """``run(channel, bp_skew_weight)`` (:func:`_analyse`) for every channel, then again with the largest band-pass
    skew weight for each channel whose own was below 1/2 where the largest is at least 1/2.

    Why: one pupil's spherical aberration skews every channel's curves (in µm of wavefront it is the same
    pupil); a channel with few band-pass tiles (its fs peak near a scan end) measures the skew as well as the
    others but with little evidence, and kept most of its curves' centres: on an F/6.9, W040 0.8-wave lens B's
    shift (-1.2 µm, 27 tiles) was applied at weight 0.1 while G's (60 tiles) was at 1, and B's surface sat
    +1.6 µm off. As the side bands of one channel (:func:`_frequency_slope`) take the strongest band's evidence,
    the channels take the strongest channel's where they disagree on whether the curves are skewed at all (a
    weight below 1/2 against one above). A symmetric lens has every weight ~0 and keeps them.
    """
    res = {ch: run(ch, None) for ch in channels}
    own = {ch: float(r.get("skew", {}).get("bp_own_weight", math.nan)) for ch, r in res.items()}
    have = [w for w in own.values() if math.isfinite(w)]
    if have:
        w_max = max(have)
        for ch, w in own.items():
            # only where the channels disagree on whether the curves are skewed: at w >= 1/2 the mixture's sd
            # sqrt(w (1 - w)) |shift| already covers the part (1 - w) |shift| left unapplied
            if math.isfinite(w) and w < 0.5 <= w_max:
                res[ch] = run(ch, w_max)
    return res


_SLOPE_KEYS = ("bp_lo", "bp_hi", "slope_cover")


def _frequency_slope(cc: dict[str, np.ndarray], z: np.ndarray, fs_cyc_per_mm: float, q: float,
                     rules: TileRules) -> dict:
    """How the band-pass peak moves with frequency, pooled over the tiles inside the slope strip of one channel.

    The band-pass curves one log-Gabor sigma below and above fs (``bp_lo``, ``bp_hi``, fs_strip.SLOPE_FACTORS)
    are fitted as the fs curves are (skew-corrected, pooled shift applied); the per-tile difference of their
    best foci, pooled (:func:`fieldcal.measure.throughfocus.pooled_mean`, Birge-inflated by its scatter), over
    the ln f between them is ``dz/dln f`` (µm). Spherical aberration makes it non-zero (the sharpest position
    of a low frequency lies nearer the minimum-RMS-spot focus); a lens without it gives 0 within its sd.
    With it the measure's effective frequency ``freq_shift_ln`` = ln(f_eff / fs)
    (:func:`fieldcal.measure.fs_strip.effective_shift_ln`, from the same fits' peak heights and widths), and with
    the fs band on the same tiles the curvature ``d2z/dln f^2`` (:func:`.throughfocus.band_frequency_terms`).
    Returns ``{"freq_slope_um", "freq_slope_sd_um", "freq_curv_um", "freq_curv_sd_um", "freq_n_tiles",
    "freq_shift_ln"}`` ({} with < 2 tiles).
    """
    seen = fs_strip.inside(cc["slope_cover"])
    mean = cc["sum"]
    ok_level = np.all(mean > 0, axis=1)
    idx = np.flatnonzero(seen & ok_level)
    if idx.size < 2:
        return {}
    fits = []
    # the fs band on the same tiles too (the grid's or the strip's band-pass): the second difference across the
    # three bands is the curvature of z(ln f), which the correction needs (throughfocus.band_peak_correction_um)
    bands = [("bp_lo", fs_strip.SLOPE_FACTORS[0]), ("bp_hi", fs_strip.SLOPE_FACTORS[1])]
    if "bandpass" in cc:
        bands.append(("bandpass", 1.0))
    for key, r in bands:
        e = cc[key][idx] / np.square(mean[idx])
        fits.append(analyse_curves(z, e, "otf", fs_cyc_per_mm * r, q, rules.curve))
    if rules.curve.skew:
        # every band's pooled skew shift, with the strongest band's evidence: one pupil's spherical aberration
        # skews them all, and a band whose own evidence is weaker (the broader low band, or a noisier high one)
        # would otherwise keep part of its curve's centre, which the slope and curvature then read as a frequency
        # dependence (F/8, W040 0.3 waves: the high band's weight 0.3 put d2z/dln f^2 at half its value)
        rep_um = rules.stage_repeatability_um
        pooled = [pooled_skew_shift(f, rep_um) for f in fits]
        w = max(p[2] for p in pooled)
        fits = [apply_pooled_skew(f, apply=True, weight=w, repeatability_um=rep_um)[0] for f in fits]
        # each band's pooled shift is one draw shared by its tiles: its sd and model error join the differences'
        # (w ~ 1 here; throughfocus.skew_model_sd_um: the model error differs between bands of different widths)
        model = [skew_model_sd_um(f) for f in fits]
        shared = [math.sqrt(w * (p[1] ** 2 + m ** 2)) for p, m in zip(pooled, model)] + [0.0] * (3 - len(pooled))
    else:
        shared = [0.0, 0.0, 0.0]
    half = 0.5 * math.log(fs_strip.SLOPE_FACTORS[1] / fs_strip.SLOPE_FACTORS[0])
    rec = band_frequency_terms(fits[0], fits[2] if len(fits) > 2 else [], fits[1], half,
                               (shared[0], shared[2], shared[1]))
    if not rec:
        return {}
    both = [(a, b) for a, b in zip(fits[0], fits[1]) if a.status == "ok" and b.status == "ok"]
    dlnf = 2.0 * half
    # the measure's effective frequency: how the band energy at the peak and the curves' widths change with f
    with np.errstate(all="ignore"):
        e_tilt = np.log(np.array([b.peak / a.peak for a, b in both])) / dlnf
        w_tilt = np.log(np.array([b.width_um / a.width_um for a, b in both])) / dlnf
    e_tilt, w_tilt = e_tilt[np.isfinite(e_tilt)], w_tilt[np.isfinite(w_tilt)]
    shift = fs_strip.effective_shift_ln(float(np.median(e_tilt)) if e_tilt.size else math.nan,
                                        float(np.median(w_tilt)) if w_tilt.size else math.nan)
    return {**rec, "freq_shift_ln": shift}


def _sml_gain_terms(stack, maps: list[_Maps], geometry: GeometryMeasurements, order: np.ndarray,
                    factors: tuple[bool, float | None] | None) -> dict[str, dict]:
    """Per channel, the bound on the SML's sensor-fixed gain exponent (:mod:`.sml_gain`) from the frames of
    largest and smallest SML: ``k_max`` of the factors ``factors`` declares, or of a camera's (pixel aperture
    at the stack's pitch, diffraction at its F-number) when the stack does not say, and the sd the band carries.
    Empty when the image does not breathe (the gain is then 1 in every frame)."""
    from . import sml_gain as sg
    meta = getattr(stack, "meta", None) or {}
    f_number = meta.get("f_number")
    f_number = float(f_number) if isinstance(f_number, (int, float)) and math.isfinite(f_number) else None
    pitch = getattr(stack, "pixel_pitch_um", None)
    if pitch is None or not math.isfinite(float(pitch)) or float(pitch) <= 0:
        # no pitch (an in-memory stack): the pixel aperture in pixel units, no diffraction (it needs cycles/mm)
        pitch, f_number = 1.0, None
    pitch = float(pitch)
    pixel, fnum = (True, f_number) if factors is None else (bool(factors[0]), factors[1])
    if not pixel and fnum is None:  # the stack says its frames carry no sensor-fixed MTF: k is 0
        return {lay.name: {"k_max": 0.0, "declared": True, "k_sd": sg.exponent_sd(0.0)} for lay in
                (mp.layout for mp in maps)
                if not np.allclose(geometry.magnification[:, geometry.channel_index(lay.name)], 1.0, rtol=0.0,
                                   atol=1e-12)}
    seen: dict[str, tuple[int, int, PlaneLayout]] = {}
    for mp in maps:
        name = mp.layout.name
        if name in seen:  # a second G site of a mosaic: the first one's spectrum
            continue
        if np.allclose(geometry.magnification[:, geometry.channel_index(name)], 1.0, rtol=0.0, atol=1e-12):
            continue
        tot = np.asarray(mp.maps["sml"], dtype=np.float64).reshape(mp.maps["sml"].shape[0], -1).sum(axis=1)
        lay = next(lay for lay in plane_layouts(stack.channels, stack.cfa) if lay.name == name)
        ks = int(np.argmax(tot))
        # the window: where the sharpest frame's SML energy is largest (its in-focus zone; on a curved field a
        # ring, whose centroid would be the defocused centre: 0.14 against the whole 1080p plane's 0.40)
        e = np.asarray(mp.maps["sml"][ks], dtype=np.float32)
        to_plane = mp.cell * mp.layout.stride / lay.stride  # a cell in unbinned plane px
        n = max(1, int(round(sg.WINDOW_PX / to_plane)))
        box = cv2.boxFilter(e, -1, (min(n, e.shape[1]), min(n, e.shape[0])), normalize=False,
                            borderType=cv2.BORDER_CONSTANT)
        cy, cx = np.unravel_index(int(np.argmax(box)), box.shape)
        centre = ((cy + 0.5) * to_plane, (cx + 0.5) * to_plane)
        seen[name] = (ks, int(np.argmin(tot)), lay, centre)
    if not seen:
        return {}
    frames = {k: stack.read(int(order[k])) for k in {i for a, b, *_ in seen.values() for i in (a, b)}}
    out = {}
    for name, (ks, kb, lay, centre) in seen.items():
        def plane(k):
            fr = frames[k]
            mosaic = not (stack.cfa is None and fr.ndim == 3)
            return sg.window(extract_plane(fr, lay) if mosaic else fr[:, :, lay.channel_index], centre)
        k_max = sg.gain_exponent(plane(ks), plane(kb), pitch * lay.stride, pitch if pixel else None, fnum, name)
        out[name] = {"k_max": k_max, "declared": factors is not None, "k_sd": sg.exponent_sd(k_max)}
    return out


def _borrow_offsets(results: dict[str, dict]) -> None:
    """``"sml@fs"``: a channel whose band-pass curves gave no offset (fewer than 2 tiles with both curves, e.g.
    its fs-contrast peaks at an end of the scan, where the broad band-pass curve fails the edge test and the
    narrower SML curve does not) takes the other channels' offset, in place.

    Why: the SML-to-fs offset is set by the lens's spherical aberration, which is the same pupil for every
    channel (in µm of wavefront, and the geometric peak does not depend on the wavelength); on a W040 = 0.8
    wave F/6.9 lens G and B measured -7.4 and -6.9 µm while R, keeping its SML, sat 8 µm off. The borrowed
    offset is the inverse-variance mean of the others' (evidence-weighted as there); its variance is theirs
    plus their spread across channels (the chromatic part). That error is one draw for the whole channel: it
    joins the band as a field-wide term (``fit.tiles.measure_offset_sd_um``), not each tile's sd, where the
    surface fit would average it away over the tiles (lens 13 of the band benchmark: R borrowed -7.3 ± 1.1 µm
    and its piston, +0.84 µm, was 1.5x the whole field-wide sd it stated).
    """
    have = {c: r["skew"] for c, r in results.items()
            if r.get("skew", {}).get("n_tiles", 0) >= 2 and r["skew"].get("offset_weight", 0.0) > 0.0}
    lack = [c for c, r in results.items() if c not in have and "skew" in r]
    if not have or not lack:
        return
    m = np.array([h["offset_um"] for h in have.values()])
    sd = np.array([max(h["offset_sd_um"], 1e-9) for h in have.values()])
    w = np.array([h["offset_weight"] for h in have.values()])
    iv = 1.0 / sd ** 2
    mean = float(np.sum(iv * m) / np.sum(iv))
    spread2 = float(np.sum(iv * (m - mean) ** 2) / np.sum(iv)) * (m.size / max(m.size - 1, 1))
    var = 1.0 / float(np.sum(iv)) + spread2
    weight = float(np.min(w))
    for c in lack:
        r = results[c]
        ok = r["status"] == "ok"
        r["z_best_um"] = np.where(ok, r["z_best_um"] + weight * mean, r["z_best_um"])
        r["skew"] = {**r["skew"], "offset_um": mean, "offset_sd_um": math.sqrt(var), "offset_weight": weight,
                     "offset_from": ",".join(have)}


# ----------------------------------------------------------------------------------------- entry points
def measure_geometry(stack, *, effort: str = "standard", centre_px: tuple[float, float] | None = None,
                     z_ref_um: float | None = None, quiet: bool = False) -> GeometryMeasurements:
    """Per-frame magnification and shift of each channel relative to the reference frame.

    Parameters
    ----------
    stack : fieldcal.formats.stack.Stack or ArrayStack
        A chart stack (read one frame at a time).
    effort : {"quick", "standard", "thorough"}
        "quick" and "standard" register G through focus (8x / 4x downsampled) and copy it to every channel
        (m(z), s(z) do not depend on colour; lateral colour is measured at the reference frame);
        "thorough" registers every channel.
    centre_px : (cx, cy), optional
        Centre of the magnification (default the image centre; use :meth:`GeometryMeasurements.recentred`
        once the optical centre is known).
    z_ref_um : float, optional
        The reference frame is the one nearest this position (default: the middle frame in z).

    Examples
    --------
    >>> geo = measure_geometry(Stack.open("STACK"))                 # doctest: +SKIP
    >>> geo.magnification[:, 0], geo.shift_x_px[:, 0]               # doctest: +SKIP
    """
    stack.require_frames(2, "geometry measurement")
    _, _, _, geo, _ = _scan(stack, want_focus=False, want_geometry=True, fs_cyc_per_mm=1.0, effort=effort,
                         centre_px=centre_px, z_ref_um=z_ref_um, quiet=quiet)
    return geo


def measure_stack(stack, *, fs_cyc_per_mm: float = 80.0, q: float = 0.05, tile_px: int | None = None,
                  effort: str = "standard", measure: str = "auto", rules: TileRules | None = None,
                  geometry: GeometryMeasurements | None = None, centre_px: tuple[float, float] | None = None,
                  z_ref_um: float | None = None, quiet: bool = False) -> tuple[TileTable, GeometryMeasurements]:
    """Measure per-tile through-focus curves and (unless given) the per-frame geometry, in one pass.

    Parameters
    ----------
    stack : fieldcal.formats.stack.Stack or ArrayStack
        A chart stack; frames are read once, in z order.
    fs_cyc_per_mm : float
        Target spatial frequency (cycles/mm at the sensor) of the band-pass measure and of ``width_um``.
    q : float
        Contrast loss that defines ``width_um`` (the half-width where contrast at fs falls by q).
    tile_px : int, optional
        Tile size in frame pixels (default :func:`default_tile_px`).
    effort : {"quick", "standard", "thorough"}
        Speed/detail trade-off (module constant ``EFFORTS``); "thorough" adds z_tan/z_sag.
    measure : {"auto", "sml", "bandpass", "sml@fs"}
        Focus measure whose curve gives ``z_best_um`` (the width always comes from the band-pass curve).
        "auto" (default): ``"sml@fs"`` (the SML moved by the channel's pooled offset to the band-pass at fs)
        where the planes resolve fs, else the SML (:func:`resolve_measure`); ``TileTable.measure`` records the
        one used. At quick effort "auto" takes the offset from a strip of tiles through the middle
        (:mod:`.fs_strip`: no widths); "sml@fs" asked for by name band-passes every tile (widths everywhere).
    rules : TileRules, optional
        Rejection thresholds.
    geometry : GeometryMeasurements, optional
        Use this geometry to place tiles instead of measuring it.

    Returns
    -------
    (TileTable, GeometryMeasurements)
    """
    _check_params(stack, fs_cyc_per_mm, q, tile_px, measure)
    asked = measure
    measure = resolve_measure(stack, float(fs_cyc_per_mm), measure, effort)
    rules = rules or TileRules()
    if rules.stage_repeatability_um is None:
        from fieldcal.calibration.pipeline import stage_repeatability  # the stage record's one reader
        rules = replace(rules, stage_repeatability_um=stage_repeatability(stack, None)[0])
    z_sorted = np.sort(np.asarray(stack.z_um, dtype=np.float64))
    if geometry is not None:
        if (geometry.z_um.size != z_sorted.size or not np.allclose(geometry.z_um, z_sorted)
                or tuple(geometry.channels) != tuple(stack.channels)):
            raise ParameterError("the geometry was measured on another stack (its z positions or channels differ)",
                                 field="geometry", fix="measure the geometry on this stack (measure_geometry(stack))")
    h, w = stack.shape
    tile = int(tile_px) if tile_px is not None else default_tile_px((h, w), effort)
    strip = slope_strip = None
    # a row of tiles through the middle (the grid's columns and rows: from the frame alone, as tile_centres lays
    # them out without motion)
    n_cols = int(math.floor(max(w - 13.0 - tile, 0.0) / tile)) + 1
    strip_rows = fs_strip.tile_rows(n_cols, int(math.floor(max(h - 13.0 - tile, 0.0) / tile)) + 1, w, tile)
    middle = ((h - 1) / 2.0, strip_rows * tile + 2.0 * fs_strip.slack_px(tile))
    if asked == "auto" and measure == SML_AT_FS and _effort(effort).get("bp_strip", False):
        # quick: the offset is one number per channel; the strip's tiles give it
        strip = middle
    if measure in ("bandpass", SML_AT_FS):
        # the sharpest position's change with frequency, one number per channel as well (fit.tiles.band_correction_um):
        # the strip's tiles when quick has one (its DFT is shared), else the fewest rows that hold MIN_TILES (its
        # term is |ln(f_eff/fs)| ~ 0.02-0.03 x the slope: the slope's sd matters little, the cost does)
        rows = min(int(math.ceil(fs_strip.MIN_TILES / max(n_cols, 1))), strip_rows)
        slope_strip = middle if strip is not None else ((h - 1) / 2.0, rows * tile + 2.0 * fs_strip.slack_px(tile))
    z, order, maps, geo, bp_scale = _scan(stack, want_focus=True, want_geometry=geometry is None,
                                          fs_cyc_per_mm=float(fs_cyc_per_mm), effort=effort, centre_px=centre_px,
                                          z_ref_um=z_ref_um, quiet=quiet, bp_all=measure in ("bandpass", SML_AT_FS),
                                          known_geometry=geometry, bp_strip=strip, slope_strip=slope_strip)
    geometry = geometry or geo
    xs, ys = tile_centres(geometry, tile)
    if xs.size == 0:
        raise ParameterError(f"no {tile} px tile fits inside every frame (the image moves too much or the tile "
                             "is too large)", field="tile_px", fix="use a smaller tile_px")
    n_grid = xs.size
    if strip is not None:  # the strip's own tiles (rows n_grid on), split off below
        sx, sy = np.meshgrid(np.unique(xs), fs_strip.tile_centres_y(strip[0], strip_rows, tile))
        xs, ys = np.concatenate([xs, sx.ravel()]), np.concatenate([ys, sy.ravel()])
    per_channel: dict[str, dict[str, np.ndarray]] = {}
    for m in maps:
        curves = _tile_curves(m, geometry, xs, ys, tile, moments_of="sml" if measure in _SML_BASED else measure)
        have = per_channel.get(m.layout.name)
        if have is None:
            per_channel[m.layout.name] = curves
        else:  # a second G site of a mosaic: pool by pixel count
            a0, a1 = have["area"], curves["area"]
            for key in curves:
                if key == "area":
                    continue
                have[key] = (have[key] * a0 + curves[key] * a1) / (a0 + a1)
            have["area"] = a0 + a1
    for cc in per_channel.values():
        # The tile's RMS second difference: the energy's mean is what stays the same as the image crosses the pixel
        # grid (focus.sml); its square root keeps the curve an amplitude, as the absolute values' was (the peak,
        # skew and breathing models are of one: ln of it is half ln of the energy). The weighted positions take
        # the energy, whose moments the maps hold.
        cc["sml_energy"] = cc["sml"]
        cc["sml"] = np.sqrt(np.maximum(cc["sml"], 0.0))
    # the band-passes followed the image: the sensor-fixed MTFs the stack declares (pixel aperture, diffraction)
    # put back at the band's own sensor frequency in every frame (breathing_mtf: +2 µm at F/7.5, exit pupil 15 mm)
    band_f = {"bandpass": 1.0, "along": 1.0, "across": 1.0, "bp_lo": fs_strip.SLOPE_FACTORS[0],
              "bp_hi": fs_strip.SLOPE_FACTORS[1]}
    factors = declared_factors(getattr(stack, "meta", None))
    if factors is not None and bp_scale is not None and not np.allclose(bp_scale, 1.0, rtol=0.0, atol=1e-12):
        pitch = float(stack.pixel_pitch_um) if factors[0] else None
        for ch, cc in per_channel.items():
            for key in band_f.keys() & cc.keys():
                cc[key] = cc[key] * band_energy_gain(float(fs_cyc_per_mm) * band_f[key], bp_scale, pitch,
                                                     factors[1], ch)
    # the SML's own sensor-fixed gain m^k (measure.sml_gain): bounded by the k of the factors the stack declares,
    # or of a camera's where it does not say (carried in the band by fit.tiles.breathing_systematic_sd_um)
    sml_gain = _sml_gain_terms(stack, maps, geometry, order, factors) if measure in _SML_BASED else {}
    cols: dict[str, list] = {k: [] for k in ("channel", "x_px", "y_px", "z_best_um", "z_sigma_um", "width_um",
                                             "peak", "status", "z_tan_um", "z_sag_um", "z_dgamma_um", "stage_gain")}
    curves_out: dict[str, list] = {"sml": [], "bandpass": []}
    skew = {}
    # curves are fitted on each channel's scale axis (symmetric under breathing), positions mapped back to z
    axes = {ch: _scale_axis(geometry, ch) for ch in stack.channels}
    offsets = {ch: None for ch in stack.channels}
    slopes: dict[str, dict] = {}
    strip_widths: dict[str, np.ndarray] = {}
    if strip is not None:
        xs, ys = xs[:n_grid], ys[:n_grid]
        on_strips = {}
        for ch, cc in per_channel.items():
            on_strips[ch] = on_strip = {k: v[n_grid:] for k, v in cc.items()}
            per_channel[ch] = {k: v[:n_grid] for k, v in cc.items() if k not in ("bandpass", "bp_cover") + _SLOPE_KEYS}
            if "bp_lo" in on_strip:
                slopes[ch] = _frequency_slope(on_strip, axes[ch].y(z), float(fs_cyc_per_mm), float(q), rules)
        strip_res = _analyse_channels(
            lambda ch, w: _analyse(on_strips[ch], axes[ch].y(z), fs_cyc_per_mm=float(fs_cyc_per_mm), q=float(q),
                                   measure=measure, rules=rules, bp_scale=bp_scale, bp_skew_weight=w), per_channel)
        for ch, res_strip in strip_res.items():
            rec = res_strip.get("skew", {})
            _to_z(res_strip, axes[ch])
            strip_widths[ch] = _strip_widths_on_grid(res_strip["width_um"], sx.ravel(), sy.ravel(), xs, ys, tile)
            offsets[ch] = {k: rec[k] for k in ("offset_um", "offset_sd_um", "offset_weight", "n_tiles",
                                               "offset_zone_sd_um", "offset_skew_sd_um", "offset_own_weight",
                                               "bp_shift_um", "bp_shift_sd_um", "bp_shift_model_sd_um",
                                               "bp_skew_weight", "bp_own_weight", "offset_frames_sd_um",
                                               "bp_shift_frames_sd_um")
                           if k in rec}
            for k in ("offset_um", "offset_sd_um", "offset_weight", "n_tiles"):
                offsets[ch].setdefault(k, 0.0)
    for ch, cc in per_channel.items():
        if "bp_lo" in cc:  # the band-pass everywhere (standard): the grid's tiles inside the slope strip
            slopes[ch] = _frequency_slope(cc, axes[ch].y(z), float(fs_cyc_per_mm), float(q), rules)
            per_channel[ch] = {k: v for k, v in cc.items() if k not in _SLOPE_KEYS}
    def grid(ch, w):
        return _analyse(per_channel[ch], axes[ch].y(z), fs_cyc_per_mm=float(fs_cyc_per_mm), q=float(q),
                        measure=measure, rules=rules, bp_scale=bp_scale, offset_from=offsets[ch], bp_skew_weight=w)
    # quick's grid has no band-pass: its strip shared the weights above
    results = (_analyse_channels(grid, stack.channels) if strip is None
               else {ch: grid(ch, None) for ch in stack.channels})
    if measure == SML_AT_FS:
        _borrow_offsets(results)
    for ch, rec in slopes.items():
        if "skew" in results[ch]:
            results[ch]["skew"] = {**results[ch]["skew"], **rec}
    for ch in stack.channels:
        cc = per_channel[ch]
        res = results[ch]
        cols["channel"].append(np.full(xs.size, ch))
        if "skew" in res:
            # ("_" keys: arrays for the measurement's own use, e.g. the frame responses; not the record's)
            skew[ch] = {k: (v if isinstance(v, (bool, str)) else float(v)) for k, v in res["skew"].items()
                        if not k.startswith("_")}
        sens = _exponent_sensitivity(cc, geometry, ch, axes[ch].y(z), res, measure, q, rules)
        cols["z_dgamma_um"].append(sens * axes[ch].dz_dy(res["z_best_um"]))
        _to_z(res, axes[ch])
        xw, yw = _weighted_positions(cc, geometry, ch, "sml_energy" if measure in _SML_BASED else measure, tile, z,
                                     res["z_best_um"])
        ok = res["status"] == "ok"  # rejected tiles keep their geometric centre
        cols["x_px"].append(np.where(ok, xw, xs))
        cols["y_px"].append(np.where(ok, yw, ys))
        if ch in strip_widths:  # quick: the strip's widths on their grid tiles (the grid has no band-pass)
            res["width_um"] = np.where(ok, strip_widths[ch], np.nan)
        for key in ("z_best_um", "z_sigma_um", "width_um", "peak", "status", "z_tan_um", "z_sag_um", "stage_gain"):
            cols[key].append(res[key])
        curves_out["sml"].append(cc["sml"])
        curves_out["bandpass"].append(cc["bandpass"] if "bandpass" in cc else np.full_like(cc["sml"], np.nan))
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    table = TileTable(channel=cat["channel"].astype(str), x_px=cat["x_px"], y_px=cat["y_px"],
                      z_best_um=cat["z_best_um"], z_sigma_um=cat["z_sigma_um"], width_um=cat["width_um"],
                      peak=cat["peak"], status=cat["status"].astype(str), z_tan_um=cat["z_tan_um"],
                      z_sag_um=cat["z_sag_um"], z_um=z, tile_px=tile, fs_cyc_per_mm=float(fs_cyc_per_mm),
                      q=float(q), measure=measure, image_size_px=(int(w), int(h)),
                      pixel_pitch_um=float(stack.pixel_pitch_um),
                      curves={k: np.concatenate(v, axis=0) for k, v in curves_out.items()},
                      z_dgamma_um=cat["z_dgamma_um"], stage_gain=cat["stage_gain"], skew=skew, sml_gain=sml_gain)
    ok = int(table.ok.sum())
    status(f"measured {len(table)} tile curves ({ok} ok): {table.counts()}", quiet=quiet)
    return table, geometry


def measure_tiles(stack, geometry: GeometryMeasurements | None = None, **kwargs) -> TileTable:
    """The :class:`TileTable` of :func:`measure_stack` (same parameters); measures geometry if not given."""
    return measure_stack(stack, geometry=geometry, **kwargs)[0]
