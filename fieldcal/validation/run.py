"""End-to-end validation against a simulated lens's truth (``fieldcal validate``).

One run takes a ``fieldcal-lens/1`` spec through the whole pipeline and compares every stage with what the
simulator knows exactly (:class:`fieldcal.simulate.truth.TruthProfile`):

1. **chart stack** — a dead-leaves chart rendered at stage positions on a grid through ``z_ref`` spanning the
   lens's focus range plus a margin, with a step set by the true focus tolerance δ (MTF at fs within q of its
   peak);
2. **calibrate** → surface error maps (RMS/max per channel), band coverage (fraction of field points where the
   true surface lies inside the 90 % credible band), geometry errors (magnification and shift slopes vs the
   spec, and the worst registration error in pixels over the focus range);
3. **plan** a stack from the calibrated profile → plan coverage (fraction of pixels whose nearest planned frame
   is within the *true* tolerance) and the frame count against the optimum for the true surfaces;
4. **scene stack** at the planned positions → composite with the calibrated profile; PSNR against the
   simulator's all-in-focus ``truth.tiff``, against a one-shot frame focused on axis and against the oracle
   composite made with the true surfaces and geometry; the relative MTF at fs in the image corners.

:func:`validate` returns a :class:`ValidationResult` (metrics, pass/fail checks against :class:`Thresholds`,
and the maps the report draws); :mod:`fieldcal.validation.report` writes the plots, ``index.html`` and
``summary.json``. See docs/validation.md.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fieldcal.errors import ParameterError
from fieldcal.optics import valid_fs_cyc_per_mm, valid_q
from fieldcal.formats import documents
from fieldcal.simulate.lens import LensSpec
from fieldcal.progress import status
from fieldcal.simulate.truth import TruthProfile

VALIDATION_FORMAT = documents.format_id("validation")
DEFAULT_WIDTH_PX = 640  # at 256 px the tiles stop far from the corners and the fit extrapolates
PROFILE_SOURCES = ("calibrate", "truth")
EFFORTS = ("quick", "standard", "thorough")
# Scene names of the CLI -> the simulator's scene names ("texture" is the colour dead-leaves scene).
SCENES = {"chart": "chart", "texture": "colour-leaves"}
SURFACE_GRID_PX = 8           # surface metrics on every 8th pixel (the posterior band is costly per point)


# ----------------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class Thresholds:
    """Pass/fail limits of the checks (docs/validation.md gives the reasons).

    Surface limits are fractions of the true focus tolerance δ of the channel, so they scale with fs and q.
    """

    surface_rms_tol_frac: float = 0.25      # RMS surface error <= δ/4: the plan's margin absorbs it
    surface_max_tol_frac: float = 1.0       # worst point within one tolerance
    band_coverage_min: float = 0.7          # nominal 0.9; below 0.7 the posterior is overconfident
    registration_px_max: float = 0.5        # worst corner displacement error over the focus range
    plan_coverage_min: float = 1.0          # every pixel of every channel in tolerance
    plan_frames_factor: float = 1.5         # N <= ceil(1.5 N_opt) + 1 (the confidence margin costs frames)
    psnr_gain_db_min: float = 1.0           # composite beats the on-axis one-shot frame by >= 1 dB
    psnr_oracle_gap_db_max: float = 0.5     # composite within 0.5 dB of the true-surface oracle


@dataclass(frozen=True)
class ValidateConfig:
    """Parameters of a validation run.

    Attributes
    ----------
    size_px : (W, H) or None
        Render size over the lens's sensor area (default ``DEFAULT_WIDTH_PX`` = 640 px wide at the sensor's
        aspect ratio: 640x360 for a 16:9 sensor).
    fs_cyc_per_mm : float or None
        Target frequency (default: 0.4 x the Nyquist frequency of the render size, rounded).
    q : float
        Allowed MTF loss at fs (defines the tolerance δ).
    effort : {"quick", "standard", "thorough"}
        Calibration effort.
    seed : int
        Seeds the chart, the noise and the samplers.
    scene : str or path
        ``"chart"`` (a dead-leaves chart with another seed than the calibration chart), ``"texture"`` (a
        colour dead-leaves scene) or an image file.
    confidence : float or None
        Coverage probability the plan asks of the profile's credible band (None: plan on the MAP surfaces).
    profile : {"calibrate", "truth"}
        ``truth`` skips calibration and plans/composites with the true surfaces (checks planning and
        compositing alone).
    chart_step_tol_frac, chart_margin_tol_frac : float
        Chart stack step and margin beyond the focus range, as fractions of the smallest true tolerance δ.
    """

    size_px: tuple[int, int] | None = None
    fs_cyc_per_mm: float | None = None
    q: float = 0.05
    effort: str = "standard"
    seed: int = 0
    scene: str | Path = "chart"
    confidence: float | None = 0.9
    profile: str = "calibrate"
    chart_step_tol_frac: float = 0.5
    chart_margin_tol_frac: float = 3.0
    noise: bool = True
    thresholds: Thresholds = field(default_factory=Thresholds)


@dataclass
class Check:
    """One pass/fail comparison: ``value <op> limit``."""

    name: str
    value: float
    limit: float
    op: str            # "<=" or ">="
    what: str

    @property
    def passed(self) -> bool:
        if not math.isfinite(self.value):
            return False
        return self.value <= self.limit + 1e-12 if self.op == "<=" else self.value >= self.limit - 1e-12

    def to_dict(self) -> dict:
        return {"name": self.name, "value": _r(self.value), "limit": _r(self.limit), "op": self.op,
                "passed": self.passed, "what": self.what}


@dataclass
class ValidationResult:
    """Metrics of every stage, the checks and (not serialised) the maps and images the report draws."""

    lens: str
    config: dict
    setup: dict
    surface: dict
    geometry: dict
    plan: dict
    composite: dict
    timings_s: dict
    checks: list[Check]
    notes: list[str] = field(default_factory=list)
    maps: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if not c.passed]

    def to_dict(self) -> dict:
        return _jsonable({"format": VALIDATION_FORMAT, "lens": self.lens, "passed": self.passed,
                          "config": self.config, "setup": self.setup, "surface": self.surface,
                          "geometry": self.geometry, "plan": self.plan, "composite": self.composite,
                          "timings_s": self.timings_s, "checks": [c.to_dict() for c in self.checks],
                          "notes": self.notes})


def _r(v, nd: int = 6):
    v = float(v)
    return round(v, nd) if math.isfinite(v) else None


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _r(v)
    if isinstance(v, Path):
        return str(v)
    return v


# ----------------------------------------------------------------------------------------- parameters
def default_size(spec: LensSpec, width_px: int = DEFAULT_WIDTH_PX) -> tuple[int, int]:
    """``width_px`` wide at the sensor's aspect ratio (height at least 16 px)."""
    s = spec.sensor
    return int(width_px), max(16, int(round(width_px * s.height_px / s.width_px)))


