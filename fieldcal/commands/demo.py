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

from ..errors import FieldcalError, ParameterError
from ..formats.atomic import write_text
from . import add_parser, parse_size

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


def run(args) -> int:
    from fieldcal.simulate.lens import LensSpec

    from fieldcal.validation.demo import compare_with_truth, demo_settings

    lens_path = Path(args.lens) if args.lens else DEFAULT_LENS
    spec0 = LensSpec.load(lens_path)
    w, h = parse_size(args.size, minimum=64)
    spec = spec0.with_sensor_size(w, h)
    from fieldcal.formats.atomic import check_output
    out = check_output(args.out, inputs=[lens_path], kind="dir")
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise ParameterError(f"{out} exists and is not empty", path=out, field="out",
                             fix="choose another --out or add --overwrite")
    if args.overwrite:  # the demo's own files only: never a link, a folder or an input under these names
        check_output(out, inputs=[lens_path], overwrite=True, kind="dir", files=("summary.json", "compare.png"))
    out.mkdir(parents=True, exist_ok=True)
    ow = ["--overwrite"] if args.overwrite else []
    t0 = time.perf_counter()
    d = demo_settings(spec, args.q)
    fs, z0, z1, step = d.fs_cyc_per_mm, d.z_start_um, d.z_stop_um, d.step_um
    print(f"fieldcal demo: lens {spec0.name} ({lens_path}), {w}x{h} px at {spec.sensor.pixel_pitch_um:.2f} µm, "
          f"fs = {fs:g} cycles/mm, q = {args.q:g}; best focus spans {d.focus_lo_um:.0f}..{d.focus_hi_um:.0f} µm "
          f"(D = {d.focus_hi_um - d.focus_lo_um:.0f} µm)")

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
    alpha = d.alpha_um
    _step("4. plan a focal sweep (per-pixel exposure masks)",
          ["plan", "sweep", str(profile), "--alpha-um", f"{alpha:g}", "--pixel-exposure-ms", "16",
           "--out", str(out / "sweep-plan.json"), "--plots", str(out / "sweep-plots"), *ow])
    scene = out / "scene-stack"
    if args.overwrite and (scene / "stack.json").is_file():  # our own earlier capture: the plan changed
        import shutil

        from fieldcal.formats.atomic import check_replaceable_folder
        check_replaceable_folder(scene, "stack.json", True, "a stack")  # nothing the user put there is deleted
        shutil.rmtree(scene)
    camera = f"sim:{lens},size={w}x{h},scene=colour-leaves,seed={args.seed}"
    _step("5. capture the scene at the planned positions (simulated stage and camera)",
          ["capture", "--plan", str(plan), "--stage", "sim", "--camera", camera, "--out", str(scene),
           "--exposure-ms", f"{spec.sensor.exposure_ms:g}"])
    composite = out / "composite.tiff"
    _step("6. composite: each pixel of each channel from the frames where it is in focus",
          ["composite", str(scene), "--profile", str(profile), "--out", str(composite), *ow])

    print("\n== 7. compare with the truth (the simulator knows the all-in-focus image)")
    summary = compare_with_truth(spec, scene, composite, args.seed, out / "compare.png")
    summary.update({"lens": str(lens_path), "size_px": [w, h], "fs_cyc_per_mm": fs, "q": args.q,
                    "effort": args.effort, "elapsed_s": round(time.perf_counter() - t0, 1)})
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print(f"  composite PSNR {summary['psnr_composite_db']:.2f} dB vs one-shot at the on-axis focus "
          f"{summary['psnr_one_shot_db']:.2f} dB ({summary['n_frames']} frames); corner crops in "
          f"{out / 'compare.png'}")
    print(f"\nfieldcal demo: done in {summary['elapsed_s']:.0f} s; open {out / 'report' / 'index.html'}")
    return 0
