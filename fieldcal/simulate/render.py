"""The frame renderer: what the simulated camera records at a stage position.

Spatially varying defocus without a kernel per pixel: the (reflect-padded) scene is Fourier transformed once
per channel; for each of a few *blur levels* the spectrum is multiplied by the analytic OTF of
:func:`fieldcal.optics.through_focus_otf` and transformed back, and every pixel linearly interpolates between the two levels
that bracket its own defocus. Levels are spaced geometrically in blur-disc diameter (ratio ``level_ratio``)
above a floor of ``level_floor_px`` pixels, with an in-focus level at zero, so the interpolation error is a
bounded fraction of the local blur change (docs/simulator.md gives the bound the tests check).

The scene is fixed, so each level is computed once, when a frame first needs it, and kept
(:class:`fieldcal.simulate.levels.LevelStack`); a frame costs a per-pixel level map (above 1 Mpx evaluated on a
coarse grid and interpolated: it is smooth), a two-level gather, the warp and the sensor, with the channels
rendered in parallel threads. docs/simulator.md ("Speed") has the figures and the agreement with the per-frame FFT path.

Astigmatic channels (``astigmatism="anisotropic"``, the default) blur with the elliptical, radially oriented
defocus PSF instead of a disc: the spectrum is split into K orientation wedges, each with its own level stack,
and each pixel blends each wedge's levels at its own diameter along that wedge's direction
(:mod:`fieldcal.simulate.astigmatism`). Channels without astigmatism render as before.

With ``optics="wave"`` the blur is :class:`fieldcal.simulate.wave.WaveBlur` instead (PSFs from the pupil function;
docs/simulator.md), applied after the geometry below (the scene is warped to the sensor first, so each sensor
pixel takes the PSF of its own defocus); the rest is shared.

Then geometry (focus breathing, stage-axis shift, lateral colour: one scale + shift per channel,
:func:`fieldcal.simulate.bandwarp.scale_shift_fast`), relative illumination and the sensor: photon and read
noise, gain, black level, clipping and quantisation (:mod:`fieldcal.simulate.noise`).
"""

from __future__ import annotations

import functools
import math
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from scipy import fft

from ..errors import ParameterError
from fieldcal.simulate.lens import LensSpec
from . import astigmatism as _astig
from . import noise as _noise
from .bandwarp import scale_shift_fast, single_threaded_blas
from .warp import remap, scale_shift
from .levels import LevelStack, fractional_level, fractional_level_lut, level_diameters_px  # noqa: F401

RENDERER_VERSION = "fieldcal-render/1"
OPTICS = ("geometric", "wave")  # image-formation paths (docs/simulator.md)
# the geometric path's astigmatic PSF: the elliptical defocus PSF, or the old round one of the RMS defocus
ASTIGMATISM = ("anisotropic", "isotropic")
WARPS = ("auto", "fast", "exact")  # the per-frame scale + shift (docs/simulator.md, "Geometry")
# "auto" uses the fast 32-tap warp only for frames above 1 Mpx (_EXACT_MAP_MAX_PX; smaller ones render as
# earlier versions did) and when the optics leave little contrast within ~0.05 cycles/px of Nyquist
# (in-focus |OTF| at 0.47 cycles/px at most this, every channel), the band a finite kernel cannot resample
# exactly: there a phase-dependent loss would move measured best focus (+0.7 µm on the triplet at 256x144,
# where that contrast is 0.96; 0.01 µm at 1920x1080, where it is 0.50). Otherwise the exact chirp-z warp, which
# costs little at the sizes where the optics are that sharp per pixel.
_FAST_WARP_MAX_NYQUIST_OTF = 0.55
# Frames up to this many pixels (per channel) draw exact Poisson photon noise from the frame's generator in
# order (bit-identical to earlier versions where the signal is); larger ones the faster per-channel draw
# (noise.add_noise_e: same mean, variance and, to < 0.01 in skewness, third cumulant).
_EXACT_NOISE_MAX_PX = 1_000_000
# Frames up to this many pixels evaluate the defocus map from the formulas at every pixel and the level in
# closed form (as earlier versions); larger ones on a coarse grid and by a table (the same values to < 0.01
# level; docs/simulator.md).
_EXACT_MAP_MAX_PX = 1_000_000
# Rec. 709 luma weights: an RGB scene seen by a monochrome sensor.
_TABLE_STEP = 1.0 / 65536.0  # cycles/px: radial OTF table resolution
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
# Largest blur disc rendered, in frame sizes (and at least _MIN_MAX_BLUR_PX): beyond it the frame is a flat
# grey to well under 1 % contrast, while the padded FFT would grow with the disc (a 1 m defocus asked for a
# 40 GiB array).
_MAX_BLUR_FRAMES = 2.0
_MIN_MAX_BLUR_PX = 256.0
# The coarse grid on which a frame's defocus is evaluated before bilinear interpolation: the signed defocus and
# the astigmatic half-difference are smooth (polynomials in rho), so the error is ~step^2/8 x curvature, and
# the curvature in px units falls as 1/(half-diagonal in px)^2: a step of half-diagonal/128 px (2..8) keeps it
# near 0.01 level (0.004 µm of defocus on the paper's triplet at 1920 x 1080). The kink of |dz| at focus is
# taken after interpolation, at full resolution.
_COARSE_PER_HALF_DIAGONAL = 128.0
_COARSE_PX = (2, 8)
# One thread per channel (also on 2 cores: three equal tasks on two threads would leave one core idle a third
# of the time; the OS shares the cores among three).
_MAX_WORKERS = 8