def nyquist_cyc_per_mm(pixel_pitch_um: float) -> float:
    return 1000.0 / (2.0 * pixel_pitch_um)


def default_fs(pixel_pitch_um: float) -> float:
    """0.4 x Nyquist, rounded to a whole number of cycles/mm (at least 1)."""
    return float(max(1, round(0.4 * nyquist_cyc_per_mm(pixel_pitch_um))))


def resolve(spec: LensSpec, config: ValidateConfig) -> tuple[LensSpec, float]:
    """Check the config against the lens; return the spec at the render size and fs."""
    c = config
    if c.effort not in EFFORTS:
        raise ParameterError(f"unknown effort {c.effort!r}", field="effort", fix="use quick, standard or thorough")
    if c.profile not in PROFILE_SOURCES:
        raise ParameterError(f"unknown profile source {c.profile!r}", field="profile",
                             fix="use calibrate (the full pipeline) or truth (skip calibration)")
    valid_q(c.q)
    if c.confidence is not None and not (0.0 < c.confidence < 1.0):
        raise ParameterError(f"confidence must be in (0, 1), got {c.confidence}", field="confidence",
                             fix="e.g. 0.9, or none (plan on the MAP surfaces)")
    if isinstance(c.seed, bool) or not isinstance(c.seed, (int, np.integer)) or c.seed < 0:
        raise ParameterError(f"seed must be a non-negative integer, got {c.seed!r}", field="seed", fix="e.g. 0")
    if isinstance(c.scene, str) and c.scene not in SCENES and not Path(c.scene).is_file():
        raise ParameterError(f"scene {c.scene!r} is neither {', '.join(SCENES)} nor an image file", path=c.scene,
                             field="scene", fix=f"use {' or '.join(SCENES)}, or the path of an existing image")
    if not (c.chart_step_tol_frac > 0 and c.chart_margin_tol_frac >= 0):
        raise ParameterError("the chart step must be > 0 and the margin >= 0", field="chart_step_tol_frac",
                             fix="e.g. step 0.5, margin 3 (fractions of the tolerance)")
    w, h = c.size_px or default_size(spec)
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ParameterError(f"image size {w}x{h} is outside 16..8192 px", field="size_px", fix="e.g. 320x180")
    sized = spec.with_sensor_size(int(w), int(h))
    nyq = nyquist_cyc_per_mm(sized.sensor.pixel_pitch_um)
    fs = default_fs(sized.sensor.pixel_pitch_um) if c.fs_cyc_per_mm is None else valid_fs_cyc_per_mm(c.fs_cyc_per_mm)
    if not fs < 0.9 * nyq:
        raise ParameterError(f"fs = {fs:g} cycles/mm is not below 90 % of the Nyquist frequency of a {w}x{h} render "
                             f"({nyq:.1f} cycles/mm at {sized.sensor.pixel_pitch_um:.2f} µm pixels: --size keeps the "
                             "sensor area, so fewer pixels are coarser)", field="fs_cyc_per_mm",
                             fix=f"use fs below {0.9 * nyq:.1f} cycles/mm (default "
                                 f"{default_fs(sized.sensor.pixel_pitch_um):g}) or a larger image size")
    return sized, fs


