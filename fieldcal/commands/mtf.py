"""`fieldcal mtf INPUT --out mtf.json`: slanted-edge (ISO 12233 e-SFR) MTF of every edge in an image or stack."""

from __future__ import annotations

import math

from ..errors import ParameterError
from . import add_parser

# library fields named for their flag even when the message names the input file
FIELD_FLAGS = {"cfa": "--cfa"}

_DESCRIPTION = """\
Find every slanted edge (dark squares or half-planes 2-20 degrees off the pixel axes) in INPUT, an image
file or a fieldcal-stack/1 folder, and measure its MTF by the ISO 12233 e-SFR method, per colour channel (per
CFA plane for raw mosaics). Each edge is classified tangential or sagittal about the optical centre and gets a
quality record (contrast, clipping, SNR, slant, ok/reason). Writes a fieldcal-mtf/1 JSON file; --plots
writes MTF50 over the field per channel and, for a stack, through-focus MTF(fs) curves of edge tracks."""


def register(sub):
    p = add_parser(sub, "mtf", "slanted-edge MTF (ISO 12233 e-SFR) of an image or a stack",
                   "fieldcal mtf chart-stack --out mtf.json --plots mtf-plots/", description=_DESCRIPTION)
    p.add_argument("input", metavar="INPUT", help="an image file (PNG/TIFF) or a stack folder")
    p.add_argument("--out", required=True, help="output fieldcal-mtf/1 JSON file")
    p.add_argument("--plots", metavar="DIR", default=None, help="also write PNG plots into DIR")
    p.add_argument("--centre", metavar="X,Y", default=None,
                   help="optical centre in px for the tangential/sagittal split (default: the frame centre)")
    p.add_argument("--cfa", default=None, choices=["RGGB", "BGGR", "GRBG", "GBRG"],
                   help="Bayer pattern of a raw single image (stacks carry their own)")
    p.add_argument("--fs", type=float, default=0.25, help="frequency of the through-focus plot, cycles/px "
                                                           "(default 0.25)")
    p.add_argument("--q", type=float, default=0.05, help="MTF loss marking the tolerance in the plot (default 0.05)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file and --plots pictures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _centre(text: str | None):
    if text is None:
        return None
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ParameterError(f"cannot read {text!r} as X,Y", field="--centre",
                             fix="give the optical centre in pixels, e.g. --centre 959.5,539.5") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ParameterError(f"{text!r} is not a finite position", field="--centre",
                             fix="give the optical centre in pixels, e.g. --centre 959.5,539.5")
    return x, y


def run(args) -> int:
    from fieldcal.formats.atomic import check_output
    from fieldcal.measure.mtf import measure_mtf
    from fieldcal.measure.mtf_plots import PLOT_FILES
    from ..progress import status, warn

    if not 0 < args.fs <= 1.0:
        raise ParameterError(f"--fs {args.fs} outside (0, 1] cycles/px", field="--fs", fix="e.g. --fs 0.25")
    if not 0 < args.q < 1:
        raise ParameterError(f"--q {args.q} outside (0, 1)", field="--q", fix="e.g. --q 0.05")
    # before any work: never over or into the image or stack measured, never over an output without --overwrite
    check_output(args.out, inputs=[args.input], overwrite=args.overwrite)
    if args.plots:
        check_output(args.plots, inputs=[args.input], overwrite=args.overwrite, kind="dir", files=PLOT_FILES,
                     field="--plots")
    res = measure_mtf(args.input, centre_px=_centre(args.centre), cfa=args.cfa, quiet=args.quiet)
    res.save(args.out)
    n_ok = sum(1 for e in res.edges if e["quality"]["ok"])
    frames = len({e["frame"] for e in res.edges})
    status(f"wrote {args.out}: {len(res.edges)} edge measurements ({n_ok} ok) in {frames} frame(s)",
           quiet=args.quiet)
    if not res.edges:
        warn("no slanted edge found (the chart needs dark squares or half-planes 2-20 degrees off the "
             "pixel axes; try `fieldcal targets --kind slanted-edge`)")
    if args.plots:
        from fieldcal.measure.mtf_plots import write_plots
        for p in write_plots(res, args.plots, args.fs, args.q):
            status(f"wrote {p}", quiet=args.quiet)
    return 0
