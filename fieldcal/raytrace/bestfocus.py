"""Best focus vs image height per channel, from the traced through-focus MTF (needs optiland).

Best focus at an image height is the image-plane position (µm from the stated image plane, + away from the
lens, the same axis as a lens spec's stage position) where the mean of the tangential and sagittal MTF at
``fs`` peaks. It is *not* the paraxial field curve: spherical aberration moves the MTF peak ~20 µm from the
paraxial focus on axis for the paper's triplet.

Search, per height and channel (optiland's through-focus helper takes at most 7 steps and swaps the T/S
labels, so the loop over defocus is ours):

1. start from the geometric foci of a tangential and a sagittal ray fan (cheap; within ~15 µm of the MTF peak);
2. a scan at ``coarse_step_um`` over ±``coarse_half_width_um`` around it, shifted while the maximum sits at
   an end of the scan (a peak far from the ray-fan estimate is still found, up to ``max_range_um``);
3. a fine scan at ``fine_step_um`` around the best coarse point and a least-squares parabola through the
   points near the maximum (separately for mean, tangential and sagittal).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import ParameterError
from ..optics import MTFCriterion
from ..progress import progress
from .optiland_backend import TracedLens
from .prescription import Prescription

DEFAULT_CHANNELS_NM = {"R": 656.3, "G": 546.1, "B": 486.1}


@dataclass(frozen=True)
class SearchSettings:
    """Defocus search (µm) and sampling of the traced MTF."""

    fs_cyc_per_mm: float = 80.0
    coarse_step_um: float = 6.0
    coarse_half_width_um: float = 24.0
    fine_step_um: float = 1.5
    fine_half_width_um: float = 4.5
    max_range_um: float = 1000.0
    num_rays: int = 64

    def __post_init__(self):
        for name in ("fs_cyc_per_mm", "coarse_step_um", "coarse_half_width_um", "fine_step_um",
                     "fine_half_width_um", "max_range_um"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be a positive number, got {v!r}", field=name,
                                     fix="use a positive value")
        if self.fine_step_um >= self.coarse_step_um:
            raise ParameterError("the fine step must be smaller than the coarse step", field="fine_step_um",
                                 fix="e.g. coarse 6 µm, fine 1.5 µm")
        if self.num_rays < 16:
            raise ParameterError(f"num_rays={self.num_rays} samples the pupil too coarsely", field="num_rays",
                                 fix="use at least 16 (64 is the default)")


@dataclass(frozen=True)
class FocusPoint:
    """Traced best focus of one channel at one image height (µm from the stated image plane)."""

    channel: str
    wavelength_nm: float
    h_mm: float
    field_angle_deg: float
    z_um: float  # peak of the mean of T and S MTF at fs
    z_tangential_um: float
    z_sagittal_um: float
    peak_mtf: float
    peak_mtf_tangential: float
    peak_mtf_sagittal: float
    chief_ray_h_mm: float  # chief-ray height of this wavelength at the d-line field angle (lateral colour)
    n_evaluations: int

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class FocusTable:
    """Traced best focus for every (channel, height)."""

    points: list[FocusPoint]
    settings: SearchSettings
    f_number: float
    prescription: str
    meta: dict = field(default_factory=dict)

    @property
    def channels(self) -> list[str]:
        return list(dict.fromkeys(p.channel for p in self.points))

    @property
    def heights_mm(self) -> np.ndarray:
        return np.array(sorted({p.h_mm for p in self.points}))

    def get(self, channel: str, h_mm: float) -> FocusPoint:
        for p in self.points:
            if p.channel == channel and abs(p.h_mm - h_mm) < 1e-9:
                return p
        raise KeyError((channel, h_mm))

    def column(self, channel: str, key: str = "z_um") -> np.ndarray:
        pts = sorted((p for p in self.points if p.channel == channel), key=lambda p: p.h_mm)
        return np.array([getattr(p, key) for p in pts], dtype=np.float64)


def _peak(dz: np.ndarray, v: np.ndarray, half_width_um: float) -> tuple[float, float]:
    """Vertex (dz, value) of a parabola fitted to the samples within ``half_width_um`` of the best one."""
    i = int(np.argmax(v))
    sel = np.abs(dz - dz[i]) <= half_width_um + 1e-9
    x, y = dz[sel], v[sel]
    if x.size < 3:
        return float(dz[i]), float(v[i])
    x0, sx = float(dz[i]), float(max(np.ptp(x), 1e-6))
    u = (x - x0) / sx  # normalised abscissa keeps the fit well conditioned
    c2, c1, c0 = np.polyfit(u, y, 2)
    if c2 >= 0.0:
        return float(dz[i]), float(v[i])
    u_star = -c1 / (2.0 * c2)
    if not (u.min() <= u_star <= u.max()):
        return float(dz[i]), float(v[i])
    return x0 + u_star * sx, float(c0 + c1 * u_star + c2 * u_star * u_star)


class _Evaluator:
    """MTF at fs through focus at one image height of a traced lens, memoised by defocus.

    At each image-plane position the field is the one whose chief ray lands at ``h_mm`` on that plane.
    """

    def __init__(self, lens: TracedLens, h_mm: float, fs: float):
        self.lens, self.h_mm, self.fs = lens, h_mm, fs
        self.cache: dict[float, tuple[float, float]] = {}

    def __call__(self, dz_um: float) -> tuple[float, float]:
        key = round(float(dz_um), 6)
        if key not in self.cache:
            self.lens.set_defocus_um(key)
            m = self.lens.mtf(self.lens.angle_for_height_deg(self.h_mm, key), [self.fs])[0]
            self.cache[key] = (m.tangential, m.sagittal)
        return self.cache[key]

    def arrays(self):
        dz = np.array(sorted(self.cache))
        ts = np.array([self.cache[k] for k in dz])
        return dz, ts[:, 0], ts[:, 1]


def find_best_focus(lens: TracedLens, h_mm: float, settings: SearchSettings,
                    start_um: float | None = None) -> dict:
    """Best focus (mean, T, S) at image height ``h_mm`` of a traced lens; the module docstring has the search."""
    s = settings
    if start_um is None:
        lens.set_defocus_um(0.0)
        t0, s0 = lens.fan_foci_um(lens.angle_for_height_deg(h_mm))
        start_um = 0.5 * (t0 + s0)
    ev = _Evaluator(lens, h_mm, s.fs_cyc_per_mm)
    n_half = max(1, int(round(s.coarse_half_width_um / s.coarse_step_um)))
    centre = float(start_um)
    for _ in range(int(s.max_range_um / s.coarse_step_um) + 1):
        grid = centre + s.coarse_step_um * np.arange(-n_half, n_half + 1)
        vals = np.array([sum(ev(z)) for z in grid])
        i = int(np.argmax(vals))
        if 0 < i < len(grid) - 1:
            break
        if abs(grid[i] - start_um) > s.max_range_um:
            raise ParameterError(f"no MTF peak within {s.max_range_um:g} µm of the ray-fan focus "
                                 f"({start_um:.1f} µm) at image height {h_mm:g} mm",
                                 field="max_range_um", fix="check the prescription (is it a focusing lens?) "
                                 "or widen the search range")
        centre = float(grid[i])  # maximum at an end of the scan: move the scan there
    z_c = float(grid[i])
    n_fine = int(round(s.fine_half_width_um / s.fine_step_um))
    for z in z_c + s.fine_step_um * np.arange(-n_fine, n_fine + 1):
        ev(z)
    dz, mt, ms = ev.arrays()
    fit_w = s.coarse_step_um + 1e-6  # fine points plus the neighbouring coarse ones
    z_mean, peak_mean = _peak(dz, 0.5 * (mt + ms), fit_w)
    z_t, peak_t = _peak(dz, mt, fit_w)
    z_s, peak_s = _peak(dz, ms, fit_w)
    return dict(z_um=z_mean, peak_mtf=peak_mean, z_tangential_um=z_t, peak_mtf_tangential=peak_t,
                z_sagittal_um=z_s, peak_mtf_sagittal=peak_s, n_evaluations=len(ev.cache))


def trace_focus_table(rx: Prescription, heights_mm, channels_nm: dict[str, float] | None = None,
                      f_number: float = 2.0, settings: SearchSettings | None = None,
                      quiet: bool = False) -> FocusTable:
    """Trace best focus for every channel at every image height (real chief-ray height, d line)."""
    settings = settings or SearchSettings()
    channels_nm = dict(channels_nm or DEFAULT_CHANNELS_NM)
    heights = [float(h) for h in heights_mm]
    if not heights or any(not math.isfinite(h) or h < 0 for h in heights):
        raise ParameterError(f"image heights must be finite and >= 0, got {heights}", field="heights",
                             fix="e.g. 0, 1.8, 3.6")
    if not (math.isfinite(f_number) and f_number > 0.3):
        raise ParameterError(f"f_number must be > 0.3, got {f_number}", field="f_number", fix="e.g. 2.0")
    # Lateral colour: where each wavelength's chief ray lands for the object point imaged at h by the d line.
    ref = TracedLens(rx, 587.56, f_number, settings.num_rays)
    angles = [ref.angle_for_height_deg(h) for h in heights]
    max_angle = max(angles + [1e-3]) * 1.3
    points = []
    jobs = [(c, w, h, a) for c, w in channels_nm.items() for h, a in zip(heights, angles)]
    lenses: dict[str, TracedLens] = {}
    for c, w, h, a in progress(jobs, total=len(jobs), desc="tracing best focus", quiet=quiet, unit="field"):
        if c not in lenses:
            lenses[c] = TracedLens(rx, w, f_number, settings.num_rays)
            lenses[c].set_max_angle_deg(max_angle)
        lens = lenses[c]
        h_c = lens.chief_ray_height_mm(a, 0.0)
        r = find_best_focus(lens, h, settings)
        points.append(FocusPoint(channel=c, wavelength_nm=float(w), h_mm=h, field_angle_deg=a,
                                 chief_ray_h_mm=h_c, **r))
    return FocusTable(points=points, settings=settings, f_number=float(f_number),
                      prescription=rx.source or rx.name)


def through_focus_tolerance_um(rx: Prescription, wavelength_nm: float = 587.56, f_number: float = 2.0,
                               fs_cyc_per_mm: float = 80.0, q: float = 0.05, h_mm: float = 0.0,
                               num_rays: int = 64) -> tuple[float, float, float]:
    """(z_best, lo, hi) µm: the range around best focus where the mean MTF at fs stays >= (1 - q) peak."""
    from scipy.optimize import brentq

    MTFCriterion(fs_cyc_per_mm, q)
    lens = TracedLens(rx, wavelength_nm, f_number, num_rays)
    r = find_best_focus(lens, h_mm, SearchSettings(fs_cyc_per_mm=fs_cyc_per_mm, num_rays=num_rays))
    ev = _Evaluator(lens, h_mm, fs_cyc_per_mm)
    target = (1.0 - q) * r["peak_mtf"]

    def g(z):
        return 0.5 * sum(ev(z)) - target

    z0 = r["z_um"]
    # the 5% depth at F/2, 80 cy/mm is ~5 µm; bracket generously (the MTF falls to 0 within ~30 µm)
    lo = brentq(g, z0 - 30.0, z0, xtol=0.02)
    hi = brentq(g, z0, z0 + 30.0, xtol=0.02)
    return float(z0), float(lo), float(hi)
