"""`fieldcal lens`: simulated lenses from a prescription table (ray traced with the optional optiland)."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import ParameterError
from ..progress import status
from . import add_parser

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


def _positive(name: str, v, fix: str):
    if v is not None and not (math.isfinite(v) and v > 0):
        raise ParameterError(f"{name} must be a positive number, got {v}", field=name, fix=fix)
    return v


def _load_and_check(args):
    from ..raytrace.build import check_first_order
    from ..raytrace.paraxial import paraxial
    from ..raytrace.prescription import load_prescription, meta_number

    rx = load_prescription(args.table)
    efl = _positive("--efl", args.efl, "e.g. --efl 17.6") or meta_number(rx, "efl_mm")
    bfl = _positive("--bfl", args.bfl, "e.g. --bfl 10.511") or meta_number(rx, "bfl_mm")
    try:
        parax = paraxial(rx)
    except ValueError as e:
        from ..errors import SpecError
        raise SpecError(f"{e}", path=args.table, field="radius", fix="check the radii and indices") from None
    check_first_order(parax, efl, bfl, args.tolerance, path=args.table)
    return rx, parax, efl, bfl


def run_check(args) -> int:
    rx, parax, efl, bfl = _load_and_check(args)
    print(f"{args.table}: {len(rx.surfaces)} surfaces, stop at row {rx.stop_index + 1}")
    print(f"  EFL {parax.efl_mm:.4f} mm" + (f" (expected {efl:g}: ok)" if efl else ""))
    print(f"  BFL {parax.bfl_mm:.4f} mm" + (f" (expected {bfl:g}: ok)" if bfl else "")
          + f"; stated image plane at {parax.image_distance_mm:g} mm ({parax.paraxial_focus_shift_um:+.1f} µm "
          "from the paraxial focus)")
    print(f"  exit pupil {parax.exit_pupil_to_image_mm:.3f} mm before the stated image plane")
    return 0


def _parse_channels(text: str) -> dict[str, float]:
    from fieldcal.simulate.lens import DEFAULT_WAVELENGTH_NM

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
    import numpy as np

    from ..raytrace.bestfocus import SearchSettings, trace_focus_table
    from ..raytrace.build import build_lens_spec, parse_sensor, sensor_geometry
    from ..raytrace.optiland_backend import require_optiland
    from ..raytrace.prescription import meta_number

    from fieldcal.formats.atomic import check_output
    out = check_output(args.out, inputs=[args.table], overwrite=args.overwrite)
    rx, parax, _, _ = _load_and_check(args)
    f_number = _positive("--f-number", args.f_number, "e.g. --f-number 2") or meta_number(rx, "f_number")
    if f_number is None:
        raise ParameterError("the F-number is not known", field="--f-number",
                             fix="give --f-number N (or '# f_number: N' in the table)")
    h_max = _positive("--image-height", args.image_height, "e.g. --image-height 3.6") or meta_number(rx, "image_height_mm")
    sensor = parse_sensor(args.sensor, h_max) if args.sensor else (3840, 2160, None)
    if h_max is None:
        w, h, pitch = sensor
        if pitch is None:
            raise ParameterError("the image height is not known", field="--image-height",
                                 fix="give --image-height MM, or --sensor WxH@PITCH (its half diagonal is used)")
        h_max = math.hypot(w / 2.0, h / 2.0) * pitch / 1000.0
    if not (2 <= args.heights <= 41):
        raise ParameterError(f"--heights must be in 2..41, got {args.heights}", field="--heights", fix="e.g. 9")
    if not (1 <= args.terms <= 4) or args.terms > args.heights - 1:
        raise ParameterError(f"--terms {args.terms} needs 1..4 and fewer than --heights ({args.heights})",
                             field="--terms", fix="e.g. --terms 2 with --heights 9")
    _positive("--fs", args.fs, "e.g. --fs 80")
    sensor_geometry(sensor, h_max)  # a sensor beyond the traced field: say so before tracing for minutes
    channels = _parse_channels(args.channels)
    settings = SearchSettings(fs_cyc_per_mm=args.fs, num_rays=args.num_rays)
    require_optiland()
    heights = np.linspace(0.0, h_max, args.heights)
    status(f"tracing {len(channels)} channel(s) x {len(heights)} heights at {args.fs:g} cy/mm, F/{f_number:g}",
           quiet=args.quiet)
    table = trace_focus_table(rx, heights, channels, f_number, settings, quiet=args.quiet)
    spec = build_lens_spec(table, parax, name=args.name or rx.name, image_height_mm=h_max, sensor=sensor,
                           n_terms=args.terms, description=str(rx.meta.get("description", "")))
    spec.save(out)
    print(f"wrote {out}: EFL {parax.efl_mm:.3f} mm, F/{f_number:g}, image height {h_max:g} mm")
    print("best focus (µm from the stated image plane; peak of mean T/S MTF at "
          f"{args.fs:g} cy/mm), traced | fitted:")
    print("  h (mm) " + "".join(f"{c:>18}" for c in channels))
    for h in heights:
        cells = []
        for c in channels:
            p = table.get(c, float(h))
            cells.append(f"{p.z_um:8.1f} | {float(spec.best_focus_um(h, 0.0, c)):7.1f}")
        print(f"  {h:6.3f} " + "".join(f"{s:>18}" for s in cells))
    return 0
