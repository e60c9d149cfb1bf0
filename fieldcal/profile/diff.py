"""Two lens profiles compared against their joint uncertainty (``fieldcal profile diff``, ``fieldcal-profile-diff/1``).

What is compared (docs/profiles.md):

* per channel and orientation (tangential and sagittal where both profiles model astigmatism, else the mean
  surface), the best-focus surface over a grid of the field;
* per channel, the measured focus tolerance (when both profiles measured it), at the first profile's (fs, q);
* per channel, the geometry: focus breathing d ln m / dz and the shift rates d shift / dz at the middle of the
  z range both scans cover, and the lateral-colour scale.

Each of these *families* is tested with a max-|z| statistic: ``z_i = (A_i - B_i) / sd_i`` at every grid point,
``sd`` from the two profiles' joint covariances added as independent (:mod:`fieldcal.profile.uncertainty`). The
null distribution of ``max_i |z_i|`` is simulated from that joint Gaussian (a fixed seed, ``n_null`` draws), so
the critical value accounts for how correlated the field is (it lies between the pointwise 1.96 and the
Bonferroni value). The families are combined by Šidák: family level ``1 - level^(1/K)``; by the Gaussian
correlation inequality, P(no family rejects) >= the product of the families' probabilities for any correlation
between families, so the whole diff's false-alarm rate is at most ``1 - level`` (given the profiles' bands).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import ndtr

from fieldcal import __version__
from fieldcal.errors import ParameterError, SpecError
from fieldcal.formats import documents
from fieldcal.profile.uncertainty import (MODES, colour_estimate, displacement_estimate, geometry_rates,
                                          has_orientations, mode_design, mode_units, surface_estimate, tile_modes,
                                          tolerance_estimate)

DIFF_FORMAT = documents.format_id("profile-diff")
#: grid columns across the field (rows follow the aspect ratio)
GRID_NX = 16
N_NULL = 10000
_SD_FLOOR = 1e-12


@dataclass(frozen=True)
class FieldGrid:
    """Test points as fractions of the frame (0..1), and their pixel positions in each profile."""

    fx: np.ndarray
    fy: np.ndarray
    shape: tuple[int, int]  # (ny, nx)

    def pixels(self, profile) -> tuple[np.ndarray, np.ndarray]:
        w, h = profile.image_size_px
        return self.fx * (w - 1), self.fy * (h - 1)


def field_grid(a, b, nx: int = GRID_NX) -> FieldGrid:
    """A grid over the frame both profiles cover (same sensor area; pixel counts may differ)."""
    (wa, ha), (wb, hb) = a.image_size_px, b.image_size_px
    if abs(wa / ha - wb / hb) > 0.01 * wa / ha:
        raise SpecError(f"the profiles' frames differ in shape ({wa}x{ha} vs {wb}x{hb})", path=b.source_path,
                        field="image", fix="compare profiles of the same camera (same sensor area)")
    sa, sb = wa * a.pixel_pitch_um, wb * b.pixel_pitch_um
    if abs(sa - sb) > 0.01 * sa:
        raise SpecError(f"the profiles' sensors differ in width ({sa / 1000:.3g} mm vs {sb / 1000:.3g} mm)",
                        path=b.source_path, field="image.pixel_pitch_um",
                        fix="compare profiles of the same camera (same sensor area)")
    nx = max(int(nx), 3)
    ny = max(3, int(round(nx * ha / wa)))
    gx, gy = np.meshgrid(np.linspace(0.0, 1.0, nx), np.linspace(0.0, 1.0, ny))
    return FieldGrid(gx.ravel(), gy.ravel(), (ny, nx))


@dataclass(frozen=True)
class MaxZTest:
    """A family's max-|z| test."""

    z: np.ndarray            # z-score per point (NaN where both sds are 0)
    max_z: float
    critical_z: float        # the family's critical value at its level
    p_value: float           # P(max |z| >= observed) under the null, Monte Carlo
    n_effective: float       # independent points that would give the same critical value (Šidák)

    @property
    def significant(self) -> bool:
        return bool(self.max_z > self.critical_z)