def true_tolerances(spec: LensSpec, fs: float, q: float) -> dict[str, float]:
    return {c: float(spec.focus_tolerance_um(fs, q, c)) for c in spec.channel_names}


def chart_positions_um(spec: LensSpec, tol_um: float, step_frac: float, margin_frac: float) -> np.ndarray:
    """Stage positions of the chart stack: a grid through z_ref over the focus range ± margin."""
    lo, hi = spec.focus_range_um()
    step = step_frac * tol_um
    margin = margin_frac * tol_um
    k0 = math.floor((lo - margin - spec.z_ref_um) / step)
    k1 = math.ceil((hi + margin - spec.z_ref_um) / step)
    return spec.z_ref_um + step * np.arange(k0, k1 + 1, dtype=np.float64)


# -------------------------------------------------------------------------------------------- metrics
def _grid(w: int, h: int, step: int):
    xs = np.unique(np.append(np.arange(0, w, step), w - 1)).astype(np.float64)
    ys = np.unique(np.append(np.arange(0, h, step), h - 1)).astype(np.float64)
    return np.meshgrid(xs, ys)


def surface_metrics(profile, truth: TruthProfile, level: float = 0.9, step_px: int = SURFACE_GRID_PX):
    """Per channel: RMS and max |MAP − true| (µm) and the fraction of points whose truth lies in the band.

    Returns ``(metrics, maps)`` with maps[channel] = (error_um, inside_band) on the evaluation grid.
    """
    if abs(truth.z_ref_um - profile.z_ref_um) > 1e-9:
        # pixel coordinates mean points of the z_ref frame: compare in the profile's own reference geometry
        truth = truth.with_z_ref(profile.z_ref_um)
    w, h = truth.image_size_px
    X, Y = _grid(w, h, step_px)
    metrics, maps = {}, {}
    for c in truth.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64)
        zp = np.asarray(profile.best_focus_um(X, Y, c), dtype=np.float64)
        lo, hi = (np.asarray(a, dtype=np.float64) for a in profile.best_focus_interval_um(X, Y, c, level=level))
        err = zp - zt
        inside = (zt >= lo - 1e-9) & (zt <= hi + 1e-9)
        metrics[c] = {"rms_um": float(np.sqrt(np.mean(err * err))), "max_um": float(np.max(np.abs(err))),
                      "bias_um": float(np.mean(err)), "band_coverage": float(np.mean(inside)),
                      "band_halfwidth_um": float(np.mean(0.5 * (hi - lo)))}
        maps[c] = (err, inside)
    return metrics, maps, (X, Y)


