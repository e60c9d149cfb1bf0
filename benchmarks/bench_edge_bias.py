"""Where the slanted-edge best focus's field-wide bias comes from (issue 13): the closed form, one effect at a time.

The clean room's edge path read best focus above the truth on 5 of 6 lenses (sym-f4 +0.05 / +0.08 / +0.01 µm,
R/G/B). This benchmark builds the exact closed form of a slanted edge through focus
(:func:`fieldcal.measure.esfr_synth.through_focus_edge`: Gaussian x geometric defocus disc x pixel aperture, the
disc's diameter ``|z - z_focus| / (N p)`` at every frame, each row of the edge its own focus so that a field
curved along the edge is modelled) and runs fieldcal's own e-SFR core (:func:`fieldcal.measure.esfr.esfr_regions`,
the clean room's region: 13 rows, half-width 8 px) and the channel's through-focus estimator
(:func:`fieldcal.measure.esfr_focus.channel_shape` + ``analyse_tracks``, as ``edge_tiles.track_foci`` calls them)
on many edges (slants 4.5-9.5 degrees as on the clean room, sub-pixel positions, 4 sampling phases of the scan). Each case switches one
effect on; the truth is known exactly (the MTF(fs) of a row peaks where its disc vanishes), so every mean error is
the estimator's.

    python benchmarks/bench_edge_bias.py --jsonl cf.jsonl            # ~1 min
    python benchmarks/bench_edge_bias.py --from-jsonl cf.jsonl --docs --notes notes.md
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

BENCH_DIR = str(Path(__file__).resolve().parent)
sys.path.insert(0, BENCH_DIR)
from _common import md_table, write_docs_section  # noqa: E402

NAME = "edge_bias_s15"
TITLE = "Slanted-edge best focus: the closed form, one effect at a time (bench_edge_bias_s15; session 15, issue 13)"
F_NUMBER, PITCH_UM, FS_CY_PER_PX, STEP_UM, N_FRAMES = 4.0, 3.0, 0.24, 6.2, 31   # the clean room's sym-f4
PHASES = (0.13, 0.37, 0.61, 0.89)
SLANTS = (4.5, 5.0, 6.0, 7.0, 8.0, 9.5)   # the clean room's 5-95 % range; 13 rows at 3 deg is under one phase cycle
X_PHASES = (0.0, 0.25, 0.5, 0.75)
ROWS, WIDTH, HALF_PX = 13, 17, 8.0

CASES = (
    # name, through_focus_edge options, scan offset from the peak (steps)
    ("flat, noise-free, scan centred", {}, 0.0),
    ("scan 5.3 steps off the peak", {}, 5.3),
    ("noise sd 0.006 (SNR 100)", {"noise_sd": 0.006}, 0.0),
    ("noise sd 0.006, scan 5.3 steps off", {"noise_sd": 0.006}, 5.3),
    ("noise sd 0.012 (SNR 50)", {"noise_sd": 0.012}, 0.0),
    ("noise sd 0.012, scan 5.3 steps off (peak near the scan's upper end)", {"noise_sd": 0.012}, 5.3),
    ("noise sd 0.012, scan 5.3 steps off the other way", {"noise_sd": 0.012}, -5.3),
    ("gradient 0.4 µm/px along the edge", {"gradient_um_per_px": 0.4}, 0.0),
    ("curvature 0.0026 µm/px² along the edge (sym-f4)", {"curvature_um_per_px2": 0.0026}, 0.0),
    ("curvature 0.026 µm/px² along the edge (10x)", {"curvature_um_per_px2": 0.026}, 0.0),
    ("curvature -0.026 µm/px² along the edge", {"curvature_um_per_px2": -0.026}, 0.0),
    ("gradient 0.4 µm/px + curvature 0.026 µm/px²", {"gradient_um_per_px": 0.4, "curvature_um_per_px2": 0.026}, 0.0),
)


def run_case(opts: dict, offset_steps: float, phase: float, *, seed: int = 0) -> dict:
    """One channel of edges (every slant x sub-pixel position), its scan at ``phase`` of a step: per-track best
    focus minus the truth at the edge's reported position, and the parts the pipeline models."""
    from fieldcal.measure.edge_tiles import window_half_px  # noqa: F401  (the window as track_foci reads it)
    from fieldcal.measure.esfr import esfr_regions
    from fieldcal.measure.esfr_focus import analyse_tracks, channel_shape, window_r_of
    from fieldcal.measure.esfr_synth import edge_focus_rows, edge_mtf_fs_curve, through_focus_edge

    z = (np.arange(N_FRAMES) - (N_FRAMES - 1) / 2.0 + phase - offset_steps) * STEP_UM   # peak (z = 0) off-centre
    curves, exact, truths, windows, info = [], [], [], [], []
    k = 0
    for slant in SLANTS:
        for xp in X_PHASES:
            k += 1
            rois = through_focus_edge(z, z_focus_um=0.0, f_number=F_NUMBER, pitch_um=PITCH_UM, slant_deg=slant,
                                      rows=ROWS, width_px=WIDTH, x_phase_px=xp, seed=seed * 1000 + k, **opts)
            res = esfr_regions(rois, half_width_px=HALF_PX)
            v = np.array([np.interp(FS_CY_PER_PX, r.freq_cy_per_px, r.mtf[0]) if r.quality[0].ok else np.nan
                          for r in res])
            ok = np.isfinite(v)
            rows_used = int(np.median([r.quality[0].rows for r in res]))
            y_mid = np.array([float(r.y_mid[0]) for r in res])
            # where the pipeline says the peak was measured: records with MTF(fs) >= half the highest, weighted
            # by MTF(fs)^2 (edge_tiles.peak_position_px)
            use = ok & (v >= 0.5 * np.nanmax(v))
            w = v[use] ** 2
            y_peak = float(np.dot(w, y_mid[use]) / w.sum())
            t_peak = (y_peak - (ROWS - 1) / 2.0) / math.cos(math.radians(slant))
            g = float(opts.get("gradient_um_per_px", 0.0))
            c = float(opts.get("curvature_um_per_px2", 0.0))
            length = rows_used / math.cos(math.radians(slant))
            truths.append(g * t_peak + 0.5 * c * t_peak * t_peak)
            windows.append(c * length * length / 24.0)   # edge_tiles.edge_window_px: the modelled mean along it
            curves.append((z[ok], v[ok]))
            zf = edge_focus_rows(ROWS, z_focus_um=0.0, slant_deg=slant, gradient_um_per_px=g, curvature_um_per_px2=c)
            r0 = (ROWS - rows_used) // 2   # the rows the e-SFR kept (esfr: whole phase cycles, centred)
            exact.append((z, edge_mtf_fs_curve(z, FS_CY_PER_PX, f_number=F_NUMBER, pitch_um=PITCH_UM,
                                               slant_deg=slant, z_focus_rows_um=zf[r0:r0 + rows_used])))
            info.append((slant, xp, rows_used, y_peak))
    wr = window_r_of(HALF_PX, FS_CY_PER_PX)
    out = {}
    for label, cv in (("esfr", curves), ("exact", exact)):
        shape = channel_shape(cv, 0.05, fs_cyc_per_um=FS_CY_PER_PX / PITCH_UM, wavelength_um=0.54, window_r=wr)
        res, _ = analyse_tracks(cv, 0.05, shape=shape)
        zb = np.array([t.z_best_um for t in res])
        out[label] = zb.tolist()
    return {"truth_at_position_um": truths, "window_um": windows, "info": info, **out}