def max_z_test(diff: np.ndarray, covs, family_level: float, n_null: int = N_NULL, seed: int = 0,
               t_block: tuple[int, int] | None = None) -> MaxZTest:
    """Max-|z| test of ``diff ~ N(0, cov)`` at ``family_level`` (e.g. 0.99), calibrated by simulation.

    Parameters
    ----------
    diff : (m,) ndarray
        Observed differences.
    covs : (m, m) ndarray or list of them
        Their covariance under the null (no difference), or several candidates: then ``z`` uses the largest sd
        of each entry and the critical value and p-value are the largest over the candidates, so the test
        holds its level under each of them.
    family_level : float
        Probability that the test does not reject when there is no difference.
    t_block : (start, dof), optional
        Entries ``start:`` have a covariance *estimated* from residuals with ``dof`` degrees of freedom: their null
        is multivariate Student-t (each Gaussian draw of the block divided by ``sqrt(chi2_dof / dof)``).
    """
    diff = np.asarray(diff, dtype=np.float64).ravel()
    covs = [covs] if isinstance(covs, np.ndarray) else list(covs)
    covs = [0.5 * (np.asarray(c, dtype=np.float64) + np.asarray(c, dtype=np.float64).T) for c in covs]
    sd = np.max([np.sqrt(np.clip(np.diag(c), 0.0, None)) for c in covs], axis=0)
    ok = sd > _SD_FLOOR
    z = np.full(diff.shape, np.nan)
    z[ok] = diff[ok] / sd[ok]
    if not ok.any():
        return MaxZTest(z, 0.0, math.inf, 1.0, 0.0)
    obs = float(np.nanmax(np.abs(z)))
    crit, p = 0.0, 0.0
    for k, c in enumerate(covs):
        t_mask = None
        if t_block is not None:
            t_mask = (np.arange(diff.size) >= t_block[0])[ok]
        null = _null_max(c[np.ix_(ok, ok)], sd[ok], n_null, seed + 7919 * k,
                         None if t_mask is None or not t_mask.any() else (t_mask, int(t_block[1])))
        crit = max(crit, float(np.quantile(null, family_level)))
        p = max(p, float((1 + np.sum(null >= obs)) / (1 + n_null)))
    return MaxZTest(z, obs, crit, p, _n_effective(crit, family_level))


def _null_max(cov: np.ndarray, sd: np.ndarray, n_null: int, seed: int, t_part=None) -> np.ndarray:
    """Draws of max_i |g_i / sd_i| for g ~ N(0, cov); ``t_part = (mask, dof)``: those entries Student-t."""
    corr = cov / np.outer(sd, sd)
    try:   # a Cholesky factor is ~10x cheaper than eigh; a tiny ridge keeps a rank-deficient matrix factorable
        root = np.linalg.cholesky(corr + 1e-10 * np.eye(corr.shape[0]))
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(corr)
        root = v * np.sqrt(np.clip(w, 0.0, None))
    rng = np.random.default_rng(seed)
    null = np.empty(n_null)
    for a in range(0, n_null, 2000):
        g = rng.standard_normal((min(2000, n_null - a), root.shape[1])) @ root.T
        if t_part is not None:
            mask, dof = t_part
            g[:, mask] /= np.sqrt(rng.chisquare(dof, size=g.shape[0]) / dof)[:, None]
        null[a:a + g.shape[0]] = np.max(np.abs(g), axis=1)
    return null


def _n_effective(crit: float, family_level: float) -> float:
    """N with (1 - 2 (1 - Phi(crit)))^N = family_level: independent points giving this critical value."""
    p1 = 2.0 * (1.0 - float(ndtr(crit)))
    if not (0.0 < p1 < 1.0):
        return 1.0
    return float(max(1.0, math.log(family_level) / math.log1p(-p1)))


def _where(grid: FieldGrid, profile, i: int) -> dict[str, float]:
    x, y = grid.pixels(profile)
    return {"x_px": float(x[i]), "y_px": float(y[i]), "x_frac": float(grid.fx[i]), "y_frac": float(grid.fy[i])}


@dataclass
class _Family:
    name: str
    kind: str                       # "surface", "tolerance", "geometry"
    channel: str
    diff: np.ndarray
    covs: list                      # candidate covariances (the test holds under each)
    labels: list[str] | None = None  # geometry: the statistic of each entry
    extra: dict[str, Any] = field(default_factory=dict)
    t_block: tuple[int, int] | None = None  # (first entry, dof) of entries with a residual-estimated variance

    @property
    def sd(self) -> np.ndarray:
        """The largest sd of each entry over the candidate covariances (what its z-score divides by)."""
        return np.max([np.sqrt(np.clip(np.diag(c), 0.0, None)) for c in self.covs], axis=0)


