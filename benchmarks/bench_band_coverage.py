"""Band coverage across random lenses, with stage errors and the leave-tiles-out self-check (issue 14).

For each lens (``fieldcal.fit.synthetic.random_lens(optics=True)``: random curvature to rho^6, colour, tilt,
decentre, astigmatism, F/2-F/4, focus breathing, stage axis tilt; mono on every 4th) a chart stack is rendered
at a small size with the simulator's noise and **stage errors** (position noise 0.1-0.5 µm, backlash 0-3 µm,
axis scale error up to 2e-4; the frames are rendered where the stage really is, recorded where it was
commanded, and the stack's stage record states the repeatability). It is calibrated at each effort and
compared with the truth *in commanded stage coordinates* (backlash and scale error included: a profile is
used with the same stage, approached from the same side) on a grid over the whole field, corners included.

Per lens and effort: coverage of the 90 % band (fraction of (point, channel)) with the leave-tiles-out band
scale (``after``) and with the scale set to 1 (``before``: the band terms as estimated without the check),
surface RMS in scan steps, mean band half-width / RMS error, the profile's self-check coverage, and time.

``--optics mixed`` (default): even lenses through the geometric image-formation path, odd ones through the
wave-optics path (``simulate_stack(optics="wave")``, issue 14), every other wave lens with spherical
aberration; the truth of a wave lens is its sharpest position (``TruthProfile(optics="wave")``).

    python benchmarks/bench_band_coverage.py --lenses 20 --jsonl rows.jsonl               # chunk 1 (lenses 0-19)
    python benchmarks/bench_band_coverage.py --start 20 --lenses 20 --jsonl rows.jsonl    # chunk 2
    python benchmarks/bench_band_coverage.py --from-jsonl rows.jsonl --docs               # docs/benchmarks.md
    python benchmarks/bench_band_coverage.py --lenses 3 --efforts quick          # smoke run
    python benchmarks/bench_band_coverage.py --lenses 40 --scheduler local      # one Dask task per lens
    python benchmarks/bench_band_coverage.py --lenses 40 --only geometric --jsonl geo.jsonl   # the 20 geometric ones
    python benchmarks/bench_band_coverage.py --from-jsonl geo.jsonl --docs --section geometric_s5 --title "Band coverage: geometric lenses (s5)"
    python benchmarks/bench_band_coverage.py --lenses 12 --plans --keep KEEP --jsonl rows.jsonl   # profiles kept
    python benchmarks/bench_band_coverage.py --replan KEEP --confidences 0.9,0.99 --plan-fs-factors 1,2 \
        --plan-coverage 0 --jsonl replan.jsonl        # --confidence plans of the kept profiles vs the truth
    python benchmarks/bench_band_coverage.py --replan-table replan.jsonl

``--scheduler local|threads|tcp://HOST:PORT`` runs one task per lens on Dask (fieldcal.batch, docs/batch.md;
an existing cluster's workers need this repository on the same path and a shared temporary folder); without
it the lenses run one after the other in this process.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import inspect
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

BENCH_DIR = str(Path(__file__).resolve().parent)
sys.path.insert(0, BENCH_DIR)
from _common import md_table, write_docs_section  # noqa: E402

NAME = "band_coverage"
STATED_TOL = 0.005


LOG_F_RANGE = (math.log(1.4), math.log(8.0))
SA_WAVES = (0.25, 0.8)   # primary spherical aberration W040 of the asymmetric wave-optics lenses (waves)


def lens_plan(k: int, optics: str = "mixed") -> tuple[str, bool, int]:
    """(optics path, spherical aberration?, width factor) of lens ``k``: with ``mixed``, even lenses geometric,
    odd ones wave optics, every other wave lens with spherical aberration (asymmetric through-focus curves)."""
    path = ("geometric" if k % 2 == 0 else "wave") if optics == "mixed" else optics
    return path, path == "wave" and (k // 2) % 2 == 0, 5 if k % 4 == 3 else 4


def lens_setup(k: int, width_px: int, optics: str = "mixed", seed: int = 9100, stage_errors: bool = True,
               variety: bool = True, telecentric: bool = False) -> dict:
    """Lens ``k``'s spec, scan and stage errors, drawn as :func:`simulate_lens` renders them (not rendered).

    The lens is ``random_lens(optics=True)`` (same surfaces as before for a given k) with its F-number redrawn
    log-uniform in F/1.4-F/8 and, on the asymmetric wave-optics lenses, W040 = 0.25-0.8 waves; every 4th lens
    is rendered 1.25x wider than ``width_px`` (``variety=False``: random_lens's own F/2-F/4, all at ``width_px``).
    ``telecentric``: the exit pupil at infinity (no breathing; bench_piston's one-effect-at-a-time cases).
    """
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.simulate.aberrations import Aberrations
    from fieldcal.validation.run import chart_positions_um, default_fs

    path, spherical, wf = lens_plan(k, optics)
    rng = np.random.default_rng(seed + k)
    spec = random_lens(rng, channels=("R", "G", "B") if k % 4 else ("Y",), optics=True)
    rng2 = np.random.default_rng(seed + 7919 * (k + 1))  # drawn apart so the surfaces stay those of lens k
    f_number = float(math.exp(rng2.uniform(*LOG_F_RANGE)))
    if variety:
        spec = replace(spec, f_number=f_number)
    else:
        wf = 4
    if spherical:
        spec = replace(spec, aberrations=Aberrations(spherical=(float(rng2.uniform(*SA_WAVES)),)))
    if telecentric:
        spec = replace(spec, exit_pupil_mm=math.inf)
    w = int(round(width_px * wf / 4))
    spec = spec.with_sensor_size(w, int(round(w * 3 / 4)))
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    stage = {"stage_noise_um": float(rng.uniform(0.1, 0.5)), "stage_backlash_um": float(rng.uniform(0.0, 3.0)),
             "stage_scale_error": float(rng.uniform(-2e-4, 2e-4))}
    if not stage_errors:
        stage = {key: 0.0 for key in stage}
    return {"path": path, "spherical": spherical, "spec": spec, "fs": fs, "z": z, "stage": stage, "width_px": w}


def simulate_lens(k: int, width_px: int, workdir: Path, optics: str = "mixed", seed: int = 9100,
                  stage_errors: bool = True, variety: bool = True):
    """Render lens ``k``'s chart stack (:func:`lens_setup`) with stage errors; returns a dict describing it."""
    from fieldcal.simulate.stackgen import simulate_stack

    L = lens_setup(k, width_px, optics, seed, stage_errors, variety)
    path, spherical, spec, fs, z, stage, w = (L[key] for key in ("path", "spherical", "spec", "fs", "z", "stage",
                                                                 "width_px"))
    kw = dict(stage)
    if path != "geometric":
        if "optics" not in inspect.signature(simulate_stack).parameters:
            raise SystemExit(f"this simulator has no optics option (asked for --optics {path})")
        kw.update(optics=path, fs_cyc_per_mm=fs)
    d = workdir / f"lens{k}"
    if not (d / "stack.json").exists():  # --keep: a stack rendered by an earlier run is the same stack
        simulate_stack(spec, d, z, scene="chart", seed=k, progress=False, **kw)
    return {"spec": spec, "dir": d, "fs": fs, "step_um": float(z[1] - z[0]), "optics": path,
            "asymmetric": bool(spherical), "f_number": spec.f_number, "width_px": w, **stage}


def evaluate(prof, lens: dict, level: float = 0.9) -> dict:
    """Coverage, RMS and band half-width against the truth in commanded stage coordinates."""
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import SURFACE_GRID_PX, _grid

    w, h = prof.image_size_px
    # the wave-optics truth is the sharpest position (MTF at fs peaks), not the spec's reference surface
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um, optics=lens.get("optics", "geometric"),
                         fs_cyc_per_mm=lens["fs"])
    X, Y = _grid(w, h, SURFACE_GRID_PX)
    cov, sq, hw, ae, mean_err = [], [], [], [], []
    for c in truth.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64)
        # the scan moves up: the carriage lags by half the backlash, so the commanded position of a true z
        zt = (zt + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
        zp = np.asarray(prof.best_focus_um(X, Y, c), dtype=np.float64)
        lo, hi = (np.asarray(a, dtype=np.float64) for a in prof.best_focus_interval_um(X, Y, c, level=level))
        cov.append(float(np.mean((zt >= lo - 1e-9) & (zt <= hi + 1e-9))))
        sq.append(float(np.mean((zp - zt) ** 2)))
        mean_err.append(float(np.mean(zp - zt)))  # the channel's piston error
        hw.append(float(np.mean(0.5 * (hi - lo))))
        # error over half-width, point by point: 1 = on the band's edge; its 90th percentile is ~1 when honest
        ae.append(np.abs(zp - zt).ravel() / np.maximum(0.5 * (hi - lo).ravel(), 1e-9))
    rms = float(np.sqrt(np.mean(sq)))
    q = np.concatenate(ae)
    return {"coverage": float(np.mean(cov)), "rms_um": rms, "hw_um": float(np.mean(hw)),
            "err_hw_p90": float(np.quantile(q, 0.9)), "err_hw_median": float(np.median(q)),
            "piston_um": mean_err}


FIELD_TERMS = ("frames", "common", "breathing", "offset", "window")


def stated_field_terms_um2(prof, channel: str, xh: np.ndarray, yh: np.ndarray, x_px=None, y_px=None,
                           piston: bool = False) -> dict:
    """Per channel, the variance (µm²) the profile states for each term that is one draw for the whole field:
    the fitted stage frames (by difference with the band without them, grid mean) or the field-wide stage term,
    the common mode, the breathing systematic, the sml@fs offset and (given the points in px) the tile-window
    correction's kappa term (grid mean: one kappa for the field, times the local Laplacian).

    ``piston=True``: each term's variance of the *grid mean* instead (what it states for the error's piston):
    the fitted frames' :meth:`Discrepancy.frames_mean_var` (a frame moves only the tiles that use it, so part of
    their pointwise share changes over the field) and the window term with the grid-mean Laplacian (one kappa
    times a Laplacian that changes sign over the field); the constant terms are the same either way."""
    s = prof.surfaces
    d = s.discrepancy
    cal = prof.calibration or {}
    zs = float(s.z_scale_um)
    ci = s.channels.index(channel)
    frames = common = 0.0
    if d is not None:
        _, extra = d.predict(xh, yh, ci)
        _, bare = d.without_nuisances().predict(xh, yh, ci)
        frames = float(np.mean(np.clip(extra - bare, 0.0, None))) * zs * zs
        if piston and d.has_stage:
            frames = float(d.frames_mean_var(xh, yh, ci)) * zs * zs
        common = (float(d.common_sd[ci]) * zs) ** 2 if d.common_sd is not None and ci < d.common_sd.size else 0.0
    if d is None or not d.has_stage:
        frames += float(s.stage_sd_um.get(channel, 0.0)) ** 2
    window = 0.0
    if x_px is not None:
        window = float(np.mean(s._window_var(np.asarray(x_px, float), np.asarray(y_px, float), channel))) * zs * zs
        if piston and s.tile_px and s.tile_correction_sd > 0:
            h = 0.5 * s.tile_px
            xp, yp = np.asarray(x_px, float), np.asarray(y_px, float)
            f = lambda dx, dy: s._eval(s.theta_map, xp + dx, yp + dy, channel)[0]
            lap = float(np.mean(f(h, 0) + f(-h, 0) + f(0, h) + f(0, -h) - 4.0 * f(0, 0))) / (h * h)
            window = (s.tile_correction_sd * lap * s.tile_px ** 2 / 24.0 * zs) ** 2
    return {"frames": frames, "common": common,
            "breathing": float((cal.get("breathing_systematic_sd_um") or {}).get(channel) or 0.0) ** 2,
            "offset": float((cal.get("measure_offset_sd_um") or {}).get(channel) or 0.0) ** 2, "window": window}


def decompose(prof, lens: dict, step_px: int = 16, level: float = 0.9) -> dict:
    """The true error on a grid, per channel, split into piston (grid mean), tilt (x and y slopes per unit of
    normalised image height) and the rest, each against the sd the profile states for it: the piston against the
    field-wide terms' variance of the grid mean (:func:`stated_field_terms_um2` with ``piston=True``) plus the posterior samples' own grid-mean spread (scaled by
    the band scale), the tilt against the samples' slope spread, the rest (piston and tilt taken out) against the
    band's remaining variance at the points (less the field-wide terms and the samples' own piston-and-tilt plane).
    Per channel lists, in µm (variances in µm²)."""
    from scipy.special import ndtri
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import _grid

    w, h = prof.image_size_px
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um, optics=lens.get("optics", "geometric"),
                         fs_cyc_per_mm=lens["fs"])
    X, Y = _grid(w, h, step_px)
    s = prof.surfaces
    xh, yh = s.geometry.normalise(X.ravel(), Y.ravel())
    A = np.column_stack([np.ones(xh.size), xh, yh])
    zq = float(ndtri(0.5 + 0.5 * level))
    out = {k: [] for k in ("dec_piston_um", "dec_tilt_um", "dec_rest_um", "dec_coef_piston_var", "dec_coef_tilt_var",
                           "dec_local_var", *(f"dec_{t}_var" for t in FIELD_TERMS))}
    for c in s.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64).ravel()
        zt = (zt + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
        zp = np.asarray(prof.best_focus_um(X, Y, c), dtype=np.float64).ravel()
        lo, hi = (np.asarray(a, dtype=np.float64).ravel() for a in prof.best_focus_interval_um(X, Y, c, level=level))
        coef, *_ = np.linalg.lstsq(A, zp - zt, rcond=None)
        rest = zp - zt - A @ coef
        terms = stated_field_terms_um2(prof, c, xh, yh, X.ravel(), Y.ravel())
        # what each term states for the piston (the grid mean): the ML multipliers compare the pistons with it
        terms_p = stated_field_terms_um2(prof, c, xh, yh, X.ravel(), Y.ravel(), piston=True)
        # the posterior samples about the MAP (coefficients, centre, model average), as the band scales them
        zsmp, _ = s._eval(s.samples, X.ravel(), Y.ravel(), c, model=s.sample_model)
        z0, _ = s._eval(s.theta_map, X.ravel(), Y.ravel(), c)
        dz = (zsmp - z0) * float(s.band_scale) * float(s.z_scale_um)
        slopes = np.linalg.lstsq(A, dz.T, rcond=None)[0]
        coef_p = float(np.var(dz.mean(axis=1)))
        # the rest has the error's plane (piston and tilt) taken out, so its stated sd leaves out the samples'
        # plane too (per point: the variance of each sample's fitted plane); the piston alone left the tilt's
        # variance in the stated local sd, 3-7 % of it, and more where the tilt is poorly fixed
        plane_var = np.var(A @ slopes, axis=1)
        band_var = ((hi - lo) / (2.0 * zq)) ** 2
        out["dec_piston_um"].append(float(coef[0]))
        out["dec_tilt_um"].append([float(coef[1]), float(coef[2])])
        out["dec_rest_um"].append(float(np.sqrt(np.mean(rest ** 2))))
        out["dec_coef_piston_var"].append(coef_p)
        out["dec_coef_tilt_var"].append(float(np.mean(np.var(slopes[1:], axis=1))))
        out["dec_local_var"].append(float(np.mean(np.clip(band_var - sum(terms.values()) - plane_var, 0.0, None))))
        for t in FIELD_TERMS:
            out[f"dec_{t}_var"].append(terms_p[t])
    return out


def decomposition_summary(rows: list[dict]) -> dict:
    """Over (lens, channel) of rows with a decomposition: RMS of piston error / stated piston sd, the median of
    |tilt error| / stated tilt sd and of rest RMS / stated local sd (0.67, 0.67 and ~1 when honest), and per
    field-wide term the maximum-likelihood multiplier of its variance (1 = honest, < 1 overstated, > 1
    understated; the piston errors modelled as N(0, sum_t a_t v_t + coefficient variance))."""
    from scipy.optimize import minimize

    P, V, C, T, TV, R, L = [], [], [], [], [], [], []
    for r in rows:
        if "dec_piston_um" not in r:
            continue
        for i in range(len(r["dec_piston_um"])):
            P.append(r["dec_piston_um"][i])
            V.append([r.get(f"dec_{t}_var", [0.0] * (i + 1))[i] for t in FIELD_TERMS])  # rows before a term: 0
            C.append(r["dec_coef_piston_var"][i])
            T.extend(r["dec_tilt_um"][i])
            TV.extend([r["dec_coef_tilt_var"][i]] * 2)
            R.append(r["dec_rest_um"][i])
            L.append(r["dec_local_var"][i])
    if not P:
        return {}
    P, V, C = np.array(P), np.array(V), np.array(C)
    tot = V.sum(axis=1) + C
    z = P / np.sqrt(np.maximum(tot, 1e-12))

    def nll(la):
        v = V @ np.exp(la) + C + 1e-6
        return 0.5 * float(np.sum(np.log(v) + P * P / v))

    res = minimize(nll, np.zeros(len(FIELD_TERMS)), method="L-BFGS-B", bounds=[(-6.0, 4.0)] * len(FIELD_TERMS))
    out = {"n": int(P.size), "piston_z_rms": float(np.sqrt(np.mean(z * z))), "piston_z_med": float(np.median(abs(z))),
           "tilt_z_med": float(np.median(np.abs(np.array(T)) / np.sqrt(np.maximum(TV, 1e-12)))),
           "rest_local_med": float(np.median(np.array(R) / np.sqrt(np.maximum(L, 1e-12)))),
           "field_share_piston": float(np.mean(V.sum(axis=1) / tot))}
    for t, a in zip(FIELD_TERMS, np.exp(res.x)):
        # a term the profiles never state has no multiplier to speak of
        out[f"ml_{t}"] = float(a) if np.any(V[:, FIELD_TERMS.index(t)] > 0) else float("nan")
        out[f"share_{t}"] = float(np.mean(V[:, FIELD_TERMS.index(t)] / tot))
    return out


def field_wide_share(prof, hw_um: float, level: float = 0.9) -> float:
    """Share of the band's variance that is common to the whole field (stage repeatability, common mode, the
    breathing and fixed systematics), per channel averaged: the part of the error one lens draws only once."""
    from scipy.special import ndtri

    zq = float(ndtri(0.5 + 0.5 * level))
    s = prof.surfaces
    d = s.discrepancy
    cal = prof.calibration or {}
    out = []
    for i, c in enumerate(s.model.channels):
        v = float(s.stage_sd_um.get(c, 0.0)) ** 2 + float(cal.get("systematic_sd_um") or 0.0) ** 2
        v += float((cal.get("breathing_systematic_sd_um") or {}).get(c) or 0.0) ** 2
        v += float((cal.get("measure_offset_sd_um") or {}).get(c) or 0.0) ** 2
        if d is not None and d.common_sd is not None and i < d.common_sd.size:
            v += (float(d.common_sd[i]) * s.z_scale_um) ** 2
        out.append(v)
    return float(min(np.mean(out) / max((hw_um / zq) ** 2, 1e-18), 1.0))


def p_coverage_in_range(share: float, lo: float = 0.75, hi: float = 0.99, level: float = 0.9) -> float:
    """Probability that a perfectly honest Gaussian band gives a lens a field coverage in [lo, hi] when a
    ``share`` of its variance is one field-wide draw c and the rest varies over the field (independent points):
    coverage(c) = P(|c + e| <= z) over e ~ N(0, 1 - share), c ~ N(0, share). A band dominated by field-wide
    terms covers all or nothing, however honest it is."""
    from scipy.special import ndtri
    from scipy.stats import norm

    zq = float(ndtri(0.5 + 0.5 * level))
    x, w = np.polynomial.hermite_e.hermegauss(80)
    c = math.sqrt(max(share, 0.0)) * x
    se = math.sqrt(max(1.0 - share, 1e-12))
    cov = norm.cdf((zq - c) / se) - norm.cdf((-zq - c) / se)
    return float(np.sum(w * ((cov >= lo) & (cov <= hi))) / np.sum(w))


def plan_check(prof, lens: dict, confidence: float = 0.9, q: float = 0.05, step_px: int = 4,
               fs_factor: float = 1.0, coverage: float | None = 0.99) -> dict:
    """A ``--confidence`` stack plan from the profile against the truth: its stated expected fraction of pixels
    in tolerance (and worst-pixel probability) vs the measured fraction of pixels whose assigned frame (nearest
    the profile's best focus) is within the lens's true tolerance of the true best focus (commanded stage
    coordinates). Wave optics: the truth's sharpest position and the pupil's own tolerance (on axis). The plan
    is drawn at ``fs_factor`` times the calibration's fs (> 1: a denser plan, a harder test), with the CLI's
    default coverage target (``coverage=None``: the confidence alone)."""
    from fieldcal.plan import StackRequest, plan_stack
    from fieldcal.plan.cover import nearest_index
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import _grid

    fs = lens["fs"] * fs_factor
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=fs, q=q, confidence=confidence, coverage=coverage))
    w, h = prof.image_size_px
    # the wave truth's sharpest position is where MTF at the calibration's fs peaks (what the profile measured)
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um, optics=lens.get("optics", "geometric"),
                         fs_cyc_per_mm=lens["fs"])
    frames = np.sort(np.asarray(plan.frames_um, dtype=np.float64))
    X, Y = _grid(w, h, step_px)
    inside = []
    for c in truth.channels:
        tol = truth.focus_tolerance_um(X, Y, c, fs, q)
        zt = (np.asarray(truth.best_focus_um(X, Y, c)) + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
        zt = zt + plan.field.refocus_um
        # the frame the plan assigns the pixel (nearest the profile's best focus), as the stated probability has it
        zp = np.asarray(prof.best_focus_um(X, Y, c)) + plan.field.refocus_um
        inside.append(np.abs(frames[nearest_index(frames, zp)] - zt) <= tol + 1e-9)
    return {"plan_stated": float(plan.stats["expected_fraction"]), "plan_worst": float(plan.stats["probability"]),
            "plan_measured": float(np.mean(np.concatenate([a.ravel() for a in inside]))),
            "plan_frames": int(frames.size), "plan_fs_factor": float(fs_factor),
            "plan_tol_source": next(iter(plan.tolerance.values()))["source"] if plan.tolerance else ""}


LENS_KEYS = ("fs", "step_um", "optics", "asymmetric", "f_number", "width_px", "stage_noise_um", "stage_backlash_um",
             "stage_scale_error")


def keep_profile(keep: Path, k: int, effort: str, lens: dict, prof) -> None:
    """Store lens ``k``'s profile at ``effort`` with its spec and stage record (``--keep``), so ``--replan`` can
    re-check plans against the truth without rendering or calibrating again."""
    keep.mkdir(parents=True, exist_ok=True)
    lens["spec"].save(keep / f"lens{k:02d}.spec.json")
    (keep / f"lens{k:02d}.meta.json").write_text(json.dumps({key: lens[key] for key in LENS_KEYS}))
    prof.save(keep / f"lens{k:02d}-{effort}.json")


def replan(keep: Path, confidences, efforts, fs_factors=(1.0,), coverage: float | None = 0.99) -> list[dict]:
    """Plan rows (``plan_check``) of every profile stored with ``--keep``, at each ``--confidence`` level."""
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.lens import LensSpec

    rows = []
    for meta_path in sorted(keep.glob("lens*.meta.json")):
        k = int(meta_path.name[4:6])
        lens = {**json.loads(meta_path.read_text()), "spec": LensSpec.load(keep / f"lens{k:02d}.spec.json")}
        for eff in efforts:
            pp = keep / f"lens{k:02d}-{eff}.json"
            if not pp.exists():
                continue
            prof = LensProfile.load(pp)
            for conf in confidences:
                for fsf in fs_factors:
                    try:
                        pc = plan_check(prof, lens, conf, fs_factor=fsf, coverage=coverage)
                    except Exception as e:  # noqa: BLE001 - a benchmark records the refusal and goes on
                        print(f"lens {k} {eff} confidence {conf} fs x{fsf}: {e}", flush=True)
                        continue
                    r = {"lens": k, "effort": eff, "confidence": conf, "coverage": coverage, "optics": lens["optics"],
                         "asymmetric": lens["asymmetric"], "f_number": lens["f_number"], **pc}
                    rows.append(r)
                    print(json.dumps(r), flush=True)
    return rows


def replan_table(rows: list[dict]) -> str:
    """One row per (effort, optics, --confidence, fs factor) of ``--replan`` rows: stated expected fraction vs
    measured fraction of pixels within the true δ, and the smallest per-pixel probability."""
    out = []
    keys = sorted({(r["effort"], r["optics"] + (" + SA" if r["asymmetric"] else ""), r["confidence"],
                    r.get("plan_fs_factor", 1.0)) for r in rows})
    for eff, opt, conf, fsf in keys:
        g = [r for r in rows if (r["effort"], r["optics"] + (" + SA" if r["asymmetric"] else ""), r["confidence"],
                                 r.get("plan_fs_factor", 1.0)) == (eff, opt, conf, fsf)]
        st = np.array([r["plan_stated"] for r in g])
        me = np.array([r["plan_measured"] for r in g])
        n = np.array([r["plan_frames"] for r in g])
        out.append({"effort": eff, "optics": opt, "confidence": conf, "fs": f"{fsf:g}x", "lenses": len(g),
                    "frames": f"{n.min()}-{n.max()}", "stated": float(st.mean()), "measured": float(me.mean()),
                    "min_measured": float(me.min()), "max_diff": float(np.max(np.abs(st - me))),
                    "within": f"{int(np.sum(np.abs(st - me) <= 0.02))}/{len(g)}",
                    "worst_p": float(min(r["plan_worst"] for r in g))})
    cols = [("effort", "effort", ""), ("optics", "optics", ""), ("--confidence", "confidence", "g"),
            ("plan fs", "fs", ""), ("lenses", "lenses", ""), ("frames", "frames", ""),
            ("mean stated (expected fraction)", "stated", ".4f"), ("mean measured", "measured", ".4f"),
            ("lowest measured", "min_measured", ".4f"), ("max abs(stated − measured)", "max_diff", ".4f"),
            ("within 2 points", "within", ""), ("smallest per-pixel probability", "worst_p", ".4f")]
    return "\n".join(md_table(out, cols))


def run_one(lens: dict, effort: str, seed: int = 0, plans: bool = False, keep: Path | None = None,
            k: int = 0) -> dict:
    import fieldcal

    t0 = time.perf_counter()
    prof = fieldcal.calibrate(lens["dir"], fs_cyc_per_mm=lens["fs"], effort=effort, z_ref_um=0.0, seed=seed,
                              quiet=True)
    dt = time.perf_counter() - t0
    if keep is not None:
        keep_profile(keep, k, effort, lens, prof)
    after = evaluate(prof, lens)
    sc = prof.diagnostics["surface"].get("self_check", {})
    scale = prof.surfaces.band_scale
    prof.surfaces.band_scale = 1.0
    before = evaluate(prof, lens)
    prof.surfaces.band_scale = scale
    # the profile's own split (fit/selfcheck.py: fitted stage frames and window exponent included) when it has one
    share = sc.get("field_wide_share", field_wide_share(prof, after["hw_um"]))
    plan = plan_check(prof, lens) if plans else {}
    dec = decompose(prof, lens)
    # how often an exactly honest band puts this lens in the window, under the profile's own joint error model
    # (the self-check's bootstrap at kappa = 1: field-wide terms, correlated coefficients; bench_band_local.py)
    from fieldcal.fit.selfcheck import coverage_draws
    pooled, _, _ = coverage_draws(prof, 1.0)
    return {**plan, **dec, "field_share": share, "p_in_range": p_coverage_in_range(share),
            "p_in_model": float(np.mean((pooled >= 0.75) & (pooled <= 0.99))),
            "cov_after": after["coverage"], "cov_before": before["coverage"], "rms_um": after["rms_um"],
            "err_hw_p90": after["err_hw_p90"], "err_hw_median": after["err_hw_median"],
            "hw_um": after["hw_um"], "hw_before_um": before["hw_um"], "band_scale": scale,
            "self_check": sc.get("coverage", float("nan")), "check_s": sc.get("time_s", float("nan")),
            # the held-out tiles' own coverage (the self-check's headline before session 11) and kappa
            "tile_check": sc.get("tile_coverage", sc.get("coverage", float("nan"))),
            "kappa": sc.get("kappa", float("nan")), "log_kappa_sd": sc.get("log_kappa_sd", float("nan")),
            # the range the profile states for its truth coverage, given its field-wide share (fit/selfcheck.py)
            "sc_expected": sc.get("coverage_expected", float("nan")),
            "sc_lo": (sc.get("coverage_range") or [float("nan")] * 2)[0],
            "sc_hi": (sc.get("coverage_range") or [float("nan")] * 2)[1],
            "sc_share": sc.get("field_wide_share", float("nan")),
            "sc_median": sc.get("coverage_median", float("nan")),
            "time_s": dt, "fit_s": prof.diagnostics["timing_s"]["fit"], "model": prof.surfaces.model.name,
            # per channel: the signed mean error and the breathing systematic's sd (focus breathing diagnosis)
            "piston_um": after["piston_um"], "exit_pupil_mm": float(lens["spec"].exit_pupil_mm),
            "breathing_sd_um": [float((prof.calibration.get("breathing_systematic_sd_um") or {}).get(c, 0.0))
                                for c in prof.channels]}


def summarise(rows, efforts):
    """One row per (effort, optics path), then per effort over all lenses."""
    out = []
    for eff in efforts:
        kind = lambda x: x["optics"] + (" + SA" if x.get("asymmetric") else "")  # noqa: E731
        groups = sorted({kind(x) for x in rows if x["effort"] == eff})
        groups += (["wave (all)"] if sum(g.startswith("wave") for g in groups) > 1 else []) + ["all"]
        for opt in groups:
            r = [x for x in rows if x["effort"] == eff
                 and (opt == "all" or opt == kind(x) or (opt == "wave (all)" and x["optics"] == "wave"))]
            if not r or (opt == "all" and len(groups) == 2):
                continue
            a = lambda k: np.array([x.get(k, np.nan) for x in r], dtype=float)  # older rows lack new keys
            ca, cb = a("cov_after"), a("cov_before")
            ratio = a("hw_um") / np.maximum(a("rms_um"), 1e-9)
            asym = [x for x in r if x.get("asymmetric")]
            out.append({"effort": eff, "optics": opt, "lenses": len(r), "cov_before": cb.mean(), "cov_after": ca.mean(),
                        "cov_min": ca.min(), "cov_max": ca.max(),
                        "in_075_099": f"{int(np.sum((ca >= 0.75) & (ca <= 0.99)))}/{len(r)}",
                        "rms_step": float(np.mean(a("rms_um") / a("step_um"))),
                        "rms_step_max": float(np.max(a("rms_um") / a("step_um"))),
                        "asym_rms_step_max": (f"{max(x['rms_um'] / x['step_um'] for x in asym):.3f} ({len(asym)})"
                                              if asym else "—"),
                        "expected_in": f"{np.nansum(a('p_in_range')):.1f}",
                        "expected_in_model": (f"{np.nansum(a('p_in_model')):.1f}" if np.isfinite(a('p_in_model')).any()
                                              else "—"), "share": float(np.nanmedian(a("field_share"))),
                        "plan": (f"{np.nanmean(a('plan_stated')):.3f} / {np.nanmean(a('plan_measured')):.3f} "
                                 f"(max diff {np.nanmax(np.abs(a('plan_stated') - a('plan_measured'))):.3f})"
                                 if np.isfinite(a("plan_stated")).any() else "—"),
                        "hw_rms": float(np.mean(ratio)), "err_hw_p90": float(np.median(a("err_hw_p90"))),
                        "scale": float(np.median(a("band_scale"))),
                        "self_check": float(np.nanmean(a("self_check"))),
                        "sc_diff": float(np.nanmean(np.abs(a("self_check") - ca))),
                        "sc_median_diff": float(np.nanmean(np.abs(a("sc_median") - ca))),
                        # the grid's coverage is a fraction of ~1300 points per channel: 1.00 on the grid is
                        # within 0.005 of a continuous 0.9995
                        "in_stated": (f"{int(np.sum((ca >= a('sc_lo') - STATED_TOL) & (ca <= a('sc_hi') + STATED_TOL)))}/{len(r)}"
                                      if np.isfinite(a("sc_lo")).any() else "—"),
                        "check_s": float(np.nanmedian(a("check_s"))), "time_s": float(np.median(a("time_s")))})
    return out


TITLE = "Band coverage with stage errors and the leave-tiles-out self-check (issue 14)"


def render_table(rows, efforts, argv_text: str, note: str = "", title: str = TITLE) -> str:
    summ = summarise(rows, efforts)
    cols = [("effort", "effort", ""), ("optics", "optics", ""), ("lenses", "lenses", ""),
            ("mean coverage before", "cov_before", ".3f"), ("mean coverage after", "cov_after", ".3f"),
            ("min", "cov_min", ".2f"), ("max", "cov_max", ".2f"), ("lenses in 0.75-0.99", "in_075_099", ""),
            ("expected if honest", "expected_in", ""),
            ("expected if honest, own error model", "expected_in_model", ""),
            ("median field-wide share", "share", ".2f"),
            ("mean RMS / step", "rms_step", ".4f"), ("max RMS / step", "rms_step_max", ".3f"),
            ("max RMS / step, asymmetric (n)", "asym_rms_step_max", ""),
            ("mean half-width / RMS", "hw_rms", ".2f"), ("median p90 of error / half-width", "err_hw_p90", ".2f"),
            ("median band scale", "scale", ".2f"),
            ("--confidence 0.9 plan: stated / measured fraction in tolerance", "plan", ""), ("mean self-check", "self_check", ".3f"),
            ("mean abs(self-check − measured)", "sc_diff", ".3f"),
            ("mean abs(stated median − measured)", "sc_median_diff", ".3f"),
            ("measured inside the profile's stated 5-95 % coverage range", "in_stated", ""),
            ("median check (s)", "check_s", ".3f"),
            ("median calibrate (s)", "time_s", ".1f")]
    per_lens = [("lens", "lens", ""), ("effort", "effort", ""), ("optics", "optics", ""), ("SA", "asym", ""),
                ("F/#", "f_number", ".1f"), ("px", "width_px", ""), ("coverage before", "cov_before", ".2f"),
                ("coverage after", "cov_after", ".2f"), ("self-check", "self_check", ".2f"),
                ("stated range", "sc_range", ""),
                ("band scale", "band_scale", ".2f"), ("RMS (µm)", "rms_um", ".3f"), ("RMS / step", "rms_step", ".3f"),
                ("half-width (µm)", "hw_um", ".3f"), ("p90 error / half-width", "err_hw_p90", ".2f"),
                ("field-wide share", "field_share", ".2f"), ("model", "model", "")]
    for x in rows:
        x["asym"] = "yes" if x.get("asymmetric") else ""
        x["rms_step"] = x["rms_um"] / x["step_um"]
        x["sc_range"] = (f"{x['sc_lo']:.2f}-{x['sc_hi']:.2f}" if math.isfinite(x.get("sc_lo", float("nan")))
                         else "—")
    lenses = len({x["lens"] for x in rows})
    dec_cols = [("effort", "effort", ""), ("optics", "optics", ""), ("lens × channel", "n", ""),
                ("RMS piston / stated piston sd", "piston_z_rms", ".2f"),
                ("median abs(piston) / sd (0.67 honest)", "piston_z_med", ".2f"),
                ("median abs(tilt) / stated tilt sd (0.67)", "tilt_z_med", ".2f"),
                ("median rest RMS / stated local sd (~1)", "rest_local_med", ".2f"),
                ("field-wide share of piston variance", "field_share_piston", ".2f"),
                *((f"ML multiplier: {t} (share)", f"ml_{t}_txt", "") for t in FIELD_TERMS)]
    dec_rows = []
    for eff in efforts:
        for opt in ("geometric", "wave", "wave + SA"):
            g = [x for x in rows if x["effort"] == eff and x["optics"] + (" + SA" if x.get("asymmetric") else "") == opt]
            d = decomposition_summary(g)
            if d:
                d.update(effort=eff, optics=opt,
                         **{f"ml_{t}_txt": (f"{d[f'ml_{t}']:.2f} ({d[f'share_{t}']:.2f})"
                                            if math.isfinite(d[f"ml_{t}"]) else "— (0)") for t in FIELD_TERMS})
                dec_rows.append(d)
    dec_text = ["", "Error decomposition (`decompose`: the true error on a 16 px grid per lens × channel split into "
                "piston, tilt and rest, each against the sd the profile states for it; ML multiplier = the factor "
                "on a field-wide term's variance that best explains the piston errors, 1 = honest, < 1 overstated):",
                "", *md_table(dec_rows, dec_cols)] if dec_rows else []
    return "\n".join([
        f"## {title}",
        "",
        f"`python benchmarks/bench_band_coverage.py {argv_text}` — {lenses} random lenses (`random_lens(optics=True)`, "
        "F-number redrawn log-uniform F/1.4-F/8; even lenses geometric optics, odd ones wave optics, every other "
        "wave lens with spherical aberration W040 0.25-0.8 waves = asymmetric through-focus curves, *SA*), "
        "every 4th lens 1.25x wider, simulator noise, stage position noise 0.1-0.5 µm, backlash 0-3 µm, axis "
        "scale error ≤ 2e-4; truth in commanded stage coordinates, and for wave optics the sharpest position "
        "(MTF at fs peaks). *before* = band terms as estimated (band scale 1), *after* = with the leave-tiles-out "
        "band scale; self-check = the profile's own cross-validated coverage; *p90 of error / half-width* ≈ 1 "
        "for an honest band (> 1 too narrow, < 1 too wide); *field-wide share* = the part of the band's variance "
        "that is one draw per lens (stage repeatability, common mode, systematics); *expected if honest* = the "
        "number of lenses a perfectly honest band with those shares would put in 0.75-0.99 "
        "(`p_coverage_in_range`); *own error model* = the same from the self-check's bootstrap of each profile "
        "(`selfcheck.coverage_draws` at kappa 1: correlated coefficient errors too, not the share alone). "
        "Machine shared (2 cores)." + (" " + note if note else ""),
        "", *md_table(summ, cols), *dec_text, "", "Per lens:", "", *md_table(rows, per_lens)])


def lens_rows(job) -> list[dict]:
    """Lens ``k``: render its stack and calibrate it at each effort (one task of a --scheduler run)."""
    k, width, optics, stage_errors, efforts, workdir, plans, keep = job
    if BENCH_DIR not in sys.path:  # on a Dask worker: this folder's modules (_common)
        sys.path.insert(0, BENCH_DIR)
    lens = simulate_lens(k, width, Path(workdir), optics, stage_errors=stage_errors)
    rows = []
    for eff in efforts:
        r = run_one(lens, eff, plans=plans, keep=keep, k=k)
        r.update(lens=k, effort=eff, step_um=lens["step_um"], optics=lens["optics"],
                 asymmetric=lens["asymmetric"], f_number=lens["f_number"], width_px=lens["width_px"])
        rows.append(r)
    return rows


def _record(rows: list[dict], jsonl: Path | None) -> None:
    """Print one lens's rows and append them to the chunk file."""
    for r in rows:
        if jsonl:
            with open(jsonl, "a") as fh:
                fh.write(json.dumps(r) + "\n")
        print(f"lens {r['lens']:2d} {r['optics'][:4]}{'+SA' if r['asymmetric'] else '   '} "
              f"F/{r['f_number']:.1f} {r['effort']:8s} cov {r['cov_before']:.2f} -> {r['cov_after']:.2f} "
              f"(self-check {r['self_check']:.2f}, scale {r['band_scale']:.2f}) rms {r['rms_um']:.3f} µm "
              f"({r['rms_um'] / r['step_um']:.3f} step) hw/rms {r['hw_um'] / max(r['rms_um'], 1e-9):.2f} "
              f"p90 err/hw {r['err_hw_p90']:.2f} calibrate {r['time_s']:.1f} s  {r['model']}", flush=True)


@contextlib.contextmanager
def _kept(folder: Path):
    """The --keep folder as the run's working folder (created, never removed)."""
    folder.mkdir(parents=True, exist_ok=True)
    yield str(folder)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lenses", type=int, default=40, help="number of random lenses (default 40)")
    ap.add_argument("--start", type=int, default=0, help="first lens index (run in chunks with --jsonl)")
    ap.add_argument("--width", type=int, default=320, help="render width in px (height = 3/4)")
    ap.add_argument("--efforts", default="quick,standard", help="comma list (default quick,standard)")
    ap.add_argument("--optics", default="mixed",
                    help="simulator image-formation path: geometric, wave or mixed (default: even lenses geometric, "
                         "odd wave)")
    ap.add_argument("--only", choices=("geometric", "wave"), default=None,
                    help="run only the lenses of this image-formation path (the same lenses as in a full run)")
    ap.add_argument("--sa", choices=("only", "without"), default=None,
                    help="run only the lenses with spherical aberration (asymmetric curves; with --only wave) or only "
                         "those without")
    ap.add_argument("--no-stage-errors", action="store_true", help="a perfect stage")
    ap.add_argument("--plans", action="store_true",
                    help="also check a --confidence 0.9 stack plan from each profile against the truth")
    ap.add_argument("--keep", type=Path, default=None,
                    help="render the stacks into this folder and reuse those already there (re-runs of the same "
                         "lenses skip the slow wave-optics rendering); store each profile, lens spec and stage "
                         "record there too (for --replan)")
    ap.add_argument("--replan", type=Path, default=None,
                    help="re-check --confidence plans of the profiles stored with --keep in this folder; no "
                         "rendering or calibration")
    ap.add_argument("--replan-table", type=Path, default=None, help="print the table of a --replan --jsonl file")
    ap.add_argument("--confidences", default="0.9", help="--replan: comma list of --confidence levels")
    ap.add_argument("--plan-fs-factors", default="1", help="--replan: plans at these multiples of the calibration's fs")
    ap.add_argument("--plan-coverage", type=float, default=0.99,
                    help="--replan: the plans' coverage target on top of --confidence (0: none, the confidence alone)")
    ap.add_argument("--jsonl", type=Path, help="append each lens's rows to this file (chunked runs)")
    ap.add_argument("--from-jsonl", type=Path, help="make the table from the rows of a --jsonl file, run nothing")
    ap.add_argument("--note", default="", help="a sentence appended to the table's caption")
    ap.add_argument("--docs", action="store_true", help="write the table into docs/benchmarks.md")
    ap.add_argument("--section", default=None,
                    help="with --docs: write to this section of docs/benchmarks.md (its key) instead of the "
                         "benchmark's own, e.g. a run restricted with --optics")
    ap.add_argument("--title", default=TITLE, help="the section's heading")
    ap.add_argument("--scheduler", default=None,
                    help="run one Dask task per lens: local, threads or tcp://HOST:PORT (default: in this process)")
    ap.add_argument("--workers", type=int, default=None, help="workers of a local cluster (default: one per CPU)")
    args = ap.parse_args(argv)
    efforts = args.efforts.split(",")
    raw = list(argv if argv is not None else sys.argv[1:])
    # the command as run, without the caption's own options (--note/--title/--section and their values)
    skip = {"--note", "--title", "--section"}
    argv_text = " ".join(a for i, a in enumerate(raw) if a not in skip and (i == 0 or raw[i - 1] not in skip))
    rows = []
    if args.replan:
        rows = replan(args.replan, [float(v) for v in args.confidences.split(",")], efforts,
                      [float(v) for v in args.plan_fs_factors.split(",")],
                      args.plan_coverage if args.plan_coverage > 0 else None)
        if args.jsonl:
            args.jsonl.write_text("".join(json.dumps(r) + "\n" for r in rows))
        print(replan_table(rows))
        return 0
    if args.replan_table:
        print(replan_table([json.loads(line) for line in args.replan_table.read_text().splitlines() if line.strip()]))
        return 0
    if args.from_jsonl:
        rows = [json.loads(line) for line in args.from_jsonl.read_text().splitlines() if line.strip()]
        rows = [r for r in rows if r["effort"] in efforts]
    else:
        from fieldcal.batch.engine import check_scheduler, run_units

        scheduler = check_scheduler(args.scheduler, args.workers) if args.scheduler else None
        with (tempfile.TemporaryDirectory(prefix="bench-bands-") if args.keep is None
              else _kept(args.keep)) as tmp:
            jobs = [(f"lens{k:02d}", (k, args.width, args.optics, not args.no_stage_errors, efforts, tmp, args.plans,
                                   args.keep))
                    for k in range(args.start, args.start + args.lenses)
                    if (args.only is None or lens_plan(k, args.optics)[0] == args.only)
                    and (args.sa is None or lens_plan(k, args.optics)[1] == (args.sa == "only"))]
            if scheduler is None:
                results = []
                for _, job in jobs:  # each lens recorded as it finishes (a long run can be cut short)
                    results.append(lens_rows(job))
                    _record(results[-1], args.jsonl)
            else:
                res = run_units(lens_rows, jobs, scheduler=scheduler, workers=args.workers, desc="lenses",
                                unit="lens", quiet=False,
                                on_result=lambda r: _record(r.value, args.jsonl) if r.ok else
                                print(f"{r.name}: FAILED: {r.error}", flush=True))
                results = [r.value for r in res if r.ok]
            rows = [r for rs in results for r in rs]
    text = render_table(rows, efforts, argv_text, args.note, args.title)
    print(text)
    if args.docs:
        write_docs_section(f"{NAME}_{args.section}" if args.section else NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
