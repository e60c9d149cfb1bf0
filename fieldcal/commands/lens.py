"""`fieldcal lens`: simulated lenses from a prescription table (ray traced with the optional optiland)."""

from __future__ import annotations

import math

from ..errors import ParameterError
from ..progress import status
from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"efl_mm": "--efl", "bfl_mm": "--bfl", "image_height_mm": "--image-height", "fs_cyc_per_mm": "--fs",
               "channels_nm": "--channels"}

_DESCRIPTION = """\
Build simulated lenses (fieldcal-lens/1) from an optical prescription.

  fieldcal lens check TABLE                       paraxial EFL, BFL and exit pupil (no ray tracing needed)
  fieldcal lens from-prescription TABLE --out LENS.json

TABLE is a CSV or JSON table with the columns surface, type, radius, thickness, nd, vd, glass, k, a4, a6,
a8 (one row per surface from the object side, the aperture stop's row labelled 'stop'); see docs/raytrace.md
and models/triplet-uncorrected.prescription.csv. from-prescription needs the optional ray-tracing extra:
pip install -e ".[raytrace]"."""

_FROM_DESCRIPTION = """\
Trace the prescription TABLE with optiland (object at infinity) and write a fieldcal-lens/1 spec: per channel,
best focus vs image height is the peak of the mean tangential/sagittal MTF at --fs, found by looping over
image-plane positions at each of --heights image heights; the spec's even polynomial in rho^2 is fitted to
it. Exit pupil comes from the paraxial trace, residual blur from the traced peak MTF, astigmatism from the
tangential/sagittal foci, lateral colour from the chief rays; the spec's "sources" block says how.

Before tracing, the paraxial EFL/BFL (d line) are checked against --efl/--bfl (or the table's '# efl_mm:' /
'# bfl_mm:' design values) within --tolerance, and every glass must be given by nd and vd or a known name.
Takes about 3 s per height and channel (27 traces: ~80 s for the defaults)."""


def register(sub):
    p = add_parser(sub, "lens", "build simulated lenses from a prescription table",
                   "fieldcal lens from-prescription models/triplet-uncorrected.prescription.csv --out lens.json",
                   description=_DESCRIPTION)
    lsub = p.add_subparsers(dest="lens_command", metavar="ACTION")
    c = add_parser(lsub, "check", "paraxial EFL/BFL/exit pupil of a prescription table (no ray tracing)",
                   "fieldcal lens check models/triplet-uncorrected.prescription.csv --efl 17.6 --bfl 10.511")
    c.add_argument("table", metavar="TABLE", help="prescription table (.csv or .json)")
    _first_order_args(c)
    c.set_defaults(func=run_check)

    f = add_parser(lsub, "from-prescription", "build a fieldcal-lens/1 spec by ray tracing a prescription",
                   "fieldcal lens from-prescription models/triplet-uncorrected.prescription.csv --out lens.json "
                   "--fs 80 --f-number 2 --image-height 3.6 --sensor 3840x2160@1.6342 --efl 17.6 --bfl 10.511",
                   description=_FROM_DESCRIPTION)
    f.add_argument("table", metavar="TABLE", help="prescription table (.csv or .json)")
    f.add_argument("--out", required=True, metavar="LENS.json", help="output lens spec")
    f.add_argument("--fs", type=float, default=80.0, metavar="CY_PER_MM",
                   help="spatial frequency of the best-focus criterion, cycles/mm (default 80)")
    f.add_argument("--f-number", type=float, metavar="N",
                   help="image-space F-number (default: the table's '# f_number:' value)")
    f.add_argument("--image-height", type=float, metavar="MM",
                   help="largest image height, mm (default: the table's '# image_height_mm:' value, else the "
                        "sensor's half diagonal)")
    f.add_argument("--sensor", metavar="WxH[@PITCH]",
                   help="sensor pixels and pitch in µm (default 3840x2160 with the corner at the image height)")
    _first_order_args(f)
    f.add_argument("--heights", type=int, default=9, metavar="N",
                   help="number of image heights traced, evenly from 0 to the image height (default 9)")
    f.add_argument("--channels", default="R=656.3,G=546.1,B=486.1", metavar="NAME=NM,...",
                   help="channels and wavelengths in nm (default R=656.3,G=546.1,B=486.1; e.g. Y=546.1)")
    f.add_argument("--terms", type=int, default=2, metavar="K",
                   help="number of curvature terms rho^2 ... rho^2K in the spec's polynomial (default 2)")
    f.add_argument("--num-rays", type=int, default=64, help="pupil sampling of optiland's FFT PSF (default 64)")
    f.add_argument("--name", help="lens name (default: the table's name)")
    f.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.set_defaults(func=run_from_prescription)
    p.set_defaults(func=lambda args: _no_action(p))