def _positions(p, z_um: np.ndarray, ch: str, pts: np.ndarray) -> np.ndarray:
    """Where z_ref pixels ``pts`` (N x 2) appear at each z: c + m(z) (p - c) + s(z) -> (Z, N, 2)."""
    cx, cy = p.optical_centre_px()
    m = np.asarray(p.magnification(z_um, ch), dtype=np.float64)[:, None]
    dx, dy = (np.asarray(a, dtype=np.float64)[:, None] for a in p.shift_px(z_um, ch))
    x = cx + m * (pts[None, :, 0] - cx) + dx
    y = cy + m * (pts[None, :, 1] - cy) + dy
    return np.stack([x, y], axis=-1)


def geometry_metrics(profile, truth: TruthProfile, z_lo_um: float, z_hi_um: float, n: int = 33) -> dict:
    """Magnification/shift slopes (profile vs truth) and the worst registration error (px) at the image corners
    and edge midpoints over ``[z_lo, z_hi]`` (where the composite takes frames from)."""
    w, h = truth.image_size_px
    z = np.linspace(z_lo_um, z_hi_um, n)
    span = max(z_hi_um - z_lo_um, 1e-9)
    pts = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, 0], [0, (h - 1) / 2],
                    [(w - 1) / 2, (h - 1) / 2]], dtype=np.float64)
    out = {"z_range_um": [float(z_lo_um), float(z_hi_um)], "channels": {}}
    worst = 0.0
    for c in truth.channels:
        d = _positions(profile, z, c, pts) - _positions(truth, z, c, pts)
        reg = float(np.max(np.hypot(d[..., 0], d[..., 1])))
        worst = max(worst, reg)

        def slope(p):
            m = np.asarray(p.magnification(np.array([z_lo_um, z_hi_um]), c), dtype=np.float64)
            sx, sy = (np.asarray(a, dtype=np.float64) for a in p.shift_px(np.array([z_lo_um, z_hi_um]), c))
            return 1e6 * (m[1] - m[0]) / span, (sx[1] - sx[0]) / span, (sy[1] - sy[0]) / span

        mp, sxp, syp = slope(profile)
        mt, sxt, syt = slope(truth)
        out["channels"][c] = {
            "mag_slope_ppm_per_um": {"profile": mp, "truth": mt, "error": mp - mt},
            "shift_x_slope_px_per_um": {"profile": sxp, "truth": sxt, "error": sxp - sxt},
            "shift_y_slope_px_per_um": {"profile": syp, "truth": syt, "error": syp - syt},
            "registration_error_px": reg,
        }
    pc, tc = np.asarray(profile.optical_centre_px(), float), np.asarray(truth.optical_centre_px(), float)
    out["optical_centre_px"] = {"profile": pc.tolist(), "truth": tc.tolist(), "error_px": float(np.hypot(*(pc - tc)))}
    out["registration_error_px"] = worst
    return out


def plan_coverage(frames_um: np.ndarray, truth: TruthProfile, tol_um: dict[str, float], refocus_um: float = 0.0):
    """Per channel: fraction of pixels (full grid) whose nearest frame is within the true tolerance, and the
    smallest margin δ − |z_frame − z_true| (µm). Returns ``(metrics, margin_maps)``."""
    from fieldcal.plan.cover import nearest_index

    w, h = truth.image_size_px
    X, Y = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    frames = np.sort(np.asarray(frames_um, dtype=np.float64))
    metrics, maps = {}, {}
    for c in truth.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64) + refocus_um
        margin = tol_um[c] - np.abs(frames[nearest_index(frames, zt)] - zt)
        metrics[c] = {"coverage": float(np.mean(margin >= -1e-9)), "min_margin_um": float(margin.min())}
        maps[c] = margin
    return metrics, maps


