"""``fieldcal.calibrate``: chart stack → lens profile (measure → fit → profile).

One streaming pass over the frames measures per-tile through-focus curves and per-frame geometry
(:mod:`fieldcal.measure`); the accepted tiles are fitted with per-channel best-focus surfaces, model selection
and a posterior (:mod:`fieldcal.fit`); magnification/shift vs z and the tolerance (width) model are fitted; the
result is a :class:`fieldcal.profile.LensProfile` with diagnostics and provenance (a sha256 of the inputs,
computed in a background thread while the frames are measured).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from fieldcal import __version__
from fieldcal.errors import FieldcalError, ParameterError, StackError
from fieldcal.optics import MTFCriterion
from fieldcal.profile.lens_profile import LensProfile
from fieldcal.progress import status, warn
from fieldcal.fit.tiles import stage_sd_um  # the band's stage term (also re-exported for callers)

EFFORTS = ("quick", "standard", "thorough")
MIN_FRAMES = 5
# No fixed systematic: the band's systematic terms (model misfit, common-mode tile error) are estimated from
# the stack's own tiles (fieldcal.fit.discrepancy, docs/fitting.md "Systematic"). A fixed 0.01 scan step was
# used before; profiles that carry it (calibration.systematic_sd_um > 0) keep their band.
SYSTEMATIC_STEP_FRACTION = 0.0
CHARTS = ("auto", "esfr", "focus-measure")


def _check(fs_cyc_per_mm, q, effort, pitch_um):
    if effort not in EFFORTS:
        raise ParameterError(f"unknown effort {effort!r}", field="effort", fix="use quick, standard or thorough")
    crit = MTFCriterion(fs_cyc_per_mm, q)
    nyquist = 1000.0 / (2.0 * pitch_um)
    if crit.fs_cyc_per_mm >= 0.9 * nyquist:
        raise ParameterError(f"fs = {fs_cyc_per_mm:g} cycles/mm is at or above 90% of the sensor's Nyquist "
                             f"frequency ({nyquist:.1f} cycles/mm at {pitch_um:g} µm pixels)", field="fs_cyc_per_mm",
                             fix=f"use fs below {0.9 * nyquist:.0f} cycles/mm (e.g. {min(80.0, 0.5 * nyquist):.0f})")


def _hash_inputs(stack, out: dict):
    """sha256 identifying the inputs: stack.json and the content of every frame file, in file order.

    Hashing the frames' content (not only the sha256 values stack.json records) makes two stacks whose
    frames differ give different hashes even when the recorded checksums were not verified (``--no-verify``).
    A stack opened with verification has its frame hashes cached, so this costs nothing more; otherwise it
    runs in a thread beside the measurement (hashlib releases the GIL).
    """
    h = hashlib.sha256()
    try:
        h.update(Path(stack.json_path).read_bytes())
        digest = getattr(stack, "frame_sha256", None)
        for i, fr in enumerate(stack.frames):
            if digest is not None:
                h.update(bytes.fromhex(digest(i)))
            else:
                with open(fr.path, "rb") as f:
                    for chunk in iter(lambda: f.read(1 << 22), b""):
                        h.update(chunk)
        out["method"] = "sha256 of stack.json and of every frame file's content"
        out["sha256"] = h.hexdigest()
    except Exception as e:  # reported in provenance, not fatal: the measurement itself will fail loudly
        out["error"] = str(e)


@contextlib.contextmanager
def one_blas_thread():
    """BLAS (OpenBLAS/MKL, through threadpoolctl) limited to one thread for the block, then restored.

    Calibration's linear algebra is small (Cholesky factors of a few hundred rows, 10-30 parameter
    normal equations, emcee's batched products): a second BLAS thread cannot speed it up, and its hand-off
    costs more than the work. Measured on 569 tiles: the surface fit took 9.5 s of CPU with OpenBLAS's
    default 2 threads against 1.9 s with one (the REML Cholesky factors 6.6 -> 0.24 s), and 4-8x that in
    wall time when other processes share the cores. The frames are measured in our own thread pool.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # a core dependency; tolerate its absence (slower, same numbers)
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def calibrate(stack, *, fs_cyc_per_mm: float = 80.0, q: float = 0.05, effort: str = "standard",
              z_ref_um: float | None = None, tile_px: int | None = None, measure: str = "auto", seed: int = 0,
              quiet: bool = False, stage_repeatability_um: float | None = None,
              chart: str = "auto", geometry_maps: str = "auto") -> LensProfile:
    """Fit a lens profile from a chart stack.

    Parameters
    ----------
    stack : Stack or path
        A ``fieldcal-stack/1`` folder of a textured chart across sensor positions spanning the field curvature.
    fs_cyc_per_mm, q : float
        Target frequency and allowed MTF loss that define the measured through-focus width (tolerance).
    effort : {"quick", "standard", "thorough"}
        quick: coarser tiles, MAP + Laplace; standard: emcee posterior; thorough: denser tiles, directional
        (astigmatism) measures, longer chains and a wider model search.
    z_ref_um : float, optional
        Reference position of the geometry model (default: the middle frame).
    tile_px : int, optional
        Tile size (default from the image size and effort).
    measure : {"auto", "sml", "bandpass"}
        Focus measure of the best-focus estimate: "auto" (default) ``"sml@fs"`` — the SML moved by each
        channel's pooled offset to the band-pass at fs (where contrast at fs peaks, the paper's best focus) —
        where the pixels resolve fs, else the SML (``calibration.measure`` records which).
    seed : int
        Seeds the samplers (reproducible profiles).
    stage_repeatability_um : float, optional
        1-sigma position repeatability of the stage (µm); default from the stage record in stack.json
        (``capture.stage.repeatability_um`` or ``noise_um``), else 0. Its effect on the best focus joins the
        band (docs/fitting.md "Stage errors").
    geometry_maps : {"auto", "charuco", "texture", "off"}
        Dense geometry maps (distortion, breathing, shift, lateral colour vs x, y, z; docs/geometry.md) from the
        ChArUco board stack.json's ``chart`` records ("auto" measures them when there is one), from the texture
        (slower), or none (the scalar magnification and shift model only).
    chart : {"auto", "esfr", "focus-measure"}
        The measurement: slanted-edge MTF through focus ("esfr"), the texture focus measure
        ("focus-measure"), or chosen from the middle frame ("auto": e-SFR when it holds enough slanted edges;
        docs/measurement.md "Calibrating from slanted edges"). Recorded as ``calibration.measurement``.

    Returns
    -------
    LensProfile

    Examples
    --------
    >>> import fieldcal
    >>> profile = fieldcal.calibrate(fieldcal.Stack.open("STACK"), effort="quick")   # doctest: +SKIP
    >>> profile.save("lens.json")                                                     # doctest: +SKIP
    """
    with one_blas_thread():
        return _calibrate(stack, fs_cyc_per_mm=fs_cyc_per_mm, q=q, effort=effort, z_ref_um=z_ref_um,
                          tile_px=tile_px, measure=measure, seed=seed, quiet=quiet,
                          stage_repeatability_um=stage_repeatability_um, chart=chart, geometry_maps=geometry_maps)


