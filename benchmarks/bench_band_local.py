"""Where the band's local part comes from, and what any change to it could do to the per-lens coverage window.

Reads the profiles a ``bench_band_coverage.py --keep KEEP`` run stored (``lensNN-EFFORT.json`` with
``lensNN.meta.json`` and ``lensNN.spec.json``; nothing is rendered or calibrated) and, per lens and effort:

* **measured**: the band's truth coverage on the benchmark's grid (``bench_band_coverage.evaluate``);
* **own error model**: how often an *exactly honest* band would put this lens's coverage inside the issue's
  window (default 0.75-0.99): the self-check's parametric bootstrap at kappa = 1
  (:func:`fieldcal.fit.selfcheck.coverage_draws`: posterior samples, the discrepancy as a Matérn field, every
  field-wide term one draw per lens). Summed over a group it is the number of lenses an honest band puts in the
  window, and the Poisson-binomial of the per-lens probabilities gives the chance of >= 18 of 20;
* **what-ifs on the band's local part** (Gaussian reading of the band, field-wide and plane terms as stated):
  the local variance (band variance less the field-wide terms and the posterior samples' piston-and-tilt plane,
  as ``bench_band_coverage.decompose`` has it) rescaled so its grid mean equals the true rest's mean square
  about the band's centre (*oracle*), the same rescaling allowed only to narrow (*oracle, narrower only*), and
  the local part removed (*none*);
* per channel, the discrepancy GP's fitted length scale in tile spacings, its identified fraction
  (``Discrepancy.gp_identified``), its amplitude over the tile noise sd and its share of the band, and the
  stated local variance split into the posterior samples' non-plane spread, the block jackknife's excess, the
  misfit term and the GP.

``python benchmarks/bench_band_local.py --keep KEEP --jsonl rows.jsonl`` (``--from-jsonl rows.jsonl`` re-renders
the tables; ``--docs --section KEY`` writes them into docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import md_table, write_docs_section  # noqa: E402

NAME = "band_local"
TITLE = "Band coverage: where the local part comes from, and the coverage window an honest band can reach"
WINDOW = (0.75, 0.99)
TARGET = 18   # of 20 lenses per group (issue 14)


def in_window_counts(p: np.ndarray) -> np.ndarray:
    """Poisson-binomial: the probability of k lenses inside the window, k = 0..n, given each lens's own
    probability ``p``."""
    dist = np.zeros(len(p) + 1)
    dist[0] = 1.0
    for q in np.asarray(p, float):
        dist[1:] = dist[1:] * (1.0 - q) + dist[:-1] * q
        dist[0] *= 1.0 - q
    return dist


def honest_window_probability(pooled: np.ndarray, window=WINDOW) -> dict:
    """Per-draw coverages of an exactly honest band -> probability inside / below / above the window."""
    c = np.asarray(pooled, float)
    return {"p_in": float(np.mean((c >= window[0]) & (c <= window[1]))), "p_below": float(np.mean(c < window[0])),
            "p_above": float(np.mean(c > window[1])), "abs_dev": float(np.mean(np.abs(c - c.mean())))}


def local_what_ifs(e: np.ndarray, band_var: np.ndarray, local_var: np.ndarray, plane: np.ndarray,
                   level: float = 0.9) -> dict:
    """Coverage of a Gaussian band (variance ``band_var``, centred where the error ``e`` is measured from) as
    stated and with its local part ``local_var`` changed: rescaled so its mean equals the mean square of the
    error's rest (``e`` less its least-squares fit on the columns of ``plane``), the same only narrowing, and
    removed. One channel's grid points."""
    from scipy.special import ndtri

    zq = float(ndtri(0.5 + 0.5 * level))
    rest = e - plane @ np.linalg.lstsq(plane, e, rcond=None)[0]
    other = band_var - local_var
    lm = float(np.mean(local_var))
    scale = float(np.mean(rest ** 2)) / lm if lm > 0 else 1.0
    inside = lambda v: float(np.mean(np.abs(e) <= zq * np.sqrt(np.clip(v, 0.0, None))))
    return {"stated": inside(band_var), "oracle": inside(other + scale * local_var),
            "oracle_narrow": inside(other + min(scale, 1.0) * local_var), "none": inside(other),
            "rest_um": float(np.sqrt(np.mean(rest ** 2))), "local_sd_um": math.sqrt(max(lm, 0.0))}


