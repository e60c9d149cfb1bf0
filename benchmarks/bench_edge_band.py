"""Slanted-edge bands read term by term against the truth: which term makes them wide, what each could do, and
how much the held-out edges can say about them (docs/benchmarks.md "bench_edge_band_s16").

Two sources of calibrated edge profiles with a known truth:

* ``--own DIR``: the own simulator's lenses of ``bench_edge_calibration.py`` (``--lens`` specs, then ``--random``
  random lenses of ``--seed``), calibrated from the cached stacks in ``--cache`` (``--size``, ``--step``,
  standard effort) and saved as DIR/<lens>.json on the first run, read back after;
* ``--cleanroom W``: the edge profiles ``bench_cleanroom.py --work W`` wrote (W/<lens>/edges-<effort>.json with
  W/<lens>/truth.json).

For every lens x channel: the band's variance by term (``bench_edge_calibration.band_terms``) at every
``--grid``-th pixel (own) or at the truth nodes (clean room), the true error there, and a Gaussian recomputation
of the band (its mid +- 1.645 sd of the summed terms), with single terms scaled; for every profile the Fisher
information the held-out edges carry on ln kappa (the self-check's ratio of true to stated field-varying error,
``fieldcal.fit.selfcheck``) at kappa = 1.

    python benchmarks/bench_edge_band.py --own /tmp/edge-prof --cache /tmp/edge-stacks \\
        --lens models/triplet-uncorrected.json --random 10
    python benchmarks/bench_edge_band.py --cleanroom /tmp/s8clean
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

Z90 = 1.6448536269514722
CLEANROOM_LENSES = ("astig-f4", "breath-sa03-f2", "f8-tilt-astig", "sa05-f2.8", "sa08-astig-f5.6", "sym-f4")
VARIANTS = (("as built", {}), ("no jackknife excess", {"jackknife_excess": 0.0}),
            ("jackknife excess at half its sd", {"jackknife_excess": 0.25}), ("no misfit term", {"misfit": 0.0}),
            ("no GP local variance", {"gp_local": 0.0}),
            ("no jackknife, misfit, GP", {"jackknife_excess": 0.0, "misfit": 0.0, "gp_local": 0.0}),
            ("common mode at half its sd", {"common": 0.25}), ("no common mode", {"common": 0.0}),
            ("samples at half their sd", {"samples": 0.25}))


def _record(prof, X, Y, zt_of, label: dict) -> list[dict]:
    from bench_edge_calibration import band_terms
    out = []
    for c in prof.channels:
        zt = np.ravel(zt_of(c))
        lo, hi = (np.ravel(a) for a in prof.best_focus_interval_um(X, Y, c))
        out.append(dict(label, ch=c, zt=zt, zm=np.ravel(prof.best_focus_um(X, Y, c)), lo=lo, hi=hi,
                        terms=band_terms(prof, X, Y, c), cov=float(np.mean((zt >= lo) & (zt <= hi)))))
    return out


def own_rows(args) -> tuple[list[dict], list]:
    import fieldcal
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.formats.stack import Stack
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import _grid

    out_dir = Path(args.own)
    out_dir.mkdir(parents=True, exist_ok=True)
    lenses = [(Path(p).stem, LensSpec.load(p)) for p in args.lens]
    rng = np.random.default_rng(args.seed)
    lenses += [(f"random-{i}", random_lens(rng, optics=True)) for i in range(args.random)]
    rows, profs = [], []
    for name, spec in lenses:
        path = out_dir / f"{name}.json"
        if path.exists():
            prof = fieldcal.LensProfile.load(path)
        else:
            w, h = (int(v) for v in args.size.split("x"))
            st = Stack.open(Path(args.cache) / f"{name}-geometric-slanted-edge-{w}x{h}-{args.step:g}um-seed{args.seed}")
            fs = round(0.25 / (float(st.pixel_pitch_um) / 1000.0), 2)
            prof = calibrate(st.path, effort="standard", fs_cyc_per_mm=fs, seed=args.seed, quiet=True)
            prof.save(path)
        w, h = prof.image_size_px
        fs = round(0.25 / (float(prof.pixel_pitch_um) / 1000.0), 2)
        truth = TruthProfile(spec, w, h, z_ref_um=prof.z_ref_um, optics="geometric", fs_cyc_per_mm=fs)
        X, Y = _grid(w, h, args.grid)
        rows += _record(prof, X, Y, lambda c: truth.best_focus_um(X, Y, c), {"lens": name})
        profs.append((name, prof))
        cov = " / ".join(f"{r['cov']:.2f}" for r in rows[-len(prof.channels):])
        print(f"{name}: {cov}", flush=True)
    return rows, profs


def cleanroom_rows(args) -> tuple[list[dict], list]:
    import fieldcal
    from bench_cleanroom import _load_truth
    from cleanroom.evaluate import truth_mean

    work = Path(args.cleanroom)
    rows, profs = [], []
    for name in CLEANROOM_LENSES:
        truth, meta = _load_truth(work / name / "truth.json")
        X, Y = np.meshgrid(np.asarray(meta["xs"]), np.asarray(meta["ys"]))
        for effort in ("quick", "standard"):
            prof = fieldcal.LensProfile.load(work / name / f"edges-{effort}.json")
            rows += _record(prof, X, Y, lambda c: truth_mean(truth, c, "edges")[0], {"lens": f"{name} {effort}"})
            profs.append((f"{name} {effort}", prof))
    return rows, profs


def gaussian_coverage(r: dict, scale: dict | None = None) -> float:
    """Coverage of the band recomputed as its mid +- z sd, the variance the terms' sum (each scaled)."""
    from bench_edge_calibration import TERMS
    scale = scale or {}
    v = sum(r["terms"][t] * scale.get(t, 1.0) for t in TERMS)
    return float(np.mean(np.abs(r["zt"] - 0.5 * (r["lo"] + r["hi"])) <= Z90 * np.sqrt(v)))


