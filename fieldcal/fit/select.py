"""Model selection and the top-level surface fit: ``fit_surfaces(tiles, geometry, effort=...)``.

Every candidate (polynomial order in rho^2, tilt on/off, decentre on/off, astigmatism on/off when the data
have tangential/sagittal foci) is fitted to its MAP and scored by BIC = -2 ln L_max + k ln n; with several
channels the fitted candidates are rescored with a tile's channels correlated (:func:`_shared_error_scores`).
Those scores give the model-average weights. The choice is a paired test on blocked held-out tiles
(:func:`_block_cv_losses`, :func:`paired_test_choice`): the candidate with the fewest parameters whose held-out
loss is not worse than the best's at one-sided level 5 % (paired block differences, the Nadeau-Bengio variance
of a cross-validated difference, Student t with K - 1 degrees of freedom), among those with model-average
weight >= 1 %. docs/fitting.md "Model selection" gives the reasons (BIC's lowest score added terms on noise
draws; the one-standard-error rule kept a centred model where a decentre was real).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from ..progress import progress, warn
from .data import MIN_TILES_PER_CHANNEL, FitError, ImageGeometry, TileData
from .discrepancy import fit_discrepancy
from .selfcheck import predictive_check
from .map import MAX_CONDITION, fit_map
from .pool import Deferred, run_tasks
from .posterior import EFFORTS, MAX_SAMPLES, laplace, run_emcee
from .result import SurfaceFit
from .surface import CENTRE_BOUND, COEF_PRIOR_SD, Rows, SurfaceModel

# Tiles must span at least this much of the normalised radius, or curvature is not identifiable.
MIN_RADIAL_SPAN = 0.15
MIN_ASTIG_ROWS = 6
# ... and at least this many before the rho^4, rho^6 astigmatism terms are tried (BIC decides)
MIN_ASTIG_POLY_ROWS = 24
BMA_MIN_WEIGHT = 0.01


def build_rows(tiles: TileData, geometry: ImageGeometry, channels: tuple[str, ...]):
    """Stack focus rows and astigmatism rows in normalised units; returns (rows, z_centre_um, z_scale_um)."""
    xh, yh = geometry.normalise(tiles.x_px, tiles.y_px)
    ci = np.array([channels.index(c) for c in tiles.channel], dtype=np.int64)
    z = tiles.z_best_um
    zc = float(np.median(z))
    # Scale by the spread of the data, never below the typical measurement error (guards a flat, noiseless set).
    zs = float(max(np.std(z), np.median(tiles.z_sigma_um), 1e-9 * max(1.0, abs(zc))))
    ast = np.isfinite(tiles.z_tan_um) & np.isfinite(tiles.z_sag_um)
    d = tiles.z_tan_um[ast] - tiles.z_sag_um[ast]
    # A difference of two directional estimates, each assumed about as good as the combined one; the
    # separate error scale s_astig corrects this assumption from the data.
    sd = math.sqrt(2.0) * tiles.z_sigma_um[ast]
    rows = Rows(x_hat=np.concatenate([xh, xh[ast]]), y_hat=np.concatenate([yh, yh[ast]]),
                ch_index=np.concatenate([ci, ci[ast]]),
                kind=np.concatenate([np.zeros(z.size, np.int64), np.ones(int(ast.sum()), np.int64)]),
                target=np.concatenate([(z - zc) / zs, d / zs]),
                sigma=np.concatenate([tiles.z_sigma_um / zs, sd / zs]))
    return rows, zc, zs


def validate_inputs(tiles: TileData, geometry: ImageGeometry, channels, source):
    if len(tiles) == 0:
        raise FitError("no accepted tiles to fit", path=source, field="tiles",
                       fix="check the stack covers best focus (measure reported every tile as rejected)")
    for c in channels:
        n = int((tiles.channel == c).sum())
        if n < MIN_TILES_PER_CHANNEL:
            raise FitError(f"channel {c} has only {n} accepted tiles; a surface needs at least "
                           f"{MIN_TILES_PER_CHANNEL}", path=source, field="tiles",
                           fix="use a finer tile grid, a chart that fills the frame, or a stack whose z range "
                               "covers best focus everywhere")
    w, h = geometry.width_px, geometry.height_px
    out = (tiles.x_px < -0.5) | (tiles.x_px > w - 0.5) | (tiles.y_px < -0.5) | (tiles.y_px > h - 0.5)
    if out.any():
        raise FitError(f"{int(out.sum())} tiles lie outside the {w}x{h} px image", path=source, field="x_px",
                       fix="tile coordinates are pixels with origin at the top-left pixel's centre")
    xh, yh = geometry.normalise(tiles.x_px, tiles.y_px)
    r = np.hypot(xh, yh)
    span = float(r.max() - r.min())
    if span < MIN_RADIAL_SPAN:
        raise FitError(f"all tiles lie at nearly one radius (rho from {r.min():.3f} to {r.max():.3f}); "
                       "field curvature cannot be separated from focus offset", path=source, field="x_px",
                       fix="measure tiles from the image centre out to the corners")


def candidate_models(channels, max_order: int, astig: bool) -> list[SurfaceModel]:
    """Mean-surface structures: order K in rho^2 with per-channel terms up to rho^(2 kc) and shared terms
    above (colour changes mostly the low orders), tilt on/off, decentre on/off. Decentre needs curvature
    and, with tilt, rho^4: at order 1 a decentre is exactly a tilt."""
    out = []
    mono = len(channels) == 1
    for order in range(max_order + 1):
        kcs = [order] if (mono or order == 0) else sorted({0, 1, order})
        for kc in kcs:
            for tilt in (False, True):
                for dec in (False, True):
                    if dec and (order == 0 or (tilt and order < 2)):
                        continue
                    out.append(SurfaceModel(tuple(channels), order, tilt, dec, astig, astig, kc))
    return out


def _decentred_siblings(cands: list[SurfaceModel], scores: dict[str, float], top: int) -> list[SurfaceModel]:
    """Decentred candidates (in candidate order) whose centred structure, with or without tilt (which a
    decentre can replace), is among the ``top`` centred fits by ``scores`` (lower is better)."""
    ranked = sorted((v, n) for n, v in scores.items())
    keep = {n for _, n in ranked[:top]}
    out = []
    for m in cands:
        if m.decentre and any(replace(m, decentre=False, tilt=t).name in keep for t in (False, True)):
            out.append(m)
    return out


def _fit_candidate(model: SurfaceModel, rows: Rows, start_from):
    """:func:`fit_map` of one candidate (a task of :func:`fieldcal.fit.pool.run_tasks`)."""
    return fit_map(model, rows, start_from=start_from)


def fit_surfaces(tiles: TileData, geometry: ImageGeometry, effort: str = "standard", seed: int = 0,
                 channels: tuple[str, ...] | None = None, quiet: bool = False,
                 source: str | None = None, leverage_corrected: bool = False, pool=None) -> SurfaceFit:
    """Fit per-channel best-focus surfaces with model selection and a posterior.

    Parameters
    ----------
    tiles : TileData
        Accepted per-tile measurements (µm, px).
    geometry : ImageGeometry
        Image size and pixel pitch of the tile coordinates.
    effort : {"quick", "standard", "thorough"}
        "quick": MAP + Laplace; "standard": emcee, modest chains; "thorough": longer chains and every
        decentred candidate.
    seed : int
        Seeds the samplers (results are reproducible).
    channels : tuple of str, optional
        Channel order (default: order of first appearance in ``tiles``).
    source : str, optional
        File name for error messages.
    leverage_corrected : bool
        The band's block covariance without the jackknife's leverage bias (slanted-edge rows;
        :func:`fieldcal.fit.discrepancy.block_jackknife_cov`).
    pool : optional
        A worker process for the fit's independent pieces (:func:`fieldcal.fit.pool.surface_pool`); the result is the
        same without one.

    Returns
    -------
    SurfaceFit
    """
    if effort not in EFFORTS:
        raise FitError(f"unknown effort {effort!r}", field="effort", fix="use quick, standard or thorough")
    eff = EFFORTS[effort]
    channels = tuple(channels) if channels is not None else tiles.channels
    unknown = sorted(set(tiles.channel) - set(channels))
    if unknown:
        raise FitError(f"tiles of channels {unknown} not in {list(channels)}", path=source, field="channel",
                       fix="pass every measured channel")
    validate_inputs(tiles, geometry, channels, source)
    rows, zc, zs = build_rows(tiles, geometry, channels)
    astig_rows = rows.n_astig >= MIN_ASTIG_ROWS
    if not astig_rows and rows.n_astig:
        keep = rows.kind == 0
        rows = Rows(*(getattr(rows, f)[keep] for f in ("x_hat", "y_hat", "ch_index", "kind", "target", "sigma")))
    t0 = time.perf_counter()
    # Stage 1: mean-surface structures (astigmatism term on whenever the data have directional foci: it
    # only touches the astigmatism rows). Stage 2: the winner with the astigmatism term toggled.
    cands = candidate_models(channels, eff.max_order, astig_rows)
    table = []
    best = None
    fits = {}

    def fittable(m):
        return rows.n >= m.n_params + 2

    def accepted(res):
        return math.isfinite(res.condition_number) and res.condition_number <= MAX_CONDITION

    def map_fits(ms, bar):
        """The MAP fits of the fittable models of ``ms`` by name, as :func:`consider` of each in turn would fit
        them (a decentred model starts from its centred sibling's fit, made before it in candidate order), in
        this process and the pool's worker: each fit depends only on its arguments."""
        todo = [m for m in ms if fittable(m)]
        ahead = {}  # the batch's own centred fits, for the decentred siblings after them
        for stage in (False, True):
            part = [m for m in todo if m.decentre == stage]
            args = []
            for m in part:
                sib = None
                if m.decentre:
                    name = replace(m, decentre=False).name
                    sib = ahead[name] if name in ahead else fits.get(name)
                args.append((m, rows, sib if sib is not None and accepted(sib) else None))
            done = run_tasks(pool, _fit_candidate, args)
            if bar:
                done = progress(done, total=len(args), desc="fit: model search", quiet=quiet, unit="model")
            ahead.update((m.name, res) for m, res in zip(part, done))
        return ahead

    def consider(m, res):
        """Score ``m``'s fit ``res`` (None where it is not fittable) and add it to the table."""
        nonlocal best
        entry = {"name": m.name, "terms": m.terms, "n_params": m.n_params}
        table.append(entry)
        if not fittable(m):
            entry.update(status="skipped: fewer rows than parameters + 2", bic=None)
            return
        entry["condition_number"] = res.condition_number
        if not accepted(res):
            entry.update(status=f"refused: degenerate design (condition number {res.condition_number:.3g} > "
                                f"{MAX_CONDITION:.0e})", bic=None)
            return
        bic = -2.0 * res.log_likelihood + m.n_params * math.log(rows.n)
        entry.update(status="ok", log_likelihood=res.log_likelihood, bic=bic, nlopt_result=res.nlopt_result,
                     n_evals=res.n_evals)
        fits[m.name] = res
        if best is None or bic < best[0]:
            best = (bic, res)

    def consider_all(ms, bar=False):
        done = map_fits(ms, bar)
        for m in ms:
            consider(m, done.get(m.name))

    if eff.decentre_top is None:
        consider_all(cands, bar=True)
    else:
        consider_all([m for m in cands if not m.decentre], bar=True)
        # ranked by the held-out loss that chooses (below), so the pruned search keeps what the full one picks
        rank = {n: float(v.sum()) for n, v in _block_cv_losses(fits, rows).items()} or {
            e["name"]: e["bic"] for e in table if e.get("bic") is not None}
        consider_all(_decentred_siblings(cands, rank, eff.decentre_top))
        tried = {e["name"] for e in table}
        for m in cands:
            if m.name not in tried:
                table.append({"name": m.name, "terms": m.terms, "n_params": m.n_params, "bic": None,
                              "status": f"not fitted: its centred structure is not among the best "
                                        f"{eff.decentre_top} by held-out loss (effort {effort}; thorough fits every candidate)"})
    if best is None and astig_rows:
        # the directional foci cannot identify any astigmatism term (e.g. a few T/S pairs in one part of the
        # field, their design singular with every structure): fit the mean surface from the focus rows alone,
        # as with too few pairs, rather than refuse a stack whose mean-surface rows are sound
        keep = rows.kind == 0
        rows = Rows(*(getattr(rows, f)[keep] for f in ("x_hat", "y_hat", "ch_index", "kind", "target", "sigma")))
        astig_rows = False
        fits.clear()
        consider_all(candidate_models(channels, eff.max_order, False))
    if best is not None and astig_rows:
        consider_all([replace(best[1].model, astig=False)])
        if rows.n_astig >= MIN_ASTIG_POLY_ROWS:  # e.g. slanted-edge T/S pairs: can follow a T - S peaked in the field
            consider_all([replace(best[1].model, astig=True, astig_order=3)])
    if best is None:
        raise FitError("no surface model could be fitted: every candidate's design is degenerate", path=source,
                       field="tiles", fix="measure tiles spread over the whole field in every channel")
    res = best[1]
    weights = _bic_weights(table)
    for e in table:
        e["chosen"] = e["name"] == res.model.name
        e["delta_bic"] = None if e.get("bic") is None else e["bic"] - best[0]
        e["weight"] = weights.get(e["name"], 0.0)
    t_map = time.perf_counter() - t0

    # Choice and weights with the error a tile shares between its colour channels: one texture, one set of
    # frames, so a tile's R, G and B best foci err together (correlation 0.3-0.9 on the simulated triplet, where
    # the per-tile error is 2-3x its reported sigma at the edge). BIC counts the three rows as independent, and
    # on 28 tiles per channel it chose a decentre and tilt on tripled evidence, at a different centre in two
    # calibrations of one lens (corners 35 µm apart, bands of a few µm) -- a few tenths of a µm of the data
    # flipped the choice. Each candidate is rescored by its Gaussian likelihood with the channels of a tile
    # correlated (the correlation fitted per candidate), so nearly equal models share the weight and their
    # spread enters the band (docs/fitting.md "Model selection").
    shared = _shared_error_scores(fits, rows)
    if shared:
        weights = _weights_from(shared)
        best_name = min(shared, key=shared.get)
        res = fits[best_name]
        for e in table:
            e["shared_score"] = shared.get(e["name"])
            e["weight"] = weights.get(e["name"], 0.0)
            e["chosen"] = e["name"] == best_name
            e["delta_shared_score"] = None if e["name"] not in shared else shared[e["name"]] - shared[best_name]
    # The choice: the simplest candidate whose blocked held-out predictive loss is not significantly worse than
    # the best's (paired test, :func:`paired_test_choice`). The scores above stay the model-average weights.
    # Why not the lowest score: the tiles' errors are heavy-tailed (~t4) and spatially correlated, so a BIC likelihood ratio overstates the
    # evidence, and with ~10 richer candidates one of them beats the simplest by a unit or two of noise: a
    # flat lens picked curvature in 4 of 20 seeds, an astigmatic one rho^4/rho^6 astigmatism terms, by
    # 0.7-1.4 (docs/fitting.md "Model selection").
    # Only among the candidates the evidence has not ruled out (model-average weight >= BMA_MIN_WEIGHT, so the
    # chosen model is always a member of the average): at 1080p the held-out blocks' own spread (SE ~70) let
    # the rule drop a per-channel rho^4 term that the correlated scores want by 57 (0.02-0.03 µm RMS in R, B).
    cv = {n: v for n, v in _block_cv_losses(fits, rows).items() if weights.get(n, 0.0) >= BMA_MIN_WEIGHT}
    # The error model of the comparison is the best held-out predictor's, not the best-fitting centred
    # model's: on a decentred lens the centred model's misfit went into its Student-t weights and nu (the tiles
    # it cannot follow read as outliers for every candidate), and the comparison could not see it (random lens 6
    # of the slanted-edge bench: held-out gain of the decentre 90 -> 160; docs/fitting.md "Model selection").
    for _ in range(CV_REF_PASSES):
        if not cv:
            break
        ref = fits[min(cv, key=lambda n: float(cv[n].sum()))]
        again = {n: v for n, v in _block_cv_losses(fits, rows, ref=ref).items() if n in cv}
        settled = min(again, key=lambda n: float(again[n].sum())) == ref.model.name if again else True
        cv = again
        if settled:
            break
    if cv:
        sizes = np.bincount(spatial_blocks(rows.x_hat, rows.y_hat))
        cv_name, cv_stats = paired_test_choice(cv, {n: fits[n].model.n_params for n in cv}, sizes)
        res = fits[cv_name]
        for e in table:
            e["chosen"] = e["name"] == cv_name
            st = cv_stats.get(e["name"])
            e["cv_delta"], e["cv_se"], e["cv_margin"] = (None, None, None) if st is None else st
    # Posterior: the chosen model by Laplace or emcee; models within a few score units (weight >= 1%) join as a
    # Bayesian model average with Laplace samples, so a term the selection narrowly dropped still widens
    # the band (docs/fitting.md "Model averaging").
    lap = laplace(res.model, rows, res.theta, seed=seed)
    unusable = None
    if not _usable_member(res.model, lap):
        # The winner's Hessian is not positive definite (a direction the tiles do not constrain): its Gaussian
        # posterior runs to the bounds. Take the best-scoring other centred model, whose posterior is identified.
        score = shared or {e["name"]: e["bic"] for e in table if e.get("bic") is not None}
        alt = [(score[n], fits[n]) for n in score
               if n in fits and not fits[n].model.decentre and n != res.model.name]
        if alt:
            unusable = res.model.name
            res = min(alt, key=lambda t: t[0])[1]
            for e in table:
                e["chosen"] = e["name"] == res.model.name
            lap = laplace(res.model, rows, res.theta, seed=seed)
    # the discrepancy depends only on the chosen MAP: fitted in the worker, when there is one, beside the posterior
    disc_job = Deferred(pool, _discrepancy_and_check, res.model, rows, res.theta, leverage_corrected)
    if eff.method == "laplace":
        post = lap
    else:
        lap_cov = np.cov(lap.samples.T)
        post = run_emcee(res.model, rows, res.theta, eff, seed=seed, ball_cov=lap_cov, quiet=quiet)
    members = [(res.model, res.theta, weights.get(res.model.name, 1.0), post.samples)]
    dropped = []
    for n, r in fits.items():
        if n == res.model.name or weights.get(n, 0.0) < BMA_MIN_WEIGHT:
            continue
        n_m = max(1, int(round(MAX_SAMPLES * weights[n])))
        lap_m = laplace(r.model, rows, r.theta, n_samples=n_m, seed=seed + 7 + len(members))
        if not _usable_member(r.model, lap_m):
            dropped.append(n)
            continue
        members.append((r.model, r.theta, weights[n], lap_m.samples))
    wsum = sum(w for _, _, w, _ in members)
    union = SurfaceModel.union([m for m, *_ in members])
    rng = np.random.default_rng(seed + 1)
    parts = []
    for m, theta, w, smp in members:
        n_m = max(1, int(round(MAX_SAMPLES * w / wsum)))
        if smp.shape[0] > n_m:
            smp = smp[rng.choice(smp.shape[0], n_m, replace=False)]
        parts.append(m.embed(smp, union))
    samples = np.concatenate(parts)
    bma = {"members": [{"name": m.name, "weight": w / wsum} for m, _, w, _ in members],
           "sample_model": union.name, "dropped_unidentified": dropped}
    disc, check = disc_job.result()
    if check.warning:
        warn(check.warning)
    t_total = time.perf_counter() - t0
    m = res.model
    diagnostics = {
        "selection": ("fewest parameters whose blocked held-out loss is not worse than the best's at one-sided "
                      f"level {CV_TEST_LEVEL:g} (paired t, Nadeau-Bengio variance: cv_delta <= cv_margin)" if cv else
                      "lowest -2 ln L + k ln n with a tile's channels correlated (shared_score)" if shared
                      else "lowest BIC = -2 ln L + k ln n over all candidates"),
        "weights": ("exp(-shared_score / 2)" if shared else "exp(-BIC / 2)"),
        "n_rows": rows.n, "n_astig_rows": rows.n_astig, "n_tiles": len(tiles),
        "condition_number": res.condition_number, "nlopt_algorithm": "LN_BOBYQA (variable projection)",
        "nlopt_result": res.nlopt_result, "log_likelihood": res.log_likelihood,
        "log_posterior": res.log_posterior,
        "error_scale": math.exp(float(m.split(res.theta)[2])),
        "student_t_nu": math.exp(float(m.split(res.theta)[4])),
        "posterior": post.diagnostics, "model_average": bma, "discrepancy": disc.diagnostics,
        "self_check": check.to_dict(),
        "dropped_unidentified_winner": unusable, "time_map_s": t_map, "time_total_s": t_total,
    }
    if m.astig_rows:
        diagnostics["error_scale_astig"] = math.exp(float(m.split(res.theta)[3]))
    if post.diagnostics.get("converged") is False:
        warn("the surface posterior did not converge; use --effort thorough")
    return SurfaceFit(m, geometry, zc, zs, res.theta, samples, table, diagnostics, effort, sample_model=union,
                      discrepancy=disc, band_scale=check.band_scale)


def _discrepancy_and_check(model: SurfaceModel, rows: Rows, theta: np.ndarray, leverage_corrected: bool):
    """The chosen model's discrepancy (:func:`fit_discrepancy`) and its self-check (:func:`predictive_check`)."""
    disc = fit_discrepancy(model, rows, theta, student_t_weights(model, rows, theta),
                           leverage_corrected=leverage_corrected)
    return disc, predictive_check(disc)


def student_t_weights(model: SurfaceModel, rows: Rows, theta: np.ndarray) -> np.ndarray:
    """E-step weights u_i = (nu + 1) / (nu + r_i^2 / sigma_i^2) of the rows at ``theta`` (outliers << 1)."""
    beta, centre, log_s, log_sa, log_nu = model.split(theta)
    X = model.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre)
    sig = model.sigma_eff(rows, log_s, log_sa)
    nu = math.exp(float(log_nu))
    return (nu + 1.0) / (nu + ((rows.target - X @ beta) / sig) ** 2)