def _calibrate(stack, *, fs_cyc_per_mm, q, effort, z_ref_um, tile_px, measure, seed, quiet,
               stage_repeatability_um, chart, geometry_maps) -> LensProfile:
    from fieldcal.formats.stack import Stack
    if not isinstance(stack, Stack):
        stack = Stack.open(stack, verify=False)
        stack.start_verify()  # the frames hash beside the imports and the chart check below (Stack.start_verify)
    from fieldcal.measure import measure_geometry, measure_stack
    from fieldcal.measure.esfr_pool import keep_pool
    from fieldcal.measure.tiles import TileRules
    from fieldcal.fit import ImageGeometry
    from fieldcal.fit.geometry import GeometryData, fit_geometry
    from fieldcal.fit.stage import fit_stage_errors
    from fieldcal.fit.tolerance import MIN_QUICK_WIDTHS, fit_tolerance
    from fieldcal.fit.width_window import correct_widths
    from fieldcal.fit.tiles import (breathing_systematic_sd_um, colour_rows, fit_tile_surfaces, geometry_columns,
                                    measure_offset_sd_um, systematic_record)

    _check(fs_cyc_per_mm, q, effort, stack.pixel_pitch_um)
    if chart not in CHARTS:
        raise ParameterError(f"unknown chart measurement {chart!r}", field="chart",
                             fix=f"use one of {', '.join(CHARTS)}")
    stack.require_frames(MIN_FRAMES, "calibration (a through-focus curve needs points on both sides of its peak)")
    finish_verify = getattr(stack, "finish_verify", lambda: None)
    try:
        kind = chart_measurement(stack, chart)
    except Exception:
        finish_verify()  # a frame changed since it was written says more than what failed to read in it
        raise
    finish_verify()  # a verification still running (Stack.start_verify) refuses a changed stack before measuring
    stage_rep, stage_src = stage_repeatability(stack, stage_repeatability_um)
    t0 = time.perf_counter()
    digest: dict = {}
    hasher = threading.Thread(target=_hash_inputs, args=(stack, digest), daemon=True)
    hasher.start()

    # the track fits' worker processes, where there are any, are kept for the surface fit's independent pieces
    # (fieldcal/fit/pool.py: their NumPy and SciPy are loaded), then closed
    with keep_pool():
        edge_summary = None
        if kind.kind == "esfr":  # the texture pass measures only the geometry (magnification, shift vs z): no focus maps
            geo_meas = measure_geometry(stack, effort=effort, z_ref_um=z_ref_um, quiet=quiet)
            table, edge_summary = measure_edges(stack, fs_cyc_per_mm=float(fs_cyc_per_mm), q=float(q),
                                                z_ref_um=float(geo_meas.z_ref_um), geometry=geo_meas, quiet=quiet)
        else:
            # the stage's repeatability: its frame errors enter every tile's curve at once (the pooled skew and offset)
            table, geo_meas = measure_stack(stack, fs_cyc_per_mm=float(fs_cyc_per_mm), q=float(q), tile_px=tile_px,
                                            effort=effort, measure=measure, z_ref_um=z_ref_um, quiet=quiet,
                                            rules=TileRules(stage_repeatability_um=stage_rep))
            _require_tiles(table, stack, kind)
        measure = table.measure  # "auto" resolved (measure.tiles.resolve_measure); "esfr" on edges
        t_measure = time.perf_counter() - t0
        counts = table.counts()
        n_ok = int(table.ok.sum())
        if n_ok == 0:
            raise StackError(f"every tile was rejected ({', '.join(f'{k}: {v}' for k, v in counts.items())})",
                             path=stack.path, fix="check that the chart is textured, in the field of view, not "
                             "saturated, and that the z range spans the best focus of the whole field with margin")
        w, h = int(stack.shape[1]), int(stack.shape[0])
        geometry = ImageGeometry(w, h, float(stack.pixel_pitch_um))
        surf, tiles = fit_tile_surfaces(table, geometry, channels=tuple(stack.channels), effort=effort, seed=seed,
                                        quiet=quiet, source=str(stack.path))
    surf.stage_sd_um = stage_sd_um(table, stage_rep)
    # the frames' position errors fitted with the surface where the tiles' curves allow (replaces the field-wide
    # term above in the band; docs/fitting.md "Stage errors")
    stage_fit = fit_stage_errors(surf, table, stage_rep)
    if kind.kind == "esfr" and edge_summary and surf.discrepancy is not None:
        _edge_common_mode(surf.discrepancy, edge_summary.get("common_mode") or {}, float(surf.z_scale_um))
    breathing_sd = breathing_systematic_sd_um(table)
    offset_sd = measure_offset_sd_um(table)
    t_fit = time.perf_counter() - t0 - t_measure
    centre = surf.optical_centre_px()
    geo_c = geo_meas.recentred(tuple(float(v) for v in centre))
    cols = geometry_columns(geo_c)
    gdata = GeometryData.from_arrays(**cols, colour_scale=colour_rows(geo_c, cols), source=str(stack.path))
    geom = fit_geometry(gdata, z_ref_um=geo_c.z_ref_um, source=str(stack.path))
    gmap, absd = _geometry_map(stack, geometry_maps, float(geo_c.z_ref_um), quiet)
    tol, tol_note = None, None
    try:
        # each tile's width without the spread of best focus inside it (fit/width_window.py); the model is about
        # the sensor centre: a decentred width field is its linear terms (fit/tolerance.py)
        if getattr(table, "measure", "") == "esfr":
            # an e-SFR row is a line, not a square: its e-SFR mixes focus only *along* the edge, and each track's
            # width is freed of that spread before the pair's (measure/edge_tiles.py). The square model put the whole gradient in: at 1920x1080 it narrowed the
            # triplet's edge widths 3 % (median) and up to 34x at the corners (δ 0.97 -> 0.94 of the truth)
            tiles_w, window_note = tiles, {"rule": "none: e-SFR widths (each freed of its along-edge spread)"}
        else:
            tiles_w, window_note = correct_widths(surf, tiles, table.z_um, float(table.tile_px), fs_cyc_per_mm, q)
        # slanted-edge widths are the defocus law's own (one blur rate, 1/N, at every wavelength): one model for
        # all channels where the data do not need one each (fit/tolerance.py)
        # the F-number (and any recorded wavelengths) convert the widths to another (fs, q) with diffraction
        # (quick's texture widths come from its band-pass strip: too few of them and the model answers instead)
        wl_rec = stack.meta.get("wavelength_nm")
        tol = fit_tolerance(tiles_w, geometry, MTFCriterion(fs_cyc_per_mm, q), source=str(stack.path),
                            shared_channels=kind.kind == "esfr", f_number=stack.meta.get("f_number"),
                            # e-SFR widths are the defocus law's: their error is symmetric in 1 / w^2
                            residuals="curvature" if kind.kind == "esfr" else "width",
                            wavelength_nm=wl_rec if isinstance(wl_rec, dict) else None,
                            min_tiles=MIN_QUICK_WIDTHS if effort == "quick" and kind.kind != "esfr" else 4)
        tol.diagnostics["width_window"] = window_note
    except FieldcalError as e:  # planning falls back to the defocus model and says so
        tol_note = f"no measured tolerance model: {e.what}"
    hasher.join()
    t_total = time.perf_counter() - t0
    scan_end = scan_end_rejections(table)
    if scan_end.get("warning"):
        warn(scan_end["warning"])
    skew_note = curve_skew_warning(table, measure)
    if skew_note:
        warn(skew_note)

    z = np.sort(np.asarray(stack.z_um, dtype=float))
    steps = np.diff(z)
    meta = stack.meta
    wl = None
    if isinstance(meta.get("wavelength_nm"), dict):
        wl = meta["wavelength_nm"]
    profile = LensProfile(
        surfaces=surf, geometry_fit=geom, tolerance_fit=tol,
        image={"width_px": w, "height_px": h, "pixel_pitch_um": float(stack.pixel_pitch_um),
               "channels": list(stack.channels), "cfa": stack.cfa},
        optics={"f_number": meta.get("f_number"), "focal_length_mm": meta.get("focal_length_mm"),
                "object_distance_mm": meta.get("object_distance_mm"), "wavelength_nm": wl},
        calibration={"fs_cyc_per_mm": float(fs_cyc_per_mm), "q": float(q), "effort": effort, "measure": measure,
                     # what the best foci were measured with: "esfr" (slanted-edge MTF(fs) through focus) or
                     # "focus-measure" (texture tiles, `measure`); `chart` says why
                     "measurement": kind.kind, "chart": kind.to_dict(),
                     "tile_px": int(table.tile_px), "seed": int(seed), "n_frames": int(len(stack)),
                     "z_range_um": [float(z[0]), float(z[-1])],
                     "z_step_um": float(np.median(steps)) if steps.size else None,
                     # kept for old readers: 0 = no fixed systematic beyond the estimated band terms below
                     "systematic_sd_um": SYSTEMATIC_STEP_FRACTION * float(np.median(steps)) if steps.size else 0.0,
                     "systematic": systematic_record(surf),
                     # 1-sigma breathing systematic per channel, shared by the whole field (µm)
                     "breathing_systematic_sd_um": breathing_sd,
                     # 1-sigma error of the sml@fs offset per channel, shared by the whole field (µm)
                     "measure_offset_sd_um": offset_sd,
                     # stage repeatability (1 sigma, µm) and where it came from; its per-channel effect on the
                     # best focus (in the band) is surfaces.stage_sd_um
                     "stage_repeatability_um": stage_rep, "stage_repeatability_source": stage_src,
                     "stage_errors": stage_fit},
        z_ref_um=float(geo_c.z_ref_um),
        diagnostics={"tiles": counts, "n_tiles_ok": n_ok,
                     **({"esfr": edge_summary} if edge_summary else {}), "surface": surf.diagnostics,
                     "geometry": getattr(geom, "diagnostics", {}),
                     "tolerance": tol_note if tol is None else getattr(tol, "diagnostics", {}),
                     "max_image_displacement_px": geo_c.max_displacement_px(),
                     "scan_end": scan_end,
                     # per channel: the pooled through-focus skew (docs/measurement.md "Asymmetric curves")
                     "curve_skew": {"channels": dict(getattr(table, "skew", {}) or {}), "warning": skew_note},
                     "timing_s": {"measure": round(t_measure, 3), "fit": round(t_fit, 3),
                                  "total": round(t_total, 3)}},
        provenance={"created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "tool": {"name": "fieldcal", "version": __version__},
                    "stack": str(Path(stack.path).resolve()), "inputs_sha256": digest.get("sha256"),
                    "inputs_hash_method": digest.get("method"),
                    "inputs_hash_error": digest.get("error"),
                    "stack_meta": {k: v for k, v in meta.items() if k != "frames"}},
        tiles=table.to_dict(), geometry_measurements=cols, geometry_map=gmap,
        absolute_distortion=absd,
    )
    _self_check_coverage(profile)
    _check_surface_support(profile, table, stack, (float(z[0]), float(z[-1])), quiet)
    status(f"calibrated {len(stack)} frames in {t_total:.1f} s from {kind.kind}: model {surf.model.name}, "
           f"{n_ok} {'edge rows' if kind.kind == 'esfr' else 'tiles'} used", quiet=quiet)
    return profile