def scene_to_channels(scene, channels: tuple[str, ...], width_px: int, height_px: int) -> np.ndarray:
    """Validate a scene array and return it as float32 H x W x C matching the lens's channels.

    H x W (or H x W x 1) is replicated to every channel; H x W x 3 is taken as R, G, B and reduced to luma
    for a one-channel (mono) lens.
    """
    a = np.asarray(scene)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3:
        raise ParameterError(f"a scene must be H x W or H x W x C, got shape {a.shape}", field="scene",
                             fix="pass a 2-D or 3-D image array")
    if a.shape[:2] != (height_px, width_px):
        raise ParameterError(f"scene is {a.shape[1]}x{a.shape[0]} px but the sensor is {width_px}x{height_px}",
                             field="scene", fix="resize the scene (simulate_stack does this for you) or use "
                             "spec.with_sensor_size(W, H)")
    a = a.astype(np.float32, copy=False)
    if not np.all(np.isfinite(a)) or a.min() < -1e-6 or a.max() > 1.0 + 1e-6:
        raise ParameterError("scene values must be finite and in [0, 1]", field="scene",
                             fix="normalise the scene to [0, 1] (e.g. divide uint8 data by 255)")
    a = np.clip(a, 0.0, 1.0)
    n = len(channels)
    c = a.shape[2]
    if c == n:
        return np.ascontiguousarray(a)
    if c == 1:
        return np.ascontiguousarray(np.repeat(a, n, axis=2))
    if c == 3 and n == 1:
        return np.ascontiguousarray((a @ _LUMA)[:, :, None])
    raise ParameterError(f"scene has {c} channels but the lens has {n} ({', '.join(channels)})", field="scene",
                         fix="pass a mono scene, an RGB scene or one plane per lens channel")