def summarise(rows: list[dict]) -> list[dict]:
    table = []
    for name, _, off in CASES:
        rr = [r for r in rows if r["case"] == name]
        if not rr:
            continue
        per_phase = {"esfr": [], "exact": [], "raw": []}
        for r in rr:
            t = np.asarray(r["truth_at_position_um"])
            wnd = np.asarray(r["window_um"])
            for lab in ("esfr", "exact"):
                e = np.asarray(r[lab], dtype=np.float64) - t - wnd   # after the pipeline's window term
                per_phase[lab].append(float(np.nanmean(e)))
            per_phase["raw"].append(float(np.nanmean(np.asarray(r["esfr"], dtype=np.float64))))
        e_all = np.concatenate([np.asarray(r["esfr"], float) - np.asarray(r["truth_at_position_um"])
                                - np.asarray(r["window_um"]) for r in rr])
        table.append({
            "case": name,
            "esfr_um": f"{np.mean(per_phase['esfr']):+.4f} ± {np.std(per_phase['esfr']) / math.sqrt(len(rr)):.4f}",
            "runs": len(rr),
            "esfr_step": f"{np.mean(per_phase['esfr']) / STEP_UM:+.4f}",
            "exact_um": f"{np.mean(per_phase['exact']):+.4f} ± {np.std(per_phase['exact']):.4f}",
            "raw_um": f"{np.mean(per_phase['raw']):+.4f}",
            "window_um": f"{np.mean([np.mean(r['window_um']) for r in rr]):+.4f}",
            "truth_pos_um": f"{np.mean([np.mean(r['truth_at_position_um']) for r in rr]):+.4f}",
            "rms_um": f"{np.sqrt(np.nanmean(e_all ** 2)):.3f}",
            "tracks": int(np.isfinite(e_all).sum()),
        })
    return table