def _first_order_args(p):
    p.add_argument("--efl", type=float, metavar="MM", help="expected effective focal length, mm "
                   "(default: the table's '# efl_mm:' value; not checked when neither is given)")
    p.add_argument("--bfl", type=float, metavar="MM", help="expected back focal length, mm "
                   "(default: the table's '# bfl_mm:' value)")
    p.add_argument("--tolerance", type=float, default=0.005, metavar="REL",
                   help="allowed relative EFL/BFL difference (default 0.005 = 0.5%%)")


def _no_action(p) -> int:
    p.print_help()
    return 2


def run_check(args) -> int:
    from ..raytrace.api import check_prescription
    chk = check_prescription(args.table, args.efl, args.bfl, args.tolerance)
    rx, parax, efl, bfl = chk.prescription, chk.paraxial, chk.efl_mm, chk.bfl_mm
    print(f"{args.table}: {len(rx.surfaces)} surfaces, stop at row {rx.stop_index + 1}")
    print(f"  EFL {parax.efl_mm:.4f} mm" + (f" (expected {efl:g}: ok)" if efl else ""))
    print(f"  BFL {parax.bfl_mm:.4f} mm" + (f" (expected {bfl:g}: ok)" if bfl else "")
          + f"; stated image plane at {parax.image_distance_mm:g} mm ({parax.paraxial_focus_shift_um:+.1f} µm "
          "from the paraxial focus)")
    print(f"  exit pupil {parax.exit_pupil_to_image_mm:.3f} mm before the stated image plane")
    return 0


def _parse_channels(text: str) -> dict[str, float]:
    from fieldcal.optics import DEFAULT_WAVELENGTH_NM

    out: dict[str, float] = {}
    for part in (text or "").split(","):
        part = part.strip()
        if not part:
            continue
        name, _, wl = part.partition("=")
        name = name.strip()
        try:
            w = float(wl) if wl.strip() else DEFAULT_WAVELENGTH_NM[name]
        except (ValueError, KeyError):
            w = float("nan")
        if not name or name in out or not (math.isfinite(w) and 350.0 <= w <= 1000.0):
            raise ParameterError(f"cannot read the channel {part!r}", field="--channels",
                                 fix="write NAME=WAVELENGTH_NM,... with distinct names and 350-1000 nm, "
                                     "e.g. R=656.3,G=546.1,B=486.1")
        out[name] = w
    if not out:
        raise ParameterError("no channels given", field="--channels", fix="e.g. --channels G=546.1")
    return out


def run_from_prescription(args) -> int:
    from ..raytrace.api import lens_from_prescription
    from ..raytrace.build import parse_sensor

    from fieldcal.formats.atomic import check_output
    out = check_output(args.out, inputs=[args.table], overwrite=args.overwrite)

    def started(channels, heights, f_number):
        status(f"tracing {len(channels)} channel(s) x {len(heights)} heights at {args.fs:g} cy/mm, F/{f_number:g}",
               quiet=args.quiet)

    sensor = parse_sensor(args.sensor, args.image_height) if args.sensor else None
    res = lens_from_prescription(args.table, fs_cyc_per_mm=args.fs, f_number=args.f_number,
                                 image_height_mm=args.image_height, sensor=sensor, heights=args.heights,
                                 channels_nm=_parse_channels(args.channels), terms=args.terms,
                                 num_rays=args.num_rays, name=args.name, efl_mm=args.efl, bfl_mm=args.bfl,
                                 tolerance=args.tolerance, quiet=args.quiet, on_start=started)
    spec = res.spec
    spec.save(out)
    print(f"wrote {out}: EFL {res.paraxial.efl_mm:.3f} mm, F/{res.f_number:g}, image height {res.image_height_mm:g} mm")
    print("best focus (µm from the stated image plane; peak of mean T/S MTF at "
          f"{args.fs:g} cy/mm), traced | fitted:")
    channels = res.table.channels
    print("  h (mm) " + "".join(f"{c:>18}" for c in channels))
    for h in res.heights_mm:
        cells = []
        for c in channels:
            p = res.table.get(c, float(h))
            cells.append(f"{p.z_um:8.1f} | {float(spec.best_focus_um(h, 0.0, c)):7.1f}")
        print(f"  {h:6.3f} " + "".join(f"{s:>18}" for s in cells))
    return 0
