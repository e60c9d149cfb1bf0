"""The fitting half of calibration: best-focus surfaces from a measured tile table, and the band terms the
table itself tells (breathing, stage), plus the per-frame geometry measurements as fit inputs.

:mod:`fieldcal.calibration` only orchestrates measure -> fit -> profile; everything that fits lives here.
"""

from __future__ import annotations

from dataclasses import replace

import math

import numpy as np

# Effective window of a measured tile relative to a uniform square of side tile_px: the measured best focus is
# z(centre) + kappa L s^2 / 24. Checked on 6 simulated random lenses (320x240, 32 px tiles): mean raw tile minus
# true centre value = the correction to within 5 % (kappa = 1); kappa's sd is a systematic of the whole field and
# joins the band (docs/fitting.md "Tile window"). The sd stays 0.05: s10-geocov measured pistons of -0.25x the
# correction on fieldcal's own renderers' breathing lenses, but those renderers blend blur levels before the
# breathing warp, which misrenders steep focus gradients (s10-corners), and an sd of 0.25 made the clean-room
# renderer's texture bands too wide (sym-f4 0.93 -> 0.99, half-width 3.8x the error): docs/fitting.md
# "Field-wide terms per stack".
TILE_WINDOW_KAPPA = 1.0
TILE_WINDOW_KAPPA_SD = 0.05


def fit_tile_surfaces(table, geometry, *, channels: tuple[str, ...], effort: str = "standard", seed: int = 0,
                      quiet: bool = False, source: str | None = None):
    """Best-focus surfaces from a measured tile table: the fitting half of :func:`calibrate`.

    Parameters
    ----------
    table : TileTable
        From :func:`fieldcal.measure.measure_stack` (``tile_px`` is used for the tile-average correction).
    geometry : fieldcal.fit.ImageGeometry
        Size and pixel pitch of the frames.
    channels, effort, seed, quiet, source
        As in :func:`fieldcal.fit.fit_surfaces`.

    Returns
    -------
    (SurfaceFit, TileData)
        The fit and the accepted tiles corrected to tile-centre values (and from the band-pass's band to fs,
        :func:`band_corrections_um`).
    """
    from fieldcal.fit import TileData
    from fieldcal.fit.pool import surface_pool

    tiles = TileData.from_table(table, source=source)
    # a worker process for the fit's independent pieces, where the fit is large enough to pay its start (started
    # now: it imports the fit's modules while this process fits the first surface and the centred candidates)
    n_rows = len(tiles) + int(np.sum(np.isfinite(tiles.z_tan_um) & np.isfinite(tiles.z_sag_um)))
    with surface_pool(n_rows) as pool:
        return _fit_tiles(table, tiles, geometry, channels, effort, seed, quiet, source, pool)


def _fit_tiles(table, tiles, geometry, channels, effort, seed, quiet, source, pool):
    """:func:`fit_tile_surfaces` with its worker ``pool`` (or None)."""
    from fieldcal.fit import fit_surfaces

    # The band-pass peaks at the mean sharpest position of its band, not at fs's: with spherical aberration near
    # diffraction that is 0.05-0.1 scan step, the same over a channel (measure.throughfocus.band_peak_correction_um)
    band = band_corrections_um(table)
    if any(band.values()):
        shift = np.array([band.get(str(c), 0.0) for c in tiles.channel])
        tiles = replace(tiles, z_best_um=tiles.z_best_um + shift, z_tan_um=tiles.z_tan_um + shift,
                        z_sag_um=tiles.z_sag_um + shift)
    # A tile measures the surface averaged over its window, not at its centre: for a surface with Laplacian
    # L the difference is kappa L s^2 / 24 (s = tile side; kappa = 1 for a uniform square window), -0.33 µm
    # for the triplet at 30 px tiles — most of the error budget. One MAP of a rich model gives L at every
    # tile (no model search: only the Laplacian is needed); the final fit sees the centre values. kappa's
    # uncertainty is a systematic shared by the whole field: it joins the band (SurfaceFit.tile_px).
    first = _first_surface(tiles, geometry, channels, source)
    correction = TILE_WINDOW_KAPPA * tile_average_correction_um(first, tiles, float(table.tile_px))
    tiles = replace(tiles, z_best_um=tiles.z_best_um - correction,
                    z_tan_um=tiles.z_tan_um - correction, z_sag_um=tiles.z_sag_um - correction)
    # slanted-edge rows: the band's block covariance without the jackknife's leverage bias (session 16)
    surf = fit_surfaces(tiles, geometry, effort=effort, seed=seed, channels=channels, quiet=quiet,
                        source=source, leverage_corrected=getattr(table, "measure", "") == "esfr", pool=pool)
    surf.tile_px = float(table.tile_px)
    surf.tile_correction_sd = TILE_WINDOW_KAPPA_SD * TILE_WINDOW_KAPPA
    return surf, tiles


