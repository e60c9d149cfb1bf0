"""Scenes with depth: fieldcal's depth from focus against the oracle and align_image_stack + enfuse.

For each depth layout of :mod:`fieldcal.simulate.depth` (steps, slope, thin bars, a relief) the paper's triplet
renders a colour stack through the scene's depth (6 focus tolerances) plus the field curvature, one frame every
``--step`` focus tolerances. Every method composites the same frames, registered by the same geometry (the
lens's truth):

* ``oracle``: the compositor with each pixel's true best focus (surface + depth): the nearest frame, blended
  across seams;
* ``oracle + Wiener``: the true best focus through dff's own combination (occlusion-aware best focus, the
  multi-frame Wiener filter of :mod:`fieldcal.composite.depth_wiener`): what dff would reach with a perfect depth;
* ``dff``: ``composite_stack(method="dff")`` (``depth="auto"``: the scene is found to have depth, best focus per
  pixel);
* ``hybrid``: ``composite_stack(method="hybrid")`` (the profile where the data agree with it, the data elsewhere);
* ``smooth surface``: ``composite_stack(method="dff", depth="flat")`` (the surface fit alone);
* ``focus-stack``: focus-stack's merge (``benchmarks/focus_stack_ref.py``, re-implemented from its sources: all
  frames per complex-wavelet coefficient, consistency filters, denoise, colour reassignment) on the same
  registered frames scaled to 8 bits (it reads 8-bit frames), scaled back;
* ``enfuse``: enfuse's contrast-weighted hard mask (``--hard-mask``, exposure and saturation weights 0) on the
  same registered frames (``apt-get install enfuse``; skipped when it is not installed).

PSNR is against the truth's all-in-focus image (border of 12 px left out); the halo is
:func:`fieldcal.simulate.depth.halo_width_px` (depth edges of > 5 µm; 1 = only the edge band itself).

Run: ``python benchmarks/bench_depth_scenes.py [--size 320x240] [--step 1.5] [--write]`` (``--write`` puts the
table into docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fieldcal.composite.api import composite_stack  # noqa: E402
from fieldcal.composite.depth_wiener import occlusion_focus_um, wiener_composite  # noqa: E402
from fieldcal.composite.stack_profile import blend_kernel, composite_with_map  # noqa: E402
from fieldcal.composite.warp import warp_frame_by_profile  # noqa: E402
from fieldcal.formats.frames import ArrayStack  # noqa: E402
from fieldcal.simulate.depth import LAYOUTS, DepthRenderer, depth_scene, halo_width_px  # noqa: E402
from fieldcal.simulate.lens import LensSpec  # noqa: E402
from fieldcal.simulate.truth import TruthProfile  # noqa: E402

sys.path.insert(0, str(REPO / "benchmarks"))
from focus_stack_ref import focus_stack  # noqa: E402

MARK_BEGIN = "<!-- bench_depth_scenes:begin -->"
MARK_END = "<!-- bench_depth_scenes:end -->"


def run_layout(layout: str, w: int, h: int, seed: int = 1, step: float = 1.5, noise: float = 1.0) -> dict:
    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json").with_sensor_size(w, h)
    if noise != 1.0:
        # `noise` times the sensor's noise at every level: shot noise through the full well, read noise directly
        sens = spec.sensor
        spec = dataclasses.replace(spec, sensor=dataclasses.replace(
            sens, full_well_e=sens.full_well_e / noise ** 2, read_noise_e=sens.read_noise_e * noise))
    fs = 0.25 / (spec.sensor.pixel_pitch_um * 1e-3)
    tol = min(spec.focus_tolerance_um(fs, 0.05, c) for c in spec.channel_names)
    scene = depth_scene(layout, w, h, 6 * tol, seed=seed)
    r = DepthRenderer(spec, scene, seed=seed + 1)
    lo, hi = spec.focus_range_um()
    z = np.arange(lo - tol, hi + 7 * tol, step * tol)
    st = ArrayStack([r.render(float(v)) for v in z], z, spec.channel_names,
                    black_level=spec.sensor.black_level_dn, white_level=spec.sensor.white_level_dn)
    truth = r.truth().astype(np.float64)
    white = float(spec.sensor.white_level_dn)
    prof = TruthProfile(spec, w, h)

    def psnr(img):
        a = np.asarray(img, np.float64)[12:-12, 12:-12, :3]
        return 10 * np.log10(white ** 2 / np.mean((a - truth[12:-12, 12:-12]) ** 2))

    def halo(img):
        return halo_width_px(img, truth, scene.depth_um, 5.0)

    xx, yy = np.meshgrid(np.arange(w), np.arange(h))
    zb = np.stack([r.best_focus_um(xx, yy, c) for c in spec.channel_names], -1).astype(np.float32)
    frames = np.arange(len(st))
    out = {"layout": layout, "frames": len(st)}
    out["oracle"] = composite_with_map(st, zb, blend_kernel(st, prof, frames, None, 0.05, 0.25), prof, frames,
                                       quiet=True)
    # the same oracle depth through dff's combination: occlusion-aware best focus, multi-frame Wiener
    zo = occlusion_focus_um(zb, 2.0 * spec.f_number * spec.sensor.pixel_pitch_um)
    ref = composite_with_map(st, zo, blend_kernel(st, prof, frames, None, 0.05, 0.25), prof, frames, quiet=True)
    out["oracle wiener"] = wiener_composite(st, zo, prof, frames, ref, geometry=prof, quiet=True)[0]
    t0 = time.perf_counter()
    auto = composite_stack(st, prof, method="dff", quiet=True)
    out["t_depth_s"] = time.perf_counter() - t0
    out["scene"] = auto.info["scene"]
    out["dff"] = auto.image
    out["hybrid"] = composite_stack(st, prof, method="hybrid", quiet=True).image
    out["smooth surface"] = composite_stack(st, prof, method="dff", depth="flat", quiet=True).image
    # the frames registered by the truth's geometry: enfuse's input, and dff's without a profile (no F-number, so
    # no Wiener filter: the depth map's blend plus the per-coefficient fine detail of composite/detail.py)
    registered = [warp_frame_by_profile(st, i, prof, w, h) for i in range(len(st))]
    reg = ArrayStack(registered, st.z_um, spec.channel_names, black_level=spec.sensor.black_level_dn,
                     white_level=spec.sensor.white_level_dn)
    free = composite_stack(reg, None, method="dff", register=False, quiet=True)
    out["dff, no profile"] = free.image
    # the defocus measured from the frames (composite/defocus_rate.py) against the lens's: a disc of |dz| / N
    out["rate"] = (free.info.get("defocus_rate", {}), step * tol / (spec.f_number * spec.sensor.pixel_pitch_um),
                   "wiener" in free.info)
    out["dff, no profile, defocus none"] = composite_stack(reg, None, method="dff", register=False,
                                                           measured_defocus=False, quiet=True).image
    out["dff, no profile, no fine detail"] = composite_stack(reg, None, method="dff", register=False,
                                                             fine_detail=False, quiet=True).image
    to8 = 255.0 / float(spec.sensor.white_level_dn)
    merged, _ = focus_stack([np.clip(np.rint(im * to8), 0, 255).astype(np.uint8) for im in registered])
    out["focus-stack"] = merged.astype(np.float32) / np.float32(to8)
    if shutil.which("enfuse"):
        d = Path(tempfile.mkdtemp())
        names = []
        for i, im in enumerate(registered):
            p = d / f"f{i:02d}.tif"
            tifffile.imwrite(p, np.clip(np.rint(im), 0, 65535).astype(np.uint16))
            names.append(str(p))
        subprocess.run(["enfuse", "--exposure-weight=0", "--saturation-weight=0", "--contrast-weight=1",
                        "--hard-mask", f"--output={d}/enfuse.tif", *names], check=True, capture_output=True)
        out["enfuse"] = tifffile.imread(d / "enfuse.tif")[..., :3]
        shutil.rmtree(d, ignore_errors=True)
    rows = {}
    for k in ("oracle", "oracle wiener", "dff", "hybrid", "smooth surface", "dff, no profile",
              "dff, no profile, defocus none", "dff, no profile, no fine detail", "focus-stack", "enfuse"):
        if k in out:
            rows[k] = (psnr(out[k]), halo(out[k]))
    out["rows"] = rows
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--step", type=float, default=1.5, help="frame spacing in focus tolerances")
    ap.add_argument("--noise", type=float, default=1.0, help="the sensor's noise times this (default 1)")
    ap.add_argument("--layouts", default=",".join(LAYOUTS), help="comma-separated layouts (default all)")
    ap.add_argument("--seed", type=int, default=1, help="the scene's and the renderer's seed (default 1)")
    ap.add_argument("--tag", default="", help="write into the section bench_depth_scenes:TAG (default: by step)")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.lower().split("x"))
    opts = ((f" --noise {a.noise:g}" if a.noise != 1.0 else "") + (f" --seed {a.seed}" if a.seed != 1 else "")
            + (f" --tag {a.tag}" if a.tag else ""))
    lines = [f"Scenes with depth ({w}x{h} px colour, paper triplet, one frame per {a.step:g} tolerances, depth 6 "
             f"tolerances, sensor noise x{a.noise:g}; `python benchmarks/bench_depth_scenes.py --size {w}x{h} "
             f"--step {a.step:g}{opts} --write`):", "",
             "| layout | frames | found | oracle dB | oracle + Wiener dB | dff dB | hybrid dB | smooth surface dB |"
             " enfuse dB | dff − enfuse | dff − oracle | dff − oracle + W | hybrid − enfuse | hybrid − oracle |"
             " hybrid − oracle + W | halo px (oracle / dff / hybrid / enfuse) | dff s |",
             "|" + " --- |" * 17]
    free = ["", "Without a profile (the same frames registered by the truth's geometry, no F-number): the blur "
                "disc's growth per frame measured from the frames (`fieldcal/composite/defocus_rate.py`) against "
                "the lens's (|dz| / N), fieldcal's default (the measured defocus's Wiener combination where it is "
                "reliable), `--defocus none` (the depth map's blend and the per-coefficient fine detail of "
                "`fieldcal/composite/detail.py`), that without the fine detail, and focus-stack's merge "
                "(`benchmarks/focus_stack_ref.py`, 8-bit frames: 8-bit rounding alone would cost nothing visible "
                "here, the truth rounded to 8 bits scores ~59 dB):", "",
            "| layout | disc px/frame measured (true) | Wiener | no profile dB | defocus none dB | no fine detail dB | "
            "focus-stack dB | no profile − enfuse | no profile − oracle | no profile − oracle + W | "
            "no profile − defocus none | no profile − focus-stack | "
            "halo px (no profile / defocus none / focus-stack) |", "|" + " --- |" * 13]
    for layout in a.layouts.split(","):
        r = run_layout(layout, w, h, seed=a.seed, step=a.step, noise=a.noise)
        R = r["rows"]
        enf = R.get("enfuse", (float("nan"), -1))
        o, ow, d, hy = R["oracle"], R["oracle wiener"], R["dff"], R["hybrid"]
        lines.append(f"| {layout} | {r['frames']} | {r['scene']} | {o[0]:.2f} | {ow[0]:.2f} | {d[0]:.2f} | "
                     f"{hy[0]:.2f} | {R['smooth surface'][0]:.2f} | {enf[0]:.2f} | {d[0] - enf[0]:+.2f} | "
                     f"{d[0] - o[0]:+.2f} | {d[0] - ow[0]:+.2f} | {hy[0] - enf[0]:+.2f} | {hy[0] - o[0]:+.2f} | "
                     f"{hy[0] - ow[0]:+.2f} | {o[1]} / {d[1]} / {hy[1]} / {enf[1]} | {r['t_depth_s']:.1f} |")
        print(lines[-1], flush=True)
        npf, nfd, fst = R["dff, no profile"], R["dff, no profile, no fine detail"], R["focus-stack"]
        non = R["dff, no profile, defocus none"]
        est, true_rate, used = r["rate"]
        measured = (f"{est['disc_px_per_step']:.2f} ± {est['sd_px_per_step']:.2f}" if est.get("reliable")
                    else f"unreliable: {est.get('reason', 'not measured')}")
        free.append(f"| {layout} | {measured} ({true_rate:.2f}) | {'yes' if used else 'no'} | {npf[0]:.2f} | "
                    f"{non[0]:.2f} | {nfd[0]:.2f} | {fst[0]:.2f} | {npf[0] - enf[0]:+.2f} | {npf[0] - o[0]:+.2f} | "
                    f"{npf[0] - ow[0]:+.2f} | {npf[0] - non[0]:+.2f} | {npf[0] - fst[0]:+.2f} | "
                    f"{npf[1]} / {non[1]} / {fst[1]} |")
        print(free[-1], flush=True)
    lines += free
    if a.write:
        doc = REPO / "docs" / "benchmarks.md"
        text = doc.read_text(encoding="utf-8")
        # one block per frame spacing; the default spacing's block keeps the original markers
        tag = f":{a.tag}" if a.tag else ("" if a.step == 1.5 else f":step{a.step:g}")
        begin, end = MARK_BEGIN.replace(":begin", tag + ":begin"), MARK_END.replace(":end", tag + ":end")
        block = "\n".join([begin, *lines, end])
        if begin in text:
            s, e = text.index(begin), text.index(end) + len(end)
            text = text[:s] + block + text[e:]
        elif MARK_END in text:
            e = text.index(MARK_END) + len(MARK_END)
            text = text[:e] + "\n\n" + block + text[e:]
        else:
            text = text.rstrip() + "\n\n## Scenes with depth\n\n" + block + "\n"
        doc.write_text(text, encoding="utf-8")

if __name__ == "__main__":
    main()
