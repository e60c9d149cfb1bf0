"""Where a profile's 90 % band is centred against its reported surface, and which centre the truth is nearer
(issues 13/14; docs/benchmarks.md section ``bench_band_centre_s16``).

The reported surface is the chosen model's MAP (``fit/select.py``: blocked held-out test) with its kriged
discrepancy; the band comes from posterior samples that include a model average (BIC-type weights), re-centred
on the kriged surface by the chosen model's MAP (``SurfaceFit._sample_surfaces``). Where the average's other
members differ from the chosen model, the band's middle is not the surface. Per profile and channel, on the
validation grid (``validation.run.SURFACE_GRID_PX``), against the simulator's truth:

* ``off_hw_med``: median over the grid of abs(band middle − surface) / band half-width;
* ``rms_surf_um`` / ``rms_mid_um``: RMS error of the reported surface and of the band's middle;
* coverage of the 90 % band as built (``cov``), and of bands centred on the surface: the same half-width
  (``cov_recentred``), the second moment of the band about the surface, sqrt(hw² + (z_q · offset)²)
  (``cov_moment``), and the band built from the chosen model's own samples only (``cov_chosen``: the first member
  of the average, the other members' samples and their ``model_average_covered`` credit dropped).

Sources (nothing is rendered here):

    python benchmarks/bench_band_centre.py --keep KEEP --jsonl tex.jsonl       # profiles kept by bench_band_coverage --keep
    python benchmarks/bench_band_centre.py --edge-cache C --edge-profiles P --jsonl edge.jsonl
    python benchmarks/bench_band_centre.py --cleanroom W --jsonl cr.jsonl     # a bench_cleanroom.py --work folder
    python benchmarks/bench_band_centre.py --from-jsonl tex.jsonl

``--edge-cache`` is a ``bench_edge_calibration.py --cache`` folder of the triplet-uncorrected lens and
``--random 10`` lenses at 480x270, 20 µm steps (the stacks are calibrated at standard effort, and the profiles
stored in / reused from ``--edge-profiles``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

Z90 = 1.6448536269514722  # the 90 % band's half-width in sd


def texture_items(keep: Path, efforts):
    """(name, effort, lens dict, profile) of the profiles ``bench_band_coverage.py --keep`` stored."""
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.lens import LensSpec

    for meta_path in sorted(keep.glob("lens*.meta.json")):
        k = int(meta_path.name[4:6])
        lens = {**json.loads(meta_path.read_text()), "spec": LensSpec.load(keep / f"lens{k:02d}.spec.json")}
        for eff in efforts:
            pp = keep / f"lens{k:02d}-{eff}.json"
            if pp.exists():
                yield k, eff, lens, LensProfile.load(pp)


def edge_items(cache: Path, profiles: Path, n_random: int = 10, size=(480, 270), step_um: float = 20.0):
    """The slanted-edge bench's lenses (triplet-uncorrected + random_lens(optics=True) x n, seed 0), calibrated
    at standard effort from the cached stacks (profiles stored in ``profiles`` and reused)."""
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.fit.synthetic import random_lens
    from fieldcal.formats.stack import Stack
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.lens import LensSpec

    profiles.mkdir(parents=True, exist_ok=True)
    lenses = [("triplet-uncorrected", LensSpec.load(REPO / "models" / "triplet-uncorrected.json"))]
    rng = np.random.default_rng(0)
    lenses += [(f"random-{i}", random_lens(rng, optics=True)) for i in range(n_random)]
    w, h = size
    for name, spec in lenses:
        where = cache / f"{name}-geometric-slanted-edge-{w}x{h}-{step_um:g}um-seed0"
        if not (where / "stack.json").exists():
            raise SystemExit(f"no cached stack {where} (render it with bench_edge_calibration.py --cache)")
        st = Stack.open(where)
        fs = round(0.25 / (float(st.pixel_pitch_um) / 1000.0), 2)  # as bench_edge_calibration
        pp = profiles / f"{name}.json"
        if pp.exists():
            prof = LensProfile.load(pp)
        else:
            prof = calibrate(st.path, effort="standard", fs_cyc_per_mm=fs, seed=0, quiet=True)
            prof.save(pp)
        yield name, "standard", {"spec": spec, "fs": fs, "optics": "geometric", "stage_backlash_um": 0.0,
                                 "stage_scale_error": 0.0, "step_um": step_um}, prof


def _truth_zs(prof, lens: dict):
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import SURFACE_GRID_PX, _grid

    w, h = prof.image_size_px
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um, optics=lens.get("optics", "geometric"),
                         fs_cyc_per_mm=lens["fs"])
    X, Y = _grid(w, h, SURFACE_GRID_PX)
    out = {}
    for c in truth.channels:
        zt = np.asarray(truth.best_focus_um(X, Y, c), dtype=np.float64)
        # commanded stage coordinates, as bench_band_coverage.evaluate
        out[c] = (zt + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
    return X, Y, out


def cleanroom_items(work: Path, efforts):
    """(lens, "CHART-effort", (X, Y, truth per channel), profile) of a ``bench_cleanroom.py --work`` folder (its
    cached profiles against the clean-room truth at the 8 x 6 nodes; on edges the mean of the T and S peaks)."""
    import fieldcal
    from benchmarks.bench_cleanroom import _load_truth
    from benchmarks.cleanroom.evaluate import truth_mean

    for tp in sorted(work.glob("*/truth.json")):
        truth, meta = _load_truth(tp)
        X, Y = np.meshgrid(np.asarray(meta["xs"]), np.asarray(meta["ys"]))
        for chart in ("texture", "edges"):
            for eff in efforts:
                pp = tp.parent / f"{chart}-{eff}.json"
                if pp.exists():
                    prof = fieldcal.LensProfile.load(pp)
                    zt = {c: np.asarray(truth_mean(truth, c, chart)[0], dtype=np.float64) for c in prof.channels}
                    yield tp.parent.name, f"{chart}-{eff}", {"optics": "clean room", "points": (X, Y, zt)}, prof


def measure(prof, lens: dict) -> dict:
    """Per channel: the band's offset from the surface, both centres' errors, and the variants' coverages."""
    X, Y, truth = lens["points"] if "points" in lens else _truth_zs(prof, lens)
    s = prof.surfaces
    members = (s.diagnostics.get("model_average") or {}).get("members") or []
    chosen_w = next((m["weight"] for m in members if m["name"] == s.model.name), 1.0)
    rows = []
    for c, zt in truth.items():
        zp = np.asarray(prof.best_focus_um(X, Y, c), dtype=np.float64)
        lo, hi = (np.asarray(a, dtype=np.float64) for a in prof.best_focus_interval_um(X, Y, c, level=0.9))
        mid, hw = 0.5 * (lo + hi), 0.5 * (hi - lo)
        off = mid - zp
        rows.append({"channel": c, "off_hw_med": float(np.median(np.abs(off) / hw)),
                     "off_hw_max": float(np.max(np.abs(off) / hw)), "hw_um": float(hw.mean()),
                     "rms_surf_um": float(np.sqrt(np.mean((zp - zt) ** 2))),
                     "rms_mid_um": float(np.sqrt(np.mean((mid - zt) ** 2))),
                     "cov": float(np.mean((zt >= lo) & (zt <= hi))),
                     "cov_recentred": float(np.mean(np.abs(zt - zp) <= hw)),
                     "cov_moment": float(np.mean(np.abs(zt - zp) <= np.sqrt(hw ** 2 + (Z90 * off) ** 2)))})
    # the chosen model's own samples: the first member of the average (fit/select.py puts it first)
    if len(members) > 1 and members[0]["name"] == s.model.name:
        samples, ma = s.samples, s.diagnostics["model_average"]
        s.samples = samples[:max(1, int(round(samples.shape[0] * members[0]["weight"])))]
        s.diagnostics["model_average"] = {**ma, "members": members[:1]}
        try:
            for r, (c, zt) in zip(rows, truth.items()):
                lo, hi = (np.asarray(a, dtype=np.float64) for a in prof.best_focus_interval_um(X, Y, c, level=0.9))
                r["cov_chosen"] = float(np.mean((zt >= lo) & (zt <= hi)))
                r["hw_chosen_um"] = float(np.mean(0.5 * (hi - lo)))
        finally:
            s.samples, s.diagnostics["model_average"] = samples, ma
    else:
        for r in rows:
            r["cov_chosen"], r["hw_chosen_um"] = r["cov"], r["hw_um"]
    return {"model": s.model.name, "members": len(members), "chosen_weight": float(chosen_w), "channels": rows}


