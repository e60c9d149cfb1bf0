"""Slanted-edge best focus under spherical aberration on the clean room: where the per-channel piston came from
(issue 13, session 18).

The clean room's sa05-f2.8 edges read G and B about +0.16 µm above the truth over the whole field, R -0.06 µm. This
benchmark separates the pieces on the renderer's own exact curves (``benchmarks/cleanroom``: the pupil quadrature
of ``otf.otf_quadrature``, times the pixel aperture, as ``truth.py`` computes the truth):

* **Exact curves at the truth nodes** (every other render node, 8 x 6, per channel): MTF(fs) of the lens sampled at
  the stack's z, plain and as the e-SFR's Hamming window reads it (taps at fs, (1 +- r) fs over the DC term at
  r fs; r = 1 / (2 h fs), h the window's half-length), read by fieldcal's edge estimator
  (:func:`fieldcal.measure.esfr_focus.channel_shape` + ``analyse_tracks``, as ``edge_tiles.track_foci`` calls
  them with the channel's default wavelength), minus the curve's true peak.
* **Measured tracks** (``fieldcal.measure.mtf.measure_mtf`` on the cached edge stack; up to ``--max-tracks`` per
  channel): the measured MTF(fs) curves; the renderer's own curve at the track (its node OTFs from the pupil FFT,
  bilinear on the lag grid, blended bilinearly between nodes with its node shifts) through the window; the
  lens's exact curve there through the window; and plain. Each set read by the estimator against the lens's true
  peak at the track, and the measured-minus-rendered MTF(fs) by defocus.
* **One node** (the G track nearest the frame's middle truth node): the true peak, the peak of the windowed
  curve, and what the estimator reads with the ray law and with the exact law.

Run it once per tree (``PYTHONPATH=<tree>``: the script appends its own repository to ``sys.path``, so the
tree on PYTHONPATH supplies ``fieldcal``), then tabulate::

    PYTHONPATH=. python benchmarks/bench_edge_bias_s18.py --work W --label branch --jsonl eb.jsonl
    python benchmarks/bench_edge_bias_s18.py --from-jsonl eb.jsonl --docs --notes notes.md

W holds ``<lens>/truth.json`` and ``<lens>/stack-edges`` as ``bench_cleanroom.py`` writes them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))      # appended: a tree on PYTHONPATH supplies fieldcal (before/after runs)
sys.path.append(str(REPO / "benchmarks"))

NAME = "edge_bias_s18"
TITLE = ("Slanted-edge best focus under spherical aberration: the e-SFR window read with the ray law "
         "(bench_edge_bias_s18; session 18, issue 13)")
INTRO = ("**Question** (issue 13: 90 % bands covering 85–95 %). On the clean room the edge bands under-covered on "
         "the spherical-aberration lenses: sa05-f2.8 per channel R 0.90–1.00, G 0.38, B 0.33, the whole surface of "
         "G and B about +0.16 µm above the truth, R −0.06 µm; breath-sa03-f2 0.42–1.00 with +0.06 µm. Which piece "
         "makes a per-channel piston: the e-SFR's measured MTF(fs) through focus, or the peak estimator? Each table "
         "below reads curves with fieldcal's edge estimator (``esfr_focus.channel_shape`` + ``analyse_tracks``, as "
         "``edge_tiles.track_foci`` calls them) against the renderer's own truth (the peak of the lens's exact "
         "MTF(80 cy/mm) from the pupil quadrature, pixel aperture included); *tree* says whose fieldcal read them.")
FS_CY_PER_MM, Q = 80.0, 0.05
A0, A1 = 0.54, 0.23   # Hamming: a0 + 2 a1 cos(pi d / h)


def _lens(truth_meta):
    from benchmarks.cleanroom.lens import CleanLens
    d = dict(truth_meta["lens"])
    d["decentre_px"], d["channels"] = tuple(d["decentre_px"]), tuple(d["channels"])
    return CleanLens(**d)


class Curves:
    """The lens's exact and the renderer's own signed MTF at a point, direction and frequency, through focus."""

    def __init__(self, lens, z_mid_um: float):
        from benchmarks.cleanroom.render import Renderer
        self.L = lens
        self.ren = Renderer(lens, {}, z_mid_um=z_mid_um, node_px=25.0)   # no chart: node grid and shifts only
        self.fpx = FS_CY_PER_MM * 1e-3 * lens.pitch_um

    def lens(self, x, y, ch, z, f, d):
        from benchmarks.cleanroom.otf import otf_quadrature
        L = self.L
        lam = L.wavelength_um(ch)
        zt, zs = L.focus_ts_um(x, y, ch)
        k = 1.0 / (8.0 * L.f_number ** 2 * lam)
        o = otf_quadrature((z - zt) * k, (z - zs) * k, L.w040_um() / lam, L.radial_unit(x, y),
                           2.0 * (f / L.pitch_um) * lam * L.f_number, d, n=32)
        return o * np.sinc(f * d[0]) * np.sinc(f * d[1])

    def rendered(self, x, y, ch, z, f, d):
        from benchmarks.cleanroom.otf import otf_native, otf_on_frequencies
        from benchmarks.cleanroom.render import _hat
        L, ren = self.L, self.ren
        fc = L.pitch_um / (L.wavelength_um(ch) * L.f_number)
        kz = 1.0 / (8.0 * L.f_number ** 2 * L.wavelength_um(ch))
        out = np.zeros(z.size)
        for a in range(ren.xs.size):
            wx = float(_hat(np.array([x]), ren.xs, a)[0])
            for b in range(ren.ys.size):
                wy = float(_hat(np.array([y]), ren.ys, b)[0])
                if wx * wy <= 0:
                    continue
                dt, ds = ren._blend_shift[ch][b, a]
                for i, zi in enumerate(z):
                    wt, ws, w040 = L.pupil_coefficients_waves(ren.xs[a], ren.ys[b], ch, zi)
                    nat = otf_native(wt + dt * kz, ws + ds * kz, w040, L.radial_unit(ren.xs[a], ren.ys[b]), ren.n_pupil)
                    out[i] += wx * wy * float(otf_on_frequencies(nat, ren.n_pupil, fc, np.array([f * d[0]]),
                                                                 np.array([f * d[1]]))[0])
        return out * np.sinc(f * d[0]) * np.sinc(f * d[1])

    def windowed(self, fn, r):
        f = self.fpx
        return np.abs((A0 * fn(f) + A1 * (fn(f * (1 + r)) + fn(f * (1 - r)))) / (A0 + 2 * A1 * fn(f * r)))

    def true_peak(self, x, y, ch, d):
        from benchmarks.cleanroom.truth import through_focus_peak
        L = self.L
        guess = 0.5 * sum(L.focus_ts_um(x, y, ch)) - 4.0 * L.f_number ** 2 * L.w040_um()
        return through_focus_peak(lambda q: np.abs(self.lens(x, y, ch, np.atleast_1d(q), self.fpx, d)), guess,
                                  30.0 + abs(guess - 0.5 * sum(L.focus_ts_um(x, y, ch))), Q, 1.0)["z_best_um"]


def read(tracks, ch, r):
    """fieldcal's edge estimator on (z, MTF(fs)) tracks: best foci, and the pooled shape's s and law."""
    from fieldcal.measure.esfr_focus import analyse_tracks, channel_shape
    from fieldcal.optics.defocus import default_wavelength_nm
    shape = channel_shape(tracks, Q, fs_cyc_per_um=FS_CY_PER_MM * 1e-3,
                          wavelength_um=default_wavelength_nm(ch) * 1e-3, window_r=r)
    res, _ = analyse_tracks(tracks, Q, shape=shape)
    return (np.array([t.z_best_um for t in res]), float(shape.s), bool(shape.selected),
            "wave" if math.isfinite(shape.nu) else "ray")


def run_lens(work: Path, name: str, channels, max_tracks: int, label: str, log) -> list[dict]:
    from fieldcal.measure.esfr_focus import window_r_of
    meta = json.loads((work / name / "truth.json").read_text())
    L = _lens(meta)
    z = np.asarray(meta["z_um"], dtype=np.float64)
    step = float(meta["step_um"])
    cv = Curves(L, float(z[(z.size - 1) // 2]))
    cache = work / name / "s18-mtf.npz"
    if cache.exists():
        recs = list(np.load(cache, allow_pickle=True)["recs"])
    else:
        from fieldcal.measure.mtf import measure_mtf
        res = measure_mtf(str(work / name / "stack-edges"))
        vals = res.mtf_at(cv.fpx)
        recs = []
        for e, v in zip(res.edges, vals):
            if e.get("track") is None:
                continue
            qd = e["quality"] or {}
            recs.append(dict(track=int(e["track"]), channel=str(e["channel"]), z=float(e["z_um"]),
                             x=float(e["x_px"]), y=float(e["y_px"]), ang=float(e["angle_deg"]),
                             ok=bool(qd.get("ok", True)), v=float(v),
                             h=float(qd.get("half_width_px") or math.nan)
                             * math.cos(math.radians(float(qd.get("slant_deg") or 0.0)))))
        np.savez(cache, recs=np.array(recs, dtype=object))
    rows = []
    for ch in channels:
        t0, c0 = time.time(), time.process_time()
        by: dict = {}
        for r in recs:
            if r["channel"] == ch and r["ok"] and np.isfinite(r["v"]):
                by.setdefault(r["track"], []).append(r)
        keys = sorted(k for k, v in by.items() if len(v) >= 9)
        h = float(np.nanmedian([r["h"] for k in keys for r in by[k]]))
        rw = window_r_of(h, cv.fpx)
        # exact curves at the truth nodes (axis-near edges: the frequency along x)
        node_tracks = {"plain": [], "window": []}
        node_truth = []
        for y in meta["ys"]:
            for x in meta["xs"]:
                tz = cv.true_peak(x, y, ch, (1.0, 0.0))
                keep = np.abs(z - tz) < 10 * step
                zz = z[keep]
                node_tracks["plain"].append((zz, np.abs(cv.lens(x, y, ch, zz, cv.fpx, (1.0, 0.0)))))
                node_tracks["window"].append((zz, cv.windowed(lambda f: cv.lens(x, y, ch, zz, f, (1.0, 0.0)), rw)))
                node_truth.append(tz)
        node_truth = np.array(node_truth)
        row = {"label": label, "lens": name, "channel": ch, "step_um": step, "window_r": rw,
               "nu": FS_CY_PER_MM * 1e-3 * L.wavelength_um(ch) * L.f_number,
               "s_true": 16 * math.pi * FS_CY_PER_MM * 1e-3 * L.f_number * L.w040_um()}
        for kind, tr in node_tracks.items():
            zb, s, sel, law = read(tr, ch, rw if kind == "window" else 0.0)
            e = zb - node_truth
            row[f"nodes_{kind}"] = {"mean_um": float(np.nanmean(e)), "sd_um": float(np.nanstd(e)), "s": s,
                                    "selected": sel, "law": law, "n": int(np.isfinite(e).sum())}
        # measured tracks and the exact curves at each
        rng = np.random.default_rng(0)
        pick = keys if len(keys) <= max_tracks else sorted(rng.choice(keys, max_tracks, replace=False).tolist())
        sets = {"measured": [], "rendered_window": [], "lens_window": [], "lens": []}
        truths, diffs = [], []
        for k in pick:
            rr = sorted(by[k], key=lambda r: r["z"])
            zz = np.array([r["z"] for r in rr])
            x, y = float(np.median([r["x"] for r in rr])), float(np.median([r["y"] for r in rr]))
            a = math.radians(float(np.median([r["ang"] for r in rr])))
            d = (abs(math.sin(a)), abs(math.cos(a)))   # the edge normal (direction (cos a, sin a) along the edge)
            tz = cv.true_peak(x, y, ch, d)
            rendered = cv.windowed(lambda f: cv.rendered(x, y, ch, zz, f, d), rw)
            lensw = cv.windowed(lambda f: cv.lens(x, y, ch, zz, f, d), rw)
            v = np.array([r["v"] for r in rr])
            sets["measured"].append((zz, v))
            sets["rendered_window"].append((zz, rendered))
            sets["lens_window"].append((zz, lensw))
            sets["lens"].append((zz, np.abs(cv.lens(x, y, ch, zz, cv.fpx, d))))
            truths.append(tz)
            diffs.append(np.stack([(zz - tz) / step, v - rendered, rendered - lensw]))
        truths = np.array(truths)
        for kind, tr in sets.items():
            zb, s, sel, law = read(tr, ch, 0.0 if kind == "lens" else rw)
            e = zb - truths
            n = int(np.isfinite(e).sum())
            row[f"tracks_{kind}"] = {"mean_um": float(np.nanmean(e)), "sem_um": float(np.nanstd(e) / math.sqrt(max(n, 1))),
                                     "s": s, "selected": sel, "law": law, "n": n}
        D = np.concatenate(diffs, axis=1)
        row["by_defocus"] = []
        for lo in range(-4, 4):
            m = (D[0] >= lo) & (D[0] < lo + 1)
            if m.any():
                row["by_defocus"].append([lo, float(np.mean(D[1][m])), float(np.std(D[1][m]) / math.sqrt(m.sum())),
                                          float(np.mean(D[2][m])), int(m.sum())])
        # one node: the track nearest the middle truth node
        xm, ym = meta["xs"][len(meta["xs"]) // 2], meta["ys"][len(meta["ys"]) // 2]
        j = int(np.argmin([(float(np.median([r["x"] for r in by[k]])) - xm) ** 2
                           + (float(np.median([r["y"] for r in by[k]])) - ym) ** 2 for k in pick]))
        zz, v = sets["measured"][j]
        x, y = float(np.median([r["x"] for r in by[pick[j]]])), float(np.median([r["y"] for r in by[pick[j]]]))
        fine = np.linspace(truths[j] - 3 * step, truths[j] + 3 * step, 601)
        wf = cv.windowed(lambda f: cv.lens(x, y, ch, fine, f, (1.0, 0.0)), rw)
        row["one_node"] = {"x_px": x, "y_px": y, "true_peak_um": float(truths[j]),
                           "windowed_peak_minus_true_um": float(fine[int(np.argmax(wf))] - truths[j]),
                           "read_measured_um": float(read(sets["measured"], ch, rw)[0][j] - truths[j])}
        row["cpu_s"], row["wall_s"] = time.process_time() - c0, time.time() - t0
        log(f"{label} {name} {ch}: nodes plain {row['nodes_plain']['mean_um']:+.3f} window "
            f"{row['nodes_window']['mean_um']:+.3f} µm ({row['nodes_window']['law']}, s {row['nodes_window']['s']:+.2f}"
            f" / true {-row['s_true']:+.2f}); tracks measured {row['tracks_measured']['mean_um']:+.3f} ± "
            f"{row['tracks_measured']['sem_um']:.3f} rendered {row['tracks_rendered_window']['mean_um']:+.3f} lens "
            f"{row['tracks_lens_window']['mean_um']:+.3f} µm; {row['wall_s']:.0f} s wall, {row['cpu_s']:.0f} s CPU")
        rows.append(row)
    return rows


def tables(rows) -> str:
    out = ["Exact curves at the truth nodes (48 per channel), read by the estimator (mean error µm, and in steps):", "",
           "| tree | lens | ch | nu = fs λ N | s true | plain: law, s, error | through the window: law, s, error µm (step) |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        p, w = r["nodes_plain"], r["nodes_window"]
        out.append(f"| {r['label']} | {r['lens']} | {r['channel']} | {r['nu']:.3f} | {-r['s_true']:+.2f} | {p['law']}, "
                   f"{p['s']:+.2f}, {p['mean_um']:+.3f} | {w['law']}, {w['s']:+.2f}, {w['mean_um']:+.3f} "
                   f"({w['mean_um'] / r['step_um']:+.4f}) |")
    out += ["", "Measured tracks (random sample per channel) and the exact curves at the same tracks, read by the "
            "estimator (mean error against the lens's true peak at the track, µm ± sem):", "",
            "| tree | lens | ch | tracks | measured (e-SFR) | renderer's curve, windowed | lens's curve, windowed | "
            "lens's curve, plain | law (measured), s |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        t = {k: r[f"tracks_{k}"] for k in ("measured", "rendered_window", "lens_window", "lens")}
        out.append(f"| {r['label']} | {r['lens']} | {r['channel']} | {t['measured']['n']} | "
                   + " | ".join(f"{t[k]['mean_um']:+.3f} ± {t[k]['sem_um']:.3f}" for k in t)
                   + f" | {t['measured']['law']}, {t['measured']['s']:+.2f} |")
    out += ["", "Measured minus the renderer's windowed MTF(fs) / the renderer's minus the lens's (both windowed), "
            "by defocus from the true peak (pooled over the sampled tracks; curves, not readings: the same in every "
            "tree):", "",
            "| lens | ch | " + " | ".join(f"[{lo:+d}, {lo + 1:+d}) steps" for lo in range(-4, 4)) + " |",
            "| --- | --- | " + " | ".join("---" for _ in range(8)) + " |"]
    seen = set()
    for r in rows:
        if (r["lens"], r["channel"]) in seen:
            continue
        seen.add((r["lens"], r["channel"]))
        cells = {b[0]: f"{b[1]:+.4f} / {b[3]:+.4f}" for b in r["by_defocus"]}
        out.append(f"| {r['lens']} | {r['channel']} | " + " | ".join(cells.get(lo, "—") for lo in range(-4, 4)) + " |")
    out += ["", "One node (the track nearest the middle truth node): the window's own shift of the peak, and the "
            "estimator's reading of the measured curve there:", "",
            "| tree | lens | ch | track at (x, y) px | true peak µm | windowed curve's peak − true µm | measured, read − true µm |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        o = r["one_node"]
        out.append(f"| {r['label']} | {r['lens']} | {r['channel']} | ({o['x_px']:.0f}, {o['y_px']:.0f}) | "
                   f"{o['true_peak_um']:+.2f} | {o['windowed_peak_minus_true_um']:+.3f} | {o['read_measured_um']:+.3f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/s13edge/cr", help="folder of <lens>/truth.json and <lens>/stack-edges")
    ap.add_argument("--lenses", default="sa05-f2.8,breath-sa03-f2,sym-f4")
    ap.add_argument("--channels", default="R,G,B")
    ap.add_argument("--max-tracks", type=int, default=40)
    ap.add_argument("--label", default="this tree")
    ap.add_argument("--jsonl", default="", help="append one row per lens and channel here")
    ap.add_argument("--from-jsonl", default="", help="comma-separated jsonl files: only tabulate")
    ap.add_argument("--docs", action="store_true", help=f"write section bench_{NAME} into docs/benchmarks.md")
    ap.add_argument("--notes", default="", help="a markdown file appended to the docs section (the reading)")
    args = ap.parse_args(argv)

    def log(msg):
        print(time.strftime("%H:%M:%S"), msg, flush=True)

    rows = []
    if args.from_jsonl:
        for p in args.from_jsonl.split(","):
            rows += [json.loads(s) for s in Path(p).read_text().splitlines() if s.strip()]
    else:
        for name in args.lenses.split(","):
            for row in run_lens(Path(args.work), name, args.channels.split(","), args.max_tracks, args.label, log):
                rows.append(row)
                if args.jsonl:
                    with open(args.jsonl, "a") as f:
                        f.write(json.dumps(row) + "\n")
    text = tables(rows)
    print(text)
    if args.docs:
        from _common import write_docs_section
        body = f"## {TITLE}\n\n" + INTRO + "\n\n" + text + "\n"
        if args.notes:
            body += "\n" + Path(args.notes).read_text()
        write_docs_section(NAME, body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