def psnr_db(image, truth, black: float, white: float, border_px: int = 0, region=None) -> float:
    """PSNR (dB) of ``image`` against ``truth`` over the signal range ``white - black``, borders excluded."""
    a = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if region is not None:
        a, t = a[region], t[region]
    elif border_px:
        a = a[border_px:-border_px, border_px:-border_px]
        t = t[border_px:-border_px, border_px:-border_px]
    mse = float(np.mean((a - t) ** 2))
    peak = float(white - black)
    if mse <= 0.0:
        return math.inf
    return 10.0 * math.log10(peak * peak / mse)


def relative_mtf(image, truth, fs_cyc_per_mm: float, pixel_pitch_um: float, rel_bandwidth: float = 0.25) -> float:
    """MTF at fs of ``image`` relative to ``truth`` (1 = as sharp as the in-focus truth), from a 2-D patch.

    Uses the cross-spectrum ``Re(I T*) / |T|²`` summed over an annulus ``fs (1 ± rel_bandwidth/2)`` after a
    Hann window and mean removal, so noise uncorrelated with the truth does not bias it, channel-averaged.
    """
    a = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if a.ndim == 2:
        a, t = a[..., None], t[..., None]
    hh, ww = a.shape[:2]
    win = np.outer(np.hanning(hh), np.hanning(ww))[..., None]
    fa = np.fft.fft2((a - a.mean(axis=(0, 1))) * win, axes=(0, 1))
    ft = np.fft.fft2((t - t.mean(axis=(0, 1))) * win, axes=(0, 1))
    fy = np.fft.fftfreq(hh)[:, None]
    fx = np.fft.fftfreq(ww)[None, :]
    f = np.hypot(fx, fy) * 1000.0 / pixel_pitch_um    # cycles/mm
    ring = np.abs(f - fs_cyc_per_mm) <= 0.5 * rel_bandwidth * fs_cyc_per_mm
    if not ring.any():
        return math.nan
    num = float(np.sum(np.real(fa * np.conj(ft))[ring]))
    den = float(np.sum((np.abs(ft) ** 2)[ring]))
    return num / den if den > 0 else math.nan


def corner_regions(w: int, h: int, border_px: int, frac: float = 0.25):
    """Slices of the four corner patches (``frac`` of each side), inside the excluded border."""
    pw, ph = max(8, int(frac * w)), max(8, int(frac * h))
    b = border_px
    xs = [slice(b, b + pw), slice(w - b - pw, w - b)]
    ys = [slice(b, b + ph), slice(h - b - ph, h - b)]
    return [(ys[j], xs[i]) for j in range(2) for i in range(2)]


def image_quality(img, truth, black, white, border_px, fs, pitch_um) -> dict:
    """PSNR over the frame and in the corners, and the relative MTF at fs in the corners (mean, worst)."""
    h, w = truth.shape[:2]
    regs = corner_regions(w, h, border_px)
    mtf = [relative_mtf(img[r], truth[r], fs, pitch_um) for r in regs]
    return {"psnr_db": psnr_db(img, truth, black, white, border_px),
            "psnr_corners_db": float(np.mean([psnr_db(img, truth, black, white, region=r) for r in regs])),
            "mtf_rel_corners_mean": float(np.nanmean(mtf)) if np.isfinite(mtf).any() else math.nan,
            "mtf_rel_corners_min": float(np.nanmin(mtf)) if np.isfinite(mtf).any() else math.nan}


def border_px_for(w: int, h: int) -> int:
    """Border excluded from image comparisons: warps and mirrored padding touch the outermost pixels."""
    return max(4, int(math.ceil(0.03 * max(w, h))))


def on_axis_focus_um(truth: TruthProfile) -> float:
    """True best focus at the optical centre of G (else the first channel): where a one-shot camera focuses."""
    ch = "G" if "G" in truth.channels else truth.channels[0]
    cx, cy = truth.optical_centre_px()
    return float(np.asarray(truth.best_focus_um(np.array([cx]), np.array([cy]), ch)).ravel()[0])