COLUMNS = [("case", "case", ""), ("e-SFR curves: mean error (µm) ± sem over runs", "esfr_um", ""), ("runs", "runs", ""),
           ("(step)", "esfr_step", ""), ("exact curves, same estimator (µm)", "exact_um", ""),
           ("raw mean best focus (µm)", "raw_um", ""), ("window term c L²/24 (µm)", "window_um", ""),
           ("truth at the reported position (µm)", "truth_pos_um", ""), ("track RMS (µm)", "rms_um", ""),
           ("tracks", "tracks", "")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jsonl", default="", help="append one row per case and phase here")
    ap.add_argument("--from-jsonl", default="", help="comma-separated jsonl files: only tabulate")
    ap.add_argument("--cases", default="", help="comma-separated case indices (default: all)")
    ap.add_argument("--seeds", type=int, default=1, help="noise draws per case and phase (seeds 0..N-1)")
    ap.add_argument("--docs", action="store_true", help=f"write section bench_{NAME} into docs/benchmarks.md")
    ap.add_argument("--notes", default="", help="a markdown file appended to the docs section (the reading)")
    args = ap.parse_args(argv)
    rows = []
    if args.from_jsonl:
        for p in args.from_jsonl.split(","):
            rows += [json.loads(s) for s in Path(p).read_text().splitlines() if s.strip()]
    else:
        pick = [int(s) for s in args.cases.split(",") if s.strip()] or list(range(len(CASES)))
        for i in pick:
            name, opts, off = CASES[i]
            t0, c0 = time.time(), time.process_time()
            for ph in PHASES:
                for sd in range(args.seeds if opts.get("noise_sd") else 1):
                    r = run_case(opts, off, ph, seed=int(ph * 100) + 1000 * sd)
                    r.update(case=name, phase=ph, seed=sd)
                    rows.append(r)
                    if args.jsonl:
                        with open(args.jsonl, "a") as f:
                            f.write(json.dumps(r) + "\n")
            print(f"{name}: {time.time() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU", flush=True)
    table = summarise(rows)
    text = "\n".join(md_table(table, COLUMNS))
    print(text)
    if args.docs:
        files = args.from_jsonl or args.jsonl or "cf.jsonl"
        body = (f"## {TITLE}\n\n`python benchmarks/bench_edge_bias.py --from-jsonl {files} --docs"
                + (f" --notes {args.notes}" if args.notes else "") + "`\n\n"
                f"**Closed form** (`fieldcal.measure.esfr_synth.through_focus_edge`: F/{F_NUMBER:g}, {PITCH_UM:g} µm "
                f"pixels, Gaussian sigma 0.5 px x geometric defocus disc x pixel aperture; {N_FRAMES} frames "
                f"{STEP_UM:g} µm apart; fs = {FS_CY_PER_PX} cy/px (80 cy/mm); the clean room's region, {ROWS} rows "
                f"x {WIDTH} px, half-width {HALF_PX:g} px; {len(SLANTS)} slants {SLANTS[0]:g}-{SLANTS[-1]:g} deg x "
                f"{len(X_PHASES)} sub-pixel positions = {len(SLANTS) * len(X_PHASES)} tracks, pooled as one channel; "
                f"scan phases {', '.join(f'{p:g}' for p in PHASES)}. *Mean error*: the tracks' best focus minus the "
                "truth at the position the pipeline reports (`edge_tiles.peak_position_px`'s MTF²-weighted row) "
                "minus the window term the fit removes (`edge_window_px`: c L²/24), i.e. what would reach the "
                "surface; *exact curves*: the same estimator on the exact MTF(fs) of the rendered edge (the mean of "
                "its rows' OTFs), so the difference is the e-SFR's):\n\n" + text + "\n")
        if args.notes:
            body += "\n" + Path(args.notes).read_text()
        write_docs_section(NAME, body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
