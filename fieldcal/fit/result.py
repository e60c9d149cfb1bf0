"""``SurfaceFit``: the chosen best-focus surface model with its posterior samples, in pixel/µm units."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fieldcal.formats.atomic import jsonable
from ..errors import ParameterError, SpecError
from .data import ImageGeometry
from .discrepancy import Discrepancy
from .surface import SurfaceModel

SURFACE_FIT_FORMAT = "fieldcal-surface-fit/1"
_POINT_CHUNK = 4096  # points per block when evaluating samples x points (bounded memory)


@dataclass
class SurfaceFit:
    """Per-channel best-focus surfaces (µm, stage coordinates) with credible bands.

    Attributes
    ----------
    model : SurfaceModel
        The chosen candidate (``model.name``, ``model.terms``).
    geometry : ImageGeometry
        Frame of the pixel coordinates.
    z_centre_um, z_scale_um : float
        z normalisation: parameters live in ``(z - z_centre_um) / z_scale_um``.
    theta_map : ndarray
        MAP parameter vector (normalised units), named by ``param_names``.
    samples : ndarray
        Posterior samples (S x P, S <= a few thousand) of the same vector.
    candidates : list of dict
        Every candidate model tried, with its score (see ``diagnostics["selection"]``).
    diagnostics : dict
        Condition number, optimiser result, posterior method, tau/acceptance/ESS or Laplace status, ...
    """

    model: SurfaceModel
    geometry: ImageGeometry
    z_centre_um: float
    z_scale_um: float
    theta_map: np.ndarray
    samples: np.ndarray
    candidates: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    effort: str = "standard"
    sample_model: SurfaceModel | None = None  # layout of ``samples`` (the union of the averaged models)
    discrepancy: Discrepancy | None = None     # correlated residual term (docs/fitting.md "Discrepancy")
    tile_px: float | None = None               # tile side of the measurement (px), for the window systematic
    tile_correction_sd: float = 0.0            # sd of kappa in the tile-window correction kappa L s^2 / 24
    # scale of the band's non-common field terms, learned by the leave-tiles-out check (fieldcal.fit.selfcheck)
    band_scale: float = 1.0
    # per channel, 1-sigma best-focus error shared by the field from stage-position noise (µm)
    stage_sd_um: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.sample_model is None:
            self.sample_model = self.model

    # ------------------------------------------------------------------ access
    @property
    def channels(self) -> tuple[str, ...]:
        return self.model.channels

    @property
    def param_names(self) -> list[str]:
        return self.model.names

    def _ch(self, channel: str) -> int:
        try:
            return self.model.channels.index(channel)
        except ValueError:
            raise ParameterError(f"no channel '{channel}' in this fit (it has {', '.join(self.channels)})",
                                 field="channel", fix=f"use one of {', '.join(self.channels)}") from None

    def _eval(self, theta, x_px, y_px, channel, fn="surface", model=None):
        x, y = np.broadcast_arrays(np.asarray(x_px, dtype=np.float64), np.asarray(y_px, dtype=np.float64))
        xh, yh = self.geometry.normalise(x.ravel(), y.ravel())
        ci = self._ch(channel)
        return getattr(model or self.model, fn)(theta, xh, yh, ci), x.shape

    def _kriged(self, xh, yh, ci, covered=None):
        """(mean, extra variance) of the discrepancy-aware posterior, normalised units (``covered``: what the
        samples already add beyond the chosen model's posterior, :meth:`Discrepancy.predict`)."""
        return self.discrepancy.predict(xh, yh, ci, covered=covered)

    def model_average_covered(self, z, xh, yh, ci):
        """Per point, the variance (normalised z²) of the posterior samples ``z`` (samples x points) beyond the
        chosen model's own posterior (``Discrepancy.iid_cov``): what a model average's other members already state,
        which the misfit term does not count again (:meth:`Discrepancy.predict`; the self-check's error model uses
        it too). None without a model average (one member), and for profiles written before (their bands kept)."""
        if (self.discrepancy is None or not self.discrepancy.misfit_beyond_average
                or len((self.diagnostics.get("model_average") or {}).get("members") or []) < 2):
            return None
        H = self.discrepancy._design(xh, yh, ci)
        own = np.einsum("mp,pq,mq->m", H, self.discrepancy.iid_cov, H)
        # the spread about the samples' own mean: the average's offset from z0 moves the band, it does not widen it
        return np.clip(np.var(np.asarray(z), axis=0) - own, 0.0, None)

    def _window_var(self, x_px, y_px, channel):
        """Variance (normalised z) of the tile-window correction's systematic: (sd_kappa L s^2 / 24)^2."""
        if not self.tile_px or self.tile_correction_sd <= 0:
            return 0.0
        h = 0.5 * self.tile_px
        f = lambda dx, dy: self._eval(self.theta_map, x_px + dx, y_px + dy, channel)[0]
        lap = (f(h, 0) + f(-h, 0) + f(0, h) + f(0, -h) - 4.0 * f(0, 0)) / (h * h)
        return (self.tile_correction_sd * lap * self.tile_px ** 2 / 24.0) ** 2

    def predict(self, x_px, y_px, channel: str) -> np.ndarray:
        """Best-focus position (µm) at pixel coordinates; arrays broadcast.

        The chosen model's generalised-least-squares surface plus the kriged discrepancy between tiles
        (without a discrepancy term: the MAP surface).
        """
        if self.discrepancy is None:
            z, shape = self._eval(self.theta_map, x_px, y_px, channel)
            return (self.z_centre_um + self.z_scale_um * z).reshape(shape)
        x, y = np.broadcast_arrays(np.asarray(x_px, dtype=np.float64), np.asarray(y_px, dtype=np.float64))
        xh, yh = self.geometry.normalise(x.ravel(), y.ravel())
        out = np.empty(xh.size)
        ci = self._ch(channel)
        for a in range(0, max(xh.size, 1), _POINT_CHUNK):
            sl = slice(a, a + _POINT_CHUNK)
            # the mean only: the variance (a triangular solve per chunk) is ~4x its cost and unused here
            out[sl] = self.discrepancy.predict(xh[sl], yh[sl], ci, with_variance=False)[0]
        return (self.z_centre_um + self.z_scale_um * out).reshape(x.shape)

    def predict_parts(self, x_px, y_px, channel: str) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` split into ``(trend_um, residual_um)``: the polynomial surface (cheap, exact anywhere)
        and the kriged discrepancy (zeros without one), which callers may grid and interpolate
        (``Discrepancy.residual_curvature_bound`` bounds the error). Their sum is :meth:`predict`."""
        x, y = np.broadcast_arrays(np.asarray(x_px, dtype=np.float64), np.asarray(y_px, dtype=np.float64))
        if self.discrepancy is None:
            return self.predict(x, y, channel), np.zeros(x.shape)
        xh, yh = self.geometry.normalise(x.ravel(), y.ravel())
        ci = self._ch(channel)
        trend = self.z_centre_um + self.z_scale_um * self.discrepancy.trend(xh, yh, ci)
        res = np.empty(xh.size)
        for a in range(0, max(xh.size, 1), _POINT_CHUNK):
            sl = slice(a, a + _POINT_CHUNK)
            res[sl] = self.discrepancy.residual(xh[sl], yh[sl], ci)
        return trend.reshape(x.shape), (self.z_scale_um * res).reshape(x.shape)

    def _sample_surfaces(self, x_px, y_px, channel):
        """Yield (slice, S x m block of surfaces in µm) over point chunks."""
        x, y = np.broadcast_arrays(np.asarray(x_px, dtype=np.float64), np.asarray(y_px, dtype=np.float64))
        xf, yf = x.ravel(), y.ravel()
        if self.discrepancy is not None:
            # one standard normal per sample: exact Gaussian marginals at every point, deterministic bands
            xi = np.random.default_rng(12345).standard_normal(self.samples.shape[0])[:, None]
        for a in range(0, max(xf.size, 1), _POINT_CHUNK):
            sl = slice(a, a + _POINT_CHUNK)
            z, _ = self._eval(self.samples, xf[sl], yf[sl], channel, model=self.sample_model)
            if self.discrepancy is not None:
                # samples spread about the MAP (coefficients, centre, model average); re-centred on the kriged
                # surface, plus the variance the correlated discrepancy adds beyond independent tiles
                z0, _ = self._eval(self.theta_map, xf[sl], yf[sl], channel)
                xh, yh = self.geometry.normalise(xf[sl], yf[sl])
                ci = self._ch(channel)
                # what the samples (a model average) add beyond the chosen model's own posterior (iid_cov: the
                # coefficients' covariance the samples carry): the misfit term does not count it again
                mean, extra = self._kriged(xh, yh, ci, covered=self.model_average_covered(z, xh, yh, ci))
                # the leave-tiles-out scale applies to what varies between tiles, not to the common mode
                cs = self.discrepancy.common_sd
                common = float(cs[ci]) ** 2 if cs is not None and ci < cs.size else 0.0
                c = float(self.band_scale)
                # fitted frame errors are already in the kriging variance (Discrepancy.has_stage)
                stage = (0.0 if self.discrepancy.has_stage
                         else float(self.stage_sd_um.get(channel, 0.0)) / self.z_scale_um)
                extra = (c * c * np.clip(extra - common, 0.0, None) + common + stage * stage
                         + self._window_var(xf[sl], yf[sl], channel))
                z = c * (z - z0) + mean + np.sqrt(extra) * xi
            yield sl, self.z_centre_um + self.z_scale_um * z

    def interval(self, x_px, y_px, channel: str, level: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
        """Central credible band (lo, hi) of the surface (µm) at ``level`` (e.g. 0.9)."""
        if not (0.0 < level < 1.0) or not math.isfinite(level):
            raise ParameterError(f"credible level must be in (0, 1), got {level}", field="level",
                                 fix="e.g. level=0.9 for a 90% band")
        shape = np.broadcast(np.asarray(x_px), np.asarray(y_px)).shape
        lo = np.empty(int(np.prod(shape)))
        hi = np.empty_like(lo)
        q = [0.5 - level / 2.0, 0.5 + level / 2.0]
        for sl, zs in self._sample_surfaces(x_px, y_px, channel):
            lo[sl], hi[sl] = np.quantile(zs, q, axis=0)
        return lo.reshape(shape), hi.reshape(shape)

    def sd(self, x_px, y_px, channel: str) -> np.ndarray:
        """Posterior standard deviation of the surface (µm)."""
        shape = np.broadcast(np.asarray(x_px), np.asarray(y_px)).shape
        out = np.empty(int(np.prod(shape)))
        for sl, zs in self._sample_surfaces(x_px, y_px, channel):
            out[sl] = zs.std(axis=0)
        return out.reshape(shape)

    def astigmatism_um(self, x_px, y_px, channel: str) -> np.ndarray:
        """MAP z_tan - z_sag (µm); zeros when the chosen model has no astigmatism term."""
        d, shape = self._eval(self.theta_map, x_px, y_px, channel, fn="astigmatism")
        return (self.z_scale_um * d).reshape(shape)

    def optical_centre_px(self) -> tuple[float, float]:
        """MAP optical centre (the sensor centre when the model has no decentre term)."""
        _, centre, *_ = self.model.split(self.theta_map)
        cx, cy = self.geometry.centre_px
        r = self.geometry.half_diagonal_px
        return (float(cx + centre[0] * r), float(cy + centre[1] * r))

    def error_scale(self) -> float:
        """MAP multiplier s of the per-tile sigmas (> 1: the tile sigmas were underestimated)."""
        return float(math.exp(self.model.split(self.theta_map)[2]))

    def coefficients_um(self, channel: str) -> dict[str, float]:
        """Physical MAP coefficients: offset and rho^2k terms in µm (rho = radius / half-diagonal), tilt in
        µm/mm (about the sensor centre), astigmatism in µm at rho = 1."""
        ci = self._ch(channel)
        beta = self.model.split(self.theta_map)[0]
        m = self.model
        out = {"offset_um": float(self.z_centre_um + self.z_scale_um * beta[m._col_channel(ci, 0)])}
        for k in range(1, m.order + 1):
            out[f"rho{2 * k}_um"] = float(self.z_scale_um * beta[m._col_power(ci, k)])
        r_mm = self.geometry.half_diagonal_px * self.geometry.pixel_pitch_um / 1000.0
        if m.tilt:
            j = m._col_tilt
            out["tilt_x_um_per_mm"] = float(self.z_scale_um * beta[j] / r_mm)
            out["tilt_y_um_per_mm"] = float(self.z_scale_um * beta[j + 1] / r_mm)
        if m.astig:
            j = m._col_astig + ci * m.astig_order
            out["astigmatism_um"] = float(self.z_scale_um * np.sum(beta[j:j + m.astig_order]))
        return out

    # ------------------------------------------------------------------ I/O
    def to_dict(self, include_samples: bool = True) -> dict[str, Any]:
        """JSON-safe dict. With ``include_samples=False`` the samples are left out (write ``self.samples``
        to a sidecar .npz and pass them back to :meth:`from_dict`)."""
        d = {"format": SURFACE_FIT_FORMAT, "effort": self.effort,
             "model": {"name": self.model.name, "terms": self.model.terms, **self.model.to_dict()},
             "geometry": self.geometry.to_dict(),
             "z_centre_um": float(self.z_centre_um), "z_scale_um": float(self.z_scale_um),
             "param_names": self.param_names,
             "sample_model": self.sample_model.to_dict(), "sample_param_names": self.sample_model.names,
             "theta_map": [float(v) for v in self.theta_map],
             "candidates": jsonable(self.candidates), "diagnostics": jsonable(self.diagnostics),
             "n_samples": int(self.samples.shape[0])}
        if self.discrepancy is not None:
            d["discrepancy"] = jsonable(self.discrepancy.to_dict())
        if self.tile_px:
            d["tile_window"] = {"tile_px": float(self.tile_px), "kappa_sd": float(self.tile_correction_sd)}
        if self.band_scale != 1.0:
            d["band_scale"] = float(self.band_scale)
        if self.stage_sd_um:
            d["stage_sd_um"] = {str(k): float(v) for k, v in self.stage_sd_um.items()}
        if include_samples:
            d["samples"] = self.samples.tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], samples: np.ndarray | None = None, path=None) -> "SurfaceFit":
        if not isinstance(d, dict) or d.get("format") != SURFACE_FIT_FORMAT:
            raise SpecError(f"not a {SURFACE_FIT_FORMAT} block", path=path, field="format",
                            fix="write it with SurfaceFit.to_dict()")
        try:
            model = SurfaceModel.from_dict(d["model"])
            theta = np.asarray(d["theta_map"], dtype=np.float64)
            if samples is None:
                if "samples" not in d:
                    raise SpecError("posterior samples are missing", path=path, field="samples",
                                    fix="keep the samples sidecar .npz next to the profile")
                samples = d["samples"]
            samples = np.asarray(samples, dtype=np.float64)
            smodel = SurfaceModel.from_dict(d.get("sample_model", d["model"]))
            if theta.shape != (model.n_params,) or samples.ndim != 2 or samples.shape[1] != smodel.n_params:
                raise SpecError(f"parameter count does not match model {model.name} ({model.n_params})",
                                path=path, field="theta_map", fix="regenerate the profile")
            disc = Discrepancy.from_dict(d["discrepancy"], model) if d.get("discrepancy") else None
            return cls(model, ImageGeometry.from_dict(d["geometry"]), float(d["z_centre_um"]),
                       float(d["z_scale_um"]), theta, samples, list(d.get("candidates", [])),
                       dict(d.get("diagnostics", {})), str(d.get("effort", "standard")), smodel, disc,
                       (d.get("tile_window") or {}).get("tile_px"),
                       float((d.get("tile_window") or {}).get("kappa_sd", 0.0)),
                       # optional keys (absent in older profiles: their bands are unchanged)
                       float(d.get("band_scale", 1.0)),
                       {str(k): float(v) for k, v in (d.get("stage_sd_um") or {}).items()})
        except (KeyError, TypeError, ValueError) as e:
            raise SpecError(f"malformed surface fit ({e})", path=path, field="surface",
                            fix="regenerate the profile with fieldcal calibrate") from None
