"""`fieldcal demo`: the whole pipeline on a built-in simulated lens, no hardware.

The demo runs the same commands a user would type, printing each one first, so that it doubles as a tour of the
CLI: simulate a chart stack → calibrate (with its report) → plan a stack and a sweep (with pictures) → capture
the scene at the planned positions through the simulated stage and camera → composite → compare with the
simulator's truth (PSNR and corner crops).
"""

from __future__ import annotations

import json
import shlex
import time
from pathlib import Path

import numpy as np

from ..errors import FieldcalError, ParameterError
from ..formats.atomic import save_figure, write_text
from . import add_parser

DEFAULT_LENS = Path(__file__).resolve().parents[2] / "models" / "triplet-uncorrected.json"


def register(sub):
    p = add_parser(sub, "demo", "run the whole pipeline on a built-in simulated lens (no hardware): simulate → "
                   "calibrate → plan → capture → composite → compare",
                   "fieldcal demo --out demo-out")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--lens", default=None,
                   help="simulated lens spec (default: the paper's uncorrected triplet, models/triplet-uncorrected.json)")
    p.add_argument("--size", default="640x360", help="render size WxH over the lens's sensor area (default 640x360)")
    p.add_argument("--effort", choices=("quick", "standard", "thorough"), default="quick",
                   help="calibration effort (default quick, to keep the demo short)")
    p.add_argument("--q", type=float, default=0.05, help="allowed MTF loss at fs (default 0.05)")
    p.add_argument("--seed", type=int, default=0, help="seed of charts, scene and noise (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing demo folder")
    p.set_defaults(func=run)


def _step(title: str, argv: list[str]) -> None:
    from ..cli import main
    print(f"\n== {title}\n$ fieldcal {' '.join(shlex.quote(a) for a in argv)}", flush=True)
    code = main(argv)
    if code != 0:
        err = FieldcalError(f"the demo stopped: `fieldcal {argv[0]}` exited with {code}",
                            fix="see the message above; run that command on its own to investigate")
        err.exit_code = code  # the step's own class of failure (2 input, 4 disk, 5 internal, ...)
        raise err


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParameterError(f"size must be WxH, got {text!r}", field="--size", fix="e.g. --size 640x360") from None
    if w < 64 or h < 64:
        raise ParameterError(f"size {w}x{h} is too small for a demo", field="--size", fix="use at least 64x64")
    return w, h


