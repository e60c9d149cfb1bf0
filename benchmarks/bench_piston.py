"""Where the field-wide positive piston comes from (issues 13/14): one effect at a time.

The band benchmark (``bench_band_coverage.py``) found the fitted-minus-true piston positive on 76-81 % of
lens x channels. This benchmark separates its causes with controlled stacks:

* **closed form** (``--closed-form``): a flat field (every tile in focus at z = 0) of exact sinusoids
  (:mod:`fieldcal.measure.texture_synth`: uniform defocus disc of diameter ``|z| / N`` at the sensor, no
  resampling), frames at equal steps; then one effect at a time: the scan's sampling phase and its offset from
  the peak, sensor noise, focus breathing (scene frequency u at sensor frequency u / m, m = exp(b z)), a
  sensor-fixed MTF (100 % pixel aperture), with and without breathing, declared or not. The tiles'
  mean best focus (``measure_stack``, each measure) is the estimator's piston: any non-zero value is the
  estimator's, since the truth is exactly 0 everywhere. ``--calibrate`` also runs ``fieldcal.calibrate`` on the
  base stack (the whole pipeline's piston).
* **our simulator** (``--lenses``): lens k of the band benchmark (``bench_band_coverage.simulate_lens``'s spec)
  rendered with ``fieldcal.simulate`` with effects switched: ``none`` (no noise, perfect stage), ``noise``,
  ``stage`` (position noise, backlash, scale error as in the band benchmark), ``noise+stage`` (the band
  benchmark's own), ``noise+telecentric`` (exit pupil at infinity: no breathing). Each is calibrated (standard)
  and compared with the truth in commanded stage coordinates (``bench_band_coverage.evaluate``).

    python benchmarks/bench_piston.py --closed-form --calibrate --jsonl cf.jsonl     # ~2 min
    python benchmarks/bench_piston.py --lenses 0,2,4 --jsonl sim.jsonl               # geometric lenses render fast
    python benchmarks/bench_piston.py --curvature 6:0,6:1,6:2,6:-1,2:1,2:2 --jsonl curv.jsonl
    python benchmarks/bench_piston.py --stage-seeds 8:0.4:1,8:0.4:2,8:0.4:3 --jsonl seeds.jsonl
    python benchmarks/bench_piston.py --from-jsonl cf.jsonl,sim.jsonl,curv.jsonl,seeds.jsonl --docs --notes notes.md
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

BENCH_DIR = str(Path(__file__).resolve().parent)
sys.path.insert(0, BENCH_DIR)
from _common import md_table, write_docs_section  # noqa: E402

NAME = "piston_s14"
TITLE = "Field-wide piston: causes one at a time (s14)"
PHASES = (0.13, 0.37, 0.61, 0.89)
EFFECTS = ("none", "noise", "stage", "noise+stage", "noise+telecentric")


# ----------------------------------------------------------------------------------------------- closed form
def closed_form_frames(z_um, *, noise: float = 0.0, **kw) -> list[np.ndarray]:
    """16-bit frames of the closed-form flat field in focus at z = 0 (:mod:`fieldcal.measure.texture_synth`)."""
    from fieldcal.measure.texture_synth import sinusoid_frame

    rng = np.random.default_rng(7)
    return [sinusoid_frame(float(z), noise=noise, rng=rng, **kw) for z in np.asarray(z_um, dtype=np.float64)]


CLOSED_FORM_CASES = (
    # name, options, scan offset from the peak (steps)
    ("scan centred on the peak", {}, 0.0),
    ("scan 2.3 steps off the peak", {}, 2.3),
    ("noise 0.5 % of full scale", {"noise": 0.005}, 0.3),
    ("100 % pixel aperture (sensor-fixed), no breathing", {"pixel_aperture": True}, 0.3),
    ("breathing d ln m/dz = +1e-4 /µm, no sensor-fixed MTF", {"breathing_per_um": 1e-4}, 0.3),
    ("breathing -1e-4 /µm, no sensor-fixed MTF", {"breathing_per_um": -1e-4}, 0.3),
    ("breathing +1e-4 /µm, pixel aperture", {"breathing_per_um": 1e-4, "pixel_aperture": True}, 0.3),
    ("breathing -1e-4 /µm, pixel aperture", {"breathing_per_um": -1e-4, "pixel_aperture": True}, 0.3),
    ("breathing +2.4e-5 /µm (exit pupil 42 mm), pixel aperture", {"breathing_per_um": 2.4e-5,
                                                                   "pixel_aperture": True}, 0.3),
    ("breathing +1e-4 /µm, pixel aperture, declared", {"breathing_per_um": 1e-4, "pixel_aperture": True,
                                                         "declare": True}, 0.3),
)


def closed_form_case(name: str, opts: dict, offset_steps: float, *, step_um: float = 20.0, n: int = 25,
                     f_number: float = 4.0, pitch_um: float = 6.0, effort: str = "standard",
                     measures=("sml", "bandpass", "auto")) -> dict:
    """Mean tile best focus (µm; the truth is 0) per measure, averaged over the sampling phases."""
    from fieldcal.formats.frames import ArrayStack
    from fieldcal.measure import measure_stack

    opts = dict(opts)
    declare = opts.pop("declare", False)
    fs = float(max(1, round(0.4 * 1000.0 / (2.0 * pitch_um))))
    res = {m: [] for m in measures}
    bound = []
    t0 = time.process_time()
    for ph in PHASES:
        z = (np.arange(n) - (n - 1) / 2.0 + ph + offset_steps) * step_um
        st = ArrayStack(closed_form_frames(z, f_number=f_number, pitch_um=pitch_um, **opts), z, ["Y"],
                        pixel_pitch_um=pitch_um)
        if declare:
            st.meta = {"sensor_mtf": {"pixel_aperture": True, "diffraction": False}, "f_number": f_number}
        for m in measures:
            t, _ = measure_stack(st, fs_cyc_per_mm=fs, effort=effort, measure=m, quiet=True)
            ok = np.asarray(t.ok, dtype=bool)
            res[m].append(float(np.mean(np.asarray(t.z_best_um)[ok])))
            if m == "sml" and t.sml_gain:
                # what the band states for the SML's breathing error (fit.tiles.breathing_systematic_sd_um)
                v = np.asarray(t.z_dgamma_um)[ok]
                bound.append(float(t.sml_gain["Y"]["k_sd"]) * float(np.sqrt(np.nanmean(v * v))))
    row = {"kind": "closed_form", "case": name, "step_um": step_um, "offset_steps": offset_steps,
           "cpu_s": time.process_time() - t0, **{f"{m}_um": float(np.mean(v)) for m, v in res.items()},
           **{f"{m}_sd_um": float(np.std(v)) for m, v in res.items()}}
    if bound:
        row["stated_sd_um"] = float(np.mean(bound))
    return row


def closed_form_calibrate(step_um: float = 20.0, n: int = 25, f_number: float = 4.0, pitch_um: float = 6.0,
                          effort: str = "standard") -> dict:
    """The whole pipeline (``fieldcal.calibrate``) on the base closed-form stack: its surface's grid mean."""
    import tempfile

    import fieldcal
    from fieldcal.formats.stack import StackWriter

    z = (np.arange(n) - (n - 1) / 2.0 + 0.37) * step_um
    fs = float(max(1, round(0.4 * 1000.0 / (2.0 * pitch_um))))
    with tempfile.TemporaryDirectory(prefix="bench-piston-") as tmp:
        d = Path(tmp) / "stack"
        wr = StackWriter.create(d, pixel_pitch_um=pitch_um, channels=["Y"], bit_depth=16, black_level=0,
                                white_level=65535, f_number=f_number)
        for zi, fr in zip(z, closed_form_frames(z, f_number=f_number, pitch_um=pitch_um)):
            wr.add_frame(fr, float(zi))
        t0 = time.process_time()
        prof = fieldcal.calibrate(str(d), fs_cyc_per_mm=fs, effort=effort, z_ref_um=0.0, quiet=True)
        cpu = time.process_time() - t0
        w, h = prof.image_size_px
        X, Y = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
        zp = np.asarray(prof.best_focus_um(X, Y, "Y"), dtype=np.float64)
        lo, hi = prof.best_focus_interval_um(X, Y, "Y", level=0.9)
    return {"kind": "closed_form_calibrate", "case": "fieldcal.calibrate, disc, phase 0.37", "step_um": step_um,
            "piston_um": float(zp.mean()), "rms_um": float(np.sqrt(np.mean(zp ** 2))),
            "hw_um": float(np.mean(0.5 * (np.asarray(hi) - np.asarray(lo)))), "cpu_s": cpu}


