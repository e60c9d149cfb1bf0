"""Scenes with depth and a lens model: the frames near each pixel's depth combined by a multi-frame Wiener filter.

Choosing one frame per pixel (or blending two across a seam) keeps one frame's noise and that frame's defocus:
a pixel half a spacing from the nearest frame is seen slightly blurred, and frames a spacing or two away carry
the same detail at lower contrast with independent noise. With a lens model (the defocus OTF ``H(f, dz)`` of the
profile: F-number, pixel pitch, wavelength) every frame is an observation of the same in-focus image, so the
minimum-mean-square-error estimate of that image at a depth ``z`` from the frames ``Y_k`` at ``z_k`` is

    X(f) = H_0(f) * sum_k H_k(f) Y_k(f) / (sum_k |H_k(f)|^2 + sigma^2 / P(f)),   H_k = H(f, z_k - z)

(the multi-frame Wiener filter; ``H_0`` the in-focus OTF, the target, as the all-in-focus truth and a stack
composite are the lens's in-focus image; ``sigma`` the frames' noise, ``P`` a power-law signal spectrum fitted to
the composite). It is evaluated on a grid of depth labels (:func:`wiener_composite`), tile by tile with only the
labels each tile's pixels use, and each pixel interpolates between the two labels around its best focus. Only frames whose blur disc at the label is at most
:data:`REACH_DISC_PX` wide take part: a more defocused frame adds nothing above its low frequencies, and near a
depth edge those carry the other side's light spread by more than the edge band.

:func:`occlusion_focus_um` makes a best-focus map respect occlusion first: a pixel beside a nearer object is
taken from a frame in which that object's blur disc does not reach it.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np

from ..errors import ParameterError
from ..progress import progress
from .dff import frame_planes, row_bands
from .source import image_size, z_positions

#: Widest blur disc (px) of a frame that takes part in a label's Wiener combination. Measured on the simulated
#: depth scenes (bench_depth_scenes, oracle depth): 1.5 px loses 0.3-0.5 dB against 2.5-3.5 px, which agree within
#: 0.1 dB; all frames (no limit) lose 0.3-0.8 dB at depth edges.
REACH_DISC_PX = 3.0
#: Spacing of the depth labels, as a change of the blur disc's diameter (px): between labels the OTFs differ by
#: less than a quarter-pixel disc, which moves the MTF at Nyquist by < 2 %.
LABEL_DISC_PX = 0.5
#: At most this many labels per image (labels widen beyond it).
MAX_LABELS = 96
#: Tiles are filtered one at a time, each with only the labels its pixels use, from a block of at most this many
#: samples (FFT size, rows x columns): 2^20, a 4 MiB complex64 half spectrum. A label's filter costs ~0.33 ns x N
#: log2 N of its block's N samples up to ~10^6 (measured on this compositor's products and inverses, 128 x 160 to
#: 1024 x 1024), 10-25 % more per sample beyond (1620 x 1100, 1620 x 2200: the spectra leave the caches), and a
#: larger block also gathers the labels of more depths where the scene's depth varies (768 / 1024-px tiles cost
#: 3-20 % more CPU in session 13): :func:`tile_grid` chooses the tiles within this bound.
TILE_BLOCK_MAX_SAMPLES = 1 << 20
#: A filter's fixed cost (its calls, beyond its transforms) in the units of :func:`tile_grid`'s model
#: (N log2 N of the block's samples, ~0.33 ns each): ~30 µs.
TILE_OVERHEAD = 1e5
#: Splits whose label-blind cost is among this many least are costed with the labels their tiles would use
#: (:func:`tile_grid`), from each cell's range of labels (cells of at least :data:`TILE_LABEL_CELL_PX` px, at most
#: ~4096 cells: ~20 ms for the board's 3 planes; a range, not samples: labels sampled every 8 px miss the rare
#: ones of small tiles, and on the real board that chose 18 tiles, 2.8x the filters, for the 6 that every tile's
#: all labels call for)
TILE_LABEL_CANDIDATES = 24
TILE_LABEL_CELL_PX = 16
#: ... from a block with this margin (px, beyond the mirror pad) of real neighbours: the filters' support
TILE_MARGIN_PX = 16
#: Noise responses each probe frame's noise is estimated from (a median: ~1.25 / sqrt(n) = 0.25 % standard error,
#: against a spread of several per cent between the probe frames, whose least is taken, and a noise level that
#: enters the filter only through the noise-to-signal ratio; 2^20 took 5x the CPU for the same figures to 3
#: digits on the real board; all of a 24 MP frame's cost seconds)
NOISE_SAMPLES = 1 << 18


def occlusion_focus_um(zb: np.ndarray, um_per_px: float) -> np.ndarray:
    """Best focus that keeps nearer objects' blur off each pixel: ``max(zb(p), max_q zb(q) - c |p - q|)``.

    A scene point nearer the lens focuses further along the stage (larger ``z``). In a frame at ``z`` a nearer
    point ``q`` spreads over a disc of radius ``|z - zb(q)| / (2 N pitch)`` px, so pixel ``p`` is free of it
    when ``z >= zb(q) - c |p - q|`` with ``c = 2 N pitch`` (``um_per_px``). The upper envelope of these cones is a
    grey dilation by a cone with the octagonal distance (edge neighbours ``c``, diagonal ``c sqrt 2``; within 8 %
    of Euclidean): what repeated 3x3 dilations give once nothing changes, computed as four 1-D cone dilations by
    doubling shifts. Smooth best-focus changes (field curvature: far less than ``c`` per pixel) are left as they
    are.

    Parameters
    ----------
    zb : H x W or H x W x C float array
        Best focus (µm), larger = nearer the lens.
    um_per_px : float
        ``2 N pitch``: the defocus (µm) that widens the blur disc's radius by one pixel.
    """
    if not (np.isfinite(um_per_px) and um_per_px > 0):
        raise ParameterError(f"um_per_px must be > 0, got {um_per_px}", field="um_per_px",
                             fix="give 2 x F-number x pixel pitch (µm)")
    z = np.asarray(zb, dtype=np.float32)
    if z.ndim == 3:
        return np.stack([occlusion_focus_um(z[..., c], um_per_px) for c in range(z.shape[2])], axis=-1)
    out = z.copy()
    if out.size == 0:
        return out
    # The envelope of the cones is the grey dilation by the octagonal cone, what a 3x3 step (edge neighbours less
    # c, diagonal ones less c sqrt 2) repeated until nothing changes converges to: z(q) less the cost of the
    # cheapest chain of such steps from q. Such a chain takes at most two step directions, in any order, so the
    # dilation is the same as four 1-D cone dilations in turn (rows, columns, both diagonals), and each of those is
    # a few doublings: shifts by 1, 2, 4, ... px at c (or c sqrt 2) per px, up to the farthest shift that can still
    # raise a pixel (the map's range over the cost per px). ~90 passes over the map instead of ~8 per cone radius
    # (px) of the repeated 3x3 step.
    span = float(out.max()) - float(out.min())
    buf = np.empty(out.size, np.float32)
    h, w = out.shape
    for (dy, dx), per_px in (((0, 1), float(um_per_px)), ((1, 0), float(um_per_px)),
                             ((1, 1), float(um_per_px) * np.sqrt(2.0)), ((1, -1), float(um_per_px) * np.sqrt(2.0))):
        s = 1
        while s * per_px < span and s < max(h, w):
            sy, sx = s * dy, s * dx
            if sy >= h or abs(sx) >= w:
                break
            cost = np.float32(s * per_px)
            # pixel p from p - s d (then from p + s d): views of the same shape, the destination written in place
            a = out[sy:, max(sx, 0):w + min(sx, 0)]
            b = out[:h - sy, max(-sx, 0):w + min(-sx, 0)]
            for dst, src in ((a, b), (b, a)):
                t = np.subtract(src, cost, out=buf[:src.size].reshape(src.shape))
                np.maximum(dst, t, out=dst)
            s *= 2
    return out


def _labels(zb: np.ndarray, step_um: float) -> tuple[np.ndarray, float]:
    """Label depths covering ``zb`` (at most :data:`MAX_LABELS`) and their spacing."""
    lo, hi = float(np.min(zb)), float(np.max(zb))
    step = max(step_um, (hi - lo) / (MAX_LABELS - 1), 1e-6)
    n = max(2, int(np.ceil((hi - lo) / step)) + 1)
    return lo + step * np.arange(n), step


def _power_law(reference: np.ndarray, pad: int, pitch_um: float, h0_fns, sigmas) -> tuple[list, list, tuple]:
    """Per plane ``c`` of ``reference`` (``H x W x P``): ``A_c, beta_c`` of ``P(f) = A f^-beta`` (power per pixel, f
    in cycles/mm) fitted to the plane's spectrum (its in-focus OTF ``h0_fns[c]`` divided out, noise ``sigmas[c]``),
    and the padded FFT shape fitted on. One plane at a time (a whole image's spectrum each), on one float32
    frequency grid for all: float32 spectra, as the frames are (the fit is a line through ~10^6 log powers)."""
    from scipy import fft

    from ..optics.sweep import radial_table, rfft_radial_grid
    from .sweep import _pad, _signal_spectrum_model

    # Everything but the transform (already on every core) and the fit's few sums is per frequency: made in row
    # bands on the compositor's threads, the same values as whole (it was serial, ~0.25 s of the board's luma
    # and chroma calls with one core idle: bench_composite_speed_s17_overlap)
    a_sig, beta, f, shape = [], [], None, None
    for c in range(reference.shape[2]):
        img = np.asarray(reference[..., c], dtype=np.float32)
        padded, shape = _pad(img - np.float32(img.mean(dtype=np.float64)), pad)
        if f is None:
            f = rfft_radial_grid(shape, pitch_um, np.float32)
            fmin = 4.0 / (max(shape) * pitch_um * 1e-3)
        spec = fft.rfft2(padded, workers=-1)
        del padded
        power = np.empty(spec.shape, np.float32)
        hs2 = np.empty(spec.shape, np.float32)
        table = radial_table(h0_fns[c], f)
        scale = np.float32(1.0 / (shape[0] * shape[1]))

        def spectra(a: int, b: int, spec=spec, power=power, hs2=hs2, table=table, scale=scale) -> None:
            pw = np.multiply(spec.real[a:b], spec.real[a:b], out=power[a:b])
            pw += np.square(spec.imag[a:b])
            pw *= scale
            h0 = hs2[a:b]
            h0[...] = np.interp(f[a:b], *table)  # (as radial_on_grid(...).astype(np.float32))
            np.multiply(h0, h0, out=h0)

        row_bands(spectra, spec.shape[0])
        del spec
        a, b = _signal_spectrum_model(power, f, hs2, float(sigmas[c]) ** 2, fmin, map_rows=row_bands)
        a_sig.append(a)
        beta.append(b)
        del power, hs2
    return a_sig, beta, shape


def _mixed(planes: list[np.ndarray], rows: np.ndarray | None) -> list[np.ndarray]:
    """The filtered planes from the channels' planes: the channels, or their weighted sums (``rows``, P x C)."""
    if rows is None:
        return planes
    out, tmp = [], None
    for row in rows:
        # sum_c m_c p_c in the channels' order, each product rounded to float32 as written out in full, with one
        # scratch plane for the products instead of a fresh array per product and per partial sum
        acc = np.multiply(planes[0], np.float32(row[0]))
        for m, p in zip(row[1:], planes[1:]):
            tmp = np.multiply(p, np.float32(m), out=tmp if tmp is not None and tmp.shape == p.shape else None)
            acc += tmp
        out.append(acc)
    return out


def _plane_noise(planes: list[np.ndarray], rows: np.ndarray | None, max_samples: int) -> list[float]:
    """Immerkaer's noise estimate (:func:`~fieldcal.composite.sweep.estimate_noise_sigma`) of each plane, or of
    each weighted sum of the planes (``rows``, P x C), from at most about ``max_samples`` responses: the operator
    on every s-th interior row (s odd), all columns (an even spread, as the estimate's own sampling). The operator is separable
    (``[1, -2, 1]`` down, then across) and linear, so a weighted sum's responses are the channels' responses
    summed with the same weights: only the sampled rows are ever filtered or mixed (the whole planes mixed and
    filtered cost ~5x as much CPU, for the same median to its sampling error, ~0.1 %)."""
    from .sweep import estimate_noise_sigma, immerkaer_sigma

    h, w = planes[0].shape
    if h < 3 or w < 3:
        return [estimate_noise_sigma(p, max_samples=max_samples) for p in _mixed(planes, rows)]
    # an odd row step: the sampled rows run through every phase of a periodic structure (a JPEG's 8-px blocks, a
    # mosaic's 2-px period) as the estimate's row-major sampling does, not through the same rows of each block
    s = max(1, int(np.ceil((h - 2) * (w - 2) / max_samples))) | 1
    resp = []
    for p in planes:
        d = np.multiply(p[1:h - 1:s], np.float32(-2.0))
        d += p[0:h - 2:s]
        d += p[2:h:s]
        r = np.multiply(d[:, 1:w - 1], np.float32(-2.0))
        r += d[:, 0:w - 2]
        r += d[:, 2:w]
        resp.append(r)
    return [immerkaer_sigma(r) for r in _mixed(resp, rows)]


def probe_plane_sigma(stack, frames, *, geometry=None, lateral_colour: bool = False,
                      mix: np.ndarray | None = None) -> list[float]:
    """Pixel noise (frame units) per channel, or per weighted sum of the channels (``mix``'s rows, P x C).

    The least of Immerkaer's estimate over up to six frames spread over the stack's z order: texture only ever
    inflates the estimate, and far from focus a frame is smooth. The frames are read and measured on the
    compositor's threads, one frame (three whole planes) per thread in flight.
    """
    from .dff import map_in_order
    from .source import default_workers

    w, h = image_size(stack)
    channels = tuple(stack.channels)
    rows = None if mix is None else np.atleast_2d(np.asarray(mix, dtype=np.float64))
    z_all = z_positions(stack)
    idx = np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    zs = z_all[order].astype(np.float64)

    def probe_sigma(k: int) -> list[float]:
        """Frame k's (z order) noise per plane."""
        planes = frame_planes(stack, geometry, float(zs[k]), int(order[k]), channels, w, h,
                              lateral_colour=lateral_colour)
        return _plane_noise(planes, rows, NOISE_SAMPLES)

    probe = np.unique(np.linspace(0, len(order) - 1, min(len(order), 6)).round().astype(int))
    per_frame = list(map_in_order(probe_sigma, [int(k) for k in probe], ahead=default_workers()))
    floor = quantization_sigma(getattr(stack, "dtype", None), rows, len(channels))
    return [max(min(s[c] for s in per_frame), floor[c]) for c in range(len(per_frame[0]))]


def quantization_sigma(dtype, rows: np.ndarray | None, n_channels: int) -> list[float]:
    """The least noise frames of integer ``dtype`` carry, per channel or per weighted sum (``rows``, P x C):
    rounding to whole DN is uniform noise of sd 1/sqrt(12) DN in each channel. Immerkaer's median reads 0 where
    more than half of a frame is flat -- a subject on a black or white background, clipped, or smoothed to
    constant blocks by JPEG -- and a Wiener filter told "no noise" inverts its OTF unregularised (the board on a
    black canvas: noise 0.0 read, the composite 21 DN RMS off the same board composited alone). Float frames: 0."""
    q = 1.0 / np.sqrt(12.0) if dtype is not None and np.dtype(dtype).kind in "ui" else 0.0
    if rows is None:
        return [q] * n_channels
    return [q * float(np.sqrt(np.sum(np.square(r)))) for r in np.atleast_2d(rows)]


def tile_grid(w: int, h: int, margin: int, workers: int, max_samples: int | None = None,
              label_maps=None) -> tuple[list[int], list[int], int, int]:
    """The Wiener step's tiles: column and row edges splitting a ``w x h`` image evenly (cores differing by at
    most a pixel, each pixel in exactly one tile) and the FFT block (``nb_y x nb_x``, the largest core with
    ``margin`` on each side, :func:`scipy.fft.next_fast_len`) they are all filtered on.

    Every tile runs the same transforms once per label it uses, so the step's cost is ~ tiles x labels x the
    block's FFT cost, ``N log2 N`` for N samples (+ :data:`TILE_OVERHEAD`). On a scene whose every tile uses
    every label (the real board) the labels are a common factor, and the split chosen is the one of least
    ``slots x (N log2 N + overhead)`` with blocks of at most ``max_samples`` (default
    :data:`TILE_BLOCK_MAX_SAMPLES`), ``slots`` the tile count rounded up to a multiple of ``workers`` (the tiles
    run one per compositor thread: a last round with threads idle costs as if they worked, and so does one tile
    alone, whose FFTs on all threads left the rest serial: a 1024 x 768 image as one tile took 16 % less CPU
    than as four 512-px squares and 30 % more wall on two threads). Ties go to fewer tiles; cores are at least
    8 px (and at most 128 tiles a side). Small margins and partial tiles are what this saves against fixed square
    tiles: 2048 x 1536 on two threads is 3 x 2 tiles on 864 x 768 blocks (rows x columns; 512-px squares: 12 on
    600 x 600, 4 % more of the model's cost), 1920 x 1080 3 x 2 on 625 x 720 (12 512-px squares: 58 % more).

    Where the depth varies slowly, a tile uses only the labels of its own depths, and larger tiles then use more
    labels each (a slope across a 2048 x 1536 image: 3 x 2 tiles took 6 % more CPU than 512-px squares).
    ``label_maps`` (``(ys, xs, lo, hi, forward)``: cells starting at rows ``ys`` and columns ``xs``, per plane each
    cell's least and greatest label below its needed pixels, ``lo > hi`` where none is needed, and the forward
    transforms a tile with work runs, frames x planes) makes the cost the labels' own: the
    :data:`TILE_LABEL_CANDIDATES` splits of least label-blind cost are costed as ``(sum over tiles of the
    transforms each would run + the idle slots at the tiles' mean) x (N log2 N + overhead)``, a tile's filters the
    labels from ``lo`` to ``hi + 1`` of the cells it touches (a cell's range may hold labels its pixels do not
    use: the count errs towards every label, the label-blind choice), its forward transforms every frame's (on
    the board the 7 frames' 3 planes, a third as many as its 66 filters: without them 18 tiles, 1105 filters,
    looked as cheap as 6 tiles' 396 and took 6-14 % more CPU). Where every tile uses every label
    (the board) that is the label-blind cost times the labels, and the same split is chosen."""
    from scipy import fft

    max_samples = TILE_BLOCK_MAX_SAMPLES if max_samples is None else int(max_samples)
    workers = max(1, int(workers))

    def splits(n: int) -> tuple[np.ndarray, np.ndarray]:
        # 1 .. n / 8 tiles along a side (at most 128: a 6000-px side's best is ~6), each with its block's side
        k = np.arange(1, max(1, min(n // 8, 128)) + 1)
        return k, np.array([fft.next_fast_len(-(-n // int(j)) + 2 * margin, real=True) for j in k])

    kx, bx = splits(w)
    ky, by = splits(h)
    n = ky[:, None] * kx[None, :]
    samples = by[:, None].astype(np.float64) * bx[None, :]
    slots = -(-n // workers) * workers
    cost = slots * (samples * np.log2(np.maximum(samples, 2.0)) + TILE_OVERHEAD)
    over = samples > max_samples
    # within the bound the least cost (ties: fewer tiles); only if no block is within it, the smallest block
    order = np.lexsort((n.ravel(), cost.ravel(), np.where(over, samples, 0.0).ravel(), over.ravel()))
    if label_maps is not None and not over.ravel()[order[0]]:
        ys, xs, lo, hi, forward = label_maps
        ye = np.append(np.asarray(ys)[1:], h) - 1  # each cell's last row and column
        xe = np.append(np.asarray(xs)[1:], w) - 1
        best = None
        for i in order[:TILE_LABEL_CANDIDATES]:
            if over.ravel()[i]:
                break
            iy, ix = np.unravel_index(i, n.shape)
            k_y, k_x, n_t = int(ky[iy]), int(kx[ix]), int(n.ravel()[i])
            # the tiles a cell touches: those of its first and of its last row and column (the even split's edges)
            tid = np.concatenate([(((np.asarray(r) * k_y) // h)[:, None] * k_x + ((np.asarray(c) * k_x) // w)[None, :])
                                  .ravel() for r in (ys, ye) for c in (xs, xe)])
            filters, busy = np.zeros(n_t), np.zeros(n_t, bool)
            for lo_c, hi_c in zip(lo, hi):
                sel = np.tile((lo_c <= hi_c).ravel(), 4)
                lo_s, hi_s, t = np.tile(lo_c.ravel(), 4)[sel], np.tile(hi_c.ravel(), 4)[sel], tid[sel]
                n_lab = int(hi_s.max()) + 3 if hi_s.size else 3
                # each range [lo, hi + 1] as +1 at lo and -1 past hi + 1, summed over the cells; covered where > 0
                marks = np.bincount(t * n_lab + lo_s, minlength=n_t * n_lab) - np.bincount(t * n_lab + hi_s + 2,
                                                                                          minlength=n_t * n_lab)
                filters += (np.cumsum(marks.reshape(n_t, n_lab), axis=1)[:, :-1] > 0).sum(axis=1)
                busy |= np.bincount(t, minlength=n_t) > 0
            filters += forward * busy  # each tile with work reads and transforms its frames' planes
            total = (filters.sum() + (slots.ravel()[i] - n_t) * filters.mean()) * (
                samples.ravel()[i] * np.log2(max(samples.ravel()[i], 2.0)) + TILE_OVERHEAD)
            if best is None or total < best[0]:  # (ties: the label-blind order)
                best = (total, i)
        order = [best[1]]
    iy, ix = np.unravel_index(order[0], n.shape)
    nx, ny = int(kx[ix]), int(ky[iy])
    return [w * i // nx for i in range(nx + 1)], [h * i // ny for i in range(ny + 1)], int(by[iy]), int(bx[ix])


def _pad_px(reach_disc_px: float) -> int:
    """Mirror padding (px) of the power law's whole-image spectrum and of the tiles' blocks: the widest blur
    disc's radius that takes part, and a margin for the filters' tails."""
    return int(np.ceil(0.5 * reach_disc_px)) + 16


@dataclass(frozen=True)
class ReferenceSignal:
    """A reference composite as the Wiener step filters it: its planes (``H x W`` float32 each: the channels, or
    the rows of a mix), each plane's signal power law ``P(f) = a_sig f^-beta`` fitted to their spectra (the padded
    FFT ``shape`` fitted on) with the noise ``sigma`` per plane taken out (:func:`reference_signal`)."""

    planes: list
    a_sig: list
    beta: list
    shape: tuple
    sigma: list
    #: the planes grouped by label spacing, each group's planes mixed as its own matrix (as the call filters them)
    groups: list


def _plane_setup(channels: tuple, mix, label_um) -> tuple:
    """The filtered planes of a Wiener call: the mix (float64, validated) and its float32 rows, the depth
    weights, each plane's OTF channel, its label spacing, and the planes grouped by spacing."""
    m32 = depth_w = None
    if mix is not None:
        mix = np.atleast_2d(np.asarray(mix, dtype=np.float64))
        if mix.shape[1] != len(channels) or not np.all(np.isfinite(mix)) or np.any(np.abs(mix).sum(axis=1) == 0):
            raise ParameterError(f"plane weights {mix.tolist()} do not match the channels {channels}", field="mix",
                                 fix="give one row of weights per plane, one weight per channel, not all zero")
        m32 = mix.astype(np.float32)
        depth_w = np.abs(m32) / np.abs(m32).sum(axis=1, keepdims=True)
        # each plane's OTFs are looked up as its heaviest channel's (the same in every channel)
        fch = tuple(channels[int(np.argmax(np.abs(row)))] for row in mix)
    else:
        fch = tuple(channels)
    n_p = len(fch)
    spacing = [label_um] * n_p if label_um is None or np.ndim(label_um) == 0 else list(label_um)
    if len(spacing) != n_p:
        raise ParameterError(f"{len(spacing)} label spacings for {n_p} planes", field="label_um",
                             fix="give one label spacing (µm), or one per filtered plane")
    spacing = [float(v or 0.0) for v in spacing]
    # planes of one spacing are filtered together, on their own labels: each group exactly as a call of its own
    plane_groups = [[c for c in range(n_p) if spacing[c] == v] for v in dict.fromkeys(spacing)]
    return mix, m32, depth_w, fch, spacing, plane_groups


def _plane_sigma(sigma, n_planes: int) -> list[float]:
    """Pixel noise per filtered plane, checked to be one per plane."""
    sigma = [float(v) for v in sigma]
    if len(sigma) != n_planes:
        raise ParameterError(f"{len(sigma)} plane noise levels for {n_planes} planes", field="plane_sigma",
                             fix="give one noise level per filtered plane (probe_plane_sigma with the same mix)")
    return sigma


def _group_planes(a: np.ndarray, planes: list, weights, n_groups: int) -> np.ndarray:
    """``a``'s planes of one group: a mix's rows multiplied as the group's own matrix (so the products round as
    they would in a call of its own), or the group's channels."""
    if weights is not None:
        return np.asarray(a, dtype=np.float32) @ weights[planes].T
    return a if n_groups == 1 else np.asarray(a)[..., planes]


def reference_signal(reference: np.ndarray, model, channels, sigma, *, mix=None, label_um=None,
                     reach_disc_px: float = REACH_DISC_PX) -> ReferenceSignal:
    """The reference's planes and signal power laws for :func:`wiener_composite` (its ``signal``), made apart so
    that a caller can fit them on a thread while it does other work (the composite: beside the occlusion cones).

    ``channels`` are the stack's, ``sigma`` the pixel noise per filtered plane (as ``plane_sigma``); ``model``,
    ``mix``, ``label_um`` and ``reach_disc_px`` as the call of :func:`wiener_composite` this is for.
    """
    mix, m32, _, fch, _, plane_groups = _plane_setup(tuple(channels), mix, label_um)
    sigma = _plane_sigma(sigma, len(fch))
    pitch = float(model.pixel_pitch_um)
    pad = _pad_px(reach_disc_px)
    planes_out, a_sig, beta, shape = [None] * len(fch), [0.0] * len(fch), [0.0] * len(fch), None
    for planes in plane_groups:
        ref_g = _group_planes(reference, planes, m32, len(plane_groups))
        # the signal's power law per plane, one plane at a time: each fit holds a whole image's spectrum (two at
        # once on threads raised the composite's peak by ~200 MB for ~0.1 s)
        a_g, b_g, shape = _power_law(ref_g, pad, pitch, [lambda t, ch=fch[c]: model.defocus_otf(t, 0.0, ch)
                                                          for c in planes], [max(sigma[c], 1e-6) for c in planes])
        for j, c in enumerate(planes):
            planes_out[c], a_sig[c], beta[c] = ref_g[..., j], a_g[j], b_g[j]
    return ReferenceSignal(planes_out, a_sig, beta, shape, sigma, plane_groups)


def wiener_composite(stack, zb: np.ndarray, model, frames, reference: np.ndarray, *, geometry=None,
                     lateral_colour: bool = False, reach_disc_px: float = REACH_DISC_PX,
                     noise_sigma=None, label_um: float | None = None, needed: np.ndarray | None = None,
                     mix: np.ndarray | None = None, plane_sigma=None, signal: ReferenceSignal | None = None,
                     quiet: bool = False) -> tuple[np.ndarray, dict]:
    """All-in-focus image of a scene with depth from a best-focus map and the lens's defocus OTF.

    Parameters
    ----------
    stack : FrameSource
        The frames.
    zb : H x W x C float32
        Best focus per pixel and channel (µm, output geometry).
    model : LensModel
        Gives ``defocus_otf``, ``f_number`` and ``pixel_pitch_um``.
    frames : array of int
        File indices to use.
    reference : H x W x C array
        A composite of the same scene (e.g. the blended one) for the signal spectrum.
    geometry : lens model, optional
        Warps frames to the output geometry (None: frames are registered).
    reach_disc_px : float
        Frames blurred by a wider disc at a label take no part in it.
    noise_sigma : sequence of float, optional
        Pixel noise (frame units) per channel, e.g. from the camera's noise model
        (:func:`fieldcal.composite.sweep.sensor_noise_sigma`); default: estimated from the frames.
    label_um : float or sequence of float, optional
        Spacing of the depth labels (µm); default :data:`LABEL_DISC_PX` of blur-disc diameter. A coarser one
        where the depth map is known no better (a defocus measured from the stack: a fraction of a frame step).
        One per filtered plane (channel, or row of ``mix``) filters each group of planes with one spacing on its
        own labels (as if by a call of its own, the same numbers: its mix, depth, labels and power law its own),
        all in one pass over the tiles: each tile's frames are read, warped and transformed once for all planes.
    needed : H x W bool array, optional
        Where the combination will be used (default everywhere); elsewhere the output is ``reference``'s and no
        label is filtered for those pixels alone.
    mix : P x C array, optional
        Filter these weighted sums of the channels instead (e.g. YCbCr's rows, or some of them), for a model whose
        OTF is the same in every channel (a measured defocus): each plane's OTF is its heaviest channel's, its
        depth the channels' weighted by the absolute weights, and ``reference``, ``needed`` and the output are
        in the planes (the caller mixes them back).
    plane_sigma : sequence of float, optional
        Pixel noise per filtered plane as :func:`probe_plane_sigma` measures it with the same ``mix`` (calls
        filtering planes of one mix apart then read the probe frames once); overrides ``noise_sigma``.
    signal : ReferenceSignal, optional
        ``reference``'s planes and power laws made beforehand by :func:`reference_signal` with this call's model,
        mix, label spacings and ``plane_sigma`` (e.g. on a thread while the caller did other work); ``reference``
        is then not read. The same numbers as made here.

    Returns
    -------
    (image, info)
        Float32 ``H x W x C`` (``H x W x P`` with ``mix``) in the frames' units, and the noise level per channel
        (plane), the number of tiles and of label filters applied (tiles x labels x channels), the labels'
        spacing (µm) and the mean number of frames per label. With several label spacings, ``info["groups"]``
        holds these per group of planes (as each group's own call would give them, and ``plane_index``: which
        planes) and the top level the planes' noise, the tiles and all filters.
    """
    from scipy import fft

    n_f = getattr(model, "f_number", None)
    if not n_f:
        raise ParameterError("the lens model has no F-number, so no defocus OTF", field="f_number",
                             fix="calibrate with the F-number recorded, or composite without the Wiener step")
    w, h = image_size(stack)
    channels = tuple(stack.channels)
    mix, _, depth_w, fch, spacing, plane_groups = _plane_setup(channels, mix, label_um)
    n_p = len(fch)
    group_of = [next(g for g, planes in enumerate(plane_groups) if c in planes) for c in range(n_p)]

    pitch = float(model.pixel_pitch_um)
    px_um = float(n_f) * pitch  # defocus that widens the blur disc's diameter by 1 px
    z_all = z_positions(stack)
    idx = np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    zs = z_all[order].astype(np.float64)
    reach = reach_disc_px * px_um
    pad = _pad_px(reach_disc_px)

    from .dff import map_in_order
    from .source import default_workers

    if plane_sigma is not None:
        sigma = _plane_sigma(plane_sigma, n_p)
    elif noise_sigma is None:
        sigma = probe_plane_sigma(stack, frames, geometry=geometry, lateral_colour=lateral_colour, mix=mix)
    else:
        sigma = [float(v) for v in np.broadcast_to(np.asarray(noise_sigma, dtype=np.float64), (len(channels),))]
        if mix is not None:  # independent noise per channel
            sigma = [float(np.sqrt(np.sum(row ** 2 * np.square(sigma)))) for row in mix]

    # the reference's planes and power laws (made by the caller beforehand, or here), then per group its planes
    # of the depth map (a mix's rows multiplied as the group's own matrix) and its labels
    if signal is None:
        signal = reference_signal(reference, model, channels, sigma, mix=mix, label_um=label_um,
                                  reach_disc_px=reach_disc_px)
    elif len(signal.planes) != n_p or signal.sigma != sigma or signal.groups != plane_groups:
        raise ParameterError(f"the reference signal was made for {len(signal.planes)} planes (grouped "
                             f"{signal.groups}) with noise {signal.sigma}, this call filters {n_p} (grouped "
                             f"{plane_groups}) with noise {sigma}", field="signal",
                             fix="make it with reference_signal for this call's mix, label spacings and noise")
    ref_planes, a_sig, beta, shape = list(signal.planes), signal.a_sig, signal.beta, signal.shape
    zb_planes = [None] * n_p
    labels, steps = [], []
    for planes in plane_groups:
        zb_g = _group_planes(zb, planes, depth_w, len(plane_groups))
        lab_g, step_g = _labels(zb_g, max(LABEL_DISC_PX * px_um, spacing[planes[0]]))
        labels.append(lab_g)
        steps.append(step_g)
        for j, c in enumerate(planes):
            zb_planes[c] = zb_g[..., j]
    del signal
    mean = [float(np.mean(ref_planes[c])) for c in range(n_p)]

    # per plane: label index below each pixel (on its group's labels) and the fraction towards the next
    lower = [np.empty((h, w), np.int16) for _ in fch]
    frac = [np.empty((h, w), np.float32) for _ in fch]
    # ... and per row, each column cell's least and greatest label below a needed pixel (the tiles' cost)
    cell = max(TILE_LABEL_CELL_PX, int(np.ceil(np.sqrt(h * w / 4096.0))))
    cx0 = np.arange(0, w, cell)
    row_lo = [np.empty((h, len(cx0)), np.int16) for _ in fch]
    row_hi = [np.empty((h, len(cx0)), np.int16) for _ in fch]
    row_any = None if needed is None else np.empty((h, len(cx0)), bool)

    def label_rows(a: int, b: int) -> None:  # per pixel: in row bands on the compositor's threads
        for c in range(n_p):
            lab, step, n_lab = labels[group_of[c]], steps[group_of[c]], len(labels[group_of[c]])
            # in place on one float64 plane (the same numbers as the expression written out: the label below is
            # integral, so subtracting it as float64 or as its int16 is the same)
            t = zb_planes[c][a:b].astype(np.float64)
            t -= lab[0]
            t /= step
            below = np.floor(t)
            np.clip(below, 0, n_lab - 2, out=below)
            # int16 (at most MAX_LABELS labels): the tiles' stable sorts by label are then radix sorts
            lower[c][a:b] = below
            t -= below
            frac[c][a:b] = np.clip(t, 0.0, 1.0, out=t)
            # (over all the cell's pixels, needed or not: a wider range errs towards the label-blind choice)
            row_lo[c][a:b] = np.minimum.reduceat(lower[c][a:b], cx0, axis=1)
            row_hi[c][a:b] = np.maximum.reduceat(lower[c][a:b], cx0, axis=1)
        if needed is not None:
            row_any[a:b] = np.logical_or.reduceat(np.asarray(needed[a:b], bool), cx0, axis=1)

    row_bands(label_rows, h)
    zb_planes = zb_g = None  # (the mixed depth maps dropped: the labels are all the tiles need)

    from ..optics.sweep import rfft_radial_grid
    from .warp import frame_maps, warp_region

    # Tiles: each core is filtered from a block with a margin of real neighbours (mirrored only at the image's
    # border), and only with the labels and frames its own pixels need: a label's filter then costs a small FFT
    # where the field curvature puts its pixels, not one of the whole image.
    margin = pad + TILE_MARGIN_PX
    # the tiles, costed with the labels each would use (each cell's range of labels)
    cy0 = np.arange(0, h, cell)
    cell_lo = [np.minimum.reduceat(r, cy0, axis=0).astype(np.intp) for r in row_lo]
    cell_hi = [np.maximum.reduceat(r, cy0, axis=0).astype(np.intp) for r in row_hi]
    if row_any is not None:  # cells without a needed pixel: no labels (lo > hi)
        empty = ~np.logical_or.reduceat(row_any, cy0, axis=0)
        for lo_c, hi_c in zip(cell_lo, cell_hi):
            lo_c[empty], hi_c[empty] = 1, 0
    edges_x, edges_y, nb_y, nb_x = tile_grid(w, h, margin, default_workers(),
                                             label_maps=(cy0, cx0, cell_lo, cell_hi, len(zs) * n_p))
    row_lo = row_hi = row_any = None
    f_grid = rfft_radial_grid((nb_y, nb_x), pitch)
    fmin = 4.0 / (max(shape) * pitch * 1e-3)  # the power law as fitted on the whole image
    # OTFs are radial: each one is a 1-D table gathered onto the grid through one index
    n_table = 4096
    f_step = float(f_grid.max()) * (1 + 1e-9) / (n_table - 1)
    f_table = np.arange(n_table) * f_step
    f_index = np.rint(f_grid / f_step).astype(np.intp)  # np.take with native indices: no cast per gather
    # |f| is the same on rows i and nb_y - i (fftfreq's negative half mirrors the positive one exactly): a gain
    # is gathered on the rows 0 .. nb_y // 2 only and read backwards for the others (half the gathers)
    half = nb_y // 2 + 1
    mirror = slice(nb_y - half, 0, -1)
    f_half = f_index[:half]
    if not np.array_equal(f_index[half:], f_half[mirror]):  # never with fftfreq's grid; kept exact regardless
        half, mirror, f_half = nb_y, slice(0, 0), f_index

    # a model whose defocus is known only within an error (a depth measured from the stack itself) gives the
    # OTF's mean and mean square over that error: the Wiener filter of a random OTF (mean in the numerator, mean
    # square in the denominator) never inverts more blur than the depth is sure of
    moments = getattr(model, "defocus_otf_moments", None)

    otf_cache: dict[tuple[float, str], tuple[np.ndarray, np.ndarray]] = {}

    def otf(dz_um: float, ch: str) -> tuple[np.ndarray, np.ndarray]:
        """The frame's OTF at defocus ``dz_um`` on the 1-D table: its mean and its mean square. Kept per
        (defocus, channel): labels a whole number of label steps from different frames meet the same defocus
        (on the real board 18 distinct ones of 176 asked for; each a few Bessel tables over the depth's error)."""
        hit = otf_cache.get((dz_um, ch))
        if hit is not None:
            return hit
        if moments is None:
            m1 = np.asarray(model.defocus_otf(f_table, dz_um, ch), dtype=np.float64)
            hit = m1, m1 * m1
        else:
            m1, m2 = moments(f_table, dz_um, ch)
            hit = np.asarray(m1, np.float64), np.asarray(m2, np.float64)
        otf_cache[(dz_um, ch)] = hit
        return hit

    h0s = [np.asarray(model.defocus_otf(f_table, 0.0, ch), dtype=np.float64) for ch in fch]
    # the noise-to-signal ratio is radial too (a power law of |f|)
    nsrs = [sigma[c] ** 2 / (a_sig[c] * np.maximum(f_table, fmin) ** (-beta[c])) for c in range(len(fch))]
    gain_cache: dict[tuple[int, int], list[np.ndarray]] = {}

    def gains(l: int, c: int, near: np.ndarray) -> list[np.ndarray]:
        """Each frame's weight in label ``l``'s Wiener filter, ``H_0 H_k / (sum_j |H_j|^2 + NSR)``, as 1-D tables
        over |f| (float32 values held as complex64): computed once per (label, channel) for all tiles (32 kB each;
        tiles on threads may both compute one, with the same result), gathered onto a tile's grid through
        ``f_index``."""
        hit = gain_cache.get((l, c))  # (a plane's labels are its group's: (l, c) names one label)
        if hit is None:
            ms = [otf(float(zs[k] - labels[group_of[c]][l]), fch[c]) for k in near]
            scale = h0s[c] / (nsrs[c] + sum(m2 for _, m2 in ms))
            # stored as complex64 (zero imaginary part): the gathered gain then multiplies the complex64 spectra
            # as it is, where a float32 one was cast to complex64 in each product first (the same numbers)
            hit = [(m1 * scale).astype(np.complex64) for m1, _ in ms]
            gain_cache[(l, c)] = hit
        return hit

    maps = {}
    tiles = [(x0, y0, x1, y1) for y0, y1 in pairwise(edges_y) for x0, x1 in pairwise(edges_x)]
    # tiles run on the compositor's threads, a core each: FFTs split over threads as well would only add their
    # hand-overs (~15 % more CPU for the same transforms, measured on two cores)
    fft_workers = 1 if len(tiles) > 1 and default_workers() > 1 else -1

    def block(k: int, bx0: int, by0: int, bx1: int, by1: int, top: int, left: int) -> list[np.ndarray]:
        """Frame k (z order) over the block, mirror-padded to the FFT size, mean removed, rfft2 per channel."""
        if k not in maps:
            maps[k] = frame_maps(geometry, float(zs[k]), channels, lateral_colour)
        bottom, right = nb_y - (by1 - by0) - top, nb_x - (bx1 - bx0) - left
        out = []
        if mix is not None and len(maps[k]) == 1 and len(channels) <= 4:
            # one map for all channels: each plane's weighted sum of the interleaved channels, less its mean, in
            # one pass (OpenCV's transform: the weights and the offset as one affine row; the same sums to float32
            # rounding) instead of three over strided channel views
            fm = maps[k][0]
            part = np.ascontiguousarray(warp_region(stack, int(order[k]), fm, bx0, by0, bx1, by1))
            for c in range(n_p):
                row = np.append(mix[c, list(fm.channels)], -mean[c]).astype(np.float32)[None]
                out.append(cv2.transform(part, row).reshape(part.shape[:2]))
        else:
            planes = [None] * len(channels)
            for fm in maps[k]:
                part = warp_region(stack, int(order[k]), fm, bx0, by0, bx1, by1)
                for j, c in enumerate(fm.channels):
                    planes[c] = part[..., j]
            out = [p - np.float32(mean[c]) for c, p in enumerate(_mixed(planes, mix))]
        # mirrored to the FFT size (OpenCV's BORDER_REFLECT is NumPy's "symmetric": the same samples, one pass)
        return [fft.rfft2(cv2.copyMakeBorder(p, top, bottom, left, right, cv2.BORDER_REFLECT),
                          workers=fft_workers).astype(np.complex64, copy=False) for p in out]

    if needed is None:
        out = np.zeros((h, w, n_p), np.float32)
    else:
        # the reference where the combination is not needed, put in place now: the tiles write only the needed
        # pixels, and the mixed reference planes need not be held through the tiles
        out = np.empty((h, w, n_p), np.float32)
        for c in range(n_p):
            out[..., c] = ref_planes[c]
    del ref_planes

    def tile(core: tuple[int, int, int, int]) -> tuple[list[int], list[list[int]]]:
        """Filter one tile (its core ``x0, y0, x1, y1``) into ``out`` (tiles' cores never overlap, so threads may
        run them concurrently); returns per group the number of filters and the frames each label used."""
        x0, y0, x1, y1 = core
        n_filters, n_frames_used = [0] * len(plane_groups), [[] for _ in plane_groups]
        bx0, by0, bx1, by1 = max(0, x0 - margin), max(0, y0 - margin), min(w, x1 + margin), min(h, y1 + margin)
        top, left = margin - (y0 - by0), margin - (x0 - bx0)  # mirrored rows/columns above/left of the block
        need = None if needed is None else needed[y0:y1, x0:x1]
        if need is not None and not need.any():
            return n_filters, n_frames_used
        # per channel, the tile's pixels (the needed ones) grouped by their lower label: each label's filter is
        # then written only where it is used, and inverted only on the rows that hold those pixels
        groups, used = [], set()
        for c in range(n_p):
            n_lab = len(labels[group_of[c]])
            l0 = lower[c][y0:y1, x0:x1].ravel()
            pix = np.arange(l0.size, dtype=np.int32) if need is None else np.flatnonzero(need.ravel()).astype(np.int32)
            # np.take, not fancy indexing: the same elements, ~30 % faster gathers
            pix = np.take(pix, np.argsort(np.take(l0, pix), kind="stable"))
            lab = np.take(l0, pix)
            # the labels present: the starts of the sorted runs (np.unique would sort them again)
            present = lab[np.flatnonzero(np.diff(lab, prepend=lab[:1] - 1))] if lab.size else lab
            bounds = dict(zip(present.tolist(), zip(np.searchsorted(lab, present, side="left").tolist(),
                                                    np.searchsorted(lab, present, side="right").tolist())))
            fr = np.take(frac[c][y0:y1, x0:x1].ravel(), pix)
            # per pixel in that order: its row, its column in the block's inverse (past the margin) and its weights
            # for the label below and above it
            groups.append((pix, pix // (x1 - x0), pix % (x1 - x0) + margin, 1.0 - fr, fr, bounds))
            used |= {(c, int(l)) for l in present} | {(c, int(min(l + 1, n_lab - 1))) for l in present}
        # the labels of all groups in order of depth (a group's own in its order): the frames each needs then
        # advance together, and a tile's frames are read once for every plane
        labels_used = sorted({(float(labels[group_of[c]][l]), group_of[c], l) for c, l in used})
        tw = x1 - x0
        row_mark = np.zeros(y1 - y0, bool)
        # each plane's sums in its pixels' label order: a label's two groups are slices there (no scattered
        # read-modify-write per filter), put in place once per tile
        acc = [np.zeros(len(g[0]), np.float32) for g in groups]
        spectra: dict[int, list[np.ndarray]] = {}
        scratch = None  # the second and later frames' products, one buffer per tile
        for zl, grp, l in labels_used:
            near = np.flatnonzero(np.abs(zs - zl) <= reach)
            below, above = np.searchsorted(zs, zl, side="right") - 1, np.searchsorted(zs, zl, side="left")
            near = np.union1d(near, [k for k in (below, above) if 0 <= k < len(zs)]).astype(int)
            for k in [k for k in spectra if k < near[0]]:
                del spectra[k]
            for k in near:
                if k not in spectra:
                    spectra[k] = block(int(k), bx0, by0, bx1, by1, top, left)
            n_frames_used[grp].append(len(near))
            for c in plane_groups[grp]:
                if (c, l) not in used:
                    continue
                pix, rr, cc, w_lo, w_hi, bounds = groups[c]
                # pixels with this label below them (weight 1 - frac) and above them (weight frac)
                here = [(slice(*bounds[m]), w_lo if m == l else w_hi) for m in (l, l - 1) if m in bounds]
                if not here:
                    continue
                n_filters[grp] += 1
                x = None
                for g, k in zip(gains(l, c, near), near):
                    # the gain on the rows 0 .. nb_y // 2, read backwards for the mirrored rows: the same
                    # products as the whole grid's gather times the spectrum
                    gh, y = np.take(g, f_half), spectra[k][c]
                    if x is None:
                        term = x = np.empty(y.shape, np.complex64)
                    else:
                        term = scratch = scratch if scratch is not None else np.empty(y.shape, np.complex64)
                    np.multiply(gh, y[:half], out=term[:half])
                    np.multiply(gh[mirror], y[half:], out=term[half:])
                    if term is not x:
                        np.add(x, term, out=x)
                x[0, 0] = np.mean([spectra[k][c][0, 0] for k in near])  # keep the mean
                # irfft2 is a complex inverse along the columns, then a real one along the rows: the second only
                # on the rows this label's pixels are in (the same numbers as the whole inverse)
                row_mark[:] = False
                for sl, _ in here:
                    row_mark[rr[sl]] = True
                rows = np.flatnonzero(row_mark)
                row_at = (np.cumsum(row_mark) - 1).astype(np.int32)
                # (both in place: x and col are this filter's own, and pocketfft then skips an output array)
                col = fft.ifft(x, axis=0, workers=fft_workers, overwrite_x=True)[margin + rows]
                img = fft.irfft(col, n=nb_x, axis=1, workers=fft_workers, overwrite_x=True).ravel()
                for sl, wgt in here:
                    v = np.take(img, np.take(row_at, rr[sl]) * nb_x + cc[sl])
                    v += np.float32(mean[c])
                    v *= wgt[sl]
                    acc[c][sl] += v
        for c in range(n_p):
            if need is None:
                plane = np.zeros((y1 - y0) * tw, np.float32)
                plane[groups[c][0]] = acc[c]
                out[y0:y1, x0:x1, c] = plane.reshape(y1 - y0, tw)
            else:  # the needed pixels only (the others hold the reference)
                out[y0:y1, x0:x1, c][groups[c][1], groups[c][2] - margin] = acc[c]
        return n_filters, n_frames_used

    n_frames_used, n_filters = [[] for _ in plane_groups], [0] * len(plane_groups)
    for nf, used_frames in progress(map_in_order(tile, tiles), total=len(tiles), desc="Wiener by depth",
                                    quiet=quiet, unit="tile"):
        for g in range(len(plane_groups)):
            n_filters[g] += nf[g]
            n_frames_used[g] += used_frames[g]

    def group_info(g: int) -> dict:
        planes = plane_groups[g]
        info = {"noise_sigma": [round(sigma[c], 3) for c in planes], "tiles": len(tiles), "filters": n_filters[g],
                "label_um": round(steps[g], 3), "frames_per_label": round(float(np.mean(n_frames_used[g])), 2)
                if n_frames_used[g] else 0.0}
        if mix is not None:
            info["planes"] = [[round(float(m), 4) for m in mix[c]] for c in planes]
        return info

    if len(plane_groups) == 1:
        return out, group_info(0)
    info = {"noise_sigma": [round(s, 3) for s in sigma], "tiles": len(tiles), "filters": sum(n_filters),
            "groups": [{**group_info(g), "plane_index": planes} for g, planes in enumerate(plane_groups)]}
    return out, info