def run(args) -> int:
    from fieldcal.simulate.lens import LensSpec

    lens_path = Path(args.lens) if args.lens else DEFAULT_LENS
    spec0 = LensSpec.load(lens_path)
    w, h = _size(args.size)
    spec = spec0.with_sensor_size(w, h)
    from fieldcal.formats.atomic import check_output
    out = check_output(args.out, inputs=[lens_path], kind="dir")
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise ParameterError(f"{out} exists and is not empty", path=out, field="--out",
                             fix="choose another --out or add --overwrite")
    if args.overwrite:  # the demo's own files only: never a link, a folder or an input under these names
        check_output(out, inputs=[lens_path], overwrite=True, kind="dir", files=("summary.json", "compare.png"))
    out.mkdir(parents=True, exist_ok=True)
    ow = ["--overwrite"] if args.overwrite else []
    t0 = time.perf_counter()

    # fs: the paper's 80 cycles/mm where the render resolves it, else 40% of this size's Nyquist
    nyquist = 1000.0 / (2.0 * spec.sensor.pixel_pitch_um)
    fs = float(min(80.0, round(0.4 * nyquist)))
    tol = min(spec.focus_tolerance_um(fs, args.q, c) for c in spec.channel_names)
    lo, hi = spec.focus_range_um()
    step = max(1.0, round(tol / 2.0, 1))
    margin = 4 * step
    z0 = spec.z_ref_um - np.ceil((spec.z_ref_um - (lo - margin)) / step) * step
    z1 = spec.z_ref_um + np.ceil(((hi + margin) - spec.z_ref_um) / step) * step
    print(f"fieldcal demo: lens {spec0.name} ({lens_path}), {w}x{h} px at {spec.sensor.pixel_pitch_um:.2f} µm, "
          f"fs = {fs:g} cycles/mm, q = {args.q:g}; best focus spans {lo:.0f}..{hi:.0f} µm (D = {hi - lo:.0f} µm)")

    lens = str(lens_path)
    chart = out / "chart-stack"
    _step("1. a through-focus stack of the calibration chart (simulated)",
          ["simulate", lens, str(chart), "--z", f"{z0:g}", f"{z1:g}", f"{step:g}", "--size", f"{w}x{h}",
           "--seed", str(args.seed), *ow])
    profile = out / "lens.json"
    _step("2. calibrate: per-channel best-focus surfaces with uncertainty, geometry vs z, tolerance",
          ["calibrate", str(chart), "--out", str(profile), "--fs", f"{fs:g}", "--q", f"{args.q:g}",
           "--effort", args.effort, "--seed", str(args.seed), "--report", str(out / "report"), "--z-ref",
           f"{spec.z_ref_um:g}", *ow])
    plan = out / "plan.json"
    _step("3. plan a focal stack: fewest frames keeping every pixel within its tolerance",
          ["plan", "stack", str(profile), "--fs", f"{fs:g}", "--q", f"{args.q:g}", "--out", str(plan),
           "--plots", str(out / "plan-plots"), *ow])
    alpha = max(2.0, round(2 * tol, 1))
    _step("4. plan a focal sweep (per-pixel exposure masks)",
          ["plan", "sweep", str(profile), "--alpha-um", f"{alpha:g}", "--pixel-exposure-ms", "16",
           "--out", str(out / "sweep-plan.json"), "--plots", str(out / "sweep-plots"), *ow])
    scene = out / "scene-stack"
    if args.overwrite and (scene / "stack.json").is_file():  # our own earlier capture: the plan changed
        import shutil
        shutil.rmtree(scene)
    camera = f"sim:{lens},size={w}x{h},scene=colour-leaves,seed={args.seed}"
    _step("5. capture the scene at the planned positions (simulated stage and camera)",
          ["capture", "--plan", str(plan), "--stage", "sim", "--camera", camera, "--out", str(scene),
           "--exposure-ms", f"{spec.sensor.exposure_ms:g}"])
    composite = out / "composite.tiff"
    _step("6. composite: each pixel of each channel from the frames where it is in focus",
          ["composite", str(scene), "--profile", str(profile), "--out", str(composite), *ow])

    print("\n== 7. compare with the truth (the simulator knows the all-in-focus image)")
    summary = _compare(spec, scene, composite, fs, args.seed, out)
    summary.update({"lens": str(lens_path), "size_px": [w, h], "fs_cyc_per_mm": fs, "q": args.q,
                    "effort": args.effort, "elapsed_s": round(time.perf_counter() - t0, 1)})
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print(f"  composite PSNR {summary['psnr_composite_db']:.2f} dB vs one-shot at the on-axis focus "
          f"{summary['psnr_one_shot_db']:.2f} dB ({summary['n_frames']} frames); corner crops in "
          f"{out / 'compare.png'}")
    print(f"\nfieldcal demo: done in {summary['elapsed_s']:.0f} s; open {out / 'report' / 'index.html'}")
    return 0


def _compare(spec, scene_dir: Path, composite_path: Path, fs: float, seed: int, out: Path) -> dict:
    """PSNR of the composite and of a one-shot frame (the planned frame nearest the on-axis focus) vs the truth."""
    import tifffile

    from ..simulate import Renderer
    from ..simulate.scene import load_scene
    from fieldcal.formats.stack import Stack
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import psnr_db

    stack = Stack.open(scene_dir)
    image, _ = load_scene("colour-leaves", spec.sensor.width_px, spec.sensor.height_px, seed=seed)
    truth = Renderer(spec, image, seed=seed).truth()
    comp = tifffile.imread(composite_path)
    cx, cy = spec.optical_centre_px()
    z_axis = float(np.mean([TruthProfile(spec).best_focus_um(cx, cy, c) for c in spec.channel_names]))
    one = int(np.argmin(np.abs(np.asarray(stack.z_um) - z_axis)))
    shot = stack.read(one)
    black, white = float(stack.black_level), float(stack.white_level)
    border = max(4, spec.sensor.width_px // 64)
    res = {"psnr_composite_db": psnr_db(comp, truth, black, white, border_px=border),
           "psnr_one_shot_db": psnr_db(shot, truth, black, white, border_px=border),
           "one_shot_z_um": float(stack.z_um[one]), "n_frames": len(stack)}
    _crops(truth, shot, comp, black, white, out / "compare.png")
    return res


def _crops(truth, shot, comp, black, white, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = truth.shape[:2]
    ch, cw = h // 4, w // 4
    fig, axes = plt.subplots(2, 3, figsize=(10, 5.6))
    for row, (y0, x0, name) in enumerate(((0, 0, "top-left corner"), (h // 2 - ch // 2, w // 2 - cw // 2, "centre"))):
        for col, (img, title) in enumerate(((shot, "one shot (on-axis focus)"), (comp, "fieldcal composite"),
                                            (truth, "truth"))):
            crop = (np.asarray(img[y0:y0 + ch, x0:x0 + cw], dtype=np.float32) - black) / (white - black)
            axes[row, col].imshow(np.clip(crop.squeeze(), 0, 1), cmap=None if crop.ndim == 3 and crop.shape[2] == 3 else "gray",
                                  interpolation="nearest")
            axes[row, col].set_title(f"{title}: {name}", fontsize=8)
            axes[row, col].axis("off")
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)
