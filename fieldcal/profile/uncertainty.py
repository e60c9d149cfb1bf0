"""Joint (field-wide) uncertainty of a profile's best-focus surface, focus tolerance and geometry.

A profile's band (:meth:`LensProfile.best_focus_interval_um`) is *pointwise*. Comparing two profiles over the
whole field needs the joint covariance of the surface at many points at once, so that a maximum over the
field can be calibrated (docs/profiles.md "How `profile diff` decides"). It is assembled from what the profile
stores, in µm, as the sum of three parts:

* **coefficients**: the posterior samples of the surface parameters (sidecar ``surface_samples``), evaluated
  at the grid and spread about their mean (scaled by the self-check's ``band_scale`` as the band is): their
  empirical covariance carries the full structure of tilt, curvature and decentre errors;
* **common mode**: terms the profile records as shared by the whole field of a channel (the common-mode tile
  error, stage repeatability, the breathing systematic, a fixed systematic): a constant covariance;
* **local**: whatever the pointwise band variance holds beyond those two (the kriged discrepancy between
  tiles, the model-misfit and tile-window terms), correlated with the discrepancy's Matérn 3/2 kernel at its
  fitted length scale.

The diagonal equals the profile's own band variance (``best_focus_sd_um`` squared plus the systematic terms
``best_focus_interval_um`` adds), so pointwise z-scores agree with the bands a user sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldcal.errors import ParameterError
from fieldcal.fit.discrepancy import matern32  # the discrepancy's own kernel

ORIENTATIONS = ("mean", "tangential", "sagittal")


#: Correlation lengths (normalised: 1 = half the diagonal) the local term is also assumed to have. The profile
#: records the discrepancy's fitted length, but the errors of two calibrations that remain after it (measurement
#: systematics shared by regions of tiles) are smoother than that fit says; a test must hold for every one.
LOCAL_LENGTHS = (0.5, 2.0)


@dataclass(frozen=True)
class FieldEstimate:
    """An estimate over points with its joint covariance (units of ``value``).

    ``cov_fixed`` is the part whose structure the profile knows (posterior samples, field-wide terms);
    ``local_sd`` the sd of the rest, correlated as Matérn 3/2 of the normalised distances ``dist`` at a length
    not known for sure (:meth:`cov` at one length, :attr:`lengths` the ones to consider).
    """

    value: np.ndarray       # (m,)
    cov_fixed: np.ndarray   # (m, m)
    local_sd: np.ndarray    # (m,)
    dist: np.ndarray        # (m, m) normalised distances
    fitted_length: float

    @property
    def lengths(self) -> tuple[float, ...]:
        return (self.fitted_length,) + tuple(v for v in LOCAL_LENGTHS if v > self.fitted_length)

    def cov(self, length: float | None = None) -> np.ndarray:
        ell = self.fitted_length if length is None else float(length)
        return self.cov_fixed + self.local_sd[:, None] * matern32(self.dist / ell) * self.local_sd[None, :]

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov_fixed) + self.local_sd ** 2, 0.0, None))


def has_orientations(profile) -> bool:
    """True when the profile's surface model carries astigmatism (tangential and sagittal surfaces differ)."""
    return bool(getattr(profile.surfaces.model, "astig", False))


def _systematic_var_um2(profile, channel: str) -> float:
    """Variance (µm²) of the field-wide terms :meth:`LensProfile.best_focus_interval_um` adds to the band."""
    cal = profile.calibration
    fixed = float(cal.get("systematic_sd_um") or 0.0)
    breathing = float((cal.get("breathing_systematic_sd_um") or {}).get(channel) or 0.0)
    offset = float((cal.get("measure_offset_sd_um") or {}).get(channel) or 0.0)
    return fixed ** 2 + breathing ** 2 + offset ** 2


def _common_var_um2(profile, channel: str) -> float:
    """Variance (µm²) the surface fit itself treats as shared by the field (common mode and stage)."""
    s = profile.surfaces
    ci = s.channels.index(channel)
    var = float(s.stage_sd_um.get(channel, 0.0)) ** 2
    disc = s.discrepancy
    if disc is not None and disc.common_sd is not None and ci < disc.common_sd.size:
        var += (float(disc.common_sd[ci]) * s.z_scale_um) ** 2
    return var


def _field_wide_var_um2(profile, channel: str) -> float:
    """Variance (µm²) of the errors shared by the whole field of one channel (systematic and common terms)."""
    var = _systematic_var_um2(profile, channel) if getattr(profile, "calibration", None) is not None else 0.0
    s = getattr(profile, "surfaces", None)
    if s is not None and channel in s.channels:
        var += _common_var_um2(profile, channel)
    return var