#: low-order components of a surface difference, fitted by generalised least squares and tested with the grid
COMPONENTS = MODES


def components_operator(profile, x_px, y_px, cov: np.ndarray) -> np.ndarray:
    """L (4 x m): the GLS estimate ``L d`` of (offset, tilt x, tilt y, rho^2) of a field ``d ~ N(., cov)``.

    Offset in µm, tilts in µm/mm on the sensor (about its centre), rho^2 in µm at the half-diagonal.
    """
    X = mode_design(profile, x_px, y_px)
    # a small ridge: the covariance may be near-singular where the field is all one correlated error
    reg = cov + 1e-9 * float(np.mean(np.diag(cov)) or 1.0) * np.eye(cov.shape[0])
    wx = np.linalg.solve(reg, X)
    L = np.linalg.solve(X.T @ wx, wx.T)
    return L * mode_units(profile)[:, None]


def _surface_family(a, b, grid, ch, orientation) -> _Family:
    ea = surface_estimate(a, *grid.pixels(a), ch, orientation)
    eb = surface_estimate(b, *grid.pixels(b), ch, orientation)
    d = ea.value - eb.value
    # the grid plus its low-order components in one max-|z| family: a smooth change (a tilt) averages over the
    # whole field in its component, where no single point may stand out
    m = d.size
    # weights that minimise a bound on the component's worst-case variance over the local term's correlation:
    # (sum |L_i| s_i)^2 <= m sum L_i^2 s_i^2, so the local variance counts m-fold (points the profiles only
    # extrapolate to, with a wide local band, get little weight)
    fixed = ea.cov_fixed + eb.cov_fixed
    L = components_operator(a, *grid.pixels(a), fixed + m * np.diag(ea.local_sd ** 2 + eb.local_sd ** 2))
    d_aug = np.concatenate([d, L @ d])
    covs = []
    for ell in sorted(set(ea.lengths) | set(eb.lengths)):
        covs.append(ea.cov(max(ell, ea.fitted_length)) + eb.cov(max(ell, eb.fitted_length)))
    # and, per component, the local term correlated in the one pattern that makes that component's variance
    # largest (signs of its weights: the Cauchy-Schwarz bound) -- a covariance with the same pointwise bands
    for row in L:
        sg = np.where(row >= 0, 1.0, -1.0)
        va, vb = ea.local_sd * sg, eb.local_sd * sg
        covs.append(fixed + np.outer(va, va) + np.outer(vb, vb))
    covs = [np.block([[c, c @ L.T], [L @ c, L @ c @ L.T]]) for c in covs]
    extra = {"a": ea, "b": eb, "orientation": orientation, "m": m}
    modes = _tile_modes_diff(a, b, ch, orientation)
    t_block = None
    if modes is not None:
        # the modes of the two calibrations' own tiles, after the mean surface: entries with a zero
        # cross-covariance to the grid -- by Sidak's inequality, treating the blocks as independent can only
        # raise the critical value, whatever their true correlation (docs/profiles.md)
        dm, cm, dof = modes
        n0 = d_aug.size
        d_aug = np.concatenate([d_aug, dm])
        covs = [np.block([[c, np.zeros((n0, dm.size))], [np.zeros((dm.size, n0)), cm]]) for c in covs]
        t_block = (n0, dof)
        extra["n_grid_entries"] = n0
    return _Family(f"{ch}/{orientation}", "surface", ch, d_aug, covs, extra=extra, t_block=t_block)


def _frac_surface(profile, fx, fy, ch, orientation) -> np.ndarray:
    """The profile's best focus (µm) of one orientation at fractions of the frame."""
    w, h = profile.image_size_px
    x, y = fx * (w - 1), fy * (h - 1)
    z = profile.best_focus_um(x, y, ch)
    if orientation != "mean":
        z = z + (0.5 if orientation == "tangential" else -0.5) * profile.surfaces.astigmatism_um(x, y, ch)
    return np.asarray(z, dtype=np.float64)