class Renderer:
    """Render frames of a scene through a simulated lens (``fieldcal-lens/1``) at stage positions.

    Parameters
    ----------
    spec : LensSpec
        The lens and sensor; the scene must have the sensor's size (``spec.with_sensor_size`` to change it).
    scene : array_like
        Linear scene radiance in [0, 1], H x W or H x W x C (see :func:`scene_to_channels`), in the geometry
        of the frame at ``spec.z_ref_um`` without lateral colour.
    seed : int
        Noise seed; a frame depends only on (seed, z), not on render order.
    level_ratio : float
        Ratio of successive blur-level diameters (> 1). Smaller is more accurate and slower.
    level_floor_px : float
        Diameter of the first non-zero level (px); below it the blur interpolates linearly to focus.
    optics : {"geometric", "wave"}
        Image formation: ``geometric`` (analytic OTFs, symmetric through focus; default) or ``wave`` (PSFs from
        the pupil function with the spec's aberrations, :mod:`fieldcal.simulate.wave`).
    fs_cyc_per_mm : float
        Wave optics only: the frequency whose MTF peak is the sharpest position (truth and level centres).
    field_grid : (int, int)
        Wave optics only: field nodes across x and y at which PSFs are computed (blended bilinearly).
    warp : {"auto", "fast", "exact"}
        The per-frame scale + shift: ``exact`` band-limited (:func:`fieldcal.simulate.warp.scale_shift`),
        ``fast`` 32-tap windowed sinc (:func:`fieldcal.simulate.bandwarp.scale_shift_fast`), ``auto`` the fast
        one only above 1 Mpx where the optics leave little contrast near Nyquist (docs/simulator.md, "Geometry").
    astigmatism : {"anisotropic", "isotropic"}
        Geometric optics only: astigmatic channels blur with the elliptical defocus PSF (semi-axes from the
        tangential and sagittal defocus, oriented radially; :mod:`fieldcal.simulate.astigmatism`; default), or
        with a disc of the RMS of the two defocus values (earlier versions; 1/K of the level memory).
    compact_levels : bool
        Anisotropic astigmatism only: keep the K orientation wedges' levels as int16 (steps of 2**-14; half the
        memory, 1.8e-5 RMS rounding per wedge) rather than float32.
    """

    def __init__(self, spec: LensSpec, scene, seed: int = 0, level_ratio: float = 1.25,
                 level_floor_px: float = 0.5, optics: str = "geometric", fs_cyc_per_mm: float = 80.0,
                 field_grid: tuple[int, int] = (5, 4), warp: str = "auto", astigmatism: str = "anisotropic",
                 compact_levels: bool = True):
        if optics not in OPTICS:
            raise ParameterError(f"unknown optics {optics!r}", field="optics", fix=f"use one of {', '.join(OPTICS)}")
        if astigmatism not in ASTIGMATISM:
            raise ParameterError(f"unknown astigmatism model {astigmatism!r}", field="astigmatism",
                                 fix=f"use one of {', '.join(ASTIGMATISM)}")
        if warp not in WARPS:
            raise ParameterError(f"unknown warp {warp!r}", field="warp", fix=f"use one of {', '.join(WARPS)}")
        if not (level_ratio > 1.0 and math.isfinite(level_ratio)):
            raise ParameterError(f"level_ratio must be > 1, got {level_ratio}", field="level_ratio",
                                 fix="e.g. 1.25")
        if not (level_floor_px > 0.0 and math.isfinite(level_floor_px)):
            raise ParameterError(f"level_floor_px must be > 0, got {level_floor_px}", field="level_floor_px",
                                 fix="e.g. 0.5")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ParameterError(f"seed must be a non-negative integer, got {seed!r}", field="seed", fix="e.g. 0")
        self.spec = spec
        self.seed = int(seed)
        self.level_ratio = float(level_ratio)
        self.level_floor_px = float(level_floor_px)
        s = spec.sensor
        self.width_px, self.height_px = s.width_px, s.height_px
        self.pitch_um = s.pixel_pitch_um
        self.channels = spec.channel_names
        _noise.check_levels(s)
        self.scene = scene_to_channels(scene, self.channels, s.width_px, s.height_px)
        self.exposure = _noise.exposure_scale(self.scene, s.signal_fraction)
        # Pixel grid (broadcastable rows/columns) and the optical centre.
        self._xs = np.arange(self.width_px, dtype=np.float64)[None, :]
        self._ys = np.arange(self.height_px, dtype=np.float64)[:, None]
        self.centre_px = spec.optical_centre_px()
        xm, ym = spec.pixel_to_mm(self._xs, self._ys)
        self._illum = spec.relative_illumination(xm, ym).astype(np.float32)
        if warp == "auto":
            f_mm = 0.47 / (self.pitch_um * 1e-3)
            near_nyquist = max(abs(float(spec.otf(f_mm, 0.0, c))) for c in self.channels)
            large = self.width_px * self.height_px > _EXACT_MAP_MAX_PX
            warp = "fast" if large and near_nyquist <= _FAST_WARP_MAX_NYQUIST_OTF else "exact"
        self.warp = warp
        self._coarse_px = int(np.clip(round(0.5 * math.hypot(self.width_px, self.height_px)
                                            / _COARSE_PER_HALF_DIAGONAL), *_COARSE_PX))
        self._spectra: dict[int, dict[int, tuple[int, np.ndarray]]] = {}  # channel -> pad -> (pad, rfft2)
        self._freq: dict[tuple[int, int], np.ndarray] = {}  # grid shape -> radial table index
        # the blur levels of each channel, computed once when first needed (levels.LevelStack)
        self._stacks = [LevelStack(self.height_px, self.width_px) for _ in self.channels]
        self.optics = optics
        self.astigmatism = astigmatism
        self.compact_levels = bool(compact_levels)
        # geometric path, astigmatic channels: wedge count K and K level stacks per channel (astigmatism.py)
        self._wedges: dict[int, int] = {}
        if optics == "geometric" and astigmatism == "anisotropic":
            for ci, ch in enumerate(self.channels):
                if spec.channel(ch).has_astigmatism:
                    self._wedges[ci] = _astig.wedge_count(self._astig_px(ch))
        self._wedge_stacks = {ci: self._new_wedge_stacks(k) for ci, k in self._wedges.items()}
        self._wedge_grids: dict[tuple, list[np.ndarray]] = {}  # (grid shape, K) -> K wedge weights on the grid
        self._wave = None
        if optics == "wave":
            from .wave import WaveBlur
            self._wave = WaveBlur(spec, self.scene, self.level_ratio, self.level_floor_px, fs_cyc_per_mm, field_grid)

    # ---------------------------------------------------------------------------------------- levels
    def diameter_px(self, defocus_um) -> np.ndarray:
        """Geometric blur-disc diameter in pixels, ``|dz| / N / pitch``."""
        return np.abs(np.asarray(defocus_um, dtype=np.float64)) / self.spec.f_number / self.pitch_um

    def _check_blur(self, max_diameter_px: float) -> None:
        """Refuse a blur disc far larger than the frame (ParameterError naming the defocus limit)."""
        limit = max(_MAX_BLUR_FRAMES * max(self.width_px, self.height_px), _MIN_MAX_BLUR_PX)
        if not max_diameter_px <= limit:
            dz = limit * self.spec.f_number * self.pitch_um
            raise ParameterError(f"a defocus of up to {max_diameter_px * self.spec.f_number * self.pitch_um:.4g} µm "
                                 f"blurs a point over {max_diameter_px:.4g} px, more than {limit:.0f} px "
                                 f"(the larger of {_MAX_BLUR_FRAMES:g} frame sizes and {_MIN_MAX_BLUR_PX:g} px): the frame would "
                                 "be a flat grey and the blur too large to compute",
                                 field="z_um", fix=f"keep stage positions within ±{dz:.4g} µm of the lens's best "
                                                   "focus (scan only the range that matters)")

    def levels_um(self, max_defocus_um: float) -> np.ndarray:
        """Defocus (µm) of the blur levels needed up to ``max_defocus_um``."""
        d = level_diameters_px(float(self.diameter_px(max_defocus_um)), self.level_ratio, self.level_floor_px)
        return d * self.spec.f_number * self.pitch_um

    # ------------------------------------------------------------------------------------- spectra
    def _pad_for(self, max_diameter_px: float, channel: str) -> int:
        """Reflect padding (px) that keeps the circular FFT convolution's wrap-around off the frame."""
        lam_px = self.spec.channel(channel).wavelength_nm * 1e-3 * self.spec.f_number / self.pitch_um
        sigma_px = self.spec.residual_blur_um / self.pitch_um
        return int(math.ceil(0.5 * max_diameter_px + 4.0 * sigma_px + 3.0 * lam_px)) + 8

    def _spectrum(self, ci: int, pad: int) -> tuple[int, np.ndarray]:
        """rfft2 of the channel padded by at least ``pad`` px (mirror), from a small cache.

        The pad is rounded up to a fixed ladder (16 * 1.5**k px), so a frame's result depends only on the
        frame, never on what was rendered before (bit-identical frames, hence identical noise draws).
        """
        pad = int(16 * 1.5 ** max(0, math.ceil(math.log(max(pad, 1) / 16) / math.log(1.5))))
        cache = self._spectra.setdefault(ci, {})  # one dict per channel: channels render in parallel threads
        if pad not in cache:
            h, w = self.height_px, self.width_px
            hp = fft.next_fast_len(h + 2 * pad, real=True)
            wp = fft.next_fast_len(w + 2 * pad, real=True)
            padded = np.pad(self.scene[:, :, ci], ((pad, hp - h - pad), (pad, wp - w - pad)), mode="symmetric")
            if len(cache) >= 2:  # bound memory: drop the oldest
                cache.pop(next(iter(cache)))
            cache[pad] = (pad, fft.rfft2(padded.astype(np.float32, copy=False), workers=-1))
        return cache[pad]

    def _radial(self, shape: tuple[int, int]) -> np.ndarray:
        """Index of each rfft2 grid point's radial frequency in a fine 1-D table (step ``_TABLE_STEP``)."""
        if shape not in self._freq:
            hp, wp = shape
            fy = fft.fftfreq(hp).astype(np.float32)[:, None]
            fx = fft.rfftfreq(wp).astype(np.float32)[None, :]
            r = np.sqrt(fy * fy + fx * fx)  # cycles/px, at most 1/sqrt(2)
            self._freq[shape] = np.rint(r / np.float32(_TABLE_STEP)).astype(np.int32)
        return self._freq[shape]

    def _otf_grid(self, shape, defocus_um: float, channel: str) -> np.ndarray:
        """The lens OTF (real, radial) on an rfft2 grid, by nearest lookup in a 1-D table.

        The table step is a power of two no coarser than 1 / (512 max(b, 4)) cycles/px for a blur disc of
        b px (and at least 1/65536), which keeps the lookup error below ~2e-3 while small blurs need only a
        short table (the table's Bessel functions dominate the cost on small images otherwise).
        """
        b_px = float(self.diameter_px(defocus_um))
        k = int(min(16, max(11, math.ceil(math.log2(512.0 * max(b_px, 4.0))))))
        shift = 16 - k
        idx = self._radial(shape)
        if shift:
            idx = (idx + (1 << (shift - 1))) >> shift  # nearest entry of the coarser table
        step = 2.0 ** -k
        f_px = np.arange(int(0.75 / step) + 2, dtype=np.float64) * step
        table = self.spec.otf(f_px / (self.pitch_um * 1e-3), defocus_um, channel).astype(np.float32)
        return table[idx]

    def blur_uniform(self, channel: str, defocus_um: float) -> np.ndarray:
        """The scene channel blurred by one defocus everywhere (exact OTF, no level interpolation)."""
        ci = self.channels.index(channel)
        self._check_blur(float(self.diameter_px(defocus_um)))
        pad, spec = self._spectrum(ci, self._pad_for(float(self.diameter_px(defocus_um)), channel))
        return self._inverse(spec, pad, self._otf_grid(self._shape(spec, pad), defocus_um, channel))

    def _shape(self, spectrum: np.ndarray, pad: int) -> tuple[int, int]:
        hp = spectrum.shape[0]
        wp = fft.next_fast_len(self.width_px + 2 * pad, real=True)
        return hp, wp

    def _inverse(self, spectrum, pad, otf_grid) -> np.ndarray:
        hp, wp = self._shape(spectrum, pad)
        img = fft.irfft2(spectrum * otf_grid, s=(hp, wp), workers=-1)
        return img[pad:pad + self.height_px, pad:pad + self.width_px]

    def _level_diameter_px(self, k: int) -> float:
        """Blur-disc diameter (px) of level k: 0, then ``floor * ratio**(k - 1)`` (:func:`level_diameters_px`)."""
        return 0.0 if k == 0 else self.level_floor_px * self.level_ratio ** (k - 1)

    def _level_image(self, ci: int, k: int) -> np.ndarray:
        """Level k of channel ci: the scene blurred by the level's defocus everywhere (exact OTF), H x W."""
        ch = self.channels[ci]
        d_px = self._level_diameter_px(k)
        pad, spectrum = self._spectrum(ci, self._pad_for(d_px, ch))
        d_um = d_px * self.spec.f_number * self.pitch_um
        return self._inverse(spectrum, pad, self._otf_grid(self._shape(spectrum, pad), d_um, ch))  # a float32 view

    def blur_map(self, channel: str, defocus_um: np.ndarray) -> np.ndarray:
        """The scene channel with a spatially varying defocus (µm, H x W), by level interpolation."""
        ci = self.channels.index(channel)
        b_px = (np.abs(np.asarray(defocus_um, dtype=np.float32))
                / np.float32(self.spec.f_number * self.pitch_um))
        b_max = float(b_px.max())
        self._check_blur(b_max)
        if b_px.size > _EXACT_MAP_MAX_PX:  # one multithreaded table lookup instead of ~10 passes
            lut, step = fractional_level_lut(b_max, self.level_ratio, self.level_floor_px)
            b_px *= np.float32(1.0 / step)
            kf = cv2.remap(lut, b_px, self._zeros(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        else:
            kf = fractional_level(b_px, self.level_ratio, self.level_floor_px)
        return self._stacks[ci].blend(kf, functools.partial(self._level_image, ci))

    # ------------------------------------------------------------------- astigmatism (geometric path)
    def _astig_px(self, channel: str) -> float:
        """Largest ``|A(rho)| / (N pitch)`` over the sensor: T - S as a blur-disc diameter in pixels."""
        s = self.spec.sensor
        xs, ys = self.spec.pixel_to_mm(np.array([0, s.width_px - 1, 0, s.width_px - 1]),
                                       np.array([0, 0, s.height_px - 1, s.height_px - 1]))
        rho = np.linspace(0.0, float(np.max(self.spec.rho(xs, ys))), 257)  # A(rho) may peak inside the field
        a = np.max(np.abs(self.spec.channel(channel).astigmatism_at(rho)))
        return float(a) / (self.spec.f_number * self.pitch_um)

    def _new_wedge_stacks(self, k: int) -> list[LevelStack]:
        return [LevelStack(self.height_px, self.width_px, compact=self.compact_levels) for _ in range(k)]

    def _wedge_grid(self, shape: tuple[int, int], k: int) -> list[np.ndarray]:
        """The K orientation-wedge weights on an rfft2 grid (float32, each hp x wp//2+1; they sum to 1)."""
        key = (shape, k)
        if key not in self._wedge_grids:
            hp, wp = shape
            fy = fft.fftfreq(hp)[:, None]
            fx = fft.rfftfreq(wp)[None, :]
            w = _astig.wedge_weights(np.arctan2(fy, fx), k)  # alpha of (0, 0) is 0: the weights still sum to 1
            self._wedge_grids[key] = [np.ascontiguousarray(w[..., j], dtype=np.float32) for j in range(k)]
        return self._wedge_grids[key]

    def _wedge_level_image(self, ci: int, j: int, k: int) -> np.ndarray:
        """Level k of wedge j of channel ci: the scene's wedge-j spectrum blurred by the level's disc, H x W."""
        ch = self.channels[ci]
        d_px = self._level_diameter_px(k)
        pad, spectrum = self._spectrum(ci, self._pad_for(d_px, ch))
        shape = self._shape(spectrum, pad)
        d_um = d_px * self.spec.f_number * self.pitch_um
        otf = self._otf_grid(shape, d_um, ch)
        otf *= self._wedge_grid(shape, self._wedges[ci])[j]
        return self._inverse(spectrum, pad, otf)

    def blur_astigmatic(self, channel: str, defocus_um, half_um, azimuth_rad) -> np.ndarray:
        """The scene channel blurred by the elliptical (astigmatic) defocus PSF of each pixel.

        ``defocus_um``: signed defocus from the mean (least-confusion) focus; ``half_um``: ``A/2``, half the
        tangential - sagittal focus difference (signed); ``azimuth_rad``: the field point's direction from the
        optical centre (image axes, x right, y down). Scalars or H x W maps. The PSF is a uniform ellipse of
        diameter ``|dz - A/2| / N`` radially and ``|dz + A/2| / N`` azimuthally, times diffraction and the
        residual Gaussian (:mod:`fieldcal.simulate.astigmatism`).
        """
        ci = self.channels.index(channel)
        # the wedge count must suit the largest T - S asked for (the lens's, or larger maps than it has)
        k = _astig.wedge_count(max(self._astig_px(channel), float(np.max(np.abs(half_um))) * 2.0
                                   / (self.spec.f_number * self.pitch_um)))
        if k > self._wedges.get(ci, 0):
            self._wedges[ci] = k
            self._wedge_stacks[ci] = self._new_wedge_stacks(k)
        shape = (self.height_px, self.width_px)
        h = np.asarray(half_um, dtype=np.float64)
        az = np.asarray(azimuth_rad, dtype=np.float64)
        to_px = 1.0 / (self.spec.f_number * self.pitch_um)
        parts = [np.broadcast_to(np.asarray(v * to_px, dtype=np.float32), shape)
                 for v in (np.asarray(defocus_um, dtype=np.float64), h * np.cos(2.0 * az), h * np.sin(2.0 * az))]
        return self._blur_parts(ci, *parts)

    def _blur_parts(self, ci: int, dz_px: np.ndarray, hc_px: np.ndarray, hs_px: np.ndarray) -> np.ndarray:
        """Anisotropic blur from the smooth parts (px of blur diameter, float32 H x W): signed defocus ``dz``,
        ``h cos 2 theta`` and ``h sin 2 theta`` (h = A/2): each wedge blends its levels at its own diameter."""
        qs = _astig.diameters_from_parts(dz_px, hc_px, hs_px, self._wedges[ci])
        b_max = max(float(q.max()) for q in qs)
        self._check_blur(b_max)
        lut = None
        if self.width_px * self.height_px > _EXACT_MAP_MAX_PX:
            lut, step = fractional_level_lut(b_max, self.level_ratio, self.level_floor_px)
        out = None
        for j, q in enumerate(qs):
            if lut is not None:
                q *= np.float32(1.0 / step)
                kf = cv2.remap(lut, q, self._zeros(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            else:
                kf = fractional_level(q, self.level_ratio, self.level_floor_px)
            img = self._wedge_stacks[ci][j].blend(kf, functools.partial(self._wedge_level_image, ci, j))
            if out is None:
                out = np.array(img, dtype=np.float32, copy=True)
            else:
                out += img
        return out

    def _astig_parts_at(self, z_um: float, channel: str, affine: np.ndarray):
        """Signed defocus from the mean focus, ``h cos 2 theta`` and ``h sin 2 theta`` (px of blur diameter,
        float32 H x W) where each scene pixel lands: above 1 Mpx from a coarse grid (all three are smooth:
        h is even in rho with no constant term), else at every pixel."""
        if self.width_px * self.height_px > _EXACT_MAP_MAX_PX and self.spec.distortion.is_zero:
            xc, _ = self._coarse_axis(self.width_px)
            yc, _ = self._coarse_axis(self.height_px)
            xd = affine[0, 0] * xc[None, :] + affine[0, 2]
            yd = affine[1, 1] * yc[:, None] + affine[1, 2]
            return tuple(self._coarse_to_full(a) for a in self._astig_parts(z_um, channel, xd, yd))
        xd, yd = self._landing(z_um, channel, affine)
        return tuple(np.ascontiguousarray(np.broadcast_to(a, (self.height_px, self.width_px)), dtype=np.float32)
                     for a in self._astig_parts(z_um, channel, xd, yd))

    def _astig_parts(self, z_um: float, channel: str, xd, yd):
        """(dz, h cos 2 theta, h sin 2 theta) in px of blur diameter at sensor pixels (xd, yd), float64."""
        xm, ym = self.spec.pixel_to_mm(xd, yd)
        to_px = 1.0 / (self.spec.f_number * self.pitch_um)
        dz = (z_um - self.spec.best_focus_um(xm, ym, channel)) * to_px
        dx = np.asarray(xm, dtype=np.float64) - self.spec.decentre_mm[0]
        dy = np.asarray(ym, dtype=np.float64) - self.spec.decentre_mm[1]
        r2 = dx * dx + dy * dy
        h = 0.5 * self.spec.channel(channel).astigmatism_at(self.spec.rho(xm, ym)) * to_px
        # cos 2 theta = (dx^2 - dy^2) / r^2, sin 2 theta = 2 dx dy / r^2; at the centre h = 0
        g = np.divide(h, r2, out=np.zeros(np.broadcast(h, r2).shape), where=r2 > 0)
        return dz, g * (dx * dx - dy * dy), g * (2.0 * dx * dy)

    def _geometric_blur(self, channel: str, z_um: float | None, affine: np.ndarray,
                        scale: float = 1.0) -> np.ndarray:
        """The geometric path's blurred scene channel at stage position z (None: the truth, at best focus).

        ``scale`` multiplies every blur diameter (disc, or both axes of the astigmatic ellipse): e.g. 1/a to blur
        in scene pixels a frame that the warp then magnifies by a."""
        ci = self.channels.index(channel)
        if z_um is None or ci not in self._wedges:
            d = self._defocus_at(z_um, channel, affine)
            return self.blur_map(channel, d if scale == 1.0 else d * np.float32(scale))
        parts = self._astig_parts_at(z_um, channel, affine)
        return self._blur_parts(ci, *(parts if scale == 1.0 else [p * np.float32(scale) for p in parts]))

    # ------------------------------------------------------------------------------------ geometry
    def _affine(self, z_um: float, channel: str, breathing: bool = True) -> np.ndarray:
        """2x3 matrix mapping a z_ref pixel p to ``c + m(z) * lc * (p - c) + s(z)``."""
        m = float(self.spec.magnification(z_um, channel)) if breathing else 1.0
        if not m > 0.0:  # m = 1 + dz / exit pupil: at m <= 0 the sensor has reached the exit pupil (division by 0)
            raise ParameterError(f"at z = {z_um:g} µm the image scale m(z) = {m:.4g} is not positive: the sensor "
                                 f"would be at or beyond the exit pupil ({self.spec.exit_pupil_mm:g} mm from it)",
                                 field="z_um", fix="keep |z - z_ref| well below the exit-pupil distance, or check "
                                                   "exit_pupil_mm in the lens spec (mm, null = telecentric)")
        a = m * self.spec.lateral_colour_scale(channel)
        sx, sy = (float(v) for v in self.spec.shift_px(z_um)) if breathing else (0.0, 0.0)
        cx, cy = self.centre_px
        return np.array([[a, 0.0, cx - a * cx + sx], [0.0, a, cy - a * cy + sy]], dtype=np.float64)

    def _defocus_at(self, z_um: float | None, channel: str, affine: np.ndarray) -> np.ndarray:
        """Effective defocus (µm, float32 H x W) for each scene pixel, evaluated where it lands on the sensor.

        ``z_um=None`` means each pixel's own best focus (the residual is then astigmatism only). Frames above
        ``_EXACT_MAP_MAX_PX`` evaluate the smooth parts on a coarse grid (:meth:`_defocus_coarse`).
        """
        if self.width_px * self.height_px > _EXACT_MAP_MAX_PX and self.spec.distortion.is_zero:
            return self._defocus_coarse(z_um, channel, affine)
        return self._defocus_exact(z_um, channel, affine)

    def _defocus_exact(self, z_um: float | None, channel: str, affine: np.ndarray) -> np.ndarray:
        """:meth:`_defocus_at` from the lens's formulas at every pixel (float64, then float32)."""
        xd, yd = self._landing(z_um, channel, affine)
        xm, ym = self.spec.pixel_to_mm(xd, yd)
        if z_um is None:
            c = self.spec.channel(channel)
            d = 0.5 * np.abs(c.astigmatism_at(self.spec.rho(xm, ym))) * np.ones((self.height_px, self.width_px))
        else:
            d = self.spec.effective_defocus_um(z_um, xm, ym, channel)
        return np.asarray(d, dtype=np.float32)

    def _signed_defocus_at(self, z_um: float | None, channel: str, affine: np.ndarray) -> np.ndarray:
        """Wave optics: signed defocus (µm) from the reference surface where each scene pixel lands.

        ``z_um=None``: each pixel at its own sharpest position (the truth image).
        """
        xd, yd = self._landing(z_um, channel, affine)
        return self._signed_defocus_mm(*self.spec.pixel_to_mm(xd, yd), z_um, channel)

    def _signed_defocus_sensor(self, z_um: float | None, channel: str) -> np.ndarray:
        """Wave optics, warp first: signed defocus (µm from the reference surface) at every sensor pixel.

        ``z_um=None``: each pixel at its own sharpest position (the truth image)."""
        return self._signed_defocus_mm(*self.spec.pixel_to_mm(self._xs, self._ys), z_um, channel)

    def _signed_defocus_mm(self, xm: np.ndarray, ym: np.ndarray, z_um: float | None, channel: str) -> np.ndarray:
        """Signed defocus (µm) at field points (mm), broadcast to the frame; refuses blur beyond the kernel bank."""
        if z_um is None:
            d = self._wave.best_focus_shift_um(channel, self.spec.rho(xm, ym))
        else:
            d = z_um - self.spec.best_focus_um(xm, ym, channel)
        d = np.broadcast_to(d, (self.height_px, self.width_px))
        self._check_blur(float(self.diameter_px(np.max(np.abs(d)))))
        return np.asarray(d, dtype=np.float64)

    def _coarse_axis(self, n: int) -> tuple[np.ndarray, int]:
        """Coarse sample positions (px) along an axis of n pixels, and the number of canvas pixels: sample j
        sits at ``(j + 0.5) s - 0.5 - s`` so that ``cv2.resize`` by s (bilinear between sample centres) covers
        pixels 0 .. n - 1 without extrapolation; the canvas is cropped by s on the low side."""
        s = self._coarse_px
        m = int(math.ceil((n + 1.5 * s) / s)) + 1
        return (np.arange(m, dtype=np.float64) + 0.5) * s - 0.5 - s, m * s

    def _coarse_blur(self, z_um: float | None, channel: str, affine: np.ndarray):
        """On the coarse grid (:meth:`_coarse_axis`): signed defocus from the mean focus and the astigmatic
        half-difference, both as blur-disc diameters (px; None where zero), and the largest effective diameter."""
        xc, _ = self._coarse_axis(self.width_px)
        yc, _ = self._coarse_axis(self.height_px)
        xd = affine[0, 0] * xc[None, :] + affine[0, 2]
        yd = affine[1, 1] * yc[:, None] + affine[1, 2]
        xm, ym = self.spec.pixel_to_mm(xd, yd)
        c = self.spec.channel(channel)
        to_px = 1.0 / (self.spec.f_number * self.pitch_um)
        dz = None if z_um is None else (z_um - self.spec.best_focus_um(xm, ym, channel)) * to_px
        # the full field polynomial A(rho), as effective_defocus_um uses on the exact path
        half = (0.5 * np.abs(c.astigmatism_at(self.spec.rho(xm, ym)))) * to_px if c.has_astigmatism else None
        if dz is not None and half is not None:
            b_max = float(np.max(np.hypot(dz, half)))
        else:
            b_max = 0.0 if dz is None and half is None else float(np.max(np.abs(dz if half is None else half)))
        return dz, half, b_max

    def prepare(self, z_um) -> None:
        """Compute now every blur level that frames at these stage positions and the truth will need (channels
        in parallel), instead of when a frame first needs it. Frames are identical either way."""
        if self._wave is not None:
            return
        zs = [None] + [_check_z(z) for z in np.atleast_1d(np.asarray(z_um, dtype=np.float64))]

        def top(b):
            self._check_blur(b)
            return int(math.floor(float(fractional_level(np.float32([b]), self.level_ratio, self.level_floor_px)[0])))

        def build(ci):
            ch = self.channels[ci]
            b = bw = 0.0
            for z in zs:
                aff = self._affine(self.spec.z_ref_um if z is None else z, ch, z is not None)
                if z is not None and ci in self._wedges:
                    # a wedge's diameter is at most max(b_T, b_S) = |dz| + |h|
                    xc, _ = self._coarse_axis(self.width_px)
                    yc, _ = self._coarse_axis(self.height_px)
                    dz, hc, hs = self._astig_parts(z, ch, aff[0, 0] * xc[None, :] + aff[0, 2],
                                                   aff[1, 1] * yc[:, None] + aff[1, 2])
                    bw = max(bw, float(np.max(np.abs(dz) + np.hypot(hc, hs))))
                else:
                    b = max(b, self._coarse_blur(z, ch, aff)[2])
            self._stacks[ci].ensure(top(b) + 1, functools.partial(self._level_image, ci))
            for j, st in enumerate(self._wedge_stacks.get(ci, [])):
                st.ensure(top(bw) + 1, functools.partial(self._wedge_level_image, ci, j))

        self._per_channel(build)

    def _defocus_coarse(self, z_um: float | None, channel: str, affine: np.ndarray) -> np.ndarray:
        """:meth:`_defocus_at` with the signed defocus from the mean focus and the astigmatic half-difference
        (both smooth) evaluated on a coarse grid and interpolated bilinearly; |dz| or sqrt(dz^2 + h^2) is taken
        at full resolution (the kink at focus stays sharp)."""
        dz, half, _ = self._coarse_blur(z_um, channel, affine)
        to_um = self.spec.f_number * self.pitch_um  # _coarse_blur works in px

        def full(a):
            return self._coarse_to_full(a * to_um)

        if dz is None and half is None:
            return np.zeros((self.height_px, self.width_px), dtype=np.float32)
        if half is None:
            return np.abs(full(dz))
        if dz is None:
            return np.ascontiguousarray(full(half))
        # sqrt(0.5 ((dz - h)^2 + (dz + h)^2)); numpy, not cv2.magnitude, whose result depends on the arrays'
        # memory alignment (frames must depend only on (seed, z))
        b = np.square(full(dz))
        b += np.square(full(half))
        return np.sqrt(b, out=b)

    def _coarse_to_full(self, a) -> np.ndarray:
        """A map on the coarse grid (:meth:`_coarse_axis`) interpolated bilinearly to every pixel (float32)."""
        xc, wt = self._coarse_axis(self.width_px)
        yc, ht = self._coarse_axis(self.height_px)
        s = self._coarse_px
        a = np.broadcast_to(a, (yc.size, xc.size)).astype(np.float32)
        return cv2.resize(a, (wt, ht), interpolation=cv2.INTER_LINEAR)[s:s + self.height_px, s:s + self.width_px]

    def _zeros(self) -> np.ndarray:
        if getattr(self, "_zero_map", None) is None:
            self._zero_map = np.zeros((self.height_px, self.width_px), dtype=np.float32)
        return self._zero_map

    def _landing(self, z_um: float | None, channel: str, affine: np.ndarray):
        """Sensor position of every scene pixel: the affine map, or the spec's full map with distortion."""
        if self.spec.distortion.is_zero:
            return affine[0, 0] * self._xs + affine[0, 2], affine[1, 1] * self._ys + affine[1, 2]
        return self.spec.sensor_px(self._xs, self._ys, self.spec.z_ref_um if z_um is None else z_um, channel,
                                   breathing=z_um is not None)

    def _warp(self, img: np.ndarray, affine: np.ndarray, z_um: float | None = None, channel: str = "") -> np.ndarray:
        if not self.spec.distortion.is_zero:  # non-affine: sample the scene where each sensor pixel comes from
            xs, ys = np.broadcast_arrays(self._xs, self._ys)
            return remap(img, *self.spec.scene_px(xs, ys, self.spec.z_ref_um if z_um is None else z_um, channel,
                                                  breathing=z_um is not None))
        if np.allclose(affine, [[1, 0, 0], [0, 1, 0]], rtol=0, atol=1e-12):
            return img
        fn = scale_shift_fast if self.warp == "fast" else scale_shift
        return fn(img, affine[0, 0], affine[0, 2], affine[1, 2])

    def _channel_linear(self, z_um: float | None, ci: int) -> np.ndarray:
        """One channel of :meth:`_linear`: blurred, warped, vignetted and exposed, float32 H x W, >= 0."""
        ch = self.channels[ci]
        aff = self._affine(self.spec.z_ref_um if z_um is None else z_um, ch, z_um is not None)
        if self._wave is not None and self._wave.warp_first:
            img = self._wave.blur(ch, self._signed_defocus_sensor(z_um, ch), 1.0,
                                  scene=self._warp(self.scene[:, :, ci], aff, z_um, ch))
        elif self._wave is not None:
            img = self._warp(self._wave.blur(ch, self._signed_defocus_at(z_um, ch, aff), float(aff[0, 0])), aff, z_um,
                             ch)
        else:
            img = self._warp(self.sensor_blur(ch, z_um, aff), aff, z_um, ch)
        img = np.multiply(img, self._exposed_illum(), dtype=np.float32)
        np.maximum(img, 0.0, out=img)  # band-limited resampling and OTF ringing can dip below zero
        return img

    def sensor_blur(self, channel: str, z_um: float, affine: np.ndarray) -> np.ndarray:
        """The scene channel blurred, in scene pixels, so that the warp ``affine`` then gives the magnified scene
        convolved with the PSF at the sensor (stage position z in µm; the defocus of each scene pixel is taken where
        it lands, and an astigmatic lens's ellipse is shrunk on both axes).

        The blur is applied before the warp (the levels are of the fixed scene), so it uses the sensor PSF
        shrunk by the warp's scale a: the defocus disc by 1/a here, the in-focus factors (diffraction, residual
        blur) by :meth:`_at_sensor_scale`. Blurring with the sensor PSF itself, then magnifying by a, widened
        the in-focus PSF by a through the scan and moved the sharpest position by -0.2 µm on breathing lenses
        (docs/simulator.md "Geometry").
        """
        a = float(affine[0, 0])
        img = self._geometric_blur(channel, z_um, affine, scale=1.0 / a)
        return self._at_sensor_scale(img, channel, a)

    def _at_sensor_scale(self, img: np.ndarray, channel: str, a: float) -> np.ndarray:
        """``img`` (blurred in scene pixels with the in-focus factors D(f) of the sensor OTF) with D(f / a)
        instead: the sensor's in-focus PSF seen in scene pixels of a frame the warp magnifies by a.

        D is the OTF at zero defocus (diffraction x residual blur); where D(f) < 1e-3 the content is gone and the
        ratio is left at 1. A no-op at a = 1 (telecentric, no lateral colour).
        """
        if abs(a - 1.0) < 1e-12:
            return img
        h, w = img.shape
        pad = 16  # mirror: the ratio's kernel is a few px (D / D at a ~ 1 +- 1e-2)
        hp = fft.next_fast_len(h + 2 * pad, real=True)
        wp = fft.next_fast_len(w + 2 * pad, real=True)
        padded = np.pad(img, ((pad, hp - h - pad), (pad, wp - w - pad)), mode="symmetric")
        shape = (hp, wp)
        f_mm = np.arange(int(0.75 / _TABLE_STEP) + 2, dtype=np.float64) * (_TABLE_STEP / (self.pitch_um * 1e-3))
        d_here = np.asarray(self.spec.otf(f_mm, 0.0, channel), dtype=np.float64)
        d_sensor = np.asarray(self.spec.otf(f_mm / a, 0.0, channel), dtype=np.float64)
        ratio = np.where(np.abs(d_here) > 1e-3, d_sensor / np.where(np.abs(d_here) > 1e-3, d_here, 1.0), 1.0)
        out = fft.irfft2(fft.rfft2(padded, workers=1) * ratio.astype(np.float32)[self._radial(shape)], s=shape,
                         workers=1)
        return np.ascontiguousarray(out[pad:pad + h, pad:pad + w], dtype=np.float32)

    def _exposed_illum(self) -> np.ndarray:
        """Relative illumination times the exposure (float32 H x W), kept while the exposure is unchanged."""
        key = float(self.exposure)
        if getattr(self, "_exposed", (None, None))[0] != key:
            self._exposed = (key, self._illum * np.float32(key))
        return self._exposed[1]

    def _per_channel(self, fn) -> list:
        """``[fn(ci) for ci in channels]``, channels in parallel threads (numpy, OpenCV and the FFTs release the
        GIL); BLAS is held to one thread meanwhile (the warp's small products). Results do not depend on the
        thread schedule: each channel touches only its own caches."""
        n = len(self.channels)
        with single_threaded_blas():
            if n == 1:
                return [fn(0)]
            with ThreadPoolExecutor(max_workers=min(n, _MAX_WORKERS)) as pool:
                return list(pool.map(fn, range(n)))

    def _linear(self, z_um: float | None) -> np.ndarray:
        planes = self._per_channel(lambda ci: self._channel_linear(z_um, ci))
        return np.stack(planes, axis=2)

    # ---------------------------------------------------------------------------------- public API
    def render_float(self, z_um: float) -> np.ndarray:
        """Linear signal at stage position z before noise and quantisation, float32 H x W x C, 1 = white."""
        return self._linear(_check_z(z_um))

    def render(self, z_um: float, noise: bool = True) -> np.ndarray:
        """The frame the camera records at stage position z (dtype from the sensor bit depth).

        H x W x C, or an H x W Bayer mosaic when ``spec.sensor.cfa`` is set.
        """
        z = _check_z(z_um)
        sensor = self.spec.sensor
        rng = _noise.frame_rng(self.seed, z) if noise else None
        if sensor.cfa or self.width_px * self.height_px <= _EXACT_NOISE_MAX_PX:
            # exact Poisson draws, in the frame generator's own order (the realisation earlier versions drew)
            signal = self._linear(z)
            if sensor.cfa:
                signal = _noise.mosaic(signal, self.channels, sensor.cfa)
            return _noise.to_dn(signal, sensor, rng)
        # large frames: one noise stream per channel (spawned from the frame's generator: still a function of
        # (seed, z)), drawn in the channel's thread with the moment-matched normal approximation above 100 e-
        rngs = rng.spawn(len(self.channels)) if rng is not None else [None] * len(self.channels)
        planes = self._per_channel(lambda ci: _noise.to_dn(self._channel_linear(z, ci)[:, :, None], sensor,
                                                           rngs[ci], exact=False))
        return np.concatenate(planes, axis=2)

    def truth(self) -> np.ndarray:
        """All-in-focus image in the geometry of z_ref (lateral colour included): each pixel blurred only by
        its in-focus PSF (diffraction, residual, astigmatic residual), with vignetting and levels, no noise.
        Always H x W x C (demosaiced even for a Bayer sensor), dtype from the bit depth."""
        return _noise.to_dn(self._linear(None), self.spec.sensor, None)

    def focus_shift_table(self, channel: str):
        """Wave optics: ``(rho, shift_um)``, the sharpest position (MTF at fs peaks) minus the lens's reference
        surface over normalised field height; ``None`` for the geometric path (they coincide)."""
        return None if self._wave is None else self._wave.shift_table(channel)

    def settings(self) -> dict:
        """What truth.json records about the renderer."""
        wave = self._wave.settings() if self._wave is not None else {}
        astig = ({"astigmatism": self.astigmatism, "orientation_wedges": {self.channels[ci]: k for ci, k in
                                                                          self._wedges.items()},
                  "orientation_otf_error": {self.channels[ci]: round(_astig.interpolation_error(
                      k, round(self._astig_px(self.channels[ci]), 3)), 4) for ci, k in self._wedges.items()},
                  "wedge_levels": "int16" if self.compact_levels else "float32"} if self._wave is None else {})
        return {"optics": self.optics, **wave, **astig, "version": RENDERER_VERSION, "level_ratio": self.level_ratio,
                "level_floor_px": self.level_floor_px, "exposure_scale": float(self.exposure),
                "warp": ("separable 32-tap Kaiser-windowed sinc (fieldcal.simulate.bandwarp.scale_shift_fast)"
                         if self.warp == "fast" else "separable band-limited resampling (chirp-z, "
                         "fieldcal.simulate.warp.scale_shift)") + ", mirrored edges", "padding": "symmetric"}


def _check_z(z_um) -> float:
    try:
        z = float(z_um)
    except (TypeError, ValueError):
        raise ParameterError(f"z must be a number (µm), got {z_um!r}", field="z_um", fix="e.g. -25.0") from None
    if not math.isfinite(z):
        raise ParameterError(f"z must be finite, got {z}", field="z_um", fix="use a finite stage position in µm")
    return z