def correlation_length(profile) -> float:
    """Correlation length of the local term, normalised image units (1 = half the diagonal)."""
    disc = profile.surfaces.discrepancy
    if disc is not None and disc.length_scale > 0:
        return float(disc.length_scale)
    # no discrepancy term: the band is the coefficients' alone; a tile spacing keeps the local term honest
    tile = float(profile.calibration.get("tile_px") or 32.0)
    return tile / profile.surfaces.geometry.half_diagonal_px


def surface_estimate(profile, x_px, y_px, channel: str, orientation: str = "mean") -> FieldEstimate:
    """Best focus (µm) of one channel and orientation at points, with its joint covariance.

    ``orientation`` is ``mean`` (the profile's best-focus surface, (z_tan + z_sag) / 2), ``tangential`` or
    ``sagittal`` (mean ± half the astigmatism; only when the profile's model has astigmatism).
    """
    if orientation not in ORIENTATIONS:
        raise ParameterError(f"unknown orientation {orientation!r}", field="orientation",
                             fix=f"use one of {', '.join(ORIENTATIONS)}")
    if orientation != "mean" and not has_orientations(profile):
        raise ParameterError("the profile's surface model has no astigmatism term", field="orientation",
                             fix="compare the mean surface")
    x = np.asarray(x_px, dtype=np.float64).ravel()
    y = np.asarray(y_px, dtype=np.float64).ravel()
    s = profile.surfaces
    ci = s.channels.index(profile._channel(channel))
    xh, yh = s.geometry.normalise(x, y)
    sign = {"mean": 0.0, "tangential": 0.5, "sagittal": -0.5}[orientation]
    value = profile.best_focus_um(x, y, channel)
    if sign:
        value = value + sign * s.astigmatism_um(x, y, channel)

    # coefficient part: the posterior samples' surfaces about their mean (µm)
    scale = s.z_scale_um * (float(s.band_scale) if s.discrepancy is not None else 1.0)
    zs = s.sample_model.surface(s.samples, xh, yh, ci)
    dev = scale * (zs - zs.mean(axis=0))
    # the band variance at each point (what the user's band shows), for the mean surface
    total = s.sd(x, y, channel) ** 2 + _systematic_var_um2(profile, channel)
    if sign:
        za = s.sample_model.astigmatism(s.samples, xh, yh, ci)
        dev_o = dev + sign * scale * (za - za.mean(axis=0))
        # the orientation's band: the mean's plus what the astigmatism samples add
        total = total + np.clip(dev_o.var(axis=0) - dev.var(axis=0), 0.0, None)
        dev = dev_o
    cov_coef = dev.T @ dev / max(dev.shape[0] - 1, 1)
    common = _common_var_um2(profile, channel) + _systematic_var_um2(profile, channel)
    rest = np.clip(total - np.diag(cov_coef), 0.0, None)
    common = min(common, float(rest.min())) if rest.size else common
    local = np.clip(rest - common, 0.0, None)
    d = np.hypot(xh[:, None] - xh[None, :], yh[:, None] - yh[None, :])
    cov = cov_coef + common
    return FieldEstimate(np.asarray(value, dtype=np.float64).ravel(), 0.5 * (cov + cov.T), np.sqrt(local), d,
                         correlation_length(profile))


def tolerance_estimate(profile, x_px, y_px, channel: str, fs_cyc_per_mm: float, q: float) -> FieldEstimate | None:
    """Measured focus tolerance (µm) at (fs, q) at points with its joint covariance; None when not measured.

    The width model is linear in its coefficients (``w0 [+ w1 rho^2 [+ wx x + wy y]]``); their covariance is
    that of the least-squares fit to the profile's accepted tiles (:func:`_tolerance_coef_cov`, tiles independent).
    """
    tol = profile.tolerance_fit
    if tol is None or channel not in tol.coef_um:
        return None
    x = np.asarray(x_px, dtype=np.float64).ravel()
    y = np.asarray(y_px, dtype=np.float64).ravel()
    ratio = float(tol.tolerance_um(x[:1], y[:1], channel, fs_cyc_per_mm, q)[0]
                  / tol.width_cal_um(x[:1], y[:1], channel)[0])
    value = tol.tolerance_um(x, y, channel, fs_cyc_per_mm, q)
    order = len(tol.coef_um[channel])
    J = tol.design(x, y, order)
    cov_coef = _tolerance_coef_cov(profile, channel, order)
    if cov_coef is None:
        return None
    cov = ratio ** 2 * (J @ cov_coef @ J.T)
    m = x.size
    return FieldEstimate(np.asarray(value, dtype=np.float64), 0.5 * (cov + cov.T), np.zeros(m), np.zeros((m, m)),
                         1.0)