def _tile_modes_diff(a, b, ch, orientation):
    """(A - B of the tile modes, their covariance, the smaller residual dof), or None where a profile lacks tiles.

    Both profiles' tiles are referred to the mean of the two surfaces (one function for both): see
    :func:`fieldcal.profile.uncertainty.tile_modes`."""
    def reference(profile):
        w, h = profile.image_size_px

        def f(x, y):
            fx, fy = np.asarray(x) / (w - 1), np.asarray(y) / (h - 1)
            return 0.5 * (_frac_surface(a, fx, fy, ch, orientation) + _frac_surface(b, fx, fy, ch, orientation))
        return f

    ma = tile_modes(a, ch, orientation, reference(a))
    mb = tile_modes(b, ch, orientation, reference(b))
    if ma is None or mb is None:
        return None
    return ma.value - mb.value, ma.cov + mb.cov, min(ma.dof, mb.dof)


def _tolerance_family(a, b, grid, ch) -> _Family | None:
    if a.tolerance_fit is None or b.tolerance_fit is None:
        return None
    crit = a.tolerance_fit.calibrated_at
    ea = tolerance_estimate(a, *grid.pixels(a), ch, crit.fs_cyc_per_mm, crit.q)
    eb = tolerance_estimate(b, *grid.pixels(b), ch, crit.fs_cyc_per_mm, crit.q)
    if ea is None or eb is None:
        return None
    return _Family(f"{ch}/tolerance", "tolerance", ch, ea.value - eb.value, [ea.cov() + eb.cov()],
                   extra={"a": ea, "b": eb, "fs_cyc_per_mm": crit.fs_cyc_per_mm, "q": crit.q})


def common_z_um(a, b) -> float:
    """Middle of the z range both scans cover (of the two ranges' middles when they do not overlap)."""
    (a0, a1), (b0, b1) = a.z_range_um, b.z_range_um
    lo, hi = max(a0, b0), min(a1, b1)
    if hi >= lo:
        return 0.5 * (lo + hi)
    return 0.25 * (a0 + a1 + b0 + b1)


def _geometry_family(a, b, ch, z_um, seen: dict) -> _Family | None:
    """The channel's geometry statistics; breathing and drift only when they are not copies of a channel
    already tested (below `thorough` effort R and B carry G's fit)."""
    ra, rb = geometry_rates(a, ch, z_um), geometry_rates(b, ch, z_um)
    keys = [k for k in ra if k in rb]
    rates = tuple((k, ra[k], rb[k]) for k in keys if k != "lateral_colour_scale")
    copy_of = seen.get(rates)
    if copy_of is None:
        seen[rates] = ch
    else:
        keys = [k for k in keys if k == "lateral_colour_scale"]
    if not keys:
        return _Family(f"{ch}/geometry", "geometry", ch, np.zeros(0), [np.zeros((0, 0))], labels=[],
                       extra={"a": ra, "b": rb, "copy_of": copy_of})
    d = np.array([ra[k].value - rb[k].value for k in keys])
    var = np.array([ra[k].sd ** 2 + rb[k].sd ** 2 for k in keys])
    return _Family(f"{ch}/geometry", "geometry", ch, d, [np.diag(var)], labels=keys,
                   extra={"a": ra, "b": rb, "copy_of": copy_of})


def common_z_range_um(a, b) -> tuple[float, float] | None:
    """The z range both scans cover, or None when they do not overlap."""
    (a0, a1), (b0, b1) = a.z_range_um, b.z_range_um
    lo, hi = max(a0, b0), min(a1, b1)
    return (lo, hi) if hi > lo else None


