"""`fieldcal simulate`: render a through-focus stack (plus its ground truth) from a simulated lens."""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import ParameterError
from ..progress import status
from . import add_parser

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
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and the texture chart (default 0)")
    p.add_argument("--size", metavar="WxH", help="render at W x H px over the same sensor area (default: the "
                   "lens's sensor size)")
    p.add_argument("--no-noise", action="store_true", help="no photon/read noise (frames still quantised)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stack in STACK")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"640x480"`` -> (640, 480); clear error otherwise."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 8 or int(m.group(2)) < 8:
        raise ParameterError(f"bad --size {text!r}", field="--size",
                             fix="give WIDTHxHEIGHT in pixels, each at least 8, e.g. --size 320x180")
    return int(m.group(1)), int(m.group(2))


def run(args) -> int:
    from fieldcal.simulate.lens import LensSpec
    from ..simulate.stackgen import simulate_stack, z_grid

    size = parse_size(args.size)
    z = z_grid(*args.z)
    if args.seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {args.seed}", field="--seed", fix="e.g. --seed 0")
    from fieldcal.formats.atomic import check_output
    scene_file = args.scene if args.scene and Path(args.scene).is_file() else None
    # the old stack is replaced as a whole: refuse when it is, or holds, the lens spec or the scene image
    check_output(args.stack, inputs=[args.lens, scene_file], kind="dir", replaces_folder=True, field="STACK")
    spec = LensSpec.load(args.lens)
    stack = simulate_stack(spec, args.stack, z, scene=args.scene, seed=args.seed, size=size,
                           progress=not args.quiet, noise=not args.no_noise, overwrite=args.overwrite)
    h, w = stack.shape
    status(f"wrote {len(stack)} frames of {w}x{h} px ({', '.join(stack.channels)}) to {args.stack}",
           quiet=args.quiet)
    return 0