# ----------------------------------------------------------------------------------------------- simulator
def simulator_case(k: int, effect: str, work: Path, width: int = 320, effort: str = "standard") -> dict:
    """Lens k of the band benchmark with one set of effects; its pistons per channel (µm)."""
    import bench_band_coverage as B

    import fieldcal
    from fieldcal.simulate.stackgen import simulate_stack

    parts = set(effect.split("+")) - {"none"}
    L = B.lens_setup(k, width, stage_errors="stage" in parts, telecentric="telecentric" in parts)
    path, spherical, spec, fs, z, stage = (L[key] for key in ("path", "spherical", "spec", "fs", "z", "stage"))
    d = work / f"lens{k}-{effect}"
    t0 = time.process_time()
    if not (d / "stack.json").exists():
        kw = dict(stage)
        if path != "geometric":
            kw.update(optics=path, fs_cyc_per_mm=fs)
        simulate_stack(spec, d, z, scene="chart", seed=k, progress=False, noise="noise" in parts, **kw)
    t1 = time.process_time()
    prof = fieldcal.calibrate(d, fs_cyc_per_mm=fs, effort=effort, z_ref_um=0.0, seed=0, quiet=True)
    ev = B.evaluate(prof, {"spec": spec, "fs": fs, "optics": path, "stage_backlash_um": stage["stage_backlash_um"],
                           "stage_scale_error": stage["stage_scale_error"]})
    skew = (prof.diagnostics.get("curve_skew") or {}).get("channels", {})
    return {"kind": "simulator", "lens": k, "effect": effect, "optics": path, "asymmetric": bool(spherical),
            "f_number": spec.f_number, "exit_pupil_mm": float(spec.exit_pupil_mm), "step_um": float(z[1] - z[0]),
            "piston_um": [float(v) for v in ev["piston_um"]], "coverage": ev["coverage"], "rms_um": ev["rms_um"],
            "offset_weight": [float((skew.get(c) or {}).get("offset_weight") or 0.0) for c in prof.channels],
            "render_cpu_s": t1 - t0, "calibrate_cpu_s": time.process_time() - t1}