def _map_family(a, b, grid: FieldGrid, ch: str, z_span: tuple[float, float]) -> _Family:
    """The channel's geometry from both profiles' maps: the displacement field over the common z range (frame
    at its start -> frame at its end; breathing, drift and distortion changing with z) and, for channels other
    than the reference, the lateral-colour field at its middle; both on the grid, in A's pixels."""
    (wa, ha), (wb, hb) = a.image_size_px, b.image_size_px
    scale = np.concatenate([np.full(grid.fx.size, (wa - 1) / (wb - 1)), np.full(grid.fy.size, (ha - 1) / (hb - 1))])
    (xa, ya), (xb, yb) = grid.pixels(a), grid.pixels(b)
    z0, z1 = z_span
    parts = [("displacement", displacement_estimate(a, xa, ya, z0, z1, ch),
              displacement_estimate(b, xb, yb, z0, z1, ch))]
    if ch != a.geometry_map.reference_channel and ch != b.geometry_map.reference_channel:
        zm = 0.5 * (z0 + z1)
        parts.append(("lateral_colour", colour_estimate(a, xa, ya, zm, ch), colour_estimate(b, xb, yb, zm, ch)))
    d = np.concatenate([ea.value - scale * eb.value for _, ea, eb in parts])
    # the parts share coefficients; a zero cross-covariance between them can only raise the critical value
    # (Sidak's inequality), so the test keeps its level
    blocks = [ea.cov_fixed + scale[:, None] * eb.cov_fixed * scale[None, :] for _, ea, eb in parts]
    cov = np.zeros((d.size, d.size))
    k = 0
    for c in blocks:
        cov[k:k + c.shape[0], k:k + c.shape[0]] = c
        k += c.shape[0]
    return _Family(f"{ch}/geometry", "geometry", ch, d, [cov], labels=None,
                   extra={"maps": [name for name, _, _ in parts], "m": grid.fx.size, "z_span_um": [z0, z1],
                          "a_values": np.concatenate([ea.value for _, ea, _ in parts])})


def diff_profiles(a, b, level: float = 0.95, nx: int = GRID_NX, n_null: int = N_NULL,
                  seed: int = 0) -> tuple[dict[str, Any], dict[str, Any]]:
    """Compare profiles ``a`` and ``b``; returns ``(document, maps)``.

    ``document`` is the ``fieldcal-profile-diff/1`` report (JSON-safe). ``maps`` holds, per surface/tolerance
    family, the grid shape and the difference, its sd and z-score on the grid (for plots).
    """
    level = float(level)
    if not (0.5 <= level < 1.0) or not math.isfinite(level):
        raise ParameterError(f"level must be in [0.5, 1), got {level}", field="level", fix="e.g. --level 0.95")
    if int(n_null) < 1000:
        raise ParameterError(f"{n_null} null draws cannot calibrate a test", field="n_null",
                             fix="use at least 1000 draws (default 10000)")
    channels = [c for c in a.channels if c in b.channels]
    if not channels:
        raise SpecError(f"the profiles share no channel ({', '.join(a.channels)} vs {', '.join(b.channels)})",
                        path=b.source_path, field="image.channels", fix="compare profiles of the same camera")
    grid = field_grid(a, b, nx)
    orientations = ("tangential", "sagittal") if has_orientations(a) and has_orientations(b) else ("mean",)
    z_geo = common_z_um(a, b)
    z_span = common_z_range_um(a, b)
    # dense maps when both profiles have them (over the z range both scans cover); else the scalar statistics
    use_maps = bool(a.has_geometry_map and b.has_geometry_map and z_span is not None)
    families: list[_Family] = []
    copies: list[_Family] = []   # geometry copied from another channel: reported with that channel's test
    seen: dict = {}
    for ch in channels:
        families += [_surface_family(a, b, grid, ch, o) for o in orientations]
        tol = _tolerance_family(a, b, grid, ch)
        if tol is not None:
            families.append(tol)
        geo = (_map_family(a, b, grid, ch, z_span) if use_maps else _geometry_family(a, b, ch, z_geo, seen))
        if geo is not None:
            (families if geo.diff.size else copies).append(geo)
    k = len(families)
    family_level = level ** (1.0 / k)
    tests = [max_z_test(f.diff, f.covs, family_level, n_null, seed + i, f.t_block) for i, f in enumerate(families)]
    p_min = min(t.p_value for t in tests)
    doc: dict[str, Any] = {
        "format": DIFF_FORMAT, "tool": {"name": "fieldcal", "version": __version__},
        "a": _describe(a), "b": _describe(b),
        "level": level, "family_level": family_level, "n_families": k,
        "method": ("max-|z| over each family (surface grid, tolerance grid, geometry statistics), its null "
                   "simulated from the joint Gaussian of the two profiles' uncertainties added as independent; "
                   "families combined by Sidak (docs/profiles.md)"),
        "grid": {"nx": grid.shape[1], "ny": grid.shape[0], "points": int(grid.fx.size)},
        "orientations": list(orientations),
        "p_value": float(min(1.0, 1.0 - (1.0 - p_min) ** k)),
        "significant": any(t.significant for t in tests),
        "channels": {}, "geometry": {"z_um": z_geo, "source": "maps" if use_maps else "scalar",
                                     "channels": {}},
    }
    maps: dict[str, Any] = {"shape": grid.shape, "fx": grid.fx, "fy": grid.fy, "families": {}}
    for f, t in zip(families, tests):
        if f.kind == "surface":
            entry = _field_entry(f, t, grid, a)
            doc["channels"].setdefault(f.channel, {"orientations": {}})["orientations"][f.extra["orientation"]] = entry
            m = f.extra["m"]
            maps["families"][f.name] = {"diff": f.diff[:m], "sd": f.sd[:m],
                                        "z": t.z[:m], "critical_z": t.critical_z, "unit": "µm",
                                        "kind": f"best focus ({f.extra['orientation']})"}
        elif f.kind == "tolerance":
            entry = _field_entry(f, t, grid, a)
            entry.update(fs_cyc_per_mm=f.extra["fs_cyc_per_mm"], q=f.extra["q"])
            doc["channels"].setdefault(f.channel, {"orientations": {}})["tolerance"] = entry
            maps["families"][f.name] = {"diff": f.diff, "sd": f.sd, "z": t.z,
                                        "critical_z": t.critical_z, "unit": "µm", "kind": "focus tolerance"}
        else:
            doc["geometry"]["channels"][f.channel] = _geometry_entry(f, t, grid, a)
    for f in copies:
        doc["geometry"]["channels"][f.channel] = {"statistics": {}, "max_z_score": 0.0, "significant": False}
    for f in families + copies:   # channels whose breathing and drift are another channel's fit
        src = f.extra.get("copy_of") if f.kind == "geometry" else None
        if src:
            g, g0 = doc["geometry"]["channels"][f.channel], doc["geometry"]["channels"][src]
            g["same_fit_as"] = src
            g["statistics"] = {**{k: v for k, v in g0["statistics"].items() if k != "lateral_colour_scale"},
                               **g["statistics"]}
            g["significant"] = bool(g["significant"] or g0["significant"])
            g["max_z_score"] = max(g["max_z_score"], g0["max_z_score"])
            g.setdefault("critical_z", g0.get("critical_z"))
    for ch in channels:   # the channel's headline: its worst surface orientation
        c = doc["channels"].setdefault(ch, {"orientations": {}})
        worst = max(c["orientations"].values(), key=lambda e: e["max_z_score"])
        c.update(max_abs_diff_um=max(e["max_abs_diff_um"] for e in c["orientations"].values()),
                 max_z_score=worst["max_z_score"], critical_z=worst["critical_z"],
                 significant=any(e["significant"] for e in c["orientations"].values())
                 or bool((c.get("tolerance") or {}).get("significant")))
    doc["geometry"]["channels"] = {ch: doc["geometry"]["channels"][ch] for ch in channels
                                   if ch in doc["geometry"]["channels"]}
    doc["geometry"]["significant"] = any(g["significant"] for g in doc["geometry"]["channels"].values())
    ad = absolute_distortion_comparison(a, b, z_geo)
    if ad is not None:
        doc["absolute_distortion"] = ad
    doc["summary"] = summary_lines(doc)
    return doc, maps