def _tolerance_coef_cov(profile, channel: str, order: int) -> np.ndarray | None:
    """Covariance of the width model's coefficients: heteroscedasticity-consistent (HC3, MacKinnon & White 1985).

    Why not ``sd^2 (A^T A)^-1`` with one pooled residual sd: the tiles' width scatter grows over the field
    (0.31 µm near the centre to 0.42-0.48 µm in the corners on the simulated triplet at 320x180), and the rho^2
    coefficient is set by the few corner tiles, so one pooled sd understated its sd. HC3 weighs each tile's own
    squared residual, inflated by its leverage ``1 / (1 - h_i)^2``; with equal scatter it is the pooled form.
    Profiles whose tiles do not carry the fitted model's residuals fall back to the pooled form.
    """
    tol, tiles = profile.tolerance_fit, profile.tiles
    if not tiles or "width_um" not in tiles or "channel" not in tiles:
        return None
    ch = np.asarray(tiles["channel"]).astype(str)
    w = np.asarray(tiles["width_um"], dtype=np.float64)
    n = min(ch.size, w.size)
    ch, w = ch[:n], w[:n]
    ok = np.ones(n, dtype=bool)
    if "status" in tiles and np.asarray(tiles["status"]).size == n:
        ok = np.asarray(tiles["status"]).astype(str) == "ok"
    m = ok & (ch == channel) & np.isfinite(w)
    if m.sum() < order + 2:
        return None
    A = tol.design(np.asarray(tiles["x_px"], float)[:n][m], np.asarray(tiles["y_px"], float)[:n][m], order)
    bread = np.linalg.pinv(A.T @ A)
    sd = float(tol.residual_sd_um.get(channel, np.std(w[m])))
    # the recorded sd is the population sd of the residuals: unbias it for the fitted coefficients
    sd2 = sd * sd * m.sum() / max(m.sum() - order, 1)
    pooled = sd2 * bread
    coef = np.asarray(tol.coef_um.get(channel, []), dtype=np.float64)
    if coef.size != order:
        return pooled
    resid = w[m] - A @ coef
    lev = np.clip(np.einsum("ij,jk,ik->i", A, bread, A), 0.0, 0.99)
    e2 = resid ** 2 / (1.0 - lev) ** 2
    return bread @ (A.T * e2) @ A @ bread


#: low-order modes of a best-focus field: offset (µm), tilt x and y (µm/mm on the sensor, about its centre) and
#: the rho^2 term (µm at the half-diagonal)
MODES = ("offset_um", "tilt_x_um_per_mm", "tilt_y_um_per_mm", "rho2_um")


def mode_design(profile, x_px, y_px) -> np.ndarray:
    """(m, 4) design of :data:`MODES` at pixels of ``profile`` (normalised by its half-diagonal, about the frame
    centre); multiply the fitted coefficients by :func:`mode_units` for the physical units."""
    w, h = profile.image_size_px
    r_px = 0.5 * float(np.hypot(w, h))
    xh = (np.asarray(x_px, float) - 0.5 * (w - 1)) / r_px
    yh = (np.asarray(y_px, float) - 0.5 * (h - 1)) / r_px
    return np.stack([np.ones_like(xh), xh, yh, xh * xh + yh * yh], axis=1)


def mode_units(profile) -> np.ndarray:
    """Factors from the normalised coefficients of :func:`mode_design` to µm, µm/mm, µm/mm, µm."""
    w, h = profile.image_size_px
    r_mm = 0.5 * float(np.hypot(w, h)) * profile.pixel_pitch_um / 1000.0
    return np.array([1.0, 1.0 / r_mm, 1.0 / r_mm, 1.0])


@dataclass(frozen=True)
class ModeFit:
    """Low-order modes (:data:`MODES`) fitted to a profile's own tile measurements, with their covariance.

    ``dof``: residual degrees of freedom of the variance estimate (the modes' null is Student-t, not Gaussian).
    """

    value: np.ndarray   # (4,)
    cov: np.ndarray     # (4, 4)
    dof: int
    n_tiles: int
    residual_sd_um: float


_TILE_COLUMN = {"mean": "z_best_um", "tangential": "z_tan_um", "sagittal": "z_sag_um"}


