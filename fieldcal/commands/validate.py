"""`fieldcal validate LENS`: the whole pipeline on a simulated lens, every stage compared with the truth.

Exit status: 0 when every check passes, 1 when a check fails (the report says which), 2 for a user error
(bad lens file or parameter), 4 when a pipeline stage is not available yet.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import ParameterError
from . import add_parser

EXAMPLE = ("fieldcal validate models/triplet-uncorrected.json --out validation   "
           "# 256 px wide, fs = 0.4 Nyquist; open validation/index.html")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParameterError(f"size must be WxH in pixels, got {text!r}", field="--size", fix="e.g. --size 256x144") from None
    return w, h


def _confidence(text: str):
    if text.lower() in ("none", "off", "0"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise ParameterError(f"confidence must be a number in (0, 1) or 'none', got {text!r}", field="--confidence",
                             fix="e.g. --confidence 0.9") from None
    return v


def register(sub):
    p = add_parser(sub, "validate", "end-to-end check against a simulated lens's truth", EXAMPLE,
                   description="Simulate a chart stack from the lens, calibrate, plan a stack, simulate a scene at the "
                               "planned positions and composite it; compare every step with the simulator's truth "
                               "(surface errors, band coverage, geometry, plan coverage, composite PSNR against a "
                               "one-shot frame and the true-surface oracle) and write a report (PNG plots, "
                               "index.html, report.md, summary.json). Exit 0 when every check passes, 1 when one "
                               "fails, 2 for a user error.")
    p.add_argument("lens", help="simulated lens spec (fieldcal-lens/1 JSON), e.g. models/triplet-uncorrected.json")
    p.add_argument("--out", default="validation", help="report folder (default: validation)")
    p.add_argument("--size", type=str, default=None,
                   help="render size WxH over the same sensor area (default 256 px wide at the sensor's aspect)")
    p.add_argument("--fs", type=float, default=None,
                   help="target frequency, cycles/mm (default 0.4 x Nyquist of the render size)")
    p.add_argument("--q", type=float, default=0.05, help="allowed MTF loss at fs (default 0.05)")
    p.add_argument("--effort", choices=("quick", "standard", "thorough"), default="standard",
                   help="calibration effort (default standard)")
    p.add_argument("--seed", type=int, default=0, help="seed of charts, noise and samplers (default 0)")
    p.add_argument("--scene", default="chart",
                   help="scene to composite: chart (dead leaves), texture (colour dead leaves) or an image file")
    p.add_argument("--confidence", type=str, default="0.9",
                   help="coverage probability the plan asks of the profile's band, or 'none' (default 0.9)")
    p.add_argument("--profile", default="calibrate",
                   help="calibrate (the full pipeline, default), truth (skip calibration; checks planning and "
                        "compositing) or PROFILE.json (judge a saved fieldcal-profile/1 calibrated at --size)")
    p.add_argument("--keep-stacks", action="store_true", help="keep the chart and scene stacks in OUT/stacks/")
    p.add_argument("--no-plots", action="store_true", help="write only summary.json, report.md and index.html")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..progress import status
    from fieldcal.validation.run import ValidateConfig, validate
    from fieldcal.validation.report import write_report

    scene = args.scene
    if scene not in ("chart", "texture") and not Path(scene).is_file():
        raise ParameterError(f"scene {scene!r} is neither chart, texture nor an image file", path=scene,
                             field="--scene", fix="use chart, texture or the path of an existing image")
    if not math.isfinite(args.q):
        raise ParameterError(f"q must be a finite number, got {args.q}", field="--q", fix="e.g. --q 0.05")
    given = None
    source = args.profile
    if source not in ("calibrate", "truth"):
        if not Path(source).is_file():
            raise ParameterError(f"profile {source!r} is neither calibrate, truth nor a profile file", path=source,
                                 field="--profile", fix="use calibrate, truth or the path of a fieldcal-profile/1 JSON")
        from fieldcal.profile.lens_profile import LensProfile
        given = LensProfile.load(source)
        source = "calibrate"
    cfg = ValidateConfig(size_px=_size(args.size) if args.size else None, fs_cyc_per_mm=args.fs, q=args.q,
                         effort=args.effort, seed=args.seed, scene=scene, confidence=_confidence(args.confidence),
                         profile=source)
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files
    inputs = [args.lens, scene if Path(scene).is_file() else None,
              *(profile_files(args.profile) if args.profile not in ("calibrate", "truth") else [])]
    out = check_output(args.out, inputs=inputs, kind="dir", overwrite=True,
                       files=("index.html", "report.md", "summary.json"))
    workdir = out / "stacks" if args.keep_stacks else None
    result = validate(args.lens, cfg, workdir=workdir, profile=given)
    write_report(result, out, plots=not args.no_plots)
    for c in result.checks:
        status(f"  {'pass' if c.passed else 'FAIL'}  {c.name}: {c.value:.4g} {c.op} {c.limit:.4g}")
    verdict = "all checks pass" if result.passed else f"{len(result.failed)} check(s) FAILED"
    print(f"fieldcal validate: {result.lens}: {verdict}; report in {out / 'index.html'}")
    return 0 if result.passed else 1
