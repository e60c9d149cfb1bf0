"""Absolute distortion, the Lensfun export, and ChArUco corners through focus (issue 16).

1. For a barrel lens (models/triplet-distortion.json: k1 -0.04 changing with z, k2, tangential p1 and p2, lateral
   colour) and a pincushion variant (k1 +0.03, k2 -0.004, no tangential terms), simulates a ChArUco stack,
   calibrates it and compares ``profile.distortion_px`` with the truth's at z_ref and at the exported position
   (the calibrated focus, clipped to the scan), per channel, inside the board's hull and over the whole frame;
   then exports the Lensfun entry and compares what lensfunpy applies (distortion + TCA, per channel) with the
   truth and with the profile.
2. Renders the board through a strongly curved field (the triplet's full curvature, same distortion) over
   +-200 µm and counts, per frame, the corners OpenCV's detector finds and those tracking adds, with their
   error against the truth; then the maps' worst RMS against the truth with and without tracking.

Run: ``PYTHONPATH=$PWD python benchmarks/bench_distortion.py [--size 480x360] [--write]`` (``--write`` replaces
the section between ``<!-- bench_distortion:start -->`` and ``<!-- bench_distortion:end -->`` of
docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, md_table, write_docs_section  # noqa: E402

import numpy as np  # noqa: E402


def lenses():
    from fieldcal.simulate.lens import Distortion, LensSpec
    barrel = LensSpec.load(REPO / "models" / "triplet-distortion.json")
    pin = dataclasses.replace(barrel, name="triplet-pincushion",
                              distortion=Distortion(k1=0.03, k2=-0.004, dk1_dz_per_um=-2e-5))
    return {"barrel + tangential": barrel, "pincushion": pin}


def _grid(size, step=4):
    w, h = size
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    return xs.astype(float), ys.astype(float)


def _lensfun(xml, size, focal, f_number):
    import lensfunpy as lf
    db = lf.Database(paths=[str(xml)], load_common=False, load_bundled=False)
    cam = db.find_cameras("fieldcal")[0]
    mod = lf.Modifier(db.find_lenses(cam)[0], cam.crop_factor, *size)
    mod.initialize(focal, f_number, 1.0, scale=1.0, flags=lf.ModifyFlags.DISTORTION | lf.ModifyFlags.TCA)
    return mod.apply_subpixel_geometry_distortion()


def absolute(size, work: Path) -> list[dict]:
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.profile.lensfun import _in_hull, lensfun_model, lensfun_xml
    from fieldcal.simulate.stackgen import simulate_stack
    from fieldcal.simulate.truth import TruthProfile
    z = np.arange(-120.0, 40.0 + 1e-9, 20.0)
    rows = []
    for label, spec in lenses().items():
        spec = spec.with_sensor_size(*size)
        st = simulate_stack(spec, work / spec.name, z, scene="charuco", seed=3, progress=False, overwrite=True)
        t0 = time.perf_counter()
        prof = calibrate(st, fs_cyc_per_mm=15.0, effort="quick", z_ref_um=0.0, quiet=True)
        t_cal = time.perf_counter() - t0
        prof.save(work / f"{spec.name}.json")
        truth = TruthProfile(spec, *size, z_ref_um=prof.z_ref_um)
        model = lensfun_model(prof)
        xml = work / f"{spec.name}.xml"
        xml.write_text(lensfun_xml(prof, model))
        xs, ys = _grid(size)
        ins = _in_hull(prof.absolute_distortion.hull_px, xs, ys)
        s = _lensfun(xml, size, prof.focal_length_mm, prof.f_number)[ys.astype(int), xs.astype(int)]
        for zname, zz in (("z_ref", prof.z_ref_um), ("export", model.z_um)):
            for i, c in enumerate(prof.channels):
                tx, ty = truth.distortion_px(xs, ys, zz, c)
                fx, fy = prof.distortion_px(xs, ys, zz, c)
                sx, sy = prof.distortion_sd_px(xs, ys, zz, c)
                e = np.hypot(fx - tx, fy - ty)
                row = {"lens": label, "z": f"{zname} ({zz:.1f} µm)", "channel": c,
                       "terms": " ".join(prof.absolute_distortion.terms), "hull": float(ins.mean()),
                       "truth_disp_px": float(np.hypot(tx - xs, ty - ys).max()),
                       "prof_in_max": float(e[ins].max()), "prof_in_rms": float(np.sqrt(np.mean(e[ins] ** 2))),
                       "prof_all_max": float(e.max()), "sd_in": float(np.mean(np.hypot(sx, sy)[ins])),
                       "calibrate_s": t_cal}
                if zname == "export":
                    el = np.hypot(s[..., i, 0] - tx, s[..., i, 1] - ty)
                    ep = np.hypot(s[..., i, 0] - fx, s[..., i, 1] - fy)
                    row.update({"lf_truth_in": float(el[ins].max()), "lf_prof_in": float(ep[ins].max()),
                                "lf_truth_all": float(el.max()), "lf_prof_all": float(ep.max())})
                rows.append(row)
    return rows


def blurred(size) -> tuple[list[dict], dict]:
    from fieldcal.charts.targets import charuco_image, charuco_spec
    from fieldcal.fit.geometry_map import fit_geometry_map
    from fieldcal.measure.charuco import charuco_correspondences
    from fieldcal.profile.lensfun import _in_hull
    from fieldcal.simulate.render import Renderer
    from fieldcal.simulate.truth import TruthProfile
    import cv2
    spec = lenses()["barrel + tangential"].with_sensor_size(*size)
    chs = tuple(dataclasses.replace(c, curvature_um=tuple(a / 0.3 for a in c.curvature_um)) for c in spec.channels)
    spec = dataclasses.replace(spec, channels=chs)   # the uncorrected triplet's full curvature
    z = np.linspace(-200.0, 200.0, 9)
    board = charuco_spec(*size)
    r = Renderer(spec, charuco_image(board), seed=1)
    frames = [r.render(float(zz)) for zz in z]
    ref = 4
    out, maps, fits = [], {}, {}
    for track in (False, True):
        stats = {}
        corr = charuco_correspondences(lambda k, ci: frames[k][..., ci], z, spec.channel_names, board, ref, "G",
                                       track_blurred=track, stats=stats)
        cp = board.corner_px(corr.point_id)
        tq = np.empty_like(corr.q_px)
        for c in spec.channel_names:
            for zz in np.unique(corr.z_um):
                m = (corr.channel == c) & (corr.z_um == zz)
                tq[m, 0], tq[m, 1] = spec.sensor_px(cp[m, 0], cp[m, 1], zz, c)
        err = np.hypot(*(corr.q_px - tq).T)
        if track:
            for k, zz in enumerate(z):
                m = (corr.z_um == zz) & (corr.channel == "G")
                out.append({"z": float(zz), "detected": stats["detected"].get(f"{k},G", 0),
                            "tracked": stats["tracked"].get(f"{k},G", 0), "of": board.n_corners,
                            "err_med": float(np.median(err[m])) if m.any() else float("nan"),
                            "err_max": float(err[m].max()) if m.any() else float("nan")})
        fits[track] = (fit_geometry_map(corr, z[ref], size),
                       cv2.convexHull(corr.p_px.astype(np.float32)).reshape(-1, 2), int(np.unique(corr.z_um).size))
    truth = TruthProfile(spec, z_ref_um=z[ref])
    xs, ys = np.meshgrid(np.linspace(0, size[0] - 1, 33), np.linspace(0, size[1] - 1, 25))
    small = _in_hull(fits[False][1], xs, ys)    # the field the detector alone measured: both maps compared there
    for track, (g, hull, n_frames) in fits.items():
        ins = _in_hull(hull, xs, ys)
        w_small = w_in = w_all = 0.0
        for zz in z:
            for c in spec.channel_names:
                tx, ty = truth.warp_px(xs, ys, zz, c)
                fx, fy = g.warp_px(xs, ys, zz, c)
                e2 = (tx - fx) ** 2 + (ty - fy) ** 2
                w_small = max(w_small, float(np.sqrt(np.mean(e2[small]))))
                w_in = max(w_in, float(np.sqrt(np.mean(e2[ins]))))
                w_all = max(w_all, float(np.sqrt(np.mean(e2))))
        maps["tracking" if track else "detector only"] = {"worst_small": w_small, "worst_in_hull": w_in,
                                                          "worst_frame": w_all, "hull": float(ins.mean()),
                                                          "frames_with_corners": n_frames}
    return out, maps


def section(a: list[dict], b: list[dict], maps: dict, size, cmd: str, load: str) -> str:
    w, h = size
    lines = ["## Absolute distortion, the Lensfun export, ChArUco through focus", "",
             f"`{cmd}` — {w}x{h} px; load average (1 min) {load} on the 2 shared cores (times inflated).", "",
             "**1. Absolute distortion and Lensfun.** ChArUco stack, scan -120 … 40 µm in 9 frames, z_ref 0, "
             "effort quick. `profile.distortion_px` against the truth's (undistorted -> distorted px, the "
             "reference channel's linear part at the centre taken out) inside the board's convex hull ('in') and "
             "over the whole frame ('all': beyond the hull the model extrapolates); lensfunpy applying the "
             "exported entry (distortion + TCA, per channel; fitted to the profile over the whole frame) against the "
             "truth and the profile. Target: Lensfun within 0.1 px of the profile (issue 16).", ""]
    lines += md_table(a, [("lens", "lens", ""), ("z", "z", ""), ("ch", "channel", ""), ("terms", "terms", ""),
                          ("hull frac", "hull", ".2f"), ("truth |D - 1| max (px)", "truth_disp_px", ".2f"),
                          ("profile err in, max (px)", "prof_in_max", ".3f"),
                          ("in, rms (px)", "prof_in_rms", ".3f"), ("all, max (px)", "prof_all_max", ".3f"),
                          ("mean sd in (px)", "sd_in", ".3f"),
                          ("Lensfun - truth in, max (px)", "lf_truth_in", ".3f"),
                          ("Lensfun - profile in, max (px)", "lf_prof_in", ".3f"),
                          ("Lensfun - truth all, max (px)", "lf_truth_all", ".3f"),
                          ("Lensfun - profile all, max (px)", "lf_prof_all", ".3f")])
    lines += ["", "**2. Corners through focus.** The same distortion with the triplet's full field curvature, "
              "-200 … 200 µm in 9 frames, reference frame z = 0, G channel; corner error against the truth.", ""]
    lines += md_table(b, [("z (µm)", "z", ".0f"), ("detected", "detected", "d"), ("tracked", "tracked", "d"),
                          ("of", "of", "d"), ("error median (px)", "err_med", ".3f"),
                          ("error max (px)", "err_max", ".3f")])
    lines += ["", "Maps fitted to these corners against the truth's `warp_px` (worst RMS over z and channel):", ""]
    lines += md_table([{"corners": k, **v} for k, v in maps.items()],
                      [("corners", "corners", ""), ("frames with corners", "frames_with_corners", "d"),
                       ("in the detector-only hull (px)", "worst_small", ".3f"),
                       ("in its own hull (px)", "worst_in_hull", ".3f"), ("its hull frac", "hull", ".2f"),
                       ("whole frame (px)", "worst_frame", ".3f")])
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="480x360", help="render size WxH (default 480x360)")
    ap.add_argument("--write", action="store_true", help="write the section of docs/benchmarks.md")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    os.environ.setdefault("FIELDCAL_PROGRESS", "0")
    load = f"{os.getloadavg()[0]:.1f}"
    with tempfile.TemporaryDirectory() as tmp:
        a = absolute(size, Path(tmp))
    b, maps = blurred(size)
    cmd = "PYTHONPATH=$PWD python benchmarks/bench_distortion.py" + (f" --size {args.size}" if args.size != "480x360"
                                                                    else "") + " --write"
    text = section(a, b, maps, size, cmd, load)
    print(text)
    if args.write:
        write_docs_section("distortion", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