def curvature_case(k: int, scale: float, work: Path, width: int = 320) -> dict:
    """Lens k's G channel (geometric path, telecentric, no astigmatism, no stage or sensor noise) with its
    field-curvature terms scaled by ``scale``: the sml@fs offset (band-pass minus SML on the same tiles), and
    for each measure alone the tile-window factor kappa (least squares of the raw tile minus the true value at
    the tile's reported position against ``L s^2 / 24``, the window mean the fit removes) and the measures'
    position difference along the focus gradient (the two energy-weighted tile centroids differ)."""
    import bench_band_coverage as B

    from fieldcal.fit.synthetic import random_lens
    from fieldcal.formats.stack import Stack
    from fieldcal.measure.tiles import measure_stack
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import chart_positions_um, default_fs

    rng = np.random.default_rng(9100 + k)
    spec = random_lens(rng, channels=("G",), optics=True)
    rng2 = np.random.default_rng(9100 + 7919 * (k + 1))
    spec = replace(spec, f_number=float(math.exp(rng2.uniform(*B.LOG_F_RANGE))), exit_pupil_mm=math.inf,
                   stage_axis_tilt_mrad=(0.0, 0.0))
    spec = replace(spec, channels=tuple(replace(c, curvature_um=tuple(scale * v for v in c.curvature_um),
                                                astigmatism_um=0.0) for c in spec.channels))
    h = int(round(width * 3 / 4))
    spec = spec.with_sensor_size(width, h)
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    d = work / f"curv-lens{k}-x{scale:g}"
    if not (d / "stack.json").exists():
        simulate_stack(spec, d, z, scene="chart", seed=k, progress=False, noise=False)
    st = Stack.open(d)
    truth = TruthProfile(spec, width, h, z_ref_um=0.0)
    row = {"kind": "curvature", "lens": k, "scale": scale, "f_number": spec.f_number, "step_um": float(z[1] - z[0])}
    t, _ = measure_stack(st, fs_cyc_per_mm=fs, effort="standard", quiet=True, z_ref_um=0.0)
    row["offset_um"] = float(t.skew["G"]["offset_um"])
    row["offset_weight"] = float(t.skew["G"]["offset_weight"])
    pos = {}
    for meas in ("sml", "bandpass"):
        t, _ = measure_stack(st, fs_cyc_per_mm=fs, effort="standard", quiet=True, measure=meas, z_ref_um=0.0)
        ok = np.asarray(t.ok, dtype=bool)
        x, y = t.x_px, t.y_px
        half = 0.5 * float(t.tile_px)
        def f(dx, dy, x=x, y=y):
            return np.asarray(truth.best_focus_um(x + dx, y + dy, "G"), dtype=np.float64)

        lap = (f(half, 0) + f(-half, 0) + f(0, half) + f(0, -half) - 4.0 * f(0, 0)) / half ** 2
        corr = lap * float(t.tile_px) ** 2 / 24.0
        raw = np.asarray(t.z_best_um) - f(0, 0)
        row[f"{meas}_kappa"] = float(np.sum(raw[ok] * corr[ok]) / np.sum(corr[ok] ** 2))
        row[f"{meas}_resid_um"] = float(np.mean(raw[ok] - corr[ok]))
        row["window_um"] = float(np.mean(corr[ok]))
        gx = (f(1.0, 0) - f(-1.0, 0)) / 2.0
        gy = (f(0, 1.0) - f(0, -1.0)) / 2.0
        pos[meas] = (x, y, np.asarray(t.z_best_um), ok, gx, gy)
    xs, ys, zs, oks, gx, gy = pos["sml"]
    xb, yb, zb, okb, _, _ = pos["bandpass"]
    both = oks & okb
    row["bp_minus_sml_um"] = float(np.mean(zb[both] - zs[both]))
    row["position_term_um"] = float(np.mean(gx[both] * (xb[both] - xs[both]) + gy[both] * (yb[both] - ys[both])))
    row["position_diff_px"] = float(np.mean(np.hypot(xb[both] - xs[both], yb[both] - ys[both])))
    return row