def lens_row(prof, lens: dict, window=WINDOW) -> dict:
    """One kept profile's row (see the module docstring)."""
    import bench_band_coverage as B
    from scipy.linalg import solve_triangular
    from scipy.special import ndtri
    from fieldcal.fit.selfcheck import coverage_draws
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import SURFACE_GRID_PX, _grid

    s = prof.surfaces
    d = s.discrepancy
    zs = float(s.z_scale_um)
    w, h = prof.image_size_px
    truth = TruthProfile(lens["spec"], w, h, z_ref_um=prof.z_ref_um, optics=lens.get("optics", "geometric"),
                         fs_cyc_per_mm=lens["fs"])
    X, Y = _grid(w, h, SURFACE_GRID_PX)
    xh, yh = s.geometry.normalise(X.ravel(), Y.ravel())
    A = np.column_stack([np.ones(xh.size), xh, yh])
    P = A @ np.linalg.pinv(A)
    zq = float(ndtri(0.95))
    measured = B.evaluate(prof, lens)
    pooled, _, _ = coverage_draws(prof, 1.0)
    row = {"measured": measured["coverage"], "rms_um": measured["rms_um"], "hw_um": measured["hw_um"],
           **honest_window_probability(pooled, window), "model": s.model.name,
           "members": len((s.diagnostics.get("model_average") or {}).get("members") or []) or 1,
           "band_scale": float(s.band_scale), "channels": []}
    cov = {k: [] for k in ("stated", "oracle", "oracle_narrow", "none")}
    bare = d.without_nuisances() if d is not None else None
    for ci, ch in enumerate(s.channels):
        zt = np.asarray(truth.best_focus_um(X, Y, ch), float).ravel()
        zt = (zt + 0.5 * lens["stage_backlash_um"]) / (1.0 + lens["stage_scale_error"])
        zp = np.asarray(prof.best_focus_um(X, Y, ch), float).ravel()
        lo, hi = (np.asarray(a, float).ravel() for a in prof.best_focus_interval_um(X, Y, ch))
        zc = 0.5 * (lo + hi)
        band_var = ((hi - lo) / (2.0 * zq)) ** 2
        terms = B.stated_field_terms_um2(prof, ch, xh, yh, X.ravel(), Y.ravel())
        zsmp, _ = s._eval(s.samples, X.ravel(), Y.ravel(), ch, model=s.sample_model)
        z0, _ = s._eval(s.theta_map, X.ravel(), Y.ravel(), ch)
        dz = (zsmp - z0) * float(s.band_scale) * zs
        plane_var = np.var(P @ dz.T, axis=1)
        local = np.clip(band_var - sum(terms.values()) - plane_var, 0.0, None)
        wi = local_what_ifs(zc - zt, band_var, local, A)
        for k in cov:
            cov[k].append(wi[k])
        c = {"ch": ch, "rest_band_centre_um": wi["rest_um"], "local_sd_um": wi["local_sd_um"]}
        ep = zp - zt
        c["rest_reported_um"] = float(np.sqrt(np.mean((ep - P @ ep) ** 2)))
        off = dz.mean(axis=0)
        c["average_offset_um"] = float(np.sqrt(np.mean((off - P @ off) ** 2)))
        dzr = dz - (P @ dz.T).T
        c["samples_var"] = float(np.mean(np.var(dzr, axis=0)))
        if d is not None:
            covered = s.model_average_covered(zsmp, xh, yh, ci)
            c2 = float(s.band_scale) ** 2 * zs * zs
            full = bare.predict(xh, yh, ci, covered=covered)[1]
            share = lambda dd: float(np.mean(full - dd.predict(xh, yh, ci, covered=covered)[1])) * c2
            c["jackknife_var"] = share(replace(bare, jk_cov=None, _cache={}))
            c["misfit_var"] = share(replace(bare, misfit_scale=0.0, _cache={}))
            c["gp_var"] = share(replace(bare, tau=np.full_like(bare.tau, 1e-12), _cache={}))
            spacing = float(d.diagnostics.get("tile_spacing") or 0.0)
            m = d.ch_index == ci
            c["ell_spacings"] = d.length_scale / spacing if spacing > 0 else float("nan")
            c["gp_identified"] = d.gp_identified()
            c["tau_over_tile_sd"] = float(d.tau[ci] / math.sqrt(float(np.median(d.noise_var[m])))) if m.any() else 0.0
            st = d._state()
            if ci in st["chol"]:
                V = solve_triangular(st["chol"][ci][0], d._kernel_rows(xh, yh, ci).T, lower=True)
                gp = np.clip(d.tau[ci] ** 2 - np.sum(V * V, axis=0), 0.0, None)
                c["gp_band_sd_um"] = float(math.sqrt(float(np.mean(gp)) * d.gp_identified())) * zs * float(s.band_scale)
            else:
                c["gp_band_sd_um"] = 0.0
        row["channels"].append(c)
    row.update({f"cov_{k}": float(np.mean(v)) for k, v in cov.items()})
    return row