def tile_modes(profile, channel: str, orientation: str = "mean", reference=None) -> ModeFit | None:
    """The modes of the profile's measured best focus per tile, by ordinary least squares; None when the
    profile holds too few tiles (or none for this orientation).

    ``reference(x_px, y_px) -> µm``: a surface subtracted first (the two compared profiles' mean surface), so the
    fixed 4-term basis only has to describe what is left; what the basis cannot describe is then nearly the same
    in two calibrations of one lens and cancels in their difference even where their tiles sit at slightly
    different positions. The covariance is the classical OLS one, ``s^2 (X'X)^-1`` with the residual variance:
    the tiles' scatter about the fit measures the repeat error of this calibration directly (noise, the
    estimator's step-dependent bias, anything the model does not hold), unlike the posterior of a model chosen
    by evidence, whose tilt and decentre terms come and go between calibrations of one lens. The offset's
    variance adds the profile's field-wide terms (band-pass offset, breathing, stage, common mode), which move
    every tile together and so never show in their scatter.
    """
    tiles = profile.tiles
    col = _TILE_COLUMN.get(orientation)
    if not tiles or col not in tiles or "channel" not in tiles:
        return None
    ch = np.asarray(tiles["channel"]).astype(str)
    z = np.asarray(tiles[col], dtype=np.float64).ravel()
    x = np.asarray(tiles["x_px"], dtype=np.float64).ravel()
    y = np.asarray(tiles["y_px"], dtype=np.float64).ravel()
    n = min(ch.size, z.size, x.size, y.size)
    ok = (ch[:n] == channel) & np.isfinite(z[:n]) & np.isfinite(x[:n]) & np.isfinite(y[:n])
    if "status" in tiles and np.asarray(tiles["status"]).size >= n:
        ok &= np.asarray(tiles["status"]).astype(str)[:n] == "ok"
    X = mode_design(profile, x[:n][ok], y[:n][ok])
    p = X.shape[1]
    if ok.sum() < p + 3:
        return None
    zz = z[:n][ok] - (0.0 if reference is None else np.asarray(reference(x[:n][ok], y[:n][ok]), float))
    coef, *_ = np.linalg.lstsq(X, zz, rcond=None)
    res = zz - X @ coef
    dof = int(ok.sum()) - p
    s2 = float(res @ res) / dof
    u = mode_units(profile)
    cov = s2 * np.linalg.pinv(X.T @ X) * np.outer(u, u)
    # errors every tile of the channel shares (the band-pass offset, breathing, stage, common mode) move all the
    # tiles together: their scatter cannot show them, and the offset mode carries all of them
    cov[0, 0] += _field_wide_var_um2(profile, channel)
    return ModeFit(coef * u, 0.5 * (cov + cov.T), dof, int(ok.sum()), float(np.sqrt(s2)))


@dataclass(frozen=True)
class Scalar:
    """A scalar estimate with its standard deviation."""

    value: float
    sd: float


def geometry_rates(profile, channel: str, z_um: float, at_px: tuple[float, float] | None = None,
                   n_draws: int = 4000, seed: int = 0) -> dict[str, Scalar]:
    """Focus breathing and image drift at ``z_um`` (independent of the profile's z_ref), with their sd.

    ``breathing_per_um``: d ln m / dz (1/µm). ``drift_x_px_per_um``, ``drift_y_px_per_um``: d/dz of where the
    point at pixel ``at_px`` (default: the frame centre) lands, ``m'(z) (p - c) + s'(z)``; a fixed pixel, because
    the shift alone depends on the optical centre ``c`` each calibration found. ``lateral_colour_scale``: the
    channel's scale relative to the reference channel. The sd comes from draws of the polynomial coefficients
    from their recorded covariance (the magnification and shift fits are independent).
    """
    g = profile.geometry_fit
    if channel not in g.mag:
        return {}
    rng = np.random.default_rng(seed)
    t = (float(z_um) - g.z_ref_um) / g.z_scale_um
    w, h = profile.image_size_px
    px = (0.5 * (w - 1), 0.5 * (h - 1)) if at_px is None else at_px
    c = profile.optical_centre_px()

    def rate(f, draws):
        k = np.arange(1, f.coef.size + 1)
        return (draws * k * t ** (k - 1)).sum(axis=-1) / g.z_scale_um, 1.0 + (draws * t ** k).sum(axis=-1)

    fm = g.mag[channel]
    dm = rng.multivariate_normal(fm.coef, fm.cov, size=n_draws, method="eigh")
    m_rate, m_val = rate(fm, dm)
    m0_rate, m0_val = rate(fm, fm.coef)
    out = {"breathing_per_um": Scalar(float(m0_rate / m0_val), float(np.std(m_rate / m_val)))}
    for key, polys, off in (("drift_x_px_per_um", g.shift_x, px[0] - c[0]), ("drift_y_px_per_um", g.shift_y, px[1] - c[1])):
        f = polys[channel]
        ds = rng.multivariate_normal(f.coef, f.cov, size=n_draws, method="eigh")
        s_rate, _ = rate(f, ds)
        s0_rate, _ = rate(f, f.coef)
        out[key] = Scalar(float(s0_rate + m0_rate * off), float(np.std(s_rate + m_rate * off)))
    if channel in g.colour and channel != g.reference_channel:
        scale, sd = g.colour[channel]
        out["lateral_colour_scale"] = Scalar(float(scale), float(sd))
    return out