def stage_seed_case(k: int, repeatability_um: float, seed: int, work: Path, width: int = 320) -> list[dict]:
    """Lens k's G channel (geometric, telecentric, noise-free) rendered with chart/stage seed ``seed``, once with a
    perfect stage and once with stage position noise of sd ``repeatability_um`` (no backlash or scale error),
    each calibrated with ``measure="sml"`` and ``"auto"`` (sml@fs): the pistons and the offset's weight."""
    import bench_band_coverage as B

    import fieldcal
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.validation.run import chart_positions_um, default_fs

    rng = np.random.default_rng(9100 + k)
    spec = random_lens(rng, channels=("G",), optics=True)
    rng2 = np.random.default_rng(9100 + 7919 * (k + 1))
    spec = replace(spec, f_number=float(math.exp(rng2.uniform(*B.LOG_F_RANGE))), exit_pupil_mm=math.inf)
    spec = spec.with_sensor_size(width, int(round(width * 3 / 4)))
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    out = []
    for r in (0.0, float(repeatability_um)):
        d = work / f"seed-lens{k}-s{seed}-r{r:g}"
        if not (d / "stack.json").exists():
            simulate_stack(spec, d, z, scene="chart", seed=seed, progress=False, noise=False, stage_noise_um=r)
        for meas in ("sml", "auto"):
            prof = fieldcal.calibrate(d, fs_cyc_per_mm=fs, effort="standard", z_ref_um=0.0, quiet=True, measure=meas)
            ev = B.evaluate(prof, {"spec": spec, "fs": fs, "optics": "geometric", "stage_backlash_um": 0.0,
                                   "stage_scale_error": 0.0})
            sk = ((prof.diagnostics.get("curve_skew") or {}).get("channels") or {}).get("G") or {}
            out.append({"kind": "stage_seed", "lens": k, "seed": seed, "repeatability_um": r, "measure": meas,
                        "step_um": float(z[1] - z[0]), "piston_um": float(ev["piston_um"][0]),
                        "offset_um": float(sk.get("offset_um") or 0.0),
                        "offset_weight": float(sk.get("offset_weight") or 0.0),
                        "bp_skew_weight": float(sk.get("bp_skew_weight") or 0.0)})
    return out


