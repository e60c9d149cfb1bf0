"""`fieldcal calibrate STACK --out PROFILE`: fit a lens profile from a chart stack."""

from __future__ import annotations

from pathlib import Path

from ..errors import ParameterError
from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"fs_cyc_per_mm": "--fs", "path": "--out"}


def register(sub):
    p = add_parser(sub, "calibrate", "fit a lens profile (best-focus surfaces with uncertainty, geometry vs z, "
                   "tolerance) from a chart stack",
                   "fieldcal calibrate chart-stack --out lens.json --fs 80 --q 0.05 --effort standard")
    p.add_argument("stack", help="fieldcal-stack/1 folder of a textured chart across sensor positions")
    p.add_argument("--out", required=True,
                   help="profile to write (.json; the samples go to <stem>.<hash>.samples.npz beside it)")
    p.add_argument("--fs", type=float, default=80.0, help="target frequency, cycles/mm at the sensor (default 80)")
    p.add_argument("--q", type=float, default=0.05, help="allowed MTF loss at fs defining the tolerance (default 0.05)")
    p.add_argument("--effort", choices=["quick", "standard", "thorough"], default="standard",
                   help="quick: MAP + Laplace; standard: emcee posterior; thorough: denser tiles, astigmatism, "
                        "longer chains, wider model search")
    p.add_argument("--z-ref", type=float, default=None, dest="z_ref_um",
                   help="reference sensor position (µm) of the geometry model (default: the middle frame)")
    p.add_argument("--tile", type=int, default=None, dest="tile_px", help="tile size in px (default from size/effort)")
    p.add_argument("--measure", choices=["auto", "sml", "bandpass", "sml@fs"], default="auto",
                   help="focus measure for best focus: band-pass energy at fs (contrast at fs), "
                        "sum-modified-Laplacian, sml@fs: the SML moved to where the band-pass at fs peaks, or "
                        "auto: sml@fs where the pixels resolve fs, its offset from a strip of tiles through the middle at "
                        "--effort quick (default)")
    p.add_argument("--chart", choices=["auto", "esfr", "focus-measure"], default="auto",
                   help="how best focus is measured: slanted edges (ISO 12233 e-SFR), texture tiles (focus "
                        "measure), or auto: from the chart the middle frame shows (default)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    p.add_argument("--stage-repeatability-um", type=float, default=None, dest="stage_repeatability_um",
                   help="stage position repeatability, 1 sigma in µm (default: the stage record in stack.json, "
                        "else 0); recorded in the profile and included in the band")
    p.add_argument("--report", default=None, metavar="DIR", help="also write the HTML report into DIR")
    p.add_argument("--overwrite", action="store_true", help="replace an existing profile (and report files)")
    p.add_argument("--geometry-maps", choices=("auto", "charuco", "texture", "off"), default="auto",
                   help="dense geometry maps (distortion, breathing, shift, lateral colour): auto measures them "
                        "when stack.json records a ChArUco chart (default); texture registers the frames' texture")
    p.add_argument("--no-verify", action="store_true",
                   help="use frames whose content no longer matches the sha256 stack.json records")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    from fieldcal.formats.atomic import SIDECAR_NAME_ROOM, check_output
    from fieldcal.formats.stack import Stack

    stack_dir = Path(args.stack)
    if stack_dir.name == "stack.json":
        stack_dir = stack_dir.parent
    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise ParameterError(f"the profile must be a .json file, got {out.name!r}", field="--out",
                             fix="e.g. --out lens.json")
    # every output is checked before the work: a bad --report must not fail after the profile is written
    check_output(out, inputs=[stack_dir], overwrite=args.overwrite, name_room=SIDECAR_NAME_ROOM)
    if args.report:
        from fieldcal.report.calibration_report import REPORT_FILES
        check_output(args.report, inputs=[stack_dir], overwrite=args.overwrite, kind="dir",
                     files=REPORT_FILES, field="--report")
    stack = Stack.open(stack_dir, verify=False)
    if not args.no_verify:
        # the frames hash on the second core while the pipeline's modules import and the chart is checked;
        # calibrate waits for it before measuring (Stack.start_verify)
        stack.start_verify()
    from fieldcal.calibration.pipeline import calibrate
    profile = calibrate(stack, fs_cyc_per_mm=args.fs, q=args.q, effort=args.effort, z_ref_um=args.z_ref_um,
                        tile_px=args.tile_px, measure=args.measure, seed=args.seed, quiet=args.quiet,
                        chart=args.chart, geometry_maps=args.geometry_maps,
                        stage_repeatability_um=args.stage_repeatability_um)
    profile.save(out)
    print(f"wrote {out} (model {profile.surfaces.model.name}; "
          f"{profile.diagnostics.get('n_tiles_ok')} tiles; z_ref {profile.z_ref_um:g} µm)")
    if args.report:
        from fieldcal.report.calibration_report import write_report
        print(f"wrote {write_report(profile, args.report)}")
    return 0