# ------------------------------------------------------------------------------------------- pipeline
def _scene_image(scene, w: int, h: int, seed: int):
    from fieldcal.simulate.scene import load_scene
    name = SCENES.get(scene, scene) if isinstance(scene, str) else scene
    # the scene chart uses another seed than the calibration chart: not the same picture
    img, label = load_scene(name, w, h, seed=seed + 1)
    return np.asarray(img, dtype=np.float32), label


def validate(lens, config: ValidateConfig | None = None, *, workdir: str | Path | None = None,
             profile=None, quiet: bool = False) -> ValidationResult:
    """Run the whole pipeline on a simulated lens and compare each stage with the truth.

    Parameters
    ----------
    lens : LensSpec or path
        A ``fieldcal-lens/1`` simulated lens.
    config : ValidateConfig, optional
        Size, fs, q, effort, seed, scene, thresholds (defaults: a small fast run).
    workdir : path, optional
        Where the chart and scene stacks are written (kept); default a temporary folder, removed afterwards.
    profile : lens profile or path, optional
        Judge this profile (a ``fieldcal-profile/1`` file, a ``LensProfile`` or any object with the profile
        interface) instead of
        calibrating: its image size must be the render size. ``config.profile`` is then ignored.
    quiet : bool
        No status lines or progress bars.

    Returns
    -------
    ValidationResult
        ``result.passed`` is True when every check holds; ``result.to_dict()`` is the summary.
    """
    config = config or ValidateConfig()
    spec0 = lens if isinstance(lens, LensSpec) else LensSpec.load(lens)
    spec, fs = resolve(spec0, config)
    if isinstance(profile, (str, Path)):
        if not Path(profile).is_file():
            raise ParameterError(f"profile {str(profile)!r} is not a file", path=profile, field="profile",
                                 fix="give the path of a fieldcal-profile/1 JSON")
        from fieldcal.profile.lens_profile import LensProfile
        profile = LensProfile.load(profile)
    if profile is not None:
        size = tuple(int(v) for v in profile.image_size_px)
        if size != (spec.sensor.width_px, spec.sensor.height_px):
            raise ParameterError(f"the profile is for {size[0]}x{size[1]} px images, the render is "
                                 f"{spec.sensor.width_px}x{spec.sensor.height_px}",
                                 path=getattr(profile, "source_path", None), field="size_px",
                                 fix=f"render at {size[0]}x{size[1]} px (the profile's size)")
        if tuple(profile.channels) != tuple(spec.channel_names):
            raise ParameterError(f"the profile's channels {','.join(profile.channels)} are not the lens's "
                                 f"{','.join(spec.channel_names)}", path=profile.source_path,
                                 field="channels", fix="validate a profile calibrated for this lens")
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="fieldcal-validate-") as tmp:
            return _run(spec, fs, config, Path(tmp), quiet, profile)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    return _run(spec, fs, config, workdir, quiet, profile)