def run(keep: Path, efforts, lenses, jsonl: Path | None, window=WINDOW) -> list[dict]:
    from fieldcal.profile.lens_profile import LensProfile
    from fieldcal.simulate.lens import LensSpec

    rows = []
    for k in lenses:
        meta = keep / f"lens{k:02d}.meta.json"
        if not meta.exists():
            continue
        lens = {**json.loads(meta.read_text()), "spec": LensSpec.load(keep / f"lens{k:02d}.spec.json")}
        for eff in efforts:
            pp = keep / f"lens{k:02d}-{eff}.json"
            if not pp.exists():
                continue
            r = {"lens": k, "effort": eff, "optics": lens["optics"], "asymmetric": lens["asymmetric"],
                 **lens_row(LensProfile.load(pp), lens, window)}
            rows.append(r)
            if jsonl:
                with open(jsonl, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
            print(f"lens {k:2d} {eff:8s} {lens['optics'][:4]} measured {r['measured']:.2f} honest P(in) "
                  f"{r['p_in']:.2f} oracle {r['cov_oracle']:.2f} none {r['cov_none']:.2f}", flush=True)
    return rows


def _window_class(c: float, window=WINDOW) -> str:
    return "below" if c < window[0] else "above" if c > window[1] else "in"


def _table(rows, cols):
    """md_table with columns given as (key, header, format)."""
    return md_table(rows, [(h, k, f) for k, h, f in cols])


def summary_tables(rows: list[dict], window=WINDOW) -> str:
    groups = []
    for eff in ("quick", "standard"):
        for optics in ("geometric", "wave"):
            rs = [r for r in rows if r["effort"] == eff and r["optics"] == optics]
            if not rs:
                continue
            counts = lambda key: [_window_class(r[key], window) for r in rs]
            fmt = lambda key: "{} / {} / {}".format(*(counts(key).count(c) for c in ("in", "below", "above")))
            dist = in_window_counts(np.array([r["p_in"] for r in rs]))
            need = min(TARGET, len(rs))
            groups.append({"effort": eff, "optics": optics, "n": len(rs), "measured": fmt("measured"),
                           "honest": "{:.1f} / {:.1f} / {:.1f}".format(sum(r["p_in"] for r in rs),
                                                                       sum(r["p_below"] for r in rs),
                                                                       sum(r["p_above"] for r in rs)),
                           "p_target": float(dist[need:].sum()),
                           "oracle": fmt("cov_oracle"), "narrow": fmt("cov_oracle_narrow"), "none": fmt("cov_none"),
                           "mean_measured": float(np.mean([r["measured"] for r in rs])),
                           "mean_none": float(np.mean([r["cov_none"] for r in rs])),
                           "abs_dev": float(np.mean([r["abs_dev"] for r in rs]))})
    lo, hi = window
    t1 = _table(groups, [("effort", "effort", "s"), ("optics", "optics", "s"), ("n", "lenses", "d"),
                           ("measured", f"measured: in {lo}-{hi} / below / above", "s"),
                           ("honest", "exactly honest band, own error model: expected in / below / above", "s"),
                           ("p_target", f"P(>= {TARGET} of 20 in) for an honest band", ".1e"),
                           ("oracle", "local part = true rest: in / below / above", "s"),
                           ("narrow", "same, narrower only", "s"), ("none", "no local part", "s"),
                           ("mean_measured", "mean coverage", ".3f"), ("mean_none", "mean, no local part", ".3f"),
                           ("abs_dev", "mean abs(coverage - expected), honest band", ".3f")])
    chans = []
    for eff in ("quick", "standard"):
        for cls in ("above", "in", "below"):
            cs = [(r, c) for r in rows if r["effort"] == eff and _window_class(r["measured"], window) == cls
                  for c in r["channels"] if "ell_spacings" in c]
            if not cs:
                continue
            tot = np.array([c["samples_var"] + c["jackknife_var"] + c["misfit_var"] + c["gp_var"] for _, c in cs])
            tot = np.maximum(tot, 1e-30)
            med = lambda key: float(np.median([c[key] for _, c in cs]))
            sh = lambda key: float(np.median(np.array([c[key] for _, c in cs]) / tot))
            chans.append({"effort": eff, "cls": cls, "n": f"{len({r['lens'] for r, _ in cs})} / {len(cs)}",
                          "bound": float(np.mean([c["ell_spacings"] < 0.55 for _, c in cs])),
                          "one": float(np.mean([c["ell_spacings"] >= 1.0 for _, c in cs])),
                          "tau": med("tau_over_tile_sd"), "gp_sd": med("gp_band_sd_um"),
                          "local": med("local_sd_um"), "rest_rep": med("rest_reported_um"),
                          "rest_c": med("rest_band_centre_um"), "off": med("average_offset_um"),
                          "s_smp": sh("samples_var"), "s_jk": sh("jackknife_var"), "s_mis": sh("misfit_var"),
                          "s_gp": sh("gp_var")})
    t2 = _table(chans, [("effort", "effort", "s"), ("cls", "measured coverage", "s"),
                          ("n", "lenses / lens x channels", "s"),
                          ("bound", "GP length at its lower bound (0.5 spacing)", ".2f"),
                          ("one", "GP length >= 1 spacing", ".2f"), ("tau", "median GP tau / tile noise sd", ".2f"),
                          ("gp_sd", "median GP sd in the band (µm)", ".3f"),
                          ("local", "median stated local sd (µm)", ".3f"),
                          ("rest_rep", "median rest about the reported surface (µm)", ".3f"),
                          ("rest_c", "median rest about the band's centre (µm)", ".3f"),
                          ("off", "median model-average centre offset, non-plane (µm)", ".3f"),
                          ("s_smp", "share: posterior samples (non-plane)", ".2f"),
                          ("s_jk", "share: jackknife excess", ".2f"), ("s_mis", "share: misfit", ".2f"),
                          ("s_gp", "share: GP", ".2f")])
    return "\n".join(t1) + "\n\n" + "\n".join(t2) + "\n"


SYNTHETIC_VARIANTS = ("as built", "no common mode", "no jackknife", "no misfit", "chosen model only",
                      "chosen model only, no misfit", "chosen model only, none of the three")


def _variant(fit, name: str):
    """A copy of a SurfaceFit with band terms taken out (the surface itself unchanged)."""
    import copy

    f = copy.copy(fit)
    d = fit.discrepancy
    none = "none of the three" in name
    f.discrepancy = replace(d, _cache={},
                            common_sd=np.zeros_like(d.common_sd) if ("common" in name or none) and
                            d.common_sd is not None else d.common_sd,
                            jk_cov=None if ("jackknife" in name or none) else d.jk_cov,
                            misfit_scale=0.0 if ("misfit" in name or none) else d.misfit_scale)
    ma = fit.diagnostics.get("model_average") or {}
    members = ma.get("members") or []
    if "chosen" in name and len(members) > 1:
        # the chosen model's own posterior: the first member's share of the samples (select.fit_surfaces)
        from fieldcal.fit.posterior import MAX_SAMPLES
        f.samples = fit.samples[:max(2, int(round(MAX_SAMPLES * members[0]["weight"])))]
        f.diagnostics = {**fit.diagnostics, "model_average": {**ma, "members": members[:1]}}
    return f


def synthetic(n: int, effort: str = "quick", window=WINDOW) -> str:
    """Lenses whose surface the model family holds (``synthetic_tiles``: polynomial truth, white tile noise), one
    channel, 9 x 7 tiles: per-lens coverage of the band as built and with terms taken out."""
    from fieldcal.fit import fit_surfaces
    from fieldcal.fit.synthetic import field_points, random_lens, synthetic_tiles

    res = {v: [] for v in SYNTHETIC_VARIANTS}
    for k in range(n):
        rng = np.random.default_rng(500 + k)
        tiles, geom, truth = synthetic_tiles(random_lens(rng, channels=("G",)), rng, nx=9, ny=7,
                                             sigma_um=(0.5, 1.0), directional=False)
        fit = fit_surfaces(tiles, geom, effort=effort, seed=0, quiet=True)
        x, y = field_points(fit.geometry, 15)
        z = truth.best_focus_um(x, y, "G")
        rms = float(np.sqrt(np.mean((fit.predict(x, y, "G") - z) ** 2)))
        for v in SYNTHETIC_VARIANTS:
            lo, hi = _variant(fit, v).interval(x, y, "G", 0.9)
            res[v].append((float(np.mean((z >= lo) & (z <= hi))), float(np.mean(0.5 * (hi - lo))) / rms))
    out = []
    for v, a in res.items():
        a = np.array(a)
        cls = [_window_class(c, window) for c in a[:, 0]]
        out.append({"variant": v, "n": len(a), "mean": float(a[:, 0].mean()),
                    "counts": f"{cls.count('in')} / {cls.count('below')} / {cls.count('above')}",
                    "hw": float(np.median(a[:, 1]))})
    return "\n".join(_table(out, [("variant", "band", "s"), ("n", "lenses", "d"), ("mean", "mean coverage", ".3f"),
                                  ("counts", f"in {window[0]}-{window[1]} / below / above", "s"),
                                  ("hw", "median half-width / RMS error", ".2f")])) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", type=Path, help="a bench_band_coverage.py --keep folder (profiles, meta, specs)")
    ap.add_argument("--efforts", default="quick,standard")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--lenses", type=int, default=40)
    ap.add_argument("--jsonl", type=Path, default=None, help="append each row here")
    ap.add_argument("--from-jsonl", type=Path, default=None, help="render the tables from rows stored before")
    ap.add_argument("--docs", action="store_true", help="write the tables into docs/benchmarks.md")
    ap.add_argument("--section", default=None, help="with --docs: the section's key (bench_band_local_KEY)")
    ap.add_argument("--note", default="", help="text put under the heading")
    ap.add_argument("--synthetic", type=int, default=0,
                    help="instead: this many synthetic lenses the surface model holds (known truth), band terms "
                         "taken out one by one")
    args = ap.parse_args(argv)
    if args.synthetic:
        text = synthetic(args.synthetic)
        print(text)
        if args.docs:
            write_docs_section(f"{NAME}_{args.section}_synthetic" if args.section else f"{NAME}_synthetic",
                               f"### Synthetic lenses the surface model holds\n\n{text}")
        return 0
    if args.from_jsonl:
        if not args.from_jsonl.exists():
            ap.error(f"no such file: {args.from_jsonl}")
        rows = [json.loads(line) for line in args.from_jsonl.read_text().splitlines() if line.strip()]
    else:
        if args.keep is None or not args.keep.is_dir():
            ap.error("--keep must name a folder written by bench_band_coverage.py --keep (or use --from-jsonl)")
        rows = run(args.keep, args.efforts.split(","), range(args.start, args.start + args.lenses), args.jsonl)
    if not rows:
        print("no kept profiles found", file=sys.stderr)
        return 1
    text = summary_tables(rows)
    print(text)
    if args.docs:
        write_docs_section(f"{NAME}_{args.section}" if args.section else NAME,
                           f"## {TITLE}\n\n{args.note}\n\n{text}" if args.note else f"## {TITLE}\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