class _FirstSurface:
    """The MAP surface of one model, with the ``predict`` of a SurfaceFit (for the Laplacian only)."""

    def __init__(self, model, theta, geometry, zc, zs):
        self.model, self.theta, self.geometry, self.zc, self.zs = model, theta, geometry, zc, zs

    def predict(self, x_px, y_px, channel):
        xh, yh = self.geometry.normalise(x_px, y_px)
        z = self.model.surface(self.theta, xh, yh, self.model.channels.index(channel))
        return self.zc + self.zs * z.reshape(np.shape(xh))


def _first_surface(tiles, geometry, channels, source):
    """One MAP fit of poly3 (per-channel up to rho^2) + tilt [+ decentre]: enough to give the Laplacian."""
    from fieldcal.fit.data import FitError
    from fieldcal.fit.map import fit_map
    from fieldcal.fit.select import build_rows, validate_inputs
    from fieldcal.fit.surface import Rows, SurfaceModel

    validate_inputs(tiles, geometry, channels, source)
    rows, zc, zs = build_rows(tiles, geometry, channels)
    keep = rows.kind == 0
    rows = Rows(*(getattr(rows, f)[keep] for f in ("x_hat", "y_hat", "ch_index", "kind", "target", "sigma")))
    n_ch = len(channels)
    for order, dec in ((3, True), (3, False), (2, False), (1, False), (0, False)):
        model = SurfaceModel(tuple(channels), order, True, dec, False, False, min(order, 1))
        if rows.n >= model.n_params + 2 * n_ch:
            res = fit_map(model, rows)
            if np.isfinite(res.condition_number) and res.condition_number < 1e8:
                return _FirstSurface(model, res.theta, geometry, zc, zs)
    raise FitError("too few tiles for a first surface fit", path=source, field="tiles",
                   fix="use a finer tile grid or a chart that fills the frame")


def tile_average_correction_um(surface, tiles, tile_px: float) -> np.ndarray:
    """Tile-averaged minus centre value of a fitted surface, L s^2 / 24, per tile row (µm).

    The mean of a smooth z over a square of side s about p is z(p) + (z_xx + z_yy) s^2 / 24 + O(s^4); the
    Laplacian comes from central differences of the surface at half a tile.
    """
    h = 0.5 * tile_px
    x = np.asarray(tiles.x_px, dtype=np.float64)
    y = np.asarray(tiles.y_px, dtype=np.float64)
    out = np.zeros(x.size)
    for c in dict.fromkeys(np.asarray(tiles.channel).tolist()):
        m = np.asarray(tiles.channel) == c
        f = lambda dx, dy: surface.predict(x[m] + dx, y[m] + dy, c)
        lap = (f(h, 0) + f(-h, 0) + f(0, h) + f(0, -h) - 4.0 * f(0, 0)) / (h * h)
        out[m] = lap * tile_px * tile_px / 24.0
    return out


def stage_sd_um(table, repeatability_um: float) -> dict[str, float]:
    """Per channel, the best-focus sd that independent per-frame stage-position noise causes (µm).

    Each curve fit gives its ``stage_gain`` = sqrt(sum c_k^2), the best-focus change per unit of frame-position
    noise (fieldcal.measure.throughfocus). The frames are shared by every tile, so the error is common to the
    tiles that use the same frames: counted as a field-wide term, the RMS gain times the repeatability.
    """
    out = {}
    gains = getattr(table, "stage_gain", None)
    for c in dict.fromkeys(np.asarray(table.channel).tolist()):
        if repeatability_um <= 0 or gains is None:
            out[c] = 0.0
            continue
        g = np.asarray(gains, dtype=np.float64)[(np.asarray(table.channel) == c) & table.ok]
        g = g[np.isfinite(g)]
        out[c] = float(repeatability_um * np.sqrt(np.mean(g * g))) if g.size else float(repeatability_um)
    return out


def measure_offset_sd_um(table) -> dict[str, float]:
    """Per channel, the sd of the ``"sml@fs"`` offset's error (µm), shared by every tile of the channel.

    The offset moving each SML best focus to the band-pass at fs is one pooled number per channel
    (:func:`fieldcal.measure.throughfocus.apply_measure_offset`; at quick effort measured on a strip of tiles,
    :mod:`fieldcal.measure.fs_strip`): its error is one draw for the whole field, a band term no fit of the
    tiles can see. A channel that borrowed the others' offset (``offset_from``) has the borrowed one's error
    here too (its tiles' sds do not carry it: ``measure.tiles._borrow_offsets``).

    With it, in quadrature, the error of the band-pass's peak moved to the sharpest position at fs: the
    band-pass weights a band of frequencies about fs, and where the sharpest position moves with frequency
    (spherical aberration) its peak is the band's weighted mean of them; :func:`band_correction_um` moves the
    tiles there, and this is that correction's sd (the measured slope and curvature of z(ln f) and the
    expansion's model error; ~0 on a lens without spherical aberration). A record without the curvature (no fs
    band on the slope strip's tiles) is not corrected: its term is ``|dz/dln f| x |ln(f_eff / fs)|``.
    """
    from fieldcal.measure.throughfocus import offset_sd_um
    out = {}
    for c, rec in (getattr(table, "skew", None) or {}).items():
        if not isinstance(rec, dict):
            out[str(c)] = 0.0
            continue
        own = offset_sd_um(rec)
        # the band-pass's own peak is that of its band, not of fs alone: the error of moving it to fs
        out[str(c)] = math.hypot(own, band_correction_um(rec)[1])
    return out