def _self_check_coverage(profile) -> None:
    """The self-check's estimate of the band's truth coverage (fit/selfcheck.py ``coverage_estimate``), from the
    finished profile's own error model and the held-out tiles' kappa; warns when the evidence puts it outside
    0.8-0.97 (docs/fitting.md "Self-checked coverage")."""
    from fieldcal.fit.selfcheck import coverage_estimate

    sc = (profile.surfaces.diagnostics or {}).get("self_check")
    if not (isinstance(sc, dict) and sc.get("status") == "ok"):
        return
    t0 = time.perf_counter()
    fit_warning = sc.get("warning")  # the tile-level one, already shown by the surface fit
    sc["tile_coverage"] = sc.get("tile_coverage", sc.get("coverage"))
    sc.update(coverage_estimate(profile, math.log(float(sc.get("kappa") or 1.0)), float(sc.get("log_kappa_sd") or 0.0)))
    sc["time_s"] = round(float(sc.get("time_s") or 0.0) + time.perf_counter() - t0, 4)
    if sc.get("warning") and not fit_warning:
        warn(sc["warning"])


def _check_surface_support(profile, table, stack, z_range_um, quiet: bool) -> None:
    """Refuse a surface the rejected tiles' curves contradict; warn when the calibrated focus (the optical
    centre) is extrapolated (:mod:`fieldcal.calibration.consistency`). Both go to ``diagnostics``."""
    from fieldcal.calibration.consistency import centre_support, check_brackets, refuse_contradicted_surface
    br = check_brackets(profile, table)
    refuse_contradicted_surface(br, stack.path, z_range_um)
    sup = centre_support(profile, table, profile.reference_channel)
    profile.diagnostics["surface_support"] = {"brackets": br.to_dict(), "centre": sup}
    if sup["warning"]:
        warn(sup["warning"])