#: why the absolute distortion is reported beside the verdict, not in it
DISTORTION_SD_NOTE = ("reported, not in the verdict: distortion_sd_px is about 3x smaller than the error on rendered "
                      "stacks (docs/geometry.md), so a max |z| of a few is expected between two calibrations of "
                      "the same lens: judge it against about 3x the joint sd")


def absolute_distortion_comparison(a, b, z_um: float, n: int = GRID_NX) -> dict[str, Any] | None:
    """Per shared channel: ``distortion_px`` of A minus B at ``z_um`` over the field both boards covered (the
    intersection of the two hulls), against the joint ``distortion_sd_px`` (independent profiles); None unless
    both profiles hold absolute distortion and have the same pixel grid."""
    from fieldcal.profile.lensfun import _in_hull
    da, db = getattr(a, "absolute_distortion", None), getattr(b, "absolute_distortion", None)
    if da is None or db is None or tuple(a.image_size_px) != tuple(b.image_size_px):
        return None
    w, h = a.image_size_px
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 2 * n), np.linspace(0, h - 1, max(3, round(2 * n * h / w))))
    inside = _in_hull(da.hull_px, gx, gy) & _in_hull(db.hull_px, gx, gy)
    if not inside.any():
        return None
    x, y = gx[inside], gy[inside]
    out: dict[str, Any] = {"z_um": float(z_um), "hull_fraction": float(inside.mean()), "note": DISTORTION_SD_NOTE,
                           "channels": {}}
    for ch in (c for c in a.channels if c in b.channels):
        (ax, ay), (bx, by) = a.distortion_px(x, y, z_um, ch), b.distortion_px(x, y, z_um, ch)
        (sax, say), (sbx, sby) = a.distortion_sd_px(x, y, z_um, ch), b.distortion_sd_px(x, y, z_um, ch)
        dx, dy = ax - bx, ay - by
        sx, sy = np.hypot(sax, sbx), np.hypot(say, sby)
        zs = np.maximum(np.abs(dx) / np.maximum(sx, _SD_FLOOR), np.abs(dy) / np.maximum(sy, _SD_FLOOR))
        d = np.hypot(dx, dy)
        i, j = int(np.argmax(d)), int(np.argmax(zs))
        out["channels"][ch] = {"max_abs_diff_px": float(d[i]), "at_max_abs_diff_px": [float(x[i]), float(y[i])],
                               "rms_diff_px": float(np.sqrt(np.mean(d * d))), "max_z_score": float(zs[j]),
                               "at_max_z_px": [float(x[j]), float(y[j])], "median_sd_px": float(np.median(np.hypot(sx, sy)))}
    return out


