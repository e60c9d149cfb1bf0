"""Model discrepancy: a spatially correlated residual term so the surface band stays honest end to end.

Why: per-tile ``z_sigma_um`` from the measurement is too small (chi ~ 4 on the triplet) *and* the residuals
of neighbouring tiles are not independent (measurement systematics shared by neighbours, a surface that is
not exactly a low-order polynomial, the tile-average correction). A posterior that treats tiles as
independent shrinks like 1/sqrt(n_tiles) and is overconfident: measured 90 % bands held the truth at only
36-73 % of field points at standard effort.

Model (per channel c, normalised units, focus rows only)::

    y_i = X_i beta + delta_c(x_i) + eps_i
    delta_c ~ GP(0, tau_c^2 k(d / ell)),   k = Matern 3/2,  d = distance in the normalised image plane
    eps_i   ~ N(0, s^2 sigma_i^2 / u_i)    (u_i: the Student-t weight of row i at the MAP, so outliers stay out)

with the length scale ``ell`` and the white-noise scale ``s`` shared by the channels and one amplitude
``tau_c`` per channel. The hyperparameters maximise the *restricted* (REML) likelihood, which integrates
beta out and so does not shrink the variance by the number of coefficients. Given them, the surface
posterior is universal kriging (closed form): the coefficients have covariance ``(X^T K^-1 X)^-1`` (honest
under correlated errors: it does not fall like 1/n once the tiles are closer than ``ell``), the discrepancy
is interpolated between tiles and returns to its prior ``tau_c^2`` away from them (corners outside the
tile grid get wider bands).

:class:`Discrepancy` keeps only its inputs (row positions, targets, noise variances, hyperparameters) so it
serialises in a few kB; the Cholesky factors are rebuilt on first use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import nlopt
import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from .surface import COEF_PRIOR_SD, Rows, SurfaceModel

MAX_ROWS_HYPER = 400          # rows per channel used to fit the hyperparameters (evenly thinned beyond)
LOG_S_BOUNDS = (math.log(0.5), math.log(1.0e4))
JITTER = 1.0e-10
# Shortest correlation length, in tile spacings. (A bound of one spacing would keep REML from splitting white
# tile noise into a GP nugget, but it moved the kriging mean: surface RMS 0.39 -> 0.93 µm on one random lens.)
ELL_MIN_SPACINGS = 0.5
# Misfit test: the chosen model against the richest linear surface with the same centre (all terms per channel
# up to rho^(2 RICH_ORDER), tilt); needs this many rows beyond its parameters.
RICH_ORDER = 3
MIN_RICH_DOF = 5
# Common-mode tile error: a fraction of the per-tile noise shared by the whole field (frame-level errors of the
# through-focus curves, shared by neighbouring tiles and the colour channels), which no fit can see in its
# residuals. Measured on 16 random lenses x 2 efforts + the triplet: the surface error beyond the independent-
# tile propagation is 0-0.75 (rms 0.4) of the per-tile noise sd (docs/fitting.md "Systematic").
COMMON_MODE_FRACTION = 0.2


def matern32(d_over_ell: np.ndarray) -> np.ndarray:
    """Matern nu = 3/2 correlation: continuous, once differentiable (tile systematics are not smooth)."""
    a = math.sqrt(3.0) * d_over_ell
    return (1.0 + a) * np.exp(-a)


def _dist(xa, ya, xb, yb) -> np.ndarray:
    return np.hypot(xa[:, None] - xb[None, :], ya[:, None] - yb[None, :])


def _nn_spacing(x, y) -> float:
    """Median nearest-neighbour distance between rows of one channel (normalised units)."""
    if x.size < 2:
        return 0.1
    d = _dist(x, y, x, y)
    np.fill_diagonal(d, np.inf)
    nn = d.min(axis=1)
    nn = nn[np.isfinite(nn) & (nn > 0)]
    return float(np.median(nn)) if nn.size else 0.1


@dataclass
class Discrepancy:
    """Universal-kriging posterior of the mean surfaces with a correlated discrepancy (normalised units).

    Attributes
    ----------
    model : SurfaceModel
        The mean-surface structure (the chosen model), evaluated at ``centre``.
    centre : (2,) ndarray
        Optical centre (normalised) of the design.
    x_hat, y_hat, ch_index, target, noise_var : ndarray
        Focus rows: position, channel index, normalised best focus and white-noise variance
        ``s^2 sigma_i^2 / u_i``.
    tau : ndarray
        Discrepancy amplitude per channel (normalised z units).
    length_scale : float
        Correlation length (normalised image-plane units: 1 = half the diagonal).
    noise_scale : float
        The fitted multiplier s of the reported per-tile sigmas.
    iid_cov : ndarray
        Covariance of the coefficients the *independent-tile* posterior has (the MAP's own weights); the band
        adds only the variance beyond it, so samples that already carry it are not counted twice.
    jk_cov : ndarray or None
        Block covariance of the coefficients (errors shared by regions of tiles; :func:`block_jackknife_cov`,
        leverage-corrected for slanted-edge rows since session 16).
    rich_model, rich_cov, misfit_scale : SurfaceModel, ndarray, float
        Misfit term ``misfit_scale * (h_r rich_cov h_r^T - h iid_cov h^T)``: the variance the richest linear
        surface adds over the chosen one, scaled by how much more than noise the two disagree on the tiles
        (the F statistic of the extra terms minus 1; 0 when the data do not support them).
    common_sd : ndarray or None
        Per channel, the sd of the error shared by the whole field (``COMMON_MODE_FRACTION`` of the per-tile
        noise sd, or measured on the stack: :meth:`set_common_mode`); added in quadrature at every point.
    stage_c, stage_prior_sd : ndarray or None, float
        Per-frame stage position errors as nuisance coefficients (:mod:`fieldcal.fit.stage`): row i's best focus
        moves by ``stage_c[i] @ e`` with ``e ~ N(0, stage_prior_sd^2)`` per frame (normalised z units). They are
        fitted jointly with the surface (GLS with their prior), so their identifiable part is removed and the
        rest is marginalised into the band, correlated over the field as the frames are shared.
    """

    model: SurfaceModel
    centre: np.ndarray
    x_hat: np.ndarray
    y_hat: np.ndarray
    ch_index: np.ndarray
    target: np.ndarray
    noise_var: np.ndarray
    tau: np.ndarray
    length_scale: float
    noise_scale: float
    iid_cov: np.ndarray
    jk_cov: np.ndarray | None = None
    diagnostics: dict = field(default_factory=dict)
    rich_model: SurfaceModel | None = None      # misfit test: the richest linear surface (same centre)
    rich_cov: np.ndarray | None = None          # its coefficient covariance under the MAP's weights
    misfit_scale: float = 0.0                   # max(F - 1, 0) * Birge ratio of the rich fit
    common_sd: np.ndarray | None = None         # per channel: common-mode sd (normalised z units)
    stage_c: np.ndarray | None = None           # rows x frames: best-focus change per frame position error
    stage_prior_sd: float = 0.0                 # the stage's repeatability (normalised z units)
    # the misfit term adds only what a model average does not state (predict's ``covered``); False for profiles
    # written before (session 13), which keep their bands
    misfit_beyond_average: bool = False
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ------------------------------------------------------------------ linear algebra (cached)
    def _design(self, x_hat, y_hat, ci: int) -> np.ndarray:
        n = np.asarray(x_hat).size
        return self.model.design(np.asarray(x_hat, float), np.asarray(y_hat, float), np.full(n, ci),
                                 np.zeros(n, np.int64), self.centre)

    @property
    def has_stage(self) -> bool:
        """True when the per-frame stage errors are fitted with the surface (and so are in :meth:`predict`)."""
        return (self.stage_c is not None and self.stage_prior_sd > 0 and self.stage_c.ndim == 2
                and self.stage_c.shape[0] == self.target.size)

    def attach_stage(self, sensitivity: np.ndarray, prior_sd: float) -> None:
        """Fit the frames' position errors with the surface (in place): ``sensitivity`` is rows x frames (the
        best-focus change of each focus row per unit of each frame's error), ``prior_sd`` the repeatability
        (normalised z units).

        The common-mode term then goes: it stood for "frame-level errors of the through-focus curves shared by
        the tiles", which the fitted frames now carry with their own correlation over the field. Kept beside
        them it counted those errors twice: over the 40 lenses of the band-coverage benchmark (stage noise
        0.1-0.5 µm) the per-channel piston errors asked for 0-0.25 of its variance, and for 1.1-2.0 of the
        fitted frames' (docs/fitting.md "Field-wide terms, term by term"). It stays where no frames are fitted
        (no stated repeatability); its value is kept in the diagnostics.
        """
        self.stage_c, self.stage_prior_sd = np.asarray(sensitivity, float), float(prior_sd)
        self._cache.clear()
        if self.has_stage and self.common_sd is not None and np.any(self.common_sd > 0):
            self.diagnostics["common_mode_sd_replaced"] = [float(v) for v in self.common_sd]
            self.diagnostics["common_mode_sd"] = [0.0] * int(self.common_sd.size)
            self.common_sd = np.zeros_like(self.common_sd)

    def set_common_mode(self, sd: np.ndarray, source: str) -> None:
        """Replace the common-mode sd (per channel, normalised z units) by one measured on the stack (in place).

        The default, ``COMMON_MODE_FRACTION`` of the per-tile noise sd, stands for frame-level errors of the
        through-focus curves shared by the tiles. A slanted-edge peak's field-wide error is its law's, which
        does not scale with the per-edge noise: over-stated 2x on fieldcal's renderer, several times
        under-stated on the clean-room's spherical aberration (docs/benchmarks.md
        "bench_edge_calibration_s10_cm"). The e-SFR peak estimator measures it on each stack
        (:func:`fieldcal.measure.esfr_focus.law_common_mode`); the stage frames, where fitted, still replace it
        (:meth:`attach_stage`)."""
        sd = np.asarray(sd, dtype=np.float64)
        if sd.shape != (len(self.model.channels),) or not np.all(np.isfinite(sd) & (sd >= 0)):
            raise ValueError(f"common-mode sd must be one finite sd >= 0 per channel, got {sd!r}")
        if self.common_sd is not None:
            self.diagnostics["common_mode_sd_default"] = [float(v) for v in self.common_sd]
        self.common_sd = sd.copy()
        self.diagnostics["common_mode_sd"] = [float(v) for v in sd]
        self.diagnostics["common_mode_fraction"] = None
        self.diagnostics["common_mode_source"] = str(source)
        self._cache.clear()

    def without_nuisances(self) -> "Discrepancy":
        """The same posterior without the fitted stage frames (their share of the band, by difference)."""
        return replace(self, stage_c=None, stage_prior_sd=0.0, _cache={})

    def _state(self):
        if "chol" in self._cache:
            return self._cache
        X = self.model.design(self.x_hat, self.y_hat, self.ch_index, np.zeros(self.x_hat.size, np.int64),
                              self.centre)
        p = X.shape[1]
        prior = np.full(p, 1.0 / COEF_PRIOR_SD ** 2)
        if self.has_stage:  # the frames' position errors: coefficients shared by every channel, prior sd r
            X = np.hstack([X, self.stage_c])
            prior = np.concatenate([prior, np.full(self.stage_c.shape[1], 1.0 / self.stage_prior_sd ** 2)])
        chol, kinv_x, kinv_y = {}, np.zeros_like(X), np.zeros(self.target.size)
        for ci in range(len(self.model.channels)):
            m = self.ch_index == ci
            if not m.any():
                continue
            K = _cov(self.x_hat[m], self.y_hat[m], self.tau[ci], self.length_scale, self.noise_var[m])
            cf = cho_factor(K, lower=True)
            chol[ci] = cf
            kinv_x[m] = cho_solve(cf, X[m])
            kinv_y[m] = cho_solve(cf, self.target[m])
        A = X.T @ kinv_x + np.diag(prior)
        A_inv = np.linalg.inv(0.5 * (A + A.T))
        # the surface coefficients' covariance without the frames: the frames' share of the band is the increase
        # over it, added outside the block jackknife's maximum in predict (the jackknife cannot see it)
        A0 = A[:p, :p] if X.shape[1] > p else A
        bare_cov = np.linalg.inv(0.5 * (A0 + A0.T)) if X.shape[1] > p else A_inv
        beta = A_inv @ (X.T @ kinv_y)
        resid = self.target - X @ beta
        alpha = np.zeros_like(resid)
        for ci, cf in chol.items():
            m = self.ch_index == ci
            alpha[m] = cho_solve(cf, resid[m])
        self._cache.update(chol=chol, X=X, kinv_x=kinv_x, beta=beta, beta_cov=A_inv, bare_cov=bare_cov, alpha=alpha,
                           p=p)
        return self._cache

    @property
    def beta(self) -> np.ndarray:
        """Generalised-least-squares coefficients of the surface under the correlated covariance."""
        st = self._state()
        return st["beta"][:st["p"]]

    @property
    def beta_cov(self) -> np.ndarray:
        """Their covariance (the stage errors marginalised)."""
        st = self._state()
        return st["beta_cov"][:st["p"], :st["p"]]

    @property
    def stage_errors(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(estimate, sd) of the per-frame stage position errors (normalised z units), or None."""
        if not self.has_stage:
            return None
        st = self._state()
        p, f = st["p"], self.stage_c.shape[1]
        return st["beta"][p:p + f], np.sqrt(np.clip(np.diag(st["beta_cov"])[p:p + f], 0.0, None))

    def _kernel_rows(self, x_hat, y_hat, ci: int) -> np.ndarray:
        """``k(x, x_i)`` between points and the channel's rows (m x n_c)."""
        m = self.ch_index == ci
        return self.tau[ci] ** 2 * matern32(_dist(x_hat, y_hat, self.x_hat[m], self.y_hat[m]) / self.length_scale)

    def gp_identified(self) -> float:
        """Fraction (0-1) of the GP's local variance that is surface rather than tile noise: 0 at the shortest
        length scale (half a tile spacing: a nugget), 1 from one spacing up (see :meth:`predict`)."""
        spacing = float(self.diagnostics.get("tile_spacing") or 0.0)
        if spacing <= 0:
            return 1.0
        return float(np.clip((self.length_scale / spacing - ELL_MIN_SPACINGS) / (1.0 - ELL_MIN_SPACINGS), 0.0, 1.0))

    def _has_gp(self, ci: int) -> bool:
        return ci in self._state()["chol"] and self.tau[ci] > 0

    def trend(self, x_hat, y_hat, ci: int) -> np.ndarray:
        """The generalised-least-squares surface ``h beta`` at points (normalised z): cheap, polynomial."""
        x_hat = np.asarray(x_hat, float).ravel()
        y_hat = np.asarray(y_hat, float).ravel()
        return self._design(x_hat, y_hat, ci) @ self.beta

    def residual(self, x_hat, y_hat, ci: int) -> np.ndarray:
        """The kriged discrepancy ``k^T K^-1 (y - X beta)`` at points (normalised z); 0 without a GP term.

        ``trend + residual`` is the kriging mean of :meth:`predict`, bit for bit.
        """
        x_hat = np.asarray(x_hat, float).ravel()
        y_hat = np.asarray(y_hat, float).ravel()
        if not self._has_gp(ci):
            return np.zeros(x_hat.size)
        return self._kernel_rows(x_hat, y_hat, ci) @ self._state()["alpha"][self.ch_index == ci]

    def residual_curvature_bound(self, ci: int) -> float:
        """Upper bound on ``|d^2 r / dx^2|`` and ``|d^2 r / dy^2|`` of :meth:`residual` (normalised units).

        For the Matern 3/2 correlation ``k(r) = (1 + a r) e^(-a r)`` (``a = sqrt(3) / ell``) a second partial
        derivative is ``-a^2 e^(-a r) [(1 - a r) cos^2 + sin^2]``, at most ``a^2 k(r) <= a^2`` in size, so
        ``|r_xx| <= tau^2 a^2 sum |alpha_i|``. Bilinear interpolation on a grid of step h (normalised) then errs
        by at most ``h^2 / 8 (|r_xx| + |r_yy|) <= h^2 / 4 * bound``. Loose (every tile at its worst at once).
        """
        if not self._has_gp(ci):
            return 0.0
        a = math.sqrt(3.0) / self.length_scale
        alpha = self._state()["alpha"][self.ch_index == ci]
        return float(self.tau[ci] ** 2 * a * a * np.sum(np.abs(alpha)))

    def predict(self, x_hat, y_hat, ci: int, with_variance: bool = True, nuisance: bool = True,
                covered=None):
        """Kriging mean and the variance *beyond* the independent-tile posterior at points (normalised z).

        Returns ``(mean, extra_var)``: ``mean = h beta + k^T K^-1 (y - X beta)``; ``extra_var`` = kriging
        variance minus ``h iid_cov h^T`` (clipped at 0). With ``with_variance=False`` returns ``(mean, None)``,
        the same mean without the triangular solve and the covariance terms (the costly part, ~4x the mean).

        The fitted stage frames (:attr:`has_stage`) add what they leave unknown to the variance *after* the block
        jackknife's maximum: a frame's error moves every tile whose curve uses it, so most of it is one shift of
        the whole field, which deleting a block of tiles does not change and the jackknife cannot see (inside
        the maximum it vanished wherever the jackknife was the larger: 0.00-0.02 µm stated where the frames
        moved the surface by 0.05-0.1 µm). ``nuisance=False`` leaves that share out (a held-out tile shares it).

        ``covered``: per point, the variance (normalised z²) the caller's posterior samples already add beyond the
        chosen model's own posterior (a model average's other members, :meth:`SurfaceFit._sample_surfaces`): the
        misfit term adds only what it states beyond that. Both say "the chosen surface may be too simple" from
        the same tiles (the misfit by the F test against the richest surface, the average by the candidates'
        scores), so their sum counted that doubt twice: on flat (poly1) random lenses with a 0.01 µm rest error
        the two together stated 0.14-0.23 µm of local sd.
        """
        st = self._state()
        x_hat = np.asarray(x_hat, float).ravel()
        y_hat = np.asarray(y_hat, float).ravel()
        H = self._design(x_hat, y_hat, ci)
        p = st["p"]
        mean = H @ st["beta"][:p]
        if not with_variance:
            if self._has_gp(ci):
                mean = mean + self._kernel_rows(x_hat, y_hat, ci) @ st["alpha"][self.ch_index == ci]
            return mean, None
        # a point's best focus has no stage term (zero columns): the frames' errors enter through the fit only
        Ha = np.hstack([H, np.zeros((H.shape[0], st["beta"].size - p))])
        var = np.einsum("mp,pq,mq->m", H, st["bare_cov"], H)
        frames = np.clip(np.einsum("mp,pq,mq->m", Ha, st["beta_cov"], Ha) - var, 0.0, None)
        if ci in st["chol"] and self.tau[ci] > 0:
            m = self.ch_index == ci
            ks = self._kernel_rows(x_hat, y_hat, ci)
            mean = mean + ks @ st["alpha"][m]
            L = st["chol"][ci][0]
            V = solve_triangular(L, ks.T, lower=True)                     # n_c x m
            R = Ha - ks @ st["kinv_x"][m]                                 # h - k^T K^-1 X
            # A GP shorter than a tile spacing cannot be told from tile noise (a nugget): its variance between
            # tiles is noise, not surface (measured: 0.15-0.4 µm sd added where the errors were 0.07-0.2 µm).
            # It counts in full from one spacing, not at all at the lower bound of half a spacing.
            local = self.gp_identified() * np.clip(self.tau[ci] ** 2 - np.sum(V * V, axis=0), 0.0, None)
            Rp = R[:, :p]
            var = local + np.einsum("mp,pq,mq->m", Rp, st["bare_cov"], Rp)
            frames = np.clip(np.einsum("mp,pq,mq->m", R, st["beta_cov"], R) - (var - local), 0.0, None)
        else:
            local = 0.0
        if self.jk_cov is not None:
            # errors shared by whole blocks of tiles look like coefficients to the GP: the block jackknife
            # sees them (docs/fitting.md "Discrepancy")
            var = np.maximum(var, local + np.einsum("mp,pq,mq->m", H, self.jk_cov, H))
        iid = np.einsum("mp,pq,mq->m", H, self.iid_cov, H)
        extra = np.clip(var - iid, 0.0, None) + (frames if nuisance else 0.0)
        if self.rich_model is not None and self.misfit_scale > 0:
            Hr = self.rich_model.design(x_hat, y_hat, np.full(x_hat.size, ci), np.zeros(x_hat.size, np.int64),
                                        self.centre)
            diff = np.einsum("mp,pq,mq->m", Hr, self.rich_cov, Hr) - iid
            misfit = self.misfit_scale * np.clip(diff, 0.0, None)
            if covered is not None:
                misfit = np.clip(misfit - np.asarray(covered, float), 0.0, None)
            extra = extra + misfit
        if self.common_sd is not None and ci < self.common_sd.size:
            extra = extra + float(self.common_sd[ci]) ** 2
        return mean, extra

    def frames_mean_var(self, x_hat, y_hat, ci: int) -> float:
        """Variance (normalised z²) the fitted stage frames add to the *mean* of the surface over the points.

        :meth:`predict`'s frames share is pointwise: ``R C R^T - R_p C_0 R_p^T`` with ``R = h - k^T K^-1 X`` (the
        surface coefficients' and the frames' columns) and ``C``, ``C_0`` the posterior covariances with and
        without the frames. A frame's error moves only the tiles whose curves use it, so where the tiles peak
        at different frames (field curvature over several scan steps) much of that share changes over the
        field and is not one shift of the whole field: the field mean's share is the same form at the mean row
        ``R̄``, at most the pointwise mean (the difference of the two covariances is positive semi-definite).
        Recalibrated with the recorded frame positions redrawn from the stated repeatability, 8 benchmark stacks'
        surfaces moved pointwise by about what the frames state, their field mean by less (docs/benchmarks.md
        "bench_band_coverage_s13"). 0 without fitted frames.
        """
        if not self.has_stage:
            return 0.0
        st = self._state()
        x_hat = np.asarray(x_hat, float).ravel()
        y_hat = np.asarray(y_hat, float).ravel()
        p = st["p"]
        H = self._design(x_hat, y_hat, ci)
        R = np.hstack([H, np.zeros((H.shape[0], st["beta"].size - p))])
        if self._has_gp(ci):
            R = R - self._kernel_rows(x_hat, y_hat, ci) @ st["kinv_x"][self.ch_index == ci]
        r = R.mean(axis=0)
        return max(float(r @ st["beta_cov"] @ r - r[:p] @ st["bare_cov"] @ r[:p]), 0.0)

    def band_terms_um(self, z_scale_um: float) -> dict[str, Any]:
        """The data-estimated band terms in µm, for the profile's record."""
        out = {"misfit_scale": float(self.misfit_scale),
               "misfit_F": self.diagnostics.get("misfit", {}).get("F"),
               "common_mode_fraction": self.diagnostics.get("common_mode_fraction"),
               "common_mode_sd_um": {c: float(z_scale_um * v) for c, v in zip(self.model.channels,
                                                                               self.common_sd)}
               if self.common_sd is not None else None}
        if self.diagnostics.get("common_mode_source"):
            out["common_mode_source"] = self.diagnostics["common_mode_source"]
        if self.diagnostics.get("common_mode_sd_replaced") is not None:
            out["common_mode"] = "replaced by the fitted stage frames (Discrepancy.attach_stage)"
        return out

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict[str, Any]:
        return {"centre": [float(v) for v in self.centre], "x_hat": self.x_hat.tolist(),
                "y_hat": self.y_hat.tolist(), "ch_index": self.ch_index.astype(int).tolist(),
                "target": self.target.tolist(), "noise_var": self.noise_var.tolist(),
                "tau": [float(v) for v in self.tau], "length_scale": float(self.length_scale),
                "noise_scale": float(self.noise_scale), "iid_cov": self.iid_cov.tolist(),
                "jk_cov": None if self.jk_cov is None else self.jk_cov.tolist(),
                "diagnostics": self.diagnostics,
                "rich_model": None if self.rich_model is None else self.rich_model.to_dict(),
                "rich_cov": None if self.rich_cov is None else self.rich_cov.tolist(),
                "misfit_scale": float(self.misfit_scale),
                "common_sd": None if self.common_sd is None else [float(v) for v in self.common_sd],
                **({"stage_c": np.round(self.stage_c, 6).tolist(), "stage_prior_sd": float(self.stage_prior_sd)}
                   if self.has_stage else {}),
                **({"misfit_beyond_average": True} if self.misfit_beyond_average else {})}

    @classmethod
    def from_dict(cls, d: dict[str, Any], model: SurfaceModel) -> "Discrepancy":
        a = lambda k: np.asarray(d[k], dtype=np.float64)
        return cls(model, a("centre"), a("x_hat"), a("y_hat"), np.asarray(d["ch_index"], dtype=np.int64),
                   a("target"), a("noise_var"), a("tau"), float(d["length_scale"]), float(d["noise_scale"]),
                   a("iid_cov"), a("jk_cov") if d.get("jk_cov") is not None else None,
                   dict(d.get("diagnostics", {})),
                   # keys added later: absent in older profiles, whose bands stay as they were
                   SurfaceModel.from_dict(d["rich_model"]) if d.get("rich_model") else None,
                   a("rich_cov") if d.get("rich_cov") is not None else None,
                   float(d.get("misfit_scale", 0.0)),
                   a("common_sd") if d.get("common_sd") is not None else None,
                   a("stage_c") if d.get("stage_c") is not None else None, float(d.get("stage_prior_sd", 0.0)),
                   bool(d.get("misfit_beyond_average", False)))


