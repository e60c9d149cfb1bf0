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

``--optics NAME`` is passed to ``simulate_stack(optics=NAME)`` when the simulator has that option (the
wave-optics path, issue 14); otherwise only ``geometric`` is available.

    python benchmarks/bench_band_coverage.py --lenses 12 --width 320 --docs     # docs/benchmarks.md table
    python benchmarks/bench_band_coverage.py --lenses 3 --efforts quick          # smoke run
    python benchmarks/bench_band_coverage.py --lenses 40 --scheduler local      # one Dask task per lens

``--scheduler local|threads|tcp://HOST:PORT`` runs one task per lens on Dask (fieldcal.batch, docs/batch.md;
an existing cluster's workers need this repository on the same path and a shared temporary folder); without
it the lenses run one after another in this process.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import md_table, write_docs_section  # noqa: E402

NAME = "band_coverage"
BENCH_DIR = str(Path(__file__).resolve().parent)


def simulate_lens(k: int, width_px: int, workdir: Path, optics: str = "geometric", seed: int = 9100,
                  stage_errors: bool = True):
    """Render lens ``k``'s chart stack with stage errors; returns a dict describing it."""
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.validation.run import chart_positions_um, default_fs

    rng = np.random.default_rng(seed + k)
    spec = random_lens(rng, channels=("R", "G", "B") if k % 4 else ("Y",), optics=True)
    spec = spec.with_sensor_size(width_px, int(round(width_px * 3 / 4)))
    fs = default_fs(spec.sensor.pixel_pitch_um)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    z = chart_positions_um(spec, tol, 0.5, 2.0)
    stage = {"stage_noise_um": float(rng.uniform(0.1, 0.5)), "stage_backlash_um": float(rng.uniform(0.0, 3.0)),
             "stage_scale_error": float(rng.uniform(-2e-4, 2e-4))}
    if not stage_errors:
        stage = {key: 0.0 for key in stage}
    kw = dict(stage)
    if optics != "geometric":
        if "optics" not in inspect.signature(simulate_stack).parameters:
            raise SystemExit(f"this simulator has no optics option (asked for --optics {optics})")
        kw["optics"] = optics
    d = workdir / f"lens{k}"
    simulate_stack(spec, d, z, scene="chart", seed=k, progress=False, **kw)
    return {"spec": spec, "dir": d, "fs": fs, "step_um": float(z[1] - z[0]), **stage}


