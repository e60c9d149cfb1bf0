"""End-to-end band coverage: random simulated lenses → chart stacks → ``fieldcal.calibrate`` → truth.

For each lens (``fieldcal.fit.synthetic.random_lens(optics=True)``: random curvature to rho^6, colour, tilt,
decentre, astigmatism, F/2-F/4, focus breathing, stage axis tilt; mono on every 4th) a chart stack is rendered
at a small size (default 320 px wide, same sensor area) with the simulator's noise, over the focus range
± 2 tolerances in steps of half the tolerance at fs = 0.4 Nyquist; it is calibrated at each effort and the
profile is compared with the truth on a grid over the whole field (corners included): coverage = fraction of
(point, channel) whose true best focus lies in the 90 % band (target 0.85-0.95), RMS/max error, mean band
half-width, time.

Writes a table into docs/benchmarks.md between ``<!-- bench_calibration_coverage:start -->`` and ``end``.

    python benchmarks/bench_calibration_coverage.py --quick       # 4 lenses, quick effort (smoke run)
    python benchmarks/bench_calibration_coverage.py               # 20 lenses, quick + standard (the lead)
    python benchmarks/bench_calibration_coverage.py --lenses 40 --scheduler local   # one Dask task per lens

``--scheduler local|threads|tcp://HOST:PORT`` runs one task per lens on Dask (fieldcal.batch, docs/batch.md;
an existing cluster's workers need this repository on the same path and a shared temporary folder, e.g.
TMPDIR on shared storage); without it the lenses run one after another in this process.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import md_table, write_docs_section  # noqa: E402

NAME = "calibration_coverage"
BENCH_DIR = str(Path(__file__).resolve().parent)


def simulate_lens(k: int, width_px: int, workdir: Path, seed: int = 7000):
    """Render lens ``k``'s chart stack (a perfect stage); returns (spec, stack dir, fs, z step)."""
    from bench_band_coverage import simulate_lens as simulate_with_stage

    lens = simulate_with_stage(k, width_px, workdir, optics="geometric", seed=seed, stage_errors=False,
                                variety=False)
    return lens["spec"], lens["dir"], lens["fs"], lens["step_um"]


def run_one(spec, stack_dir, fs, effort, seed=0) -> dict:
    import fieldcal
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import surface_metrics

    t0 = time.perf_counter()
    prof = fieldcal.calibrate(stack_dir, fs_cyc_per_mm=fs, effort=effort, z_ref_um=0.0, seed=seed, quiet=True)
    dt = time.perf_counter() - t0
    w, h = prof.image_size_px
    m, _, _ = surface_metrics(prof, TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um))
    v = list(m.values())
    return {"coverage": float(np.mean([x["band_coverage"] for x in v])),
            "rms_um": float(np.sqrt(np.mean([x["rms_um"] ** 2 for x in v]))),
            "max_um": max(x["max_um"] for x in v), "bias_um": float(np.mean([x["bias_um"] for x in v])),
            "halfwidth_um": float(np.mean([x["band_halfwidth_um"] for x in v])), "time_s": dt,
            "fit_s": prof.diagnostics["timing_s"]["fit"], "model": prof.surfaces.model.name}


def lens_rows(job) -> list[dict]:
    """Lens ``k``: render its stack and calibrate it at each effort (one task of a --scheduler run)."""
    k, width, efforts, workdir = job
    if BENCH_DIR not in sys.path:  # on a Dask worker: this folder's modules (bench_band_coverage, _common)
        sys.path.insert(0, BENCH_DIR)
    spec, d, fs, step = simulate_lens(k, width, Path(workdir))
    rows = []
    for eff in efforts:
        r = run_one(spec, d, fs, eff)
        r.update(lens=k, effort=eff, step_um=step, channels=len(spec.channels))
        rows.append(r)
    return rows


def print_rows(res) -> None:
    if not res.ok:
        print(f"{res.name}: FAILED: {res.error}", flush=True)
        return
    for r in res.value:
        print(f"lens {r['lens']:2d} {r['effort']:8s} cov {r['coverage']:.2f} rms {r['rms_um']:.3f} µm "
              f"({r['rms_um'] / r['step_um']:.3f} step) max {r['max_um']:.2f} hw {r['halfwidth_um']:.3f} "
              f"fit {r['fit_s']:.1f} s  {r['model']}", flush=True)


