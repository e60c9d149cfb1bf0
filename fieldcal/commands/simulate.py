"""`fieldcal simulate`: render a through-focus stack (plus its ground truth) from a simulated lens."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import ParameterError
from ..progress import status
from . import add_parser, parse_size

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"start_um": "--z START", "stop_um": "--z STOP", "step_um": "--z STEP", "z_um": "--z",
               "fs_cyc_per_mm": "--fs", "out": "STACK"}

_DESCRIPTION = """\
Render what a camera with the simulated lens LENS (a fieldcal-lens/1 file, e.g. models/*.json) records
at each stage position and write the frames as a fieldcal-stack/1 folder STACK, with truth.json (the lens,
seed, scene, positions and renderer settings) and truth.tiff (the all-in-focus image at z_ref) beside them.

--z START STOP STEP (µm) gives START, START+STEP, ... up to STOP, including STOP when it lands on the grid:
--z -200 200 25 gives 17 frames. --size WxH renders the same sensor area with fewer (or more) pixels, so
the field curvature in µm is unchanged and a small stack is quick."""


def register(sub):
    p = add_parser(sub, "simulate", "render a through-focus stack from a simulated lens",
                   "fieldcal simulate models/triplet-uncorrected.json out --z -200 200 25 --size 480x270",
                   description=_DESCRIPTION)
    p.add_argument("lens", metavar="LENS", help="simulated lens spec (fieldcal-lens/1 JSON)")
    p.add_argument("stack", metavar="STACK", help="output stack folder (must not exist or be empty)")
    p.add_argument("--z", nargs=3, type=float, required=True, metavar=("START", "STOP", "STEP"),
                   help="stage positions in µm: START STOP STEP (STOP included when on the grid)")
    p.add_argument("--scene", default="chart",
                   help="chart (random texture, default), charuco, slanted-edge, colour-leaves (a colour test "
                        "scene), or an image file")
    p.add_argument("--chart", metavar="TARGETS.json", help="record the ChArUco board the scene shows (targets.json "
                   "of `fieldcal targets`) in stack.json; --scene charuco records its own board")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and the texture chart (default 0)")
    p.add_argument("--size", metavar="WxH", help="render at W x H px over the same sensor area (default: the "
                   "lens's sensor size)")
    p.add_argument("--no-noise", action="store_true", help="no photon/read noise (frames still quantised)")
    p.add_argument("--optics", choices=("geometric", "wave"), default="geometric", metavar="OPTICS",
                   help="image formation: geometric (analytic blur-disc OTFs, default) or wave (PSFs from the pupil "
                        "with the spec's aberrations, spectral bands, pixel aperture; docs/simulator.md)")
    p.add_argument("--fs", type=float, default=80.0, metavar="CYC_PER_MM",
                   help="wave optics: the frequency whose MTF peak is the true best focus in truth.json (default 80)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stack in STACK")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from fieldcal.simulate.lens import LensSpec
    from ..simulate.stackgen import simulate_stack, z_grid

    size = parse_size(args.size)
    z = z_grid(*args.z)
    if not (args.fs > 0 and math.isfinite(args.fs)):
        raise ParameterError(f"fs must be a positive frequency, got {args.fs}", field="fs_cyc_per_mm", fix="e.g. 80")
    from fieldcal.formats.atomic import check_output
    scene_file = args.scene if args.scene and Path(args.scene).is_file() else None
    # the old stack is replaced as a whole: refuse when it is, or holds, the lens spec or the scene image
    check_output(args.stack, inputs=[args.lens, scene_file], kind="dir", replaces_folder=True, field="stack")
    spec = LensSpec.load(args.lens)
    chart = None
    if args.chart:
        from ..charts.targets import chart_record_from_targets
        chart = chart_record_from_targets(args.chart)
    stack = simulate_stack(spec, args.stack, z, scene=args.scene, seed=args.seed, size=size,
                           progress=not args.quiet, noise=not args.no_noise, overwrite=args.overwrite,
                           optics=args.optics, fs_cyc_per_mm=args.fs, chart=chart)
    h, w = stack.shape
    status(f"wrote {len(stack)} frames of {w}x{h} px ({', '.join(stack.channels)}) to {args.stack}",
           quiet=args.quiet)
    return 0