def _geometry_entry(f: _Family, t: MaxZTest, grid: FieldGrid | None = None, a=None) -> dict[str, Any]:
    if f.labels is None:   # dense maps
        m = f.extra["m"]
        maps = {}
        for i, name in enumerate(f.extra["maps"]):
            sl = slice(2 * m * i, 2 * m * (i + 1))
            dx, dy = f.diff[sl][:m], f.diff[sl][m:]
            mag = np.hypot(dx, dy)
            z = t.z[sl]
            zmax = np.nanmax(np.abs(np.stack([z[:m], z[m:]])), axis=0)
            j, jz = int(np.argmax(mag)), int(np.nanargmax(zmax))
            ax, ay = f.extra["a_values"][sl][:m], f.extra["a_values"][sl][m:]
            maps[name] = {"max_abs_diff_px": float(mag[j]), "at_max_abs_diff": _where(grid, a, j),
                          "rms_diff_px": float(np.sqrt(np.mean(mag ** 2))),
                          "max_abs_a_px": float(np.max(np.hypot(ax, ay))),
                          "max_z_score": float(zmax[jz]), "at_max_z": _where(grid, a, jz),
                          "median_sd_px": float(np.median(f.sd[sl]))}
        return {"statistics": {}, "maps": maps, "z_span_um": f.extra["z_span_um"], "max_z_score": t.max_z,
                "critical_z": t.critical_z, "p_value": t.p_value, "significant": t.significant}
    stats = {}
    for i, key in enumerate(f.labels):
        stats[key] = {"a": f.extra["a"][key].value, "b": f.extra["b"][key].value, "diff": float(f.diff[i]),
                      "sd": float(f.sd[i]), "z_score": _num(t.z[i])}
    return {"statistics": stats, "max_z_score": t.max_z, "critical_z": t.critical_z, "p_value": t.p_value,
            "significant": t.significant}


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _field_entry(f: _Family, t: MaxZTest, grid: FieldGrid, a) -> dict[str, Any]:
    m = f.extra.get("m", f.diff.size)
    d, zf = f.diff[:m], t.z[:m]
    i_abs = int(np.argmax(np.abs(d)))
    i_z = int(np.nanargmax(np.abs(zf))) if np.isfinite(zf).any() else i_abs
    sd_all = f.sd
    sd = sd_all[:m]
    comps = {name: {"diff": float(f.diff[m + i]), "sd": float(sd_all[m + i]), "z_score": _num(t.z[m + i])}
             for i, name in enumerate(COMPONENTS)} if f.diff.size > m else None
    n0 = f.extra.get("n_grid_entries")
    modes = {name: {"diff": float(f.diff[n0 + i]), "sd": float(sd_all[n0 + i]), "z_score": _num(t.z[n0 + i])}
             for i, name in enumerate(MODES)} if n0 is not None else None
    return {"components": comps, "tile_modes": modes,
            "tile_modes_dof": None if f.t_block is None else int(f.t_block[1]),
            "max_abs_diff_um": float(abs(d[i_abs])), "at_max_abs_diff": _where(grid, a, i_abs),
            "max_z_score": float(np.nanmax(np.abs(zf))), "max_z_statistic": float(t.max_z),
            "at_max_z": {**_where(grid, a, i_z), "diff_um": float(d[i_z]), "sd_um": float(sd[i_z])},
            "mean_diff_um": float(np.mean(d)), "rms_diff_um": float(np.sqrt(np.mean(d * d))),
            "median_sd_um": float(np.median(sd)),
            "critical_z": float(t.critical_z), "p_value": float(t.p_value),
            "n_effective_points": float(t.n_effective), "significant": t.significant}