# ----------------------------------------------------------------------------------------------- tables
def render(rows: list[dict], argv_text: str, notes: str = "") -> str:
    out = [f"### {TITLE}", "", f"`python benchmarks/bench_piston.py {argv_text}`", ""]
    cf = [r for r in rows if r["kind"] == "closed_form"]
    if cf:
        out += ["**Closed form** (`fieldcal.measure.texture_synth`: exact sinusoids, flat field in focus at z = 0, "
                "256x192 px, 6 µm pixels, F/4 disc blur, 25 frames at 20 µm, "
                f"fs 33 cycles/mm, standard effort; mean over the tiles and over {len(PHASES)} sampling phases "
                f"{', '.join(str(p) for p in PHASES)} of a step; the truth is 0, so each figure is the estimator's "
                "piston; `sd` over the phases; *stated breathing sd*: the band's field-wide term for the SML's "
                "breathing error, `sml_gain.k_sd` x the tiles' RMS `z_dgamma_um`):", ""]
        tab = []
        for r in cf:
            d = {"case": r["case"]}
            for m in ("sml", "bandpass", "auto"):
                if f"{m}_um" in r:
                    d[m] = f"{r[f'{m}_um']:+.4f} ± {r[f'{m}_sd_um']:.4f} ({r[f'{m}_um'] / r['step_um']:+.4f} step)"
            d["bound"] = f"{r['stated_sd_um']:.3f}" if "stated_sd_um" in r else ""
            tab.append(d)
        out += md_table(tab, [("case", "case", ""), ("SML (µm)", "sml", ""), ("band-pass (µm)", "bandpass", ""),
                              ("auto = sml@fs (µm)", "auto", ""), ("stated breathing sd (µm)", "bound", "")])
        out.append("")
    cc = [r for r in rows if r["kind"] == "closed_form_calibrate"]
    for r in cc:
        out += [f"Whole pipeline on the base stack ({r['case']}): surface grid mean {r['piston_um']:+.4f} µm, RMS "
                f"{r['rms_um']:.4f} µm, band half-width {r['hw_um']:.3f} µm ({r['cpu_s']:.1f} s CPU).", ""]
    sim = [r for r in rows if r["kind"] == "simulator"]
    if sim:
        out += ["**Our simulator, one effect at a time** (lenses of `bench_band_coverage`, 320 px, standard; piston = "
                "grid mean of fitted minus true best focus per channel, truth in commanded stage coordinates; "
                "*offset applied* = channels whose sml@fs offset weight is ≥ 1/2):", ""]
        tab = []
        groups = {}
        for r in sim:
            groups.setdefault((r["optics"], "telecentric" if r["effect"].endswith("telecentric") or
                               not math.isfinite(r["exit_pupil_mm"]) else "breathing", r["effect"]), []).append(r)
        for (optics, br, eff), rs in sorted(groups.items()):
            p = np.concatenate([r["piston_um"] for r in rs])
            s = np.concatenate([[r["step_um"]] * len(r["piston_um"]) for r in rs])
            w = np.concatenate([r["offset_weight"] for r in rs])
            tab.append({"optics": optics, "pupil": br, "effects": eff, "lenses": len(rs), "n": p.size,
                        "pos": float(np.mean(p > 0)), "median": float(np.median(p)), "mean": float(np.mean(p)),
                        "step": float(np.mean(p / s)), "sem": float(np.std(p / s) / math.sqrt(p.size)),
                        "applied": float(np.mean(w >= 0.5))})
        out += md_table(tab, [("optics", "optics", ""), ("exit pupil", "pupil", ""), ("effects", "effects", ""),
                              ("lenses", "lenses", ""), ("lens × channel", "n", ""), ("positive", "pos", ".2f"),
                              ("median (µm)", "median", "+.3f"), ("mean (µm)", "mean", "+.3f"),
                              ("mean (step)", "step", "+.4f"), ("sem (step)", "sem", ".4f"),
                              ("offset applied", "applied", ".2f")])
        out.append("")
        per = [{"lens": r["lens"], "effects": r["effect"], "optics": r["optics"], "F": r["f_number"],
                "pupil": r["exit_pupil_mm"], "step": r["step_um"],
                "piston": " ".join(f"{v:+.3f}" for v in r["piston_um"]),
                "w": " ".join(f"{v:.2f}" for v in r["offset_weight"]), "cov": r["coverage"]} for r in sim]
        out += ["Per lens:", ""] + md_table(per, [("lens", "lens", ""), ("effects", "effects", ""),
                                                  ("optics", "optics", ""), ("F", "F", ".1f"),
                                                  ("exit pupil (mm)", "pupil", ".1f"), ("step (µm)", "step", ".1f"),
                                                  ("piston per channel (µm)", "piston", ""),
                                                  ("offset weight", "w", ""), ("coverage", "cov", ".2f")])
        out.append("")
    cv = [r for r in rows if r["kind"] == "curvature"]
    if cv:
        out += ["**The sml@fs offset on a curved field** (`--curvature`: the lens's G channel, geometric path, "
                "telecentric, no astigmatism, no stage or sensor noise, its curvature terms scaled; *offset* = the "
                "pooled band-pass minus SML on the same tiles that `sml@fs` would apply; *window* = the mean "
                "`L s²/24` the fit removes; *kappa* = raw tile minus true value at the tile's reported position "
                "regressed on the window term, each measure alone at its own energy-weighted positions; "
                "*position term* = the mean of ∇z · (band-pass centroid − SML centroid)):", ""]
        out += md_table(cv, [("lens", "lens", ""), ("curvature x", "scale", "g"), ("F", "f_number", ".1f"),
                             ("step (µm)", "step_um", ".1f"), ("offset (µm)", "offset_um", "+.3f"),
                             ("weight", "offset_weight", ".2f"), ("window (µm)", "window_um", "+.3f"),
                             ("kappa SML", "sml_kappa", ".2f"), ("kappa band-pass", "bandpass_kappa", ".2f"),
                             ("band-pass − SML, own positions (µm)", "bp_minus_sml_um", "+.3f"),
                             ("position term (µm)", "position_term_um", "+.3f"),
                             ("centroid distance (px)", "position_diff_px", ".2f")])
        out.append("")
    ss = [r for r in rows if r["kind"] == "stage_seed"]
    if ss:
        out += ["**Stage position noise alone** (`--stage-seeds`: the lens's G channel, geometric, telecentric, no "
                "sensor noise, no backlash or scale error; each seed draws the chart and the frames' position "
                "errors; piston per calibration, `measure=sml` against the default `auto` = sml@fs):", ""]
        tab = []
        for key in sorted({(r["lens"], r["repeatability_um"], r["measure"]) for r in ss}):
            rs = [r for r in ss if (r["lens"], r["repeatability_um"], r["measure"]) == key]
            p = np.array([r["piston_um"] for r in rs])
            tab.append({"lens": key[0], "r": key[1], "measure": key[2], "n": len(rs),
                        "pistons": " ".join(f"{v:+.3f}" for v in p), "mean": float(p.mean()),
                        "pos": float(np.mean(p > 0)),
                        "offset": " ".join(f"{r['offset_um']:+.2f}@{r['offset_weight']:.2f}" for r in rs)})
        out += md_table(tab, [("lens", "lens", ""), ("position noise sd (µm)", "r", "g"), ("measure", "measure", ""),
                              ("seeds", "n", ""), ("pistons (µm)", "pistons", ""), ("mean (µm)", "mean", "+.3f"),
                              ("positive", "pos", ".2f"), ("sml@fs offset @ weight", "offset", "")])
        out.append("")
    if notes:
        out += [notes.rstrip(), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--closed-form", action="store_true", help="the closed-form cases (measure_stack)")
    ap.add_argument("--calibrate", action="store_true", help="with --closed-form: also fieldcal.calibrate the base")
    ap.add_argument("--lenses", default="", help="comma list of band-benchmark lens indices (our simulator)")
    ap.add_argument("--effects", default=",".join(EFFECTS), help=f"comma list of {', '.join(EFFECTS)}")
    ap.add_argument("--curvature", default="",
                    help="LENS:SCALE,... curvature-scaled noise-free telecentric stacks of band-benchmark lenses (the "
                         "sml@fs offset and each measure's tile-window factor)")
    ap.add_argument("--stage-seeds", default="",
                    help="LENS:SD:SEED,... noise-free telecentric stacks with stage position noise of sd SD (µm) and "
                         "without, calibrated with sml and sml@fs")
    ap.add_argument("--work", type=Path, default=None, help="folder for the simulator's stacks (kept; default: temp)")
    ap.add_argument("--jsonl", type=Path, default=None, help="append each row to this file")
    ap.add_argument("--from-jsonl", default="", help="comma list of --jsonl files: make the tables, run nothing")
    ap.add_argument("--notes", type=Path, default=None, help="a markdown file appended to the section (the reading)")
    ap.add_argument("--docs", action="store_true", help=f"write the section bench_{NAME} of docs/benchmarks.md")
    args = ap.parse_args(argv)
    for e in [e for e in args.effects.split(",") if e]:
        if e not in EFFECTS:
            print(f"error: unknown effect {e!r}: use {', '.join(EFFECTS)}", file=sys.stderr)
            return 2
    rows: list[dict] = []

    def record(r):
        rows.append(r)
        print(json.dumps(r), flush=True)
        if args.jsonl:
            with open(args.jsonl, "a") as fh:
                fh.write(json.dumps(r) + "\n")

    if args.from_jsonl:
        for f in args.from_jsonl.split(","):
            rows += [json.loads(line) for line in Path(f).read_text().splitlines() if line.strip()]
    else:
        if args.closed_form:
            for name, opts, off in CLOSED_FORM_CASES:
                record(closed_form_case(name, opts, off))
            if args.calibrate:
                record(closed_form_calibrate())
        if args.lenses or args.curvature or args.stage_seeds:
            import contextlib
            import tempfile
            with (tempfile.TemporaryDirectory(prefix="bench-piston-") if args.work is None
                  else contextlib.nullcontext(str(args.work))) as tmp:
                Path(tmp).mkdir(parents=True, exist_ok=True)
                for k in [int(v) for v in args.lenses.split(",") if v.strip()]:
                    for e in [e for e in args.effects.split(",") if e]:
                        record(simulator_case(k, e, Path(tmp)))
                for item in [v for v in args.stage_seeds.split(",") if v.strip()]:
                    k, r, sd = item.split(":")
                    for row in stage_seed_case(int(k), float(r), int(sd), Path(tmp)):
                        record(row)
                for item in [v for v in args.curvature.split(",") if v.strip()]:
                    k, _, sc = item.partition(":")
                    record(curvature_case(int(k), float(sc or 1.0), Path(tmp)))
    raw = list(argv if argv is not None else sys.argv[1:])
    skip = {"--notes", "--jsonl"}
    argv_text = " ".join(a for i, a in enumerate(raw) if a not in skip and (i == 0 or raw[i - 1] not in skip))
    text = render(rows, argv_text, args.notes.read_text() if args.notes else "")
    print(text)
    if args.docs:
        write_docs_section(NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