VARIANTS = (("band as built", "cov"), ("same half-width about the surface", "cov_recentred"),
            ("second moment about the surface", "cov_moment"), ("chosen model's samples only", "cov_chosen"))


def summary(rows: list[dict], lo: float, hi: float, per_lens: bool) -> str:
    """Markdown table per (effort, optics): offsets, both centres' errors, and in / below / above [lo, hi] of
    each band variant (per lens: coverage averaged over channels; else per lens x channel)."""
    groups = {}
    for r in rows:
        groups.setdefault((r["effort"], r["optics"]), []).append(r)
    head = ["set", "lens × channels", "median abs(middle − surface) / half-width", "n > 0.1 / 0.25 / 0.5",
            "median of the grid's max abs(middle − surface) / half-width",
            "mean RMS error: surface / middle (µm)", "middle nearer the truth (where offset > 0.1)",
            *(f"{name}: mean / in / below / above ({'lenses' if per_lens else 'lens × ch'})" for name, _ in VARIANTS)]
    out = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for (eff, opt), g in sorted(groups.items()):
        ch = [q for r in g for q in r["channels"]]
        a = lambda key: np.array([q[key] for q in ch])
        off, rs, rm = a("off_hw_med"), a("rms_surf_um"), a("rms_mid_um")
        big = off > 0.1
        cells = [f"{eff} {opt}", str(len(ch)), f"{np.median(off):.3f}",
                 f"{np.sum(off > 0.1)} / {np.sum(off > 0.25)} / {np.sum(off > 0.5)}", f"{np.median(a('off_hw_max')):.2f}",
                 f"{rs.mean():.3f} / {rm.mean():.3f}",
                 f"{np.sum(rm < rs)}/{len(ch)} ({np.sum(rm[big] < rs[big])}/{int(big.sum())})"]
        for _, key in VARIANTS:
            c = (np.array([np.mean([q[key] for q in r["channels"]]) for r in g]) if per_lens else a(key))
            cells.append(f"{c.mean():.3f} / {np.sum((c >= lo) & (c <= hi))} / {np.sum(c < lo)} / {np.sum(c > hi)}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", type=Path, help="profiles kept by bench_band_coverage.py --keep")
    ap.add_argument("--efforts", default="quick,standard")
    ap.add_argument("--edge-cache", type=Path, help="bench_edge_calibration.py --cache folder (see above)")
    ap.add_argument("--edge-profiles", type=Path, help="where the edge profiles are stored and reused")
    ap.add_argument("--cleanroom", type=Path, help="a bench_cleanroom.py --work folder (its cached profiles)")
    ap.add_argument("--jsonl", type=Path, help="write one row per profile here")
    ap.add_argument("--from-jsonl", type=Path, help="summarise the rows of a --jsonl file, run nothing")
    args = ap.parse_args(argv)
    if args.from_jsonl:
        rows = [json.loads(line) for line in args.from_jsonl.read_text().splitlines() if line.strip()]
    else:
        if args.cleanroom is not None:
            items = cleanroom_items(args.cleanroom, args.efforts.split(","))
        elif args.keep is not None:
            items = texture_items(args.keep, args.efforts.split(","))
        elif args.edge_cache is not None and args.edge_profiles is not None:
            items = edge_items(args.edge_cache, args.edge_profiles)
        else:
            ap.error("give --keep, or --edge-cache with --edge-profiles, or --from-jsonl")
        rows = []
        for name, eff, lens, prof in items:
            r = {"lens": name, "effort": eff, "optics": lens.get("optics", "geometric"), **measure(prof, lens)}
            rows.append(r)
            if args.jsonl:
                with open(args.jsonl, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
            print(name, eff, r["model"], f"members {r['members']} chosen weight {r['chosen_weight']:.2f}",
                  " ".join(f"{q['channel']}: off/hw {q['off_hw_med']:.2f} rms {q['rms_surf_um']:.3f}/{q['rms_mid_um']:.3f} "
                           f"cov {q['cov']:.2f} {q['cov_recentred']:.2f} {q['cov_moment']:.2f} {q['cov_chosen']:.2f}"
                           for q in r["channels"]), flush=True)
    edges = all(isinstance(r["lens"], str) for r in rows)  # edge bench or clean room: per lens x channel
    print(summary(rows, 0.85, 0.95, per_lens=False) if edges else
          summary(rows, 0.75, 0.99, per_lens=True) + "\n\n" + summary(rows, 0.85, 0.95, per_lens=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