def summarise(rows, efforts):
    out = []
    for eff in efforts:
        r = [x for x in rows if x["effort"] == eff]
        if not r:
            continue
        cov = np.array([x["coverage"] for x in r])
        out.append({"effort": eff, "lenses": len(r), "cov_mean": cov.mean(), "cov_sd": cov.std(),
                    "cov_min": cov.min(), "cov_in": f"{int(np.sum((cov >= 0.85) & (cov <= 0.95)))}/{len(r)}",
                    "rms_step": float(np.median([x["rms_um"] / x["step_um"] for x in r])),
                    "rms_um": float(np.median([x["rms_um"] for x in r])),
                    "max_um": float(np.median([x["max_um"] for x in r])),
                    "hw_um": float(np.median([x["halfwidth_um"] for x in r])),
                    "fit_s": float(np.median([x["fit_s"] for x in r])),
                    "time_s": float(np.median([x["time_s"] for x in r]))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="4 lenses, quick effort only (smoke run)")
    ap.add_argument("--lenses", type=int, default=None, help="number of random lenses (default 20)")
    ap.add_argument("--width", type=int, default=320, help="render width in px (height = 3/4)")
    ap.add_argument("--efforts", default=None, help="comma list (default quick,standard; --quick: quick)")
    ap.add_argument("--docs", action="store_true", help="write docs/benchmarks.md (default for full runs)")
    ap.add_argument("--scheduler", default=None,
                    help="run one Dask task per lens: local, threads or tcp://HOST:PORT (default: in this process)")
    ap.add_argument("--workers", type=int, default=None, help="workers of a local cluster (default: one per CPU)")
    args = ap.parse_args(argv)
    n = args.lenses or (4 if args.quick else 20)
    efforts = (args.efforts or ("quick" if args.quick else "quick,standard")).split(",")
    from fieldcal.batch.engine import check_scheduler, run_units

    scheduler = check_scheduler(args.scheduler, args.workers)
    with tempfile.TemporaryDirectory(prefix="bench-calcov-") as tmp:
        jobs = [(f"lens{k:02d}", (k, args.width, efforts, tmp)) for k in range(n)]
        results = run_units(lens_rows, jobs, scheduler=scheduler, workers=args.workers, desc="lenses",
                            unit="lens", quiet=scheduler is None, on_result=print_rows)
    rows = [r for res in results if res.ok for r in res.value]
    summ = summarise(rows, efforts)
    cols = [("effort", "effort", ""), ("lenses", "lenses", ""), ("mean coverage", "cov_mean", ".3f"),
            ("sd", "cov_sd", ".3f"), ("min", "cov_min", ".2f"), ("lenses in 0.85-0.95", "cov_in", ""),
            ("median RMS (µm)", "rms_um", ".3f"), ("median RMS / step", "rms_step", ".4f"),
            ("median max error (µm)", "max_um", ".2f"), ("median band half-width (µm)", "hw_um", ".3f"),
            ("median fit time (s)", "fit_s", ".2f"), ("median calibrate time (s)", "time_s", ".1f")]
    run = "--quick run (a smoke run; the full run replaces it)" if args.quick else "full run"
    text = "\n".join([
        "## Calibration end to end: 90 % band coverage over random lenses",
        "",
        f"`python benchmarks/bench_calibration_coverage.py {' '.join(argv if argv is not None else sys.argv[1:])}`"
        f" — {run}. {n} random simulated lenses (`random_lens(optics=True)`: curvature to ρ⁶, colour, tilt, "
        f"decentre, astigmatism, F/2-F/4, focus breathing (exit pupil 12-60 mm, telecentric 1 in 4), stage axis "
        f"tilt; every 4th mono) rendered as chart stacks at {args.width} px wide over the same sensor "
        "area, simulator noise, fs = 0.4 Nyquist, steps of half the focus tolerance over the focus range ± 2 "
        "tolerances; `fieldcal.calibrate` → `surface_metrics` against `TruthProfile(spec, W, H, "
        "z_ref_um=profile.z_ref_um)` on a grid over the whole field (corners included). Coverage = fraction of "
        "(point, channel) whose truth lies in the 90 % band (target 0.85-0.95). Machine shared (2 cores).",
        "", *md_table(summ, cols)])
    print(text)
    if args.docs or not args.quick:
        write_docs_section(NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
