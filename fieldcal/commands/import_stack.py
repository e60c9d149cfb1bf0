"""`fieldcal import`: make a stack folder from a camera's files (TIFF, PNG, JPEG, DNG, camera raw)."""

from __future__ import annotations

from ..progress import status
from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"z_start_um": "--z", "z_step_um": "--z", "pixel_pitch_um": "--pixel-pitch-um", "images": "IMAGE"}

_DESCRIPTION = """\
Make a fieldcal-stack/1 folder STACK from the files a camera wrote, one per stage position. Frames are taken
in natural-sort order of their names (img2 before img10) at z = START, START+STEP, ..., or at the positions
of a CSV of file,z_um rows. TIFF, PNG and JPEG frames are copied as they are (or linked with --link); DNG and
camera raw files are read with LibRaw (rawpy) and stored as 16-bit Bayer mosaics with their CFA pattern and
black/white levels, so calibration measures each colour plane without demosaicing.

Make, model, f-number, focal length, exposure and pixel pitch are taken from the files' EXIF data where
present; --pixel-pitch-um is required when the files do not state the pitch. Mixed sizes, cameras, file
types or CFA patterns are refused."""


def register(sub):
    p = add_parser(sub, "import", "make a stack folder from camera files (TIFF/PNG/JPEG/DNG/raw)",
                   "fieldcal import shots/*.JPG --out stack --z 0 20 --pixel-pitch-um 1.4",
                   description=_DESCRIPTION)
    p.add_argument("images", metavar="IMAGE", nargs="+", help="frame files, or a folder holding them")
    p.add_argument("--out", required=True, metavar="STACK", help="stack folder to create")
    z = p.add_mutually_exclusive_group(required=True)
    z.add_argument("--z", nargs=2, type=float, metavar=("START", "STEP"),
                   help="stage position of the first frame and the step between frames (µm)")
    z.add_argument("--z-csv", metavar="FILE", help="CSV of file,z_um rows (any order; header optional)")
    p.add_argument("--pixel-pitch-um", type=float, metavar="P", help="sensor pixel pitch (µm), if not in EXIF")
    p.add_argument("--f-number", type=float, metavar="N", help="working f-number (overrides EXIF)")
    p.add_argument("--focal-length-mm", type=float, metavar="F", help="focal length (mm; overrides EXIF)")
    p.add_argument("--object-distance-mm", type=float, metavar="D", help="distance to the chart or scene (mm)")
    p.add_argument("--link", nargs="?", const="hard", choices=["hard", "symlink"],
                   help="hard-link (default for --link) or symlink the frames instead of copying them")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stack in STACK")
    p.add_argument("--chart", metavar="TARGETS.json", help="record the ChArUco board the frames show (targets.json "
                   "of `fieldcal targets`) in stack.json, for `calibrate`'s geometry maps")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..formats.importer import import_stack

    z_start, z_step = (args.z if args.z else (None, None))
    chart = None
    if args.chart:  # read before anything is written: a bad chart file leaves no stack behind
        from ..charts.targets import chart_record_from_targets
        chart = chart_record_from_targets(args.chart)
    stack = import_stack(args.images, args.out, z_start_um=z_start, z_step_um=z_step, z_csv=args.z_csv,
                         pixel_pitch_um=args.pixel_pitch_um, f_number=args.f_number,
                         focal_length_mm=args.focal_length_mm, object_distance_mm=args.object_distance_mm,
                         link=args.link, overwrite=args.overwrite)
    if chart is not None:
        from ..formats.stack import Stack, record_chart
        record_chart(args.out, chart)
        stack = Stack.open(args.out)
    h, w = stack.shape
    kind = f"{stack.cfa} Bayer mosaics" if stack.cfa else ", ".join(stack.channels)
    status(f"imported {len(stack)} frames of {w}x{h} px ({kind}, pitch {stack.pixel_pitch_um:g} µm) into "
           f"{args.out}", quiet=args.quiet)
    return 0