def _cov(x, y, tau, ell, noise_var) -> np.ndarray:
    K = tau ** 2 * matern32(_dist(x, y, x, y) / ell)
    K[np.diag_indices_from(K)] += noise_var + JITTER * (tau ** 2 + float(np.mean(noise_var)))
    return K


def fit_discrepancy(model: SurfaceModel, rows: Rows, theta_map: np.ndarray, weights: np.ndarray,
                    max_eval: int = 300, leverage_corrected: bool = False) -> Discrepancy:
    """Fit the discrepancy hyperparameters (REML, nlopt LN_BOBYQA) for the chosen model at its MAP.

    Parameters
    ----------
    model : SurfaceModel
        The chosen mean-surface model.
    rows : Rows
        All rows (astigmatism rows are ignored: they do not touch the mean surface).
    theta_map : ndarray
        The model's MAP (gives the centre, the error scale and the Student-t dof).
    weights : ndarray
        Student-t weights ``u_i`` of the rows at the MAP (1 for a Gaussian row, << 1 for an outlier).
    leverage_corrected : bool
        The block covariance without the delete-one-block jackknife's leverage bias
        (:func:`block_jackknife_cov`); slanted-edge rows use it (session 16), texture tiles keep the jackknife.
    """
    beta_map, centre, log_s, _, _ = model.split(np.asarray(theta_map, float))
    centre = np.asarray(centre, float)
    focus = rows.kind == 0
    xh, yh, ci = rows.x_hat[focus], rows.y_hat[focus], rows.ch_index[focus]
    y = rows.target[focus]
    u = np.clip(np.asarray(weights, float)[focus], 1e-6, None)
    base_var = rows.sigma[focus] ** 2 / u                         # noise variance at s = 1
    nc = len(model.channels)
    X = model.design(xh, yh, ci, np.zeros(xh.size, np.int64), centre)
    s_map = math.exp(float(log_s))
    W = u / (s_map * rows.sigma[focus]) ** 2
    A_iid = (X.T * W) @ X + np.eye(X.shape[1]) / COEF_PRIOR_SD ** 2
    iid_cov = np.linalg.inv(0.5 * (A_iid + A_iid.T))

    # Hyperparameter fit on at most MAX_ROWS_HYPER rows per channel (evenly thinned: spacing preserved).
    sel = np.zeros(xh.size, dtype=bool)
    for c in range(nc):
        idx = np.flatnonzero(ci == c)
        if idx.size > MAX_ROWS_HYPER:
            idx = idx[np.linspace(0, idx.size - 1, MAX_ROWS_HYPER).round().astype(int)]
        sel[idx] = True
    Xs, ys, bvs = X[sel], y[sel], base_var[sel]
    xs_, ys_, cis = xh[sel], yh[sel], ci[sel]
    blocks = [(c, np.flatnonzero(cis == c)) for c in range(nc) if (cis == c).any()]
    D = {c: _dist(xs_[m], ys_[m], xs_[m], ys_[m]) for c, m in blocks}
    spacing = float(np.median([_nn_spacing(xs_[m], ys_[m]) for _, m in blocks]))
    ell_lo, ell_hi = ELL_MIN_SPACINGS * spacing, 3.0
    r0 = y - X @ beta_map
    res_sd = max(float(np.std(r0)), 1e-6)
    tau_lo, tau_hi = 1e-4 * res_sd, 10.0 * res_sd
    p = X.shape[1]
    prior = np.eye(p) / COEF_PRIOR_SD ** 2

    def neg_reml(v):
        log_s_, log_ell = v[0], v[1]
        tau = np.exp(v[2:])
        ell = math.exp(log_ell)
        nv = math.exp(2.0 * log_s_) * bvs
        logdet = 0.0
        kx = np.zeros_like(Xs)
        ky = np.zeros_like(ys)
        for c, m in blocks:
            K = tau[c] ** 2 * matern32(D[c] / ell)
            K[np.diag_indices_from(K)] += nv[m] + JITTER * (tau[c] ** 2 + float(np.mean(nv[m])))
            try:
                cf = cho_factor(K, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                return 1e300
            logdet += 2.0 * float(np.sum(np.log(np.diag(cf[0]))))
            kx[m] = cho_solve(cf, Xs[m], check_finite=False)
            ky[m] = cho_solve(cf, ys[m], check_finite=False)
        A = Xs.T @ kx + prior
        try:
            cA = cho_factor(A, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return 1e300
        b = Xs.T @ ky
        quad = float(ys @ ky - b @ cho_solve(cA, b, check_finite=False))
        val = 0.5 * (logdet + 2.0 * float(np.sum(np.log(np.diag(cA[0])))) + quad)
        return val if math.isfinite(val) else 1e300

    lo = np.array([LOG_S_BOUNDS[0], math.log(ell_lo)] + [math.log(tau_lo)] * nc)
    hi = np.array([LOG_S_BOUNDS[1], math.log(ell_hi)] + [math.log(tau_hi)] * nc)
    best = None
    # Starts: the MAP's error scale; a discrepancy of half the residual spread at 2 and 6 tile spacings.
    for ell0 in (2.0 * spacing, 6.0 * spacing):
        x0 = np.clip(np.array([log_s - 0.3, math.log(ell0)] + [math.log(0.5 * res_sd)] * nc), lo, hi)
        f0 = neg_reml(x0)
        if best is None or f0 < best[0]:
            best = (f0, x0)
    opt = nlopt.opt(nlopt.LN_BOBYQA, lo.size)
    opt.set_lower_bounds(lo.tolist())
    opt.set_upper_bounds(hi.tolist())
    opt.set_min_objective(lambda v, g: neg_reml(np.asarray(v)))
    opt.set_xtol_abs(1e-4)
    opt.set_ftol_abs(1e-5)
    opt.set_maxeval(max_eval)
    opt.set_initial_step(np.minimum(0.25 * (hi - lo), 0.7).tolist())
    try:
        v = np.asarray(opt.optimize(best[1].tolist()))
        res = int(opt.last_optimize_result())
    except nlopt.RoundoffLimited:
        v, res = best[1], int(nlopt.ROUNDOFF_LIMITED)
    if neg_reml(v) > best[0]:
        v = best[1]
    s = math.exp(float(v[0]))
    ell = math.exp(float(v[1]))
    tau = np.exp(v[2:])
    diag = {"kernel": "matern32", "length_scale": ell, "tau": [float(t) for t in tau], "noise_scale": s,
            "tile_spacing": spacing, "n_rows_hyper": int(sel.sum()), "nlopt_result": res,
            "neg_reml": float(neg_reml(v))}
    jk_cov, n_blocks = block_jackknife_cov(X, y, W * s_map ** 2 / s ** 2, xh, yh,
                                           leverage_corrected=leverage_corrected)
    diag["jackknife_blocks"] = n_blocks
    diag["block_covariance"] = "CR2 (leverage-corrected)" if leverage_corrected else "delete-one-block jackknife"
    rich, rich_cov, misfit_scale, diag["misfit"] = misfit_term(model, centre, xh, yh, ci, y, W, iid_cov)
    noise_var = s * s * base_var
    # per-tile noise sd of each channel: the median of the fitted white-noise variances (outliers excluded)
    common = np.array([COMMON_MODE_FRACTION * math.sqrt(float(np.median(noise_var[ci == c]))) if (ci == c).any()
                       else 0.0 for c in range(nc)])
    diag["common_mode_fraction"] = COMMON_MODE_FRACTION
    diag["common_mode_sd"] = [float(v) for v in common]
    return Discrepancy(model, centre, xh, yh, ci.astype(np.int64), y, noise_var, tau, ell, s, iid_cov,
                       jk_cov, diag, rich, rich_cov, misfit_scale, common, misfit_beyond_average=True)


def misfit_term(model: SurfaceModel, centre, xh, yh, ci, y, w, iid_cov):
    """F test of the chosen model against the richest linear surface with the same centre.

    Both are weighted least-squares fits with the MAP's weights ``w`` (``u_i / (s sigma_i)^2``). For nested
    fits, ``RSS_c - RSS_r`` has expectation ``k`` (the extra terms) times the noise scale if the chosen model
    is right; ``F = ((RSS_c - RSS_r) / k) / (RSS_r / (n - p_r))``. Its excess ``(F - 1) k phi`` (phi = the
    rich fit's Birge ratio) estimates the weighted squared misfit on the tiles, and since the difference
    variance ``h_r C_r h_r^T - h C_c h^T`` sums (weighted) to ``k`` over the tiles, scaling it by
    ``max(F - 1, 0) phi`` adds, on average over the tiles, exactly that misfit — shaped like the extra terms
    (largest where the two models can differ most: the corners).

    Returns ``(rich_model or None, rich_cov or None, scale, diagnostics)``.
    """
    rich = SurfaceModel(model.channels, max(model.order, RICH_ORDER), True, model.decentre, False, False, None)
    n = y.size
    Xr = rich.design(xh, yh, ci, np.zeros(n, np.int64), centre)
    Xc = model.design(xh, yh, ci, np.zeros(n, np.int64), centre)
    # the chosen design may carry astigmatism columns that are zero on focus rows: count live columns only
    live_c = np.any(Xc != 0, axis=0)
    k = Xr.shape[1] - int(live_c.sum())
    if k <= 0 or n - Xr.shape[1] < MIN_RICH_DOF:
        return None, None, 0.0, {"status": f"skipped: {n} rows for {Xr.shape[1]} rich terms", "k": int(k)}
    prior_r = np.eye(Xr.shape[1]) / COEF_PRIOR_SD ** 2
    Ar = (Xr.T * w) @ Xr + prior_r
    try:
        cov_r = np.linalg.inv(0.5 * (Ar + Ar.T))
    except np.linalg.LinAlgError:
        return None, None, 0.0, {"status": "skipped: singular rich design", "k": int(k)}
    if not np.all(np.isfinite(cov_r)) or np.linalg.cond(Ar) > 1e12:
        return None, None, 0.0, {"status": "skipped: ill-conditioned rich design", "k": int(k)}
    beta_r = cov_r @ ((Xr.T * w) @ y)
    beta_c = iid_cov @ ((Xc.T * w) @ y)
    rss_r = float(np.sum(w * (y - Xr @ beta_r) ** 2))
    rss_c = float(np.sum(w * (y - Xc @ beta_c) ** 2))
    phi = rss_r / (n - Xr.shape[1])
    F = max(rss_c - rss_r, 0.0) / k / max(phi, 1e-300)
    scale = max(F - 1.0, 0.0) * phi
    return rich, cov_r, scale, {"status": "ok", "rich_model": rich.name, "k": int(k), "F": float(F),
                                "birge_ratio": float(phi), "scale": float(scale)}


JK_BLOCKS = (4, 3)  # blocks across x and y of the tile layout
MIN_JK_BLOCKS = 6


def block_jackknife_cov(X, y, w, x_hat, y_hat, blocks=JK_BLOCKS, leverage_corrected: bool = True):
    """Block covariance of the weighted least-squares coefficients: errors shared by regions of tiles.

    Tiles are grouped into ``blocks`` rectangles of the tile layout; errors may be correlated in any way
    within a block. Each block's residuals ``e_g`` are taken through ``(I - H_gg)^(-1/2)`` (``H_gg`` the block's
    leverage in the weighted fit, the prior included) before the cluster sum (Bell & McCaffrey's "CR2"):

        Cov = A^-1 [sum_g X_g' W_g^(1/2) (I - H_gg)^(-1/2) W_g^(1/2) e_g e_g' ...] A^-1,  A = X'WX + prior.

    Why not the delete-one-block jackknife it replaces: deleting block g moves the fit by ``(I - H_gg)^-1``
    times the block's residuals, so the jackknife is the same sum with ``(I - H_gg)^-1``, biased up wherever a
    block carries much of the fit (the layout's corner blocks carry the rho^4 - rho^6 terms there: block
    leverage up to 1.4 of 5-11 coefficients on 12 blocks). With independent noise of the stated variance its
    expectation is A^-1 (to the prior's share: 0.94-1.02x the exact covariance at the centre, middle and corners
    of an 18 x 10 edge layout with a poly3 + tilt surface) where the jackknife's was 1.22-1.48x; with an error
    shared by every row of a block 0.87-1.05x against 1.28-1.42x (tests/test_block_covariance.py). Inflated by
    (t_{0.95, B-1} / z_{0.95})^2 for the few blocks, as before. Returns ``(cov or None, B)``.

    ``leverage_corrected=False`` gives the delete-one-block jackknife, which the texture path keeps: on 20
    random texture lenses (quick) CR2 moved 2 geometric lenses across the edges of their coverage window
    (0.78 -> 0.74, 0.99 -> 1.00) and the wave ones not at all; its bands are judged on the 40-lens band-coverage
    benchmark, not run for this change (docs/benchmarks.md "bench_edge_band_s16").
    """
    from scipy.special import ndtri, stdtrit

    def span(v, n):
        lo, hi = float(v.min()), float(v.max())
        return np.clip(((v - lo) / max(hi - lo, 1e-12) * n).astype(int), 0, n - 1)

    lab = span(x_hat, blocks[0]) * blocks[1] + span(y_hat, blocks[1])
    ids = np.unique(lab)
    if ids.size < MIN_JK_BLOCKS:
        return None, int(ids.size)
    p = X.shape[1]
    prior = np.eye(p) / COEF_PRIOR_SD ** 2
    if not leverage_corrected:
        return _delete_block_jackknife(X, y, w, lab, ids, prior)
    A = (X.T * w) @ X + prior
    try:
        A_inv = np.linalg.inv(0.5 * (A + A.T))
    except np.linalg.LinAlgError:
        return None, int(ids.size)
    resid = y - X @ (A_inv @ ((X.T * w) @ y))
    meat = np.zeros((p, p))
    B = 0
    for k in ids:
        m = lab == k
        sw = np.sqrt(w[m])
        Z = X[m] * sw[:, None]                     # W_g^(1/2) X_g
        H = Z @ A_inv @ Z.T                        # the block's leverage (eigenvalues in [0, 1) with the prior)
        ev, U = np.linalg.eigh(0.5 * (H + H.T))
        if not np.all(np.isfinite(ev)):
            continue
        ev = np.clip(ev, 0.0, 1.0 - 1e-6)
        u = Z.T @ (U @ ((U.T @ (sw * resid[m])) / np.sqrt(1.0 - ev)))
        meat += np.outer(u, u)
        B += 1
    if B < MIN_JK_BLOCKS:
        return None, B
    infl = (float(stdtrit(B - 1, 0.95)) / float(ndtri(0.95))) ** 2
    return infl * (A_inv @ meat @ A_inv), B


def _delete_block_jackknife(X, y, w, lab, ids, prior):
    """The delete-one-block jackknife covariance (t-inflated), ``(cov or None, B)``: see
    :func:`block_jackknife_cov`."""
    from scipy.special import ndtri, stdtrit

    Xw = X.T * w
    A = Xw @ X + prior
    b = Xw @ y
    est = []
    for k in ids:
        m = lab == k
        Xm = X[m]
        Ak = A - (Xm.T * w[m]) @ Xm
        bk = b - (Xm.T * w[m]) @ y[m]
        try:
            est.append(np.linalg.solve(Ak, bk))
        except np.linalg.LinAlgError:
            continue
    B = len(est)
    if B < MIN_JK_BLOCKS:
        return None, B
    E = np.array(est)
    d = E - E.mean(axis=0)
    cov = (B - 1) / B * (d.T @ d)
    infl = (float(stdtrit(B - 1, 0.95)) / float(ndtri(0.95))) ** 2
    return infl * cov, B