def _run(spec: LensSpec, fs: float, cfg: ValidateConfig, work: Path, quiet: bool, given=None) -> ValidationResult:
    import tifffile

    from fieldcal.composite import composite_stack
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.simulate import Renderer, simulate_stack

    th = cfg.thresholds
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    notes: list[str] = []
    w, h = spec.sensor.width_px, spec.sensor.height_px
    truth = TruthProfile(spec)
    tols = true_tolerances(spec, fs, cfg.q)
    tol_min = min(tols.values())
    z_lo, z_hi = spec.focus_range_um()
    setup = {"size_px": [w, h], "pixel_pitch_um": spec.sensor.pixel_pitch_um,
             "nyquist_cyc_per_mm": nyquist_cyc_per_mm(spec.sensor.pixel_pitch_um), "fs_cyc_per_mm": fs,
             "q": cfg.q, "true_tolerance_um": tols, "focus_range_um": [z_lo, z_hi], "D_um": z_hi - z_lo,
             "channels": list(spec.channel_names)}
    maps: dict[str, Any] = {"truth_profile": truth}

    # 1. chart stack + calibration -----------------------------------------------------------------
    source = "given" if given is not None else cfg.profile
    if given is not None:
        profile = given
        setup["chart"] = None
        notes.append("a given profile is judged: no chart stack was simulated or calibrated")
    elif cfg.profile == "calibrate":
        from fieldcal.calibration.pipeline import calibrate
        z_chart = chart_positions_um(spec, tol_min, cfg.chart_step_tol_frac, cfg.chart_margin_tol_frac)
        setup["chart"] = {"n_frames": int(z_chart.size), "z_first_um": float(z_chart[0]),
                          "z_last_um": float(z_chart[-1]), "step_um": float(z_chart[1] - z_chart[0])
                          if z_chart.size > 1 else 0.0}
        status(f"validate: chart stack, {z_chart.size} frames {z_chart[0]:.0f}..{z_chart[-1]:.0f} µm "
               f"at {w}x{h} px", quiet)
        t0 = time.perf_counter()
        chart = simulate_stack(spec, work / "chart-stack", z_chart, scene="chart", seed=cfg.seed,
                               progress=not quiet, noise=cfg.noise, overwrite=True)
        timings["simulate_chart"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        profile = calibrate(chart, fs_cyc_per_mm=fs, q=cfg.q, effort=cfg.effort, z_ref_um=spec.z_ref_um,
                            seed=cfg.seed, quiet=quiet)
        timings["calibrate"] = time.perf_counter() - t0
        maps["profile_object"] = profile
    else:
        profile = truth
        notes.append("profile = truth: calibration skipped; surface, band and geometry checks are trivially exact")
        setup["chart"] = None

    # 2. surfaces, bands, geometry -------------------------------------------------------------------
    t0 = time.perf_counter()
    surf, surf_maps, grid = surface_metrics(profile, truth)
    geom = geometry_metrics(profile, truth, z_lo, z_hi)
    timings["compare_profile"] = time.perf_counter() - t0
    maps["surface"] = surf_maps
    maps["surface_grid"] = grid
    maps["profile"] = profile

    # 3. plan ----------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    req = StackRequest(fs_cyc_per_mm=fs, q=cfg.q, confidence=cfg.confidence)
    confidence_ok = True
    try:
        plan = plan_stack(profile, req)
    except ParameterError as e:
        if cfg.confidence is None or e.field != "confidence":
            raise
        confidence_ok = False
        notes.append(f"the plan at confidence {cfg.confidence} is impossible ({e.what}); planned on the MAP "
                     "surfaces instead")
        plan = plan_stack(profile, StackRequest(fs_cyc_per_mm=fs, q=cfg.q))
    n_opt = plan_stack(truth, StackRequest(fs_cyc_per_mm=fs, q=cfg.q)).n_frames
    frames_um = np.asarray(plan.frames_um, dtype=np.float64)
    cov, margin_maps = plan_coverage(frames_um, truth, tols, plan.field.refocus_um)
    timings["plan"] = time.perf_counter() - t0
    plan_info = {"n_frames": plan.n_frames, "n_optimal_true": int(n_opt), "frames_um": frames_um.tolist(),
                 "confidence": cfg.confidence if confidence_ok else None, "confidence_feasible": confidence_ok,
                 "q_used": plan.q_used, "coverage": cov,
                 "coverage_min": min(v["coverage"] for v in cov.values()),
                 "min_margin_um": min(v["min_margin_um"] for v in cov.values())}
    maps["plan_margin"] = margin_maps
    maps["plan_frames_um"] = frames_um

    # 4. scene stack at the planned positions, composites ---------------------------------------------
    t0 = time.perf_counter()
    scene, scene_label = _scene_image(cfg.scene, w, h, cfg.seed)
    status(f"validate: scene stack ({scene_label}), {plan.n_frames} planned frames", quiet)
    sstack = simulate_stack(spec, work / "scene-stack", frames_um, scene=scene, seed=cfg.seed + 1,
                            progress=not quiet, noise=cfg.noise, overwrite=True)
    truth_img = tifffile.imread(work / "scene-stack" / "truth.tiff")
    if truth_img.ndim == 2:
        truth_img = truth_img[..., None]
    z_one = on_axis_focus_um(truth)
    one = np.asarray(Renderer(spec, scene, seed=cfg.seed + 1).render(z_one, noise=cfg.noise))
    if one.ndim == 2:
        one = one[..., None]
    timings["simulate_scene"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    comp = composite_stack(sstack, profile, "profile", fs_cyc_per_mm=fs, q=cfg.q,
                           focus_offset_um=plan.field.refocus_um, quiet=quiet).image
    timings["composite"] = time.perf_counter() - t0
    oracle = composite_stack(sstack, truth, "profile", fs_cyc_per_mm=fs, q=cfg.q, quiet=quiet).image
    black, white = float(sstack.black_level), float(sstack.white_level)
    if comp.ndim == 2:
        comp, oracle = comp[..., None], oracle[..., None]
    b = border_px_for(w, h)
    pitch = spec.sensor.pixel_pitch_um
    q_comp = image_quality(comp, truth_img, black, white, b, fs, pitch)
    q_one = image_quality(one, truth_img, black, white, b, fs, pitch)
    q_orc = image_quality(oracle, truth_img, black, white, b, fs, pitch)
    composite = {"scene": scene_label, "border_px": b, "z_one_shot_um": z_one, "black_level": black,
                 "white_level": white, "composite": q_comp, "one_shot": q_one, "oracle": q_orc,
                 "gain_over_one_shot_db": q_comp["psnr_db"] - q_one["psnr_db"],
                 "gap_to_oracle_db": q_orc["psnr_db"] - q_comp["psnr_db"]}
    maps["images"] = {"truth": truth_img, "one_shot": one, "composite": comp, "oracle": oracle}
    timings["total"] = time.perf_counter() - t_all

    # 5. checks --------------------------------------------------------------------------------------
    checks: list[Check] = []
    if source != "truth":
        for c, m in surf.items():
            checks.append(Check(f"surface_rms_{c}", m["rms_um"], th.surface_rms_tol_frac * tols[c], "<=",
                                f"RMS error of the {c} best-focus surface (µm) <= {th.surface_rms_tol_frac:g} δ"))
            checks.append(Check(f"surface_max_{c}", m["max_um"], th.surface_max_tol_frac * tols[c], "<=",
                                f"largest error of the {c} surface (µm) <= {th.surface_max_tol_frac:g} δ"))
            checks.append(Check(f"band_coverage_{c}", m["band_coverage"], th.band_coverage_min, ">=",
                                f"fraction of field points whose true {c} focus lies in the 90 % band"))
        checks.append(Check("registration_px", geom["registration_error_px"], th.registration_px_max, "<=",
                            "worst displacement error (px) of the geometry model at the image corners and edges "
                            "over the focus range"))
    if cfg.confidence is not None:
        checks.append(Check("plan_confidence_feasible", float(confidence_ok), 1.0, ">=",
                            f"a plan at confidence {cfg.confidence} exists (the profile's band is narrower than the "
                            "tolerance everywhere); 0 means it was planned on the MAP surfaces"))
    checks.append(Check("plan_coverage", plan_info["coverage_min"], th.plan_coverage_min, ">=",
                        "fraction of pixels (every channel) whose nearest planned frame is within the true tolerance"))
    checks.append(Check("plan_frames", plan.n_frames, math.ceil(th.plan_frames_factor * n_opt) + 1, "<=",
                        f"planned frames vs the optimum for the true surfaces ({n_opt})"))
    checks.append(Check("psnr_gain_over_one_shot_db", composite["gain_over_one_shot_db"], th.psnr_gain_db_min, ">=",
                        "composite PSNR minus the PSNR of one frame focused on axis (dB)"))
    checks.append(Check("psnr_gap_to_oracle_db", composite["gap_to_oracle_db"], th.psnr_oracle_gap_db_max, "<=",
                        "oracle (true surfaces and geometry) PSNR minus composite PSNR (dB)"))
    cfg_d = asdict(cfg)
    cfg_d["scene"] = str(cfg.scene)
    cfg_d["fs_cyc_per_mm"] = fs
    cfg_d["size_px"] = [w, h]
    cfg_d["profile"] = source
    return ValidationResult(lens=spec.name, config=cfg_d, setup=setup, surface=surf, geometry=geom, plan=plan_info,
                            composite=composite, timings_s={k: round(v, 3) for k, v in timings.items()},
                            checks=checks, notes=notes, maps=maps)
