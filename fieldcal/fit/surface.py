"""Best-focus surface models: terms, parameter layout, design matrices and the (robust) log-posterior.

A model is one choice of terms for all channels (docs/fitting.md gives the formulas)::

    z_c(x, y) = a_c0 + sum_{k=1..K} a_ck rho^{2k} + t_x x_hat + t_y y_hat           (mean surface)
    z_tan,c - z_sag,c = A_c rho^2 (+ A_c2 rho^4 + A_c3 rho^6 with astig_order 3)     (astigmatism rows)
    rho^2 = (x_hat - c_x)^2 + (y_hat - c_y)^2

in normalised coordinates (``data.ImageGeometry.normalise``) and normalised z (``(z - z_centre) / z_scale``).
Focus offset a_c0, curvature a_ck and astigmatism A_c are per channel; tilt (t_x, t_y) and the optical
centre (c_x, c_y) are shared (one lens, one sensor).

The parameter vector is ``[linear coefficients..., nonlinear...]``; nonlinear are the centre (if decentre),
``log_s`` (error scale of the focus rows), ``log_s_astig`` (error scale of the astigmatism rows, if any) and
``log_nu`` (Student-t degrees of freedom: the robust loss). Every function here is vectorised over a leading
batch axis of parameter vectors, so the same code serves the MAP, the Laplace Hessian and emcee's walkers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.special import gammaln

# Priors and bounds (normalised units; docs/fitting.md "Priors").
COEF_PRIOR_SD = 1.0e3      # N(0, 1000^2) on every linear coefficient: proper but negligible (z is O(1))
CENTRE_BOUND = 0.25        # optical centre within a quarter of the half-diagonal of the sensor centre
LOG_S_BOUNDS = (math.log(0.5), math.log(1.0e4))  # error scale s: floor 0.5 (bands at most 2x tighter)
LOG_NU_BOUNDS = (math.log(2.0), math.log(200.0))  # Student-t dof: 2 = very heavy tails, 200 ~ Gaussian


@dataclass(frozen=True)
class Rows:
    """Stacked observations in normalised units.

    kind 0 rows are best-focus measurements (target z_hat), kind 1 rows are astigmatism differences
    (target (z_tan - z_sag) / z_scale).
    """

    x_hat: np.ndarray
    y_hat: np.ndarray
    ch_index: np.ndarray
    kind: np.ndarray
    target: np.ndarray
    sigma: np.ndarray

    @property
    def n(self) -> int:
        return int(self.target.size)

    @property
    def n_astig(self) -> int:
        return int((self.kind == 1).sum())


@dataclass(frozen=True)
class SurfaceModel:
    """One candidate: polynomial order K in rho^2, and switches for tilt, decentre and astigmatism."""

    channels: tuple[str, ...]
    order: int
    tilt: bool
    decentre: bool
    astig: bool
    astig_rows: bool  # the data have tangential/sagittal rows (adds the log_s_astig nuisance)
    channel_order: int | None = None  # rho^2k terms per channel up to this k; higher k shared (None: all)
    # astigmatism terms per channel (rho^2 .. rho^(2 astig_order)): a traced T - S can peak inside the field
    # (the triplet's, docs/raytrace.md), which one rho^2 term cannot follow; select.py tries 3 on many T/S rows
    astig_order: int = 1

    @property
    def kc(self) -> int:
        """Highest per-channel power index (terms above it are shared by all channels)."""
        return self.order if self.channel_order is None else min(self.channel_order, self.order)

    # Column layout: [per channel: a0, a1..a_kc] [shared: a_{kc+1}..a_K] [tilt_x, tilt_y] [astig per channel]
    def _col_channel(self, ci: int, k: int) -> int:
        return ci * (self.kc + 1) + k

    def _col_shared(self, k: int) -> int:
        return len(self.channels) * (self.kc + 1) + (k - self.kc - 1)

    def _col_power(self, ci: int, k: int) -> int:
        return self._col_channel(ci, k) if k <= self.kc else self._col_shared(k)

    @property
    def _col_tilt(self) -> int:
        return len(self.channels) * (self.kc + 1) + (self.order - self.kc)

    @property
    def _col_astig(self) -> int:
        return self._col_tilt + (2 if self.tilt else 0)

    @property
    def name(self) -> str:
        parts = [f"poly{self.order}" if self.kc == self.order or len(self.channels) == 1
                 else f"poly{self.order}(per-channel<=rho^{2 * self.kc})"]
        if self.tilt:
            parts.append("tilt")
        if self.decentre:
            parts.append("decentre")
        if self.astig:
            parts.append("astig" if self.astig_order == 1 else f"astig(rho^2..rho^{2 * self.astig_order})")
        return "+".join(parts)

    @property
    def terms(self) -> list[str]:
        t = ["offset"] + [f"rho^{2 * k}" + (" (shared)" if k > self.kc and len(self.channels) > 1 else "")
                          for k in range(1, self.order + 1)]
        if self.tilt:
            t.append("tilt")
        if self.decentre:
            t.append("decentre")
        if self.astig:
            t.append("astigmatism")
        return t

    # ------------------------------------------------------------------ layout
    @cached_property
    def linear_names(self) -> list[str]:
        names = []
        for c in self.channels:
            names += [f"a{k}[{c}]" for k in range(self.kc + 1)]
        names += [f"a{k}" for k in range(self.kc + 1, self.order + 1)]
        if self.tilt:
            names += ["tilt_x", "tilt_y"]
        if self.astig:
            for c in self.channels:
                names += [f"astig[{c}]"] + [f"astig{k}[{c}]" for k in range(2, self.astig_order + 1)]
        return names

    @cached_property
    def nonlinear_names(self) -> list[str]:
        names = ["centre_x", "centre_y"] if self.decentre else []
        names.append("log_s")
        if self.astig_rows:
            names.append("log_s_astig")
        names.append("log_nu")
        return names

    @cached_property
    def names(self) -> list[str]:
        return self.linear_names + self.nonlinear_names

    @cached_property
    def n_linear(self) -> int:
        return len(self.linear_names)

    @cached_property
    def n_params(self) -> int:
        return len(self.names)

    def nonlinear_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = [], []
        if self.decentre:
            lo += [-CENTRE_BOUND] * 2
            hi += [CENTRE_BOUND] * 2
        lo.append(LOG_S_BOUNDS[0]); hi.append(LOG_S_BOUNDS[1])
        if self.astig_rows:
            lo.append(LOG_S_BOUNDS[0]); hi.append(LOG_S_BOUNDS[1])
        lo.append(LOG_NU_BOUNDS[0]); hi.append(LOG_NU_BOUNDS[1])
        return np.array(lo), np.array(hi)

    def split(self, theta: np.ndarray):
        """(beta, centre (..., 2), log_s, log_s_astig or None, log_nu) from a (batch of) parameter vector(s)."""
        p = self.n_linear
        beta = theta[..., :p]
        i = p
        if self.decentre:
            centre = theta[..., i:i + 2]
            i += 2
        else:
            centre = np.zeros(theta.shape[:-1] + (2,))
        log_s = theta[..., i]
        i += 1
        log_sa = None
        if self.astig_rows:
            log_sa = theta[..., i]
            i += 1
        log_nu = theta[..., i]
        return beta, centre, log_s, log_sa, log_nu

    # ------------------------------------------------------------------ design
    def design(self, x_hat, y_hat, ch_index, kind, centre) -> np.ndarray:
        """Design matrix. ``centre`` (2,) gives (n, p); a batch (B, 2) gives (B, n, p)."""
        centre = np.asarray(centre, dtype=np.float64)
        batch = centre.ndim == 2
        cx = centre[..., 0:1] if batch else centre[0]
        cy = centre[..., 1:2] if batch else centre[1]
        r2 = (x_hat - cx) ** 2 + (y_hat - cy) ** 2          # (B, n) or (n,)
        shape = r2.shape + (self.n_linear,)
        X = np.zeros(shape)
        mean_row = kind == 0
        nc = len(self.channels)
        pw = [np.ones_like(r2)]
        for k in range(1, self.order + 1):
            pw.append(pw[-1] * r2)
        for ci in range(nc):
            sel = (ch_index == ci) & mean_row
            for k in range(self.kc + 1):
                X[..., self._col_channel(ci, k)] = np.where(sel, pw[k], 0.0)
        for k in range(self.kc + 1, self.order + 1):
            X[..., self._col_shared(k)] = np.where(mean_row, pw[k], 0.0)
        if self.tilt:
            j = self._col_tilt
            X[..., j] = np.where(mean_row, x_hat, 0.0)
            X[..., j + 1] = np.where(mean_row, y_hat, 0.0)
        if self.astig:
            j = self._col_astig
            for ci in range(nc):
                for k in range(1, self.astig_order + 1):
                    X[..., j + ci * self.astig_order + k - 1] = np.where((ch_index == ci) & ~mean_row, pw[k]
                                                                         if k <= self.order else r2 ** k, 0.0)
        return X

    # ------------------------------------------------------------------ likelihood
    def sigma_eff(self, rows: Rows, log_s, log_sa):
        """Effective per-row scale s * sigma (batch-aware)."""
        log_s = np.asarray(log_s, dtype=np.float64)[..., None]
        if self.astig_rows and log_sa is not None:
            log_sa = np.asarray(log_sa, dtype=np.float64)[..., None]
            scale = np.where(rows.kind == 0, np.exp(log_s), np.exp(log_sa))
        else:
            scale = np.exp(log_s) * np.ones(rows.n)
        return scale * rows.sigma

    def log_likelihood(self, theta: np.ndarray, rows: Rows) -> np.ndarray:
        """Student-t log-likelihood of a (batch of) parameter vector(s)."""
        theta = np.asarray(theta, dtype=np.float64)
        beta, centre, log_s, log_sa, log_nu = self.split(theta)
        if theta.ndim == 1:
            X = self.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
            pred = X @ beta
        elif self.decentre:
            X = self.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
            pred = np.einsum("bnp,bp->bn", X, beta)
        else:
            X = self.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, np.zeros(2))
            pred = beta @ X.T
        sig = self.sigma_eff(rows, log_s, log_sa)
        return student_t_loglik(rows.target - pred, sig, np.exp(log_nu))

    def in_support(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(theta)
        lo, hi = self.nonlinear_bounds()
        nl = theta[:, self.n_linear:]
        return np.all((nl >= lo) & (nl <= hi), axis=1) & np.all(np.isfinite(theta), axis=1)

    def log_prior(self, theta: np.ndarray) -> np.ndarray:
        """Gaussian on linear coefficients, uniform (in the stored parametrisation) inside the bounds."""
        theta = np.asarray(theta, dtype=np.float64)
        beta = theta[..., :self.n_linear]
        lp = -0.5 * np.sum((beta / COEF_PRIOR_SD) ** 2, axis=-1)
        ok = self.in_support(theta)
        if theta.ndim == 1:
            return float(lp) if ok[0] else -np.inf
        return np.where(ok, lp, -np.inf)

    def log_posterior(self, theta: np.ndarray, rows: Rows) -> np.ndarray:
        """Unnormalised log-posterior; -inf outside the prior support (never evaluated there)."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.ndim == 1:
            lp = self.log_prior(theta)
            if not np.isfinite(lp):
                return -np.inf
            return lp + float(np.sum(self.log_likelihood(theta, rows)))
        out = np.full(theta.shape[0], -np.inf)
        ok = self.in_support(theta)
        if ok.any():
            t = theta[ok]
            out[ok] = self.log_prior(t) + np.sum(self.log_likelihood(t, rows), axis=-1)
        return out

    def log_posterior_fn(self, rows: Rows):
        """A fast ``log_posterior`` for batches of parameter vectors on fixed ``rows`` (for emcee).

        Same values as :meth:`log_posterior`; the design matrix (without a decentre), the row masks and the
        constant terms are computed once instead of at every call.
        """
        p = self.n_linear
        lo, hi = self.nonlinear_bounds()
        X0 = None if self.decentre else self.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, np.zeros(2))
        decentred_pred = self.row_predictor(rows) if self.decentre else None
        focus = rows.kind == 0
        split_scales = self.astig_rows
        log_sigma_sum = float(np.sum(np.log(rows.sigma)))
        n_focus, n_all = int(focus.sum()), rows.n
        inv_sigma = 1.0 / rows.sigma
        y = rows.target

        def f(theta: np.ndarray) -> np.ndarray:
            theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
            out = np.full(theta.shape[0], -np.inf)
            nl = theta[:, p:]
            ok = np.all((nl >= lo) & (nl <= hi), axis=1) & np.all(np.isfinite(theta), axis=1)
            if not ok.any():
                return out
            t = theta[ok]
            beta, centre, log_s, log_sa, log_nu = self.split(t)
            pred = beta @ X0.T if X0 is not None else decentred_pred(beta, centre)
            if split_scales:
                inv_s = np.where(focus, np.exp(-log_s)[:, None], np.exp(-log_sa)[:, None])
                log_s_sum = n_focus * log_s + (n_all - n_focus) * log_sa
            else:
                inv_s = np.exp(-log_s)[:, None]
                log_s_sum = n_all * log_s
            nu = np.exp(log_nu)
            # z^2 / nu = ((y - pred) / (s sigma))^2 / nu, in place (walkers x rows: the chain's largest arrays)
            z2 = np.subtract(y, pred, out=pred)  # pred is this call's own array
            z2 *= inv_sigma
            z2 *= inv_s
            np.square(z2, out=z2)
            z2 /= nu[:, None]
            ll = (n_all * (gammaln(0.5 * (nu + 1.0)) - gammaln(0.5 * nu) - 0.5 * np.log(nu * np.pi))
                  - log_s_sum - log_sigma_sum
                  - 0.5 * (nu + 1.0) * np.sum(np.log1p(z2, out=z2), axis=1))
            out[ok] = ll - 0.5 * np.sum((beta / COEF_PRIOR_SD) ** 2, axis=1)
            return out

        return f

    def row_predictor(self, rows: Rows):
        """``pred(beta (B, p), centre (B, 2)) -> (B, n)``: the rows' model values, ``design(..., centre) @ beta``.

        Without building the (B, n, p) design: each row's coefficient of rho^{2k} is gathered from beta (an
        appended zero where the row has none) and the polynomial is summed by Horner's rule. Same values as the
        design product up to rounding (~1e-16 relative); at a decentre the design is rebuilt per walker at every
        emcee step, which cost 3-5x the rest of the log-posterior (docs/fitting.md "Posterior and effort").
        """
        nc = len(self.channels)
        mean_row = rows.kind == 0
        ci = np.asarray(rows.ch_index)
        k_max = max(self.order, self.astig_order if self.astig else 0)
        zero = self.n_linear                              # index of the appended zero coefficient
        cols = np.full((k_max + 1, rows.n), zero, dtype=np.intp)
        for k in range(self.order + 1):
            for c in range(nc):
                cols[k, mean_row & (ci == c)] = self._col_power(c, k)
        if self.astig:
            for c in range(nc):
                for k in range(1, self.astig_order + 1):
                    cols[k, ~mean_row & (ci == c)] = self._col_astig + c * self.astig_order + k - 1
        used = [k for k in range(k_max + 1) if np.any(cols[k] != zero)]
        k_top = max(used) if used else 0
        x_hat, y_hat = rows.x_hat, rows.y_hat
        tx = np.where(mean_row, x_hat, 0.0) if self.tilt else None
        ty = np.where(mean_row, y_hat, 0.0) if self.tilt else None

        def pred(beta: np.ndarray, centre: np.ndarray) -> np.ndarray:
            b = np.concatenate([beta, np.zeros(beta.shape[:-1] + (1,))], axis=-1)
            r2 = (x_hat - centre[:, 0:1]) ** 2 + (y_hat - centre[:, 1:2]) ** 2
            out = np.take(b, cols[k_top], axis=1)
            for k in range(k_top - 1, -1, -1):
                out *= r2
                out += np.take(b, cols[k], axis=1)
            if self.tilt:
                j = self._col_tilt
                out = out + beta[:, j:j + 1] * tx + beta[:, j + 1:j + 2] * ty
            return out

        return pred

    # ------------------------------------------------------------------ prediction
    def surface(self, theta: np.ndarray, x_hat, y_hat, channel_index: int) -> np.ndarray:
        """Normalised mean surface at points for parameter vector(s): (m,) or (B, m)."""
        theta = np.asarray(theta, dtype=np.float64)
        x_hat = np.asarray(x_hat, dtype=np.float64).ravel()
        y_hat = np.asarray(y_hat, dtype=np.float64).ravel()
        beta, centre, *_ = self.split(theta)
        r2 = _radius2(theta, centre, x_hat, y_hat)
        j0 = self._col_channel(channel_index, 0)
        z = beta[..., j0:j0 + 1] * np.ones_like(r2)
        pw = np.ones_like(r2)
        for k in range(1, self.order + 1):
            pw = pw * r2
            j = self._col_power(channel_index, k)
            z = z + beta[..., j:j + 1] * pw
        if self.tilt:
            j = self._col_tilt
            z = z + beta[..., j:j + 1] * x_hat + beta[..., j + 1:j + 2] * y_hat
        return z

    def astigmatism(self, theta: np.ndarray, x_hat, y_hat, channel_index: int) -> np.ndarray:
        """Normalised z_tan - z_sag at points (0 when the model has no astigmatism term)."""
        theta = np.asarray(theta, dtype=np.float64)
        x_hat = np.asarray(x_hat, dtype=np.float64).ravel()
        y_hat = np.asarray(y_hat, dtype=np.float64).ravel()
        beta, centre, *_ = self.split(theta)
        if not self.astig:
            return np.zeros(theta.shape[:-1] + x_hat.shape)
        r2 = _radius2(theta, centre, x_hat, y_hat)
        j = self._col_astig + channel_index * self.astig_order
        out = 0.0
        for k in range(1, self.astig_order + 1):
            b = beta[..., j + k - 1:j + k] if theta.ndim == 2 else beta[j + k - 1]
            out = out + b * r2 ** k
        return out

    def embed(self, theta: np.ndarray, target: "SurfaceModel") -> np.ndarray:
        """Express parameter vector(s) of this model in the layout of a larger ``target`` model.

        Every candidate is nested in the union model: a shared coefficient becomes equal per-channel
        coefficients, an absent term a zero, an absent decentre a zero centre.
        """
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        if (target.order < self.order or (self.tilt and not target.tilt) or (self.decentre and not target.decentre)
                or (self.astig and not target.astig) or target.astig_rows != self.astig_rows
                or (self.astig and target.astig_order < self.astig_order)
                or target.channels != self.channels):
            raise ValueError(f"{self.name} is not nested in {target.name}")
        out = np.zeros((theta.shape[0], target.n_params))
        for ci in range(len(self.channels)):
            for k in range(self.order + 1):
                out[:, target._col_power(ci, k)] = theta[:, self._col_power(ci, k)]
        if self.tilt:
            out[:, target._col_tilt:target._col_tilt + 2] = theta[:, self._col_tilt:self._col_tilt + 2]
        if self.astig:
            for ci in range(len(self.channels)):
                src_j = self._col_astig + ci * self.astig_order
                dst_j = target._col_astig + ci * target.astig_order
                out[:, dst_j:dst_j + self.astig_order] = theta[:, src_j:src_j + self.astig_order]
        # nonlinear block: [centre?] log_s [log_s_astig] log_nu
        src = theta[:, self.n_linear:]
        dst_start = target.n_linear
        if target.decentre:
            if self.decentre:
                out[:, dst_start:dst_start + 2] = src[:, :2]
            dst_start += 2
        out[:, dst_start:] = src[:, 2:] if self.decentre else src
        return out

    @classmethod
    def union(cls, models: list["SurfaceModel"]) -> "SurfaceModel":
        """The smallest model in which every one of ``models`` is nested (all terms per channel)."""
        order = max(m.order for m in models)
        m0 = models[0]
        return cls(m0.channels, order, any(m.tilt for m in models), any(m.decentre for m in models),
                   any(m.astig for m in models), m0.astig_rows, order,
                   max(m.astig_order if m.astig else 1 for m in models))

    def to_dict(self) -> dict:
        return {"channels": list(self.channels), "order": self.order, "tilt": self.tilt,
                "decentre": self.decentre, "astig": self.astig, "astig_rows": self.astig_rows,
                "channel_order": self.kc, "astig_order": self.astig_order}

    @classmethod
    def from_dict(cls, d: dict) -> "SurfaceModel":
        return cls(tuple(d["channels"]), int(d["order"]), bool(d["tilt"]), bool(d["decentre"]),
                   bool(d["astig"]), bool(d["astig_rows"]), int(d.get("channel_order", d["order"])),
                   int(d.get("astig_order", 1)))


def _radius2(theta: np.ndarray, centre: np.ndarray, x_hat: np.ndarray, y_hat: np.ndarray) -> np.ndarray:
    """rho^2 about the centre of one parameter vector (m,) or of each of a batch (B, m)."""
    if theta.ndim == 2:
        return (x_hat - centre[..., 0:1]) ** 2 + (y_hat - centre[..., 1:2]) ** 2
    return (x_hat - centre[0]) ** 2 + (y_hat - centre[1]) ** 2


def student_t_loglik(resid, sigma, nu):
    """Elementwise log-density of a Student-t with scale sigma and nu dof (nu broadcast over the batch)."""
    nu = np.asarray(nu, dtype=np.float64)
    if nu.ndim:
        nu = nu[..., None]
    z2 = (resid / sigma) ** 2
    return (gammaln(0.5 * (nu + 1.0)) - gammaln(0.5 * nu) - 0.5 * np.log(nu * np.pi) - np.log(sigma)
            - 0.5 * (nu + 1.0) * np.log1p(z2 / nu))