def evaluate(prof, lens: dict, level: float = 0.9) -> dict:
    """Coverage, RMS and band half-width against the truth in commanded stage coordinates."""
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import SURFACE_GRID_PX, _grid

    w, h = prof.image_size_px
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um)
    X, Y = _grid(w, h, SURFACE_GRID_PX)
    cov, sq, hw = [], [], []
    for c in truth.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64)
        # the scan moves up: the carriage lags by half the backlash, so the commanded position of a true z
        zt = (zt + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
        zp = np.asarray(prof.best_focus_um(X, Y, c), dtype=np.float64)
        lo, hi = (np.asarray(a, dtype=np.float64) for a in prof.best_focus_interval_um(X, Y, c, level=level))
        cov.append(float(np.mean((zt >= lo - 1e-9) & (zt <= hi + 1e-9))))
        sq.append(float(np.mean((zp - zt) ** 2)))
        hw.append(float(np.mean(0.5 * (hi - lo))))
    rms = float(np.sqrt(np.mean(sq)))
    return {"coverage": float(np.mean(cov)), "rms_um": rms, "hw_um": float(np.mean(hw))}


def run_one(lens: dict, effort: str, seed: int = 0) -> dict:
    import fieldcal

    t0 = time.perf_counter()
    prof = fieldcal.calibrate(lens["dir"], fs_cyc_per_mm=lens["fs"], effort=effort, z_ref_um=0.0, seed=seed,
                              quiet=True)
    dt = time.perf_counter() - t0
    after = evaluate(prof, lens)
    sc = prof.diagnostics["surface"].get("self_check", {})
    scale = prof.surfaces.band_scale
    prof.surfaces.band_scale = 1.0
    before = evaluate(prof, lens)
    prof.surfaces.band_scale = scale
    return {"cov_after": after["coverage"], "cov_before": before["coverage"], "rms_um": after["rms_um"],
            "hw_um": after["hw_um"], "hw_before_um": before["hw_um"], "band_scale": scale,
            "self_check": sc.get("coverage", float("nan")), "check_s": sc.get("time_s", float("nan")),
            "time_s": dt, "fit_s": prof.diagnostics["timing_s"]["fit"], "model": prof.surfaces.model.name}


def lens_rows(job) -> list[dict]:
    """Lens ``k``: render its stack and calibrate it at each effort (one task of a --scheduler run)."""
    k, width, optics, stage_errors, efforts, workdir = job
    if BENCH_DIR not in sys.path:  # on a Dask worker: this folder's modules (_common)
        sys.path.insert(0, BENCH_DIR)
    lens = simulate_lens(k, width, Path(workdir), optics, stage_errors=stage_errors)
    rows = []
    for eff in efforts:
        r = run_one(lens, eff)
        r.update(lens=k, effort=eff, step_um=lens["step_um"])
        rows.append(r)
    return rows


def print_rows(res) -> None:
    if not res.ok:
        print(f"{res.name}: FAILED: {res.error}", flush=True)
        return
    for r in res.value:
        print(f"lens {r['lens']:2d} {r['effort']:8s} cov {r['cov_before']:.2f} -> {r['cov_after']:.2f} "
              f"(self-check {r['self_check']:.2f}, scale {r['band_scale']:.2f}) rms {r['rms_um']:.3f} µm "
              f"({r['rms_um'] / r['step_um']:.3f} step) hw/rms {r['hw_um'] / max(r['rms_um'], 1e-9):.2f} "
              f"check {1000 * r['check_s']:.0f} ms, calibrate {r['time_s']:.1f} s  {r['model']}", flush=True)


def summarise(rows, efforts):
    out = []
    for eff in efforts:
        r = [x for x in rows if x["effort"] == eff]
        if not r:
            continue
        a = lambda k: np.array([x[k] for x in r], dtype=float)
        ca, cb = a("cov_after"), a("cov_before")
        ratio = a("hw_um") / np.maximum(a("rms_um"), 1e-9)
        out.append({"effort": eff, "lenses": len(r), "cov_before": cb.mean(), "cov_after": ca.mean(),
                    "cov_min": ca.min(), "in_075_099": f"{int(np.sum((ca >= 0.75) & (ca <= 0.99)))}/{len(r)}",
                    "rms_step": float(np.mean(a("rms_um") / a("step_um"))),
                    "rms_step_max": float(np.max(a("rms_um") / a("step_um"))),
                    "hw_rms": float(np.median(ratio)), "scale": float(np.median(a("band_scale"))),
                    "self_check": float(np.nanmean(a("self_check"))),
                    "sc_diff": float(np.nanmean(np.abs(a("self_check") - ca))),
                    "check_s": float(np.nanmedian(a("check_s"))), "time_s": float(np.median(a("time_s")))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lenses", type=int, default=12, help="number of random lenses (default 12)")
    ap.add_argument("--width", type=int, default=320, help="render width in px (height = 3/4)")
    ap.add_argument("--efforts", default="quick,standard", help="comma list (default quick,standard)")
    ap.add_argument("--optics", default="geometric", help="simulator image-formation path (default geometric)")
    ap.add_argument("--no-stage-errors", action="store_true", help="a perfect stage")
    ap.add_argument("--docs", action="store_true", help="write the table into docs/benchmarks.md")
    ap.add_argument("--scheduler", default=None,
                    help="run one Dask task per lens: local, threads or tcp://HOST:PORT (default: in this process)")
    ap.add_argument("--workers", type=int, default=None, help="workers of a local cluster (default: one per CPU)")
    args = ap.parse_args(argv)
    efforts = args.efforts.split(",")
    from fieldcal.batch.engine import check_scheduler, run_units

    scheduler = check_scheduler(args.scheduler, args.workers)
    with tempfile.TemporaryDirectory(prefix="bench-bands-") as tmp:
        jobs = [(f"lens{k:02d}", (k, args.width, args.optics, not args.no_stage_errors, efforts, tmp))
                for k in range(args.lenses)]
        results = run_units(lens_rows, jobs, scheduler=scheduler, workers=args.workers, desc="lenses",
                            unit="lens", quiet=scheduler is None, on_result=print_rows)
    rows = [r for res in results if res.ok for r in res.value]
    summ = summarise(rows, efforts)
    cols = [("effort", "effort", ""), ("lenses", "lenses", ""), ("mean coverage before", "cov_before", ".3f"),
            ("mean coverage after", "cov_after", ".3f"), ("min", "cov_min", ".2f"),
            ("lenses in 0.75-0.99", "in_075_099", ""), ("mean RMS / step", "rms_step", ".4f"),
            ("max RMS / step", "rms_step_max", ".3f"), ("median half-width / RMS", "hw_rms", ".2f"),
            ("median band scale", "scale", ".2f"), ("mean self-check", "self_check", ".3f"),
            ("mean abs(self-check − measured)", "sc_diff", ".3f"), ("median check (s)", "check_s", ".3f"),
            ("median calibrate (s)", "time_s", ".1f")]
    per_lens = [("lens", "lens", ""), ("effort", "effort", ""), ("coverage before", "cov_before", ".2f"),
                ("coverage after", "cov_after", ".2f"), ("self-check", "self_check", ".2f"),
                ("band scale", "band_scale", ".2f"), ("RMS (µm)", "rms_um", ".3f"), ("half-width (µm)", "hw_um", ".3f"),
                ("model", "model", "")]
    text = "\n".join([
        "## Band coverage with stage errors and the leave-tiles-out self-check (issue 14)",
        "",
        f"`python benchmarks/bench_band_coverage.py {' '.join(argv if argv is not None else sys.argv[1:])}`"
        f" — {args.lenses} random lenses (`random_lens(optics=True)`, optics path `{args.optics}`) at "
        f"{args.width} px wide, simulator noise, stage position noise 0.1-0.5 µm, backlash 0-3 µm, axis scale "
        "error ≤ 2e-4; truth in commanded stage coordinates. *before* = band terms as estimated (band scale 1), "
        "*after* = with the leave-tiles-out band scale; self-check = the profile's own cross-validated "
        "held-out-tile coverage. Machine shared (2 cores).",
        "", *md_table(summ, cols), "", "Per lens:", "", *md_table(rows, per_lens)])
    print(text)
    if args.docs:
        write_docs_section(NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