GEOMETRY_MAPS = ("auto", "charuco", "texture", "off")


def _geometry_map(stack, mode: str, z_ref_um: float, quiet: bool):
    """The dense geometry maps calibrate measures and the absolute distortion (ChArUco only): (None, None) for
    the scalar model only."""
    from fieldcal.formats.stack import stack_chart
    if mode not in GEOMETRY_MAPS:
        raise ParameterError(f"unknown geometry_maps {mode!r}", field="geometry_maps",
                             fix=f"use one of {', '.join(GEOMETRY_MAPS)}")
    chart = stack_chart(stack.meta, stack.json_path)
    if mode == "off" or (mode == "auto" and not (chart and chart.get("kind") == "charuco")):
        return None, None
    from fieldcal.measure.charuco import measure_geometry
    return measure_geometry(stack, z_ref_um, chart=chart, source="auto" if mode == "auto" else mode,
                                quiet=quiet)


def chart_measurement(stack, chart: str = "auto"):
    """The measurement a stack's chart calls for (:class:`fieldcal.measure.edge_tiles.ChartKind`).

    "auto" looks at the middle frame of the scan (:func:`fieldcal.measure.edge_tiles.chart_kind`): a
    slanted-edge chart has many edges that pass the e-SFR rules; a texture chart has none. An explicit
    choice is recorded as given (its edge counts are then not measured, -1)."""
    from fieldcal.measure.edge_tiles import ChartKind, chart_kind

    order = [int(k) for k in stack.order_by_z]
    mid = order[len(order) // 2]
    z_mid = float(np.asarray(stack.z_um, dtype=float)[mid])
    if chart != "auto":
        return ChartKind(chart, -1, -1, z_mid)
    return chart_kind(stack.read_normalized(mid), tuple(stack.channels), getattr(stack, "cfa", None), z_mid)


def _edge_common_mode(disc, common: dict, z_scale_um: float) -> None:
    """The band's field-wide term of slanted-edge rows: the error the channel's peaks share, measured on its
    tracks (:func:`fieldcal.measure.esfr_focus.law_common_mode`), not a fraction of the per-edge noise
    (docs/measurement.md "The band's field-wide term"). Where the stage frames are fitted
    (``Discrepancy.has_stage``) they carry the frames' share; the law's stays."""
    def sd(c):
        v = common.get(c) or {}
        if disc.has_stage:
            return math.hypot(float(v.get("law_um", 0.0)), float(v.get("shape_um", 0.0)))
        return float(v.get("sd_um", 0.0))
    disc.set_common_mode(np.array([sd(c) for c in disc.model.channels]) / z_scale_um,
                         "measured by the e-SFR peak estimator (measure.esfr_focus.law_common_mode)"
                         + ("; frames' share in the fitted stage frames" if disc.has_stage else ""))


def measure_edges(stack, *, fs_cyc_per_mm: float, q: float, z_ref_um: float, geometry=None, quiet: bool = False):
    """Slanted-edge best foci through the stack as a tile table (:func:`fieldcal.measure.edge_tiles.edge_table`;
    ``geometry`` the stack's breathing, which places each track where its peak was measured);
    refuses when a channel has too few edges for a surface."""
    from fieldcal.fit.data import MIN_TILES_PER_CHANNEL
    from fieldcal.measure.edge_tiles import edge_table
    from fieldcal.measure.mtf import measure_mtf

    status("measuring slanted edges through focus (e-SFR)", quiet=quiet)
    res = measure_mtf(stack, quiet=quiet)
    h, w = stack.shape
    table, summary = edge_table(res, fs_cyc_per_mm=fs_cyc_per_mm, q=q, pixel_pitch_um=float(stack.pixel_pitch_um),
                                z_um=stack.z_um, image_size_px=(w, h), z_ref_um=z_ref_um,
                                channels=tuple(stack.channels), geometry=geometry)
    n = {c: int((table.ok & (table.channel == c)).sum()) for c in stack.channels}
    few = {c: v for c, v in n.items() if v < MIN_TILES_PER_CHANNEL}
    if few:
        raise StackError(f"the chart is a slanted-edge chart but too few edges give a best focus at "
                         f"fs = {fs_cyc_per_mm:g} cycles/mm ({', '.join(f'{c}: {v}' for c, v in few.items())}; "
                         f"a surface needs {MIN_TILES_PER_CHANNEL} per channel; track status "
                         f"{summary['status']})", path=stack.path,
                         fix="use a chart with more slanted edges over the whole field (fieldcal chart), a z range "
                             "that passes best focus everywhere with margin, or a lower --fs")
    return table, summary


def _require_tiles(table, stack, kind) -> None:
    """Refuse a focus-measure calibration with too few textured tiles in a channel: neither measurement can
    give a surface, so say what the middle frame showed and what to change."""
    from fieldcal.fit.data import MIN_TILES_PER_CHANNEL
    from fieldcal.measure.edge_tiles import MIN_CHART_EDGES

    n = {c: int((table.ok & (table.channel == c)).sum()) for c in stack.channels}
    few = {c: v for c, v in n.items() if v < MIN_TILES_PER_CHANNEL}
    if not few:
        return
    edges = (f"{kind.edges_ok} usable slanted edges (of {kind.edges_found} found; e-SFR needs {MIN_CHART_EDGES})"
             if kind.edges_found >= 0 else "no slanted-edge check (the focus measure was requested)")
    counts = ", ".join(f"{k}: {v}" for k, v in table.counts().items())
    tiles = ("every tile was rejected" if not table.ok.any() else
             f"too few textured tiles give a best focus ({', '.join(f'{c}: {v}' for c, v in few.items())}; "
             f"a surface needs {MIN_TILES_PER_CHANNEL} per channel)")
    raise StackError(f"neither measurement works on this stack: {tiles} (tile status {counts}) and the middle "
                     f"frame shows {edges}",
                     path=stack.path, fix="calibrate on a random-texture or slanted-edge chart (fieldcal chart) "
                     "that fills the frame, exposed without clipping, over a z range that passes best focus "
                     "everywhere with margin")



def curve_skew_warning(table, measure: str) -> str | None:
    """A warning when the SML's through-focus curves are skewed the same way over the field (evidence weight
    > 0.5, shift > 0.1 step): on such a lens (spherical aberration) the SML peaks elsewhere than contrast at fs,
    which the paper's best focus is; the band-pass measure gives that point."""
    if measure != "sml":
        return None
    z = np.sort(np.asarray(table.z_um, dtype=float))
    step = float(np.median(np.diff(z))) if z.size > 1 else math.nan
    bad = [c for c, r in (getattr(table, "skew", {}) or {}).items()
           if r.get("weight", 0.0) > 0.5 and abs(r.get("shift_um", 0.0)) > 0.1 * step]
    if not bad:
        return None
    return (f"the through-focus curves of {', '.join(bad)} are skewed (sharpest position "
            + ", ".join(f"{table.skew[c]['shift_um']:+.2f} µm" for c in bad)
            + " from the centre; spherical aberration?): the SML's peak is then not where contrast at fs peaks. "
            "Calibrate with --measure bandpass (what the default, auto, uses where the pixels resolve fs) "
            "for the paper's best focus")


def stage_repeatability(stack, given: float | None) -> tuple[float, str]:
    """The stage's 1-sigma repeatability (µm) and its source: the argument, else the stage record of
    stack.json (``capture.stage.repeatability_um``, or a simulated stage's ``noise_um``), else 0."""
    if given is not None:
        if not (isinstance(given, (int, float)) and math.isfinite(given) and given >= 0):
            raise ParameterError(f"stage repeatability must be a finite value >= 0 µm, got {given}",
                                 field="stage_repeatability_um", fix="e.g. 0.5 (µm, 1 sigma)")
        return float(given), "given"
    rec = ((stack.meta.get("capture") or {}).get("stage") or {}) if isinstance(stack.meta, dict) else {}
    for key in ("repeatability_um", "noise_um"):
        v = rec.get(key) if isinstance(rec, dict) else None
        if isinstance(v, (int, float)) and math.isfinite(v) and v >= 0:
            return float(v), f"stack.json capture.stage.{key}"
    return 0.0, "none (no stage record; 0 assumed)"


def scan_end_rejections(table) -> dict:
    """Tiles rejected because their peak is at or beyond an end of the scan, per end, with a warning.

    Their part of the field is then extrapolated from the others (on the triplet at F/4 that put the centre
    1 µm low; docs/benchmarks.md), so the remedy — scanning further at that end — is worth saying.
    """
    st = np.asarray(table.status).astype(str)
    bad = np.isin(st, ("peak_at_edge", "peak_outside_range"))
    z = np.asarray(table.z_um, dtype=np.float64)
    out = {"n_tiles": int(bad.sum()), "fraction": float(bad.mean()) if st.size else 0.0,
           "n_low_end": 0, "n_high_end": 0}
    curves = (getattr(table, "curves", None) or {}).get("sml")
    if not bad.any() or z.size < 2 or curves is None or len(curves) != st.size:
        return out
    k = np.argmax(np.nan_to_num(np.asarray(curves)[bad], nan=-np.inf), axis=1)
    order = np.argsort(z)
    high = z[k] >= z[order[z.size // 2]]
    out["n_high_end"], out["n_low_end"] = int(high.sum()), int((~high).sum())
    ends = []
    if out["n_low_end"]:
        ends.append(f"below {z.min():g} µm")
    if out["n_high_end"]:
        ends.append(f"above {z.max():g} µm")
    out["warning"] = (f"{out['n_tiles']} tiles ({100 * out['fraction']:.0f} %) peak at or beyond an end of the scan "
                      f"and were rejected; their part of the field is extrapolated. Extend the scan "
                      f"{' and '.join(ends)} by a few focus tolerances")
    return out