def counts(cov, lo=0.85, hi=0.95) -> str:
    cov = np.asarray(cov)
    return f"{cov.mean():.3f} / {np.sum((cov >= lo) & (cov <= hi))} / {np.sum(cov < lo)} / {np.sum(cov > hi)}"


def shares_table(rows) -> str:
    from bench_edge_calibration import TERMS
    lines = ["| coverage | lens x channels | " + " | ".join(f"{t} share" for t in TERMS)
             + " | median band sd (µm) | median error RMS (µm) | median piston² / error² |",
             "|" + " --- |" * (len(TERMS) + 5)]
    for lab, lo, hi in (("above 0.95", 0.9501, 2.0), ("0.85-0.95", 0.85, 0.9501), ("below 0.85", -1.0, 0.85)):
        g = [r for r in rows if lo <= r["cov"] < hi]
        if not g:
            continue
        sh = np.array([[np.mean(r["terms"][t]) for t in TERMS] for r in g])
        sh /= sh.sum(axis=1, keepdims=True)
        sd = [math.sqrt(np.mean(sum(r["terms"][t] for t in TERMS))) for r in g]
        e = [r["zm"] - r["zt"] for r in g]
        lines.append(f"| {lab} | {len(g)} | " + " | ".join(f"{v:.2f}" for v in np.median(sh, axis=0))
                     + f" | {np.median(sd):.3f} | {np.median([math.sqrt(np.mean(x * x)) for x in e]):.3f}"
                     f" | {np.median([x.mean() ** 2 / np.mean(x * x) for x in e]):.2f} |")
    return "\n".join(lines)


def variants_table(rows) -> str:
    lines = ["| band (Gaussian recomputation) | mean / in 0.85-0.95 / below / above |", "| --- | --- |",
             f"| measured | {counts([r['cov'] for r in rows])} |"]
    lines += [f"| {lab} | {counts([gaussian_coverage(r, sc) for r in rows])} |" for lab, sc in VARIANTS]
    return "\n".join(lines)


def held_out_information(prof) -> dict:
    """Fisher information of ln kappa at kappa = 1 from the held-out edges (r ~ N(0, kappa² v + nv)):
    ``2 sum (v / (v + nv))²``; with it the smallest factor the edges could tell from 1 at 90 %."""
    from fieldcal.fit.selfcheck import held_out_predictions
    r, v, nv, _ = held_out_predictions(prof.surfaces.discrepancy)
    ok = np.isfinite(r) & np.isfinite(v) & (nv > 0)
    f = v[ok] / (v[ok] + nv[ok])
    sd = 1.0 / math.sqrt(max(2.0 * float(np.sum(f * f)), 1e-300))
    sc = (prof.diagnostics.get("surface") or {}).get("self_check") or {}
    return {"n": int(ok.sum()), "v_over_nv": float(np.median(v[ok] / nv[ok])), "sd_ln_kappa": sd,
            "factor90": math.exp(Z90 * sd), "kappa_90": sc.get("kappa_90")}


def information_table(profs) -> str:
    lines = ["| profile | held-out edges | median band variance / edge noise variance | Fisher sd of ln κ at κ = 1 "
             "| smallest factor detectable at 90 % | self-check κ 90 % interval |", "| --- | --- | --- | --- | --- | --- |"]
    for name, prof in profs:
        h = held_out_information(prof)
        k = h["kappa_90"] or [float("nan")] * 2
        lines.append(f"| {name} | {h['n']} | {h['v_over_nv']:.3f} | {h['sd_ln_kappa']:.2f} | {h['factor90']:.1f} "
                     f"| {k[0]:.2f}-{k[1]:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--own", default="", help="folder of the own simulator's edge profiles (written on first use)")
    ap.add_argument("--cache", default="", help="bench_edge_calibration.py's stack cache (for --own's first run)")
    ap.add_argument("--lens", action="append", default=[], help="lens spec(s), as bench_edge_calibration.py")
    ap.add_argument("--random", type=int, default=0, help="also this many random lenses of --seed")
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--step", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--grid", type=int, default=16, help="own simulator: every GRID-th pixel")
    ap.add_argument("--cleanroom", default="", help="bench_cleanroom.py's --work folder (its edge profiles)")
    args = ap.parse_args(argv)
    if not args.own and not args.cleanroom:
        ap.error("give --own DIR (with --cache) and/or --cleanroom W")
    for label, fn, on in (("own simulator", own_rows, args.own), ("clean room", cleanroom_rows, args.cleanroom)):
        if not on:
            continue
        rows, profs = fn(args)
        print(f"\n### {label}: the band's variance by term (median share, grid mean)\n\n{shares_table(rows)}")
        print(f"\n### {label}: Gaussian recomputation, single terms scaled\n\n{variants_table(rows)}")
        print(f"\n### {label}: what the held-out edges can say\n\n{information_table(profs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