def _usable_member(model: SurfaceModel, lap) -> bool:
    """A model-average member joins if its Laplace samples are finite and, without a decentre, its Hessian is
    positive definite. A decentred model's coefficients are drawn conditionally on each drawn centre
    (:func:`fieldcal.fit.posterior.laplace`), so a weakly located centre widens the band where the model
    extrapolates instead of running the coefficients to the bounds: no threshold on the centre's sd decides
    membership (one did, and a few tenths of a µm of the data flipped the chosen model)."""
    if not model.decentre and not lap.diagnostics.get("hessian_positive_definite", False):
        return False
    return bool(np.all(np.isfinite(lap.samples)))


SHARED_RHO_GRID = np.linspace(0.0, 0.95, 20)  # candidate correlations of a tile's channels (profiled out)


def tile_groups(x_hat: np.ndarray, y_hat: np.ndarray, ch_index: np.ndarray) -> np.ndarray:
    """Group id per row: the rows of one tile in different channels (positions within a quarter of the tile
    spacing: lateral colour moves a tile's centre a little between channels)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pts = np.column_stack([x_hat, y_hat])
    nn = []
    for c in np.unique(ch_index):
        m = ch_index == c
        if m.sum() >= 2:
            d, _ = cKDTree(pts[m]).query(pts[m], k=2)
            nn.append(d[:, 1])
    nn = np.concatenate(nn) if nn else np.zeros(0)
    nn = nn[nn > 0]
    spacing = float(np.median(nn)) if nn.size else 0.0
    tree = cKDTree(pts)
    pairs = np.array(sorted(tree.query_pairs(0.25 * spacing)), dtype=np.int64).reshape(-1, 2)
    pairs = pairs[ch_index[pairs[:, 0]] != ch_index[pairs[:, 1]]] if pairs.size else pairs
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(pts.shape[0],) * 2)
    return connected_components(g, directed=False)[1]


def _shared_error_scores(fits: dict, rows: Rows) -> dict[str, float]:
    """Per fitted candidate, -2 ln L + k ln n with a tile's channels correlated.

    Focus rows only; row i's variance is (sigma_i)^2 / u_i (u_i: the Student-t weight at the best-fitting centred
    candidate's MAP, the same for every candidate, so outliers stay out) times a common scale, and rows of one tile (:func:`tile_groups`) correlate with rho. The
    coefficients are their generalised least-squares values at the candidate's MAP centre; the scale is
    profiled in closed form and rho on a grid. The astigmatism rows keep their independent Student-t likelihood.
    """
    focus = rows.kind == 0
    if len(np.unique(rows.ch_index[focus])) < 2:
        return {}
    xh, yh, ci, y = rows.x_hat[focus], rows.y_hat[focus], rows.ch_index[focus], rows.target[focus]
    grp = tile_groups(xh, yh, ci)
    order = np.argsort(grp, kind="stable")
    xh, yh, ci, y, grp = xh[order], yh[order], ci[order], y[order], grp[order]
    starts = np.flatnonzero(np.r_[True, grp[1:] != grp[:-1]])
    sizes = np.diff(np.r_[starts, grp.size])
    n = int(y.size)
    # One set of row variances for every candidate (a likelihood ratio needs the same error model): the
    # Student-t weights of the best-fitting centred candidate, the most flexible smooth surface, so a row is an
    # outlier against the field's shape, not against a candidate that bends (or a heavy-tailed fit that drops
    # rows it does not fit).
    centred = [r for r in fits.values() if not r.model.decentre]
    ref = max(centred or list(fits.values()), key=lambda r: r.log_likelihood)
    u = student_t_weights(ref.model, rows, ref.theta)[focus][order]
    sd = rows.sigma[focus][order] / np.sqrt(np.clip(u, 1e-6, None))
    out = {}
    for name, r in fits.items():
        m = r.model
        _, centre, *_ = m.split(r.theta)
        X = m.design(xh, yh, ci, np.zeros(n, np.int64), centre) / sd[:, None]
        yw0 = y / sd
        best = None
        for rho in SHARED_RHO_GRID:
            Xw, yw, logdet = _whiten_blocks(X, yw0, starts, sizes, rho)
            A = Xw.T @ Xw + np.eye(m.n_linear) / COEF_PRIOR_SD ** 2
            b = Xw.T @ yw
            try:
                quad = float(yw @ yw - b @ np.linalg.solve(A, b))
            except np.linalg.LinAlgError:
                continue
            if not quad > 0:
                continue
            # Gaussian log-likelihood with the common scale profiled: -n/2 (ln(2 pi quad / n) + 1) - logdet/2
            ll = -0.5 * n * (math.log(2.0 * math.pi * quad / n) + 1.0) - 0.5 * logdet - float(np.sum(np.log(sd)))
            if best is None or ll > best:
                best = ll
        if best is None:
            continue
        if rows.n_astig and m.astig_rows:
            best += float(np.sum(m.log_likelihood(r.theta, rows)[rows.kind == 1]))
        k = m.n_linear + (2 if m.decentre else 0)
        out[name] = -2.0 * best + k * math.log(rows.n)
    return out


CV_BLOCKS = 10  # about this many spatial blocks of tiles are held out in turn (ESL 7.10: 5- or 10-fold)
# One-sided level of the paired test that lets a richer model replace a simpler one (paired_test_choice)
CV_TEST_LEVEL = 0.05
# Passes that move the comparison's error model to the best held-out predictor (fit_surfaces)
CV_REF_PASSES = 3


def spatial_blocks(x_hat: np.ndarray, y_hat: np.ndarray, n_blocks: int = CV_BLOCKS) -> np.ndarray:
    """Block id per row: cells of a grid of about ``n_blocks`` over the rows' bounding box, as near square as the
    field allows (a 4:3 field: 4 x 3). Neighbouring tiles, and every row of one tile (its channels and its
    tangential/sagittal row), fall in one block, so a held-out block's errors are not predicted by the
    errors they share with the rows that fit it."""
    wx = float(np.ptp(x_hat)) or 1.0
    wy = float(np.ptp(y_hat)) or 1.0
    nx = max(1, math.ceil(math.sqrt(n_blocks * wx / wy)))
    ny = max(1, math.ceil(n_blocks / nx))
    ix = np.minimum(((x_hat - x_hat.min()) / wx * nx).astype(np.int64), nx - 1)
    iy = np.minimum(((y_hat - y_hat.min()) / wy * ny).astype(np.int64), ny - 1)
    return np.unique(iy * nx + ix, return_inverse=True)[1].reshape(-1)


def _block_cv_losses(fits: dict, rows: Rows, ref=None) -> dict[str, np.ndarray]:
    """Per fitted candidate, its held-out loss on each spatial block (:func:`spatial_blocks`).

    One error model for every candidate (a comparison needs one, and a candidate that misfits must not hide it in
    a wider error scale or heavier tails): the Student-t of ``ref`` (a MAP fit; default the best-fitting centred
    candidate, the most flexible smooth surface; :func:`fit_surfaces` then moves it to the best held-out
    predictor), its scale s sigma_i, nu and weights u_i. Each
    candidate's coefficients are the weighted least squares with weights u_i / (s sigma_i)^2 (the Student-t
    MAP's fixed point); leaving block B out of that fit gives residuals (I - H_BB)^-1 e_B exactly, so the cost is
    one hat matrix per candidate instead of a refit per fold. Loss of a block: the Student-t deviance
    sum (nu + 1) ln(1 + r^2 / (nu s^2 sigma^2)) of its held-out rows (-2 ln p less its model-free constant).
    A decentred candidate refits its centre too, linearised at its MAP (exact to first order): a centre held at
    its all-data value has seen the held-out block, and made a decentre the best predictor on most flat-lens
    seeds for that reason alone.
    """
    blocks = spatial_blocks(rows.x_hat, rows.y_hat)
    members = [np.flatnonzero(blocks == b) for b in range(int(blocks.max()) + 1)]
    centred = [r for r in fits.values() if not r.model.decentre]
    if not centred:
        return {}
    if ref is None:
        ref = max(centred, key=lambda r: r.log_likelihood)
    _, _, log_s, log_sa, log_nu = ref.model.split(ref.theta)
    sig = ref.model.sigma_eff(rows, log_s, log_sa)
    sd = sig / np.sqrt(np.clip(student_t_weights(ref.model, rows, ref.theta), 1e-6, None))
    nu = math.exp(float(log_nu))
    y = rows.target / sd
    out = {}
    for name, r in fits.items():
        m = r.model
        _, centre, *_ = m.split(r.theta)
        X = m.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre) / sd[:, None]
        ridge = np.full(m.n_linear, 1.0 / COEF_PRIOR_SD ** 2)
        try:
            beta = np.linalg.solve(X.T @ X + np.diag(ridge), X.T @ y)
        except np.linalg.LinAlgError:
            continue
        e = y - X @ beta
        if m.decentre:
            h = 1e-5
            dc = [(m.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre + h * d) @ beta
                   - m.design(rows.x_hat, rows.y_hat, rows.ch_index, rows.kind, centre - h * d) @ beta)
                  / (2.0 * h) / sd for d in np.eye(2)]
            X = np.column_stack([X] + dc)
            ridge = np.r_[ridge, 1.0 / CENTRE_BOUND ** 2, 1.0 / CENTRE_BOUND ** 2]
        try:
            held = held_out_residuals(X, e, ridge, members)
        except np.linalg.LinAlgError:
            continue
        loss = np.array([float(np.sum((nu + 1.0) * np.log1p((r * sd[idx] / sig[idx]) ** 2 / nu)))
                         for r, idx in zip(held, members)])
        if np.all(np.isfinite(loss)):
            out[name] = loss
    return out


def held_out_residuals(X: np.ndarray, e: np.ndarray, ridge: np.ndarray, members: list) -> list[np.ndarray]:
    """Residuals of each block of rows predicted by the ridge least squares fitted to all other rows.

    ``X`` (n, p) and the all-row residuals ``e`` are whitened (unit variances), ``ridge`` (p,) the prior
    precisions. With H = X (X^T X + diag(ridge))^-1 X^T, leaving block B out gives (I - H_BB)^-1 e_B exactly
    (the block-deletion identity), so no fold is refitted.
    """
    Ainv_Xt = np.linalg.solve(X.T @ X + np.diag(ridge), X.T)
    return [np.linalg.solve(np.eye(idx.size) - X[idx] @ Ainv_Xt[:, idx], e[idx]) for idx in members]


def paired_test_choice(losses: dict[str, np.ndarray], n_params: dict[str, int], block_rows: np.ndarray,
                       level: float = CV_TEST_LEVEL):
    """The candidate with the fewest parameters whose held-out loss is not significantly worse than the best's.

    ``losses``: per candidate, its loss on each of K held-out blocks (same blocks, same error model for every
    candidate), whose total is the cross-validation estimate; ``block_rows``: the rows in each block. A candidate
    m is compared with the best b by its per-block differences d_k = L_m,k - L_b,k (paired: what the blocks share
    cancels), D = sum d_k. Blocked cross-validation differences are positively correlated (every two folds
    share most of their training rows), so the naive variance K s_d^2 is optimistic; it is inflated by
    Nadeau & Bengio's factor 1 + K n_test / n_train (Machine Learning 52, 2003, "corrected resampled t-test";
    ~2.1 for 10 blocks). m is kept if D <= t_{1 - level, K - 1} sqrt(K s_d^2 (1 + K n_test / n_train)): one-sided
    at ``level``, with the blocks' degrees of freedom. Ties in parameters go to the lower loss.

    Returns (name, {name: (D, SE of D, margin)}).
    """
    # the t quantile from scipy.special: scipy.stats costs ~0.6 s to import, a quarter of a quick calibration
    from scipy.special import stdtrit

    tot = {n: float(v.sum()) for n, v in losses.items()}
    best = min(tot, key=tot.get)
    k = int(losses[best].size)
    block_rows = np.asarray(block_rows, dtype=np.float64)
    n_test = float(block_rows.mean()) if block_rows.size else 0.0
    n_train = float(block_rows.sum()) - n_test
    inflate = 1.0 + k * n_test / n_train if n_train > 0 else math.inf
    quantile = float(stdtrit(k - 1, 1.0 - level)) if k > 1 else math.inf
    stats = {}
    for n, v in losses.items():
        d = v - losses[best]
        delta = tot[n] - tot[best]
        se = float(math.sqrt(k * np.var(d, ddof=1) * inflate)) if k > 1 else math.inf
        # one block (no test possible): nothing is shown worse, so the simplest is kept
        margin = 0.0 if n == best else quantile * se
        stats[n] = (delta, se if n != best else 0.0, margin)
    ok = [n for n, (delta, _, margin) in stats.items() if delta <= margin]
    return min(ok, key=lambda n: (n_params[n], tot[n])), stats


def _whiten_blocks(X, y, starts, sizes, rho):
    """Whiten rows sorted into consecutive blocks of equal correlation rho (unit variances).

    For a block of size k, C = (1 - rho) I + rho 11^T has the symmetric inverse square root
    (I - J) / sqrt(1 - rho) + J / sqrt(1 + (k - 1) rho) with J = 11^T / k (the block mean and its contrasts), and
    log det C = (k - 1) ln(1 - rho) + ln(1 + (k - 1) rho). Returns (Xw, yw, log det).
    """
    k = np.repeat(sizes, sizes).astype(np.float64)
    a = 1.0 / math.sqrt(1.0 - rho)
    c = 1.0 / np.sqrt(1.0 + (k - 1.0) * rho)

    def apply(v):
        mean = np.repeat(np.add.reduceat(v, starts, axis=0) / sizes.reshape((-1,) + (1,) * (v.ndim - 1)), sizes,
                         axis=0)
        cc = c.reshape((-1,) + (1,) * (v.ndim - 1))
        return a * (v - mean) + cc * mean

    logdet = float(np.sum((sizes - 1) * math.log(1.0 - rho) + np.log(1.0 + (sizes - 1) * rho)))
    return apply(X), apply(y), logdet


def _weights_from(scores: dict[str, float]) -> dict[str, float]:
    """exp(-score / 2), normalised: approximate posterior model probabilities from BIC-like scores."""
    if not scores:
        return {}
    b0 = min(scores.values())
    w = {n: math.exp(-0.5 * (b - b0)) for n, b in scores.items()}
    tot = sum(w.values())
    return {n: v / tot for n, v in w.items()}


def _bic_weights(table) -> dict[str, float]:
    """Approximate posterior model probabilities exp(-BIC/2), normalised over the fitted candidates."""
    return _weights_from({e["name"]: e["bic"] for e in table if e.get("bic") is not None})
