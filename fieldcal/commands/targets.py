"""`fieldcal targets`: write printable calibration charts (PNG with dpi, PDF at exact size, targets.json)."""

from __future__ import annotations

from ..errors import ParameterError
from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"width_mm": "--size-mm", "height_mm": "--size-mm"}


def register(sub):
    p = add_parser(sub, "targets", "write printable calibration charts (texture, ChArUco, slanted edge)",
                   "fieldcal targets --out calibration_targets --kind all --size-mm 297x210 --dpi 300 --seed 0",
                   description="Write printable calibration charts: a dead-leaves random texture (focus), a ChArUco "
                               "board (geometry) and a slanted-edge grid (MTF), each as a PNG carrying its dpi and a "
                               "PDF page of the exact physical size, plus targets.json describing every file. "
                               "Print at 100 % scale (no fit-to-page).")
    p.add_argument("--out", default="calibration_targets", help="output folder (default: calibration_targets)")
    p.add_argument("--kind", default="all", choices=["texture", "charuco", "slanted-edge", "all"],
                   help="which chart (default: all)")
    p.add_argument("--size-mm", default="297x210",
                   help="printed size WIDTHxHEIGHT in mm, or A5/A4/A3/A2/letter/legal (landscape); default 297x210")
    p.add_argument("--dpi", default="300", help="print resolution in dots per inch, 50..1200 (default: 300)")
    p.add_argument("--seed", default="0", help="random-texture seed (default: 0)")
    p.add_argument("--format", default="png,pdf", help="comma-separated: png, pdf (default: png,pdf)")
    p.add_argument("--lens", default=None, metavar="LENS.json",
                   help="a fieldcal-lens/1 spec: report the dpi and chart size this camera needs at its object "
                        "distance, and warn when --dpi/--size-mm fall short")
    p.set_defaults(func=run)


def _number(text: str, field: str, kind=float):
    try:
        return kind(text)
    except (TypeError, ValueError):
        raise ParameterError(f"cannot read {text!r} as a number", field=field,
                             fix=f"give a {'whole ' if kind is int else ''}number") from None


def run(args) -> int:
    from ..progress import status
    from fieldcal.charts.targets import KINDS, parse_size_mm, write_targets

    from fieldcal.formats.atomic import check_output
    check_output(args.out, inputs=[args.lens], kind="dir")
    width_mm, height_mm = parse_size_mm(args.size_mm)
    dpi = _number(args.dpi, "dpi")
    seed = _number(args.seed, "seed", int)
    formats = tuple(f.strip().lower() for f in str(args.format).split(",") if f.strip())
    if args.lens:
        _check_for_lens(args.lens, width_mm, height_mm, dpi)
    kinds = KINDS if args.kind == "all" else (args.kind,)
    from fieldcal.charts.targets import target_files
    # every file's name checked before any chart is drawn: a link or folder at the fifth name must not leave
    # four charts and no targets.json behind (targets rewrites its own files, so no --overwrite)
    check_output(args.out, inputs=[args.lens], kind="dir", overwrite=True,
                 files=target_files(width_mm, height_mm, dpi, kinds=kinds, seed=seed, formats=formats))
    manifest = write_targets(args.out, width_mm, height_mm, dpi, kinds=kinds, seed=seed, formats=formats,
                             quiet=False)
    names = {f for e in manifest["charts"][-len(kinds):] for f in e["files"]}
    for f in sorted(names):
        status(f"wrote {args.out}/{f}")
    status(f"wrote {args.out}/targets.json ({width_mm:g} x {height_mm:g} mm at {dpi:g} dpi; print at 100 %)")
    return 0


def _check_for_lens(lens_path: str, width_mm: float, height_mm: float, dpi: float) -> None:
    from fieldcal.charts.targets import check_chart_for_lens
    from fieldcal.simulate.lens import LensSpec
    from ..progress import status, warn

    spec = LensSpec.load(lens_path)
    req, warnings = check_chart_for_lens(spec, width_mm, height_mm, dpi)
    status(f"{spec.name} at {spec.object_distance_mm:g} mm: magnification {req['magnification']:.4f}, "
           f"needs >= {req['min_dpi']:.0f} dpi and a chart of >= {req['field_width_mm']:.0f} x "
           f"{req['field_height_mm']:.0f} mm to fill the field")
    for w in warnings:
        warn(w)