def band_correction_um(rec: dict) -> tuple[float, float]:
    """(correction, sd) µm of one channel's ``table.skew`` record: what moves the band-pass measure's peak (and
    the ``"sml@fs"`` best foci, which the offset put there) to the sharpest position at fs itself
    (:func:`fieldcal.measure.throughfocus.band_peak_correction_um` with the log-Gabor ring's ln-f variance)."""
    from fieldcal.measure.fs_strip import BAND_LOG_VAR
    from fieldcal.measure.throughfocus import band_peak_correction_um
    if not isinstance(rec, dict):
        return 0.0, 0.0
    return band_peak_correction_um(rec, BAND_LOG_VAR)


def band_corrections_um(table) -> dict[str, float]:
    """Per channel, :func:`band_correction_um` of its ``table.skew`` record (none for a channel without one: a
    table whose best focus is not the band-pass's, ``measure="sml"``, has no record of the slope)."""
    return {str(c): band_correction_um(rec)[0] for c, rec in (getattr(table, "skew", None) or {}).items()}


def breathing_systematic_sd_um(table) -> dict[str, float]:
    """Per channel, the sd of the best-focus error the SML's breathing correction leaves (µm).

    The scale-following SML is invariant to the scene's magnification; what breathing leaves is a gain m^k on
    the curve from the MTFs fixed at the sensor while the scene grows (pixel aperture, diffraction). The
    measurement divides out the k of the factors the stack declares and records the sd of what is left
    (``table.sml_gain[c]["k_sd"]``, :mod:`fieldcal.measure.sml_gain`: the dilated operator's own, plus a
    camera's k where the stack does not say); a table without that record (older) takes
    ``SML_SCALE_RESIDUAL_SD``. Every tile of a channel shares that error, scaled by its own sensitivity dz/dk
    (measured on this stack): the RMS of those sensitivities times the sd is a systematic no fit can see. Zero
    without breathing (telecentric).
    """
    from fieldcal.measure.tiles import SML_SCALE_RESIDUAL_SD

    out = {}
    sens = getattr(table, "z_dgamma_um", None)
    gains = getattr(table, "sml_gain", None) or {}
    for c in dict.fromkeys(np.asarray(table.channel).tolist()):
        if sens is None:
            out[c] = 0.0
            continue
        v = np.asarray(sens, dtype=np.float64)[(np.asarray(table.channel) == c) & table.ok]
        v = v[np.isfinite(v)]
        k_sd = float(gains[c]["k_sd"]) if c in gains else SML_SCALE_RESIDUAL_SD
        out[c] = float(k_sd * np.sqrt(np.mean(v * v))) if v.size else 0.0
    return out


def systematic_record(surf) -> dict:
    """How the band's systematic terms were estimated from this stack (the values in µm)."""
    d = surf.discrepancy
    rec = {"method": "estimated from the stack's tiles: model misfit by the F test of the chosen surface "
                     "against the richest linear surface; common-mode tile error as a fixed fraction of the "
                     "fitted per-tile noise sd (docs/fitting.md 'Systematic')"}
    if d is not None:
        rec.update(d.band_terms_um(float(surf.z_scale_um)))
    return rec


def colour_rows(geo, cols) -> np.ndarray | None:
    """Lateral colour per row: the channel's scale relative to G (or the first channel) at the reference frame."""
    lcs = geo.lateral_colour_scale
    if not lcs:
        return None
    ref = "G" if "G" in geo.channels else geo.channels[0]
    base = float(lcs.get(ref, 1.0))
    at_ref = np.isclose(cols["z_um"], geo.z_ref_um)
    return np.array([float(lcs[c]) / base if (a and c in lcs) else np.nan
                     for c, a in zip(cols["channel"], at_ref)])


def geometry_columns(geo) -> dict:
    """Per-frame measurements flattened to columns (one row per frame and channel) for reports."""
    n, c = geo.magnification.shape
    # The reference frame's values are 1 and 0 by definition (sigma 0); fit_geometry ignores those rows for
    # slopes, but wants positive sigmas.
    tiny = 1e-12
    return {"z_um": np.repeat(geo.z_um, c), "channel": np.tile(np.asarray(geo.channels, dtype=str), n),
            "magnification": geo.magnification.ravel(), "mag_sigma": np.maximum(geo.mag_sigma.ravel(), tiny),
            "shift_x_px": geo.shift_x_px.ravel(), "shift_y_px": geo.shift_y_px.ravel(),
            "shift_sigma_px": np.maximum(geo.shift_sigma_px.ravel(), tiny)}