def _invert_map(gmap, x, y, z_um: float, channel: str) -> tuple[np.ndarray, np.ndarray]:
    """The z_ref-geometry points that ``channel`` of the frame at ``z_um`` shows at (x, y) (fixed point: the maps
    are within ~1e-2 of the identity in their derivative)."""
    px, py = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
    for _ in range(30):
        qx, qy = gmap.warp_px(px, py, z_um, channel)
        ex, ey = qx - x, qy - y
        px, py = px - ex, py - ey
        if max(np.max(np.abs(ex), initial=0.0), np.max(np.abs(ey), initial=0.0)) < 1e-9:
            break
    return px, py


def _map_rows(gmap, px, py, z_um: float, channel: str) -> np.ndarray:
    """(2m, P) derivative (px) of the warp of points (px, py) at z with respect to the channel's coefficients:
    x rows then y rows."""
    cm = gmap.channels[channel]
    ux = (px - gmap.centre_px[0]) / gmap.norm_px
    uy = (py - gmap.centre_px[1]) / gmap.norm_px
    t = np.full(ux.shape, (float(z_um) - gmap.z_ref_um) / gmap.z_scale_um)
    dx, dy = cm.design(ux, uy, t)
    return gmap.norm_px * np.concatenate([dx, dy])


def displacement_estimate(profile, x, y, z_from_um: float, z_to_um: float, channel: str) -> FieldEstimate:
    """Where the points at pixels (x, y) of the frame at ``z_from_um`` move by ``z_to_um`` (px; x entries then
    y), from the profile's geometry maps, with the joint covariance of the map coefficients.

    A frame-to-frame map ``W(z_to) o W(z_from)^-1``: it does not depend on which frame the calibration chose as
    z_ref, so two profiles of one lens agree on it (breathing, drift and distortion changing with z). The
    covariance neglects the inverse's own dependence on the coefficients (its derivative differs from the
    identity by ~1e-2).
    """
    g = profile.geometry_map
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    px, py = _invert_map(g, x, y, z_from_um, channel)
    qx, qy = g.warp_px(px, py, z_to_um, channel)
    J = _map_rows(g, px, py, z_to_um, channel) - _map_rows(g, px, py, z_from_um, channel)
    cov = J @ g.channels[channel].cov @ J.T
    return _fixed_estimate(np.concatenate([qx - x, qy - y]), cov)


def colour_estimate(profile, x, y, z_um: float, channel: str) -> FieldEstimate:
    """Where ``channel`` shows the scene point the reference channel shows at pixels (x, y) of the frame at z,
    minus (x, y) (px; x entries then y): lateral colour and any difference of distortion between channels, from
    the geometry maps, with the covariance of both channels' coefficients (fitted separately: added)."""
    g = profile.geometry_map
    ref = g.reference_channel
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    px, py = _invert_map(g, x, y, z_um, ref)
    qx, qy = g.warp_px(px, py, z_um, channel)
    # d(q)/d(theta_c) directly; through p = W_ref^-1(x): dq = -(dW_ref) to first order
    Jc = _map_rows(g, px, py, z_um, channel)
    Jr = _map_rows(g, px, py, z_um, ref)
    cov = Jc @ g.channels[channel].cov @ Jc.T + Jr @ g.channels[ref].cov @ Jr.T
    return _fixed_estimate(np.concatenate([qx - x, qy - y]), cov)


def _fixed_estimate(value: np.ndarray, cov: np.ndarray) -> FieldEstimate:
    m = value.size
    return FieldEstimate(value, 0.5 * (cov + cov.T), np.zeros(m), np.zeros((m, m)), 1.0)