def _describe(p) -> dict[str, Any]:
    w, h = p.image_size_px
    return {"path": p.source_path, "lens": (p.provenance.get("stack_meta") or {}).get("lens"),
            "image_size_px": [w, h], "channels": list(p.channels), "effort": p.calibration.get("effort"),
            "z_range_um": list(p.z_range_um), "created_utc": p.provenance.get("created_utc")}


def summary_lines(doc: dict[str, Any]) -> list[str]:
    """The human-readable verdict, one line per family."""
    lines = [f"{'DIFFERENT' if doc['significant'] else 'no significant difference'} at the "
             f"{100 * doc['level']:g}% level (p = {doc['p_value']:.3g}; {doc['n_families']} families, "
             f"each at {100 * doc['family_level']:.2f}%)"]
    for ch, c in doc["channels"].items():
        for o, e in c["orientations"].items():
            at = e["at_max_z"]
            lines.append(f"  {ch} {o:10s} best focus: max |A-B| {e['max_abs_diff_um']:.2f} µm, max |z| "
                         f"{e['max_z_score']:.2f} (critical {e['critical_z']:.2f}) at ({at['x_px']:.0f}, "
                         f"{at['y_px']:.0f}) px: {at['diff_um']:+.2f} ± {at['sd_um']:.2f} µm"
                         + ("  SIGNIFICANT" if e["significant"] else ""))
            for label, key in (("components A-B", "components"), ("tile modes A-B", "tile_modes")):
                comps = e.get(key) or {}
                if comps:
                    lines.append(f"      {label}: " + "; ".join(
                        f"{k} {v['diff']:+.3g} ± {v['sd']:.2g} (z {v['z_score']:+.1f})" for k, v in comps.items()
                        if v["z_score"] is not None))
        if c.get("tolerance"):
            e = c["tolerance"]
            lines.append(f"  {ch} tolerance: max |A-B| {e['max_abs_diff_um']:.2f} µm, max |z| {e['max_z_score']:.2f}"
                         f" (critical {e['critical_z']:.2f})" + ("  SIGNIFICANT" if e["significant"] else ""))
    for ch, g in doc["geometry"]["channels"].items():
        if g.get("maps"):
            z0, z1 = g["z_span_um"]
            lines.append(f"  {ch} geometry maps, {z0:.0f} -> {z1:.0f} µm: " + "; ".join(
                f"{name} max |A-B| {e['max_abs_diff_px']:.3f} px (of {e['max_abs_a_px']:.2f}), max |z| "
                f"{e['max_z_score']:.1f}" for name, e in g["maps"].items())
                + f" (critical {g['critical_z']:.2f})" + ("  SIGNIFICANT" if g["significant"] else ""))
            continue
        parts = []
        for key, s in g["statistics"].items():
            z = s["z_score"]
            parts.append(f"{key} {s['diff']:+.3g} ± {s['sd']:.2g} (z {z:+.1f})" if z is not None
                         else f"{key} {s['diff']:+.3g}")
        lines.append(f"  {ch} geometry at z = {doc['geometry']['z_um']:.0f} µm: " + "; ".join(parts)
                     + ("  SIGNIFICANT" if g["significant"] else ""))
    ad = doc.get("absolute_distortion")
    for ch, e in ((ad or {}).get("channels") or {}).items():
        lines.append(f"  {ch} absolute distortion at z = {ad['z_um']:.0f} µm over both boards' hulls: max |A-B| "
                     f"{e['max_abs_diff_px']:.3f} px, max |z| {e['max_z_score']:.1f} against the joint sd")
    if ad:
        lines.append(f"    ({ad['note']})")
    return lines
