"""`fieldcal profile show|diff|export`: read a lens profile, compare two, write one for other tools."""

from __future__ import annotations

import json
import math
import sys

from . import add_parser

FIELD_FLAGS = {"level": "--level", "out": "--out", "n_null": "--draws", "z_um": "--z"}

EXIT_SIGNIFICANT = 1

_DESCRIPTION = """\
Read, compare and export lens profiles (fieldcal-profile/1, from `fieldcal calibrate`).

  fieldcal profile show PROFILE                      a summary a person reads
  fieldcal profile diff A B [--json] [--plot DIR]    are A and B different beyond their uncertainty?
  fieldcal profile export PROFILE --format lensfun --out lens.xml

See docs/profiles.md."""

_DIFF_DESCRIPTION = """\
Compare the best-focus surfaces (per channel; tangential and sagittal when both profiles model astigmatism),
the measured focus tolerances and the geometry (focus breathing, image drift, lateral colour) of profiles A
and B against their joint uncertainty (the two profiles' posteriors, independent). Each is a max-|z| test over
a grid of the field plus the difference's offset, tilt and rho^2, calibrated by simulating the joint null;
the families are combined so that, if A and B are calibrations of the same lens, the whole diff reports a
difference with probability at most 1 - LEVEL.

Exit status: 0 when the comparison ran, whether or not it found a difference (the verdict is printed and in
the JSON's "significant"); with --fail-if-significant, 1 when it found one. 2 for bad input."""

_EXPORT_DESCRIPTION = """\
Write the profile as a Lensfun database entry (version 1, which the lensfunpy package reads): camera, lens,
the absolute distortion (poly5 about a fitted centre) measured from the ChArUco board and transverse chromatic
aberration (poly3) at the calibrated focus -- the stage position where the reference channel is sharpest at
the optical centre, clipped to the scan (or --z). A profile without absolute distortion (texture-only) is
refused; --allow-no-distortion writes its TCA alone, with no distortion element, and says so in the file.
fieldcal measures no vignetting, so the entry has none. Load it with lensfunpy.Database(paths=["lens.xml"])."""


def register(sub):
    p = add_parser(sub, "profile", "show, compare (diff) and export lens profiles",
                   "fieldcal profile diff before.json after.json --plot diff/", description=_DESCRIPTION)
    psub = p.add_subparsers(dest="profile_command", metavar="ACTION")
    s = add_parser(psub, "show", "print a summary of a lens profile", "fieldcal profile show lens.json")
    s.add_argument("profile", metavar="PROFILE", help="lens profile (.json from `fieldcal calibrate`)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=run_show)

    d = add_parser(psub, "diff", "compare two lens profiles against their joint uncertainty",
                   "fieldcal profile diff before.json after.json --json --plot diff/",
                   description=_DIFF_DESCRIPTION)
    d.add_argument("a", metavar="A", help="first lens profile")
    d.add_argument("b", metavar="B", help="second lens profile (differences are A - B)")
    d.add_argument("--level", type=float, default=0.95,
                   help="confidence level of the whole comparison (default 0.95)")
    d.add_argument("--json", action="store_true", help="print the fieldcal-profile-diff/1 document instead of text")
    d.add_argument("--out", metavar="DIFF.json", help="also write the fieldcal-profile-diff/1 document here")
    d.add_argument("--plot", metavar="DIR", help="write difference maps (PNG) into DIR")
    d.add_argument("--grid", type=int, default=16, metavar="NX",
                   help="grid columns across the field (rows follow the aspect ratio; default 16)")
    d.add_argument("--draws", type=int, default=10000, metavar="N",
                   help="simulated null draws that calibrate each max-|z| test (default 10000)")
    d.add_argument("--fail-if-significant", action="store_true",
                   help=f"exit with status {EXIT_SIGNIFICANT} when the profiles differ significantly")
    d.add_argument("--overwrite", action="store_true", help="replace an existing --out file or plots")
    d.set_defaults(func=run_diff)

    e = add_parser(psub, "export", "write a lens profile for other tools (Lensfun)",
                   "fieldcal profile export lens.json --format lensfun --out lens.xml",
                   description=_EXPORT_DESCRIPTION)
    e.add_argument("profile", metavar="PROFILE", help="lens profile (.json from `fieldcal calibrate`)")
    e.add_argument("--format", required=True, choices=["lensfun"], help="output format")
    e.add_argument("--out", required=True, metavar="FILE.xml", help="output file")
    e.add_argument("--z", type=float, default=None, metavar="UM",
                   help="stage position of the exported geometry (default: the calibrated focus)")
    e.add_argument("--allow-no-distortion", action="store_true",
                   help="export a profile without absolute distortion (texture-only): TCA only, no distortion "
                        "element (Lensfun then leaves the geometry alone)")
    e.add_argument("--lens-name", help="the lens's model name in the database (default: the stack's lens name)")
    e.add_argument("--camera-name", help="the camera's model name (default: the stack's camera, else "
                                         "'calibrated camera')")
    e.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    e.set_defaults(func=run_export)
    p.set_defaults(func=lambda args: _no_action(p))


def _no_action(p) -> int:
    p.print_help()
    return 2


def run_show(args) -> int:
    from fieldcal.profile import LensProfile
    from fieldcal.profile.show import format_summary, profile_summary
    s = profile_summary(LensProfile.load(args.profile))
    if args.json:
        from fieldcal.formats.atomic import jsonable
        print(json.dumps(jsonable(s), indent=1, ensure_ascii=False))
    else:
        print(format_summary(s))
    return 0


def run_diff(args) -> int:
    from pathlib import Path

    from fieldcal.formats import documents
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile import LensProfile
    from fieldcal.profile.diff import diff_profiles
    from fieldcal.profile.diff_plots import plot_file_name, write_plots
    from fieldcal.profile.lens_profile import profile_files

    inputs = profile_files(args.a) + profile_files(args.b)
    if args.out:
        check_output(args.out, inputs=inputs, overwrite=args.overwrite, suffixes=(".json",))
    a, b = LensProfile.load(args.a), LensProfile.load(args.b)
    doc, maps = diff_profiles(a, b, level=args.level, nx=args.grid, n_null=args.draws)
    if args.plot:
        check_output(args.plot, inputs=inputs, overwrite=args.overwrite, kind="dir", field="--plot",
                     files=[plot_file_name(n) for n in maps["families"]])
        doc["plots"] = [str(p) for p in write_plots(maps, args.plot, Path(args.a).stem, Path(args.b).stem)]
    if args.out:
        documents.write(args.out, doc, "profile-diff")
    if args.json:
        sys.stdout.write(documents.dumps(doc, "profile-diff", args.out or "stdout", indent=1))
    else:
        print("\n".join(doc["summary"]))
        if args.plot:
            print(f"plots in {args.plot}")
    sys.stdout.flush()
    return EXIT_SIGNIFICANT if (args.fail_if_significant and doc["significant"]) else 0


def run_export(args) -> int:
    from fieldcal.formats.atomic import atomic_write_text, check_output
    from fieldcal.profile import LensProfile
    from fieldcal.profile.lens_profile import profile_files
    from fieldcal.profile.lensfun import lensfun_model, lensfun_xml

    out = check_output(args.out, inputs=profile_files(args.profile), overwrite=args.overwrite,
                       suffixes=(".xml",))
    prof = LensProfile.load(args.profile)
    model = lensfun_model(prof, z_um=args.z, allow_no_distortion=args.allow_no_distortion)
    atomic_write_text(out, lensfun_xml(prof, model, lens_name=args.lens_name, camera_name=args.camera_name))
    for note in model.notes:
        print(f"warning: {note}", file=sys.stderr)
    fit = ", ".join(f"{ch} {v:.3f}" + (f" / {model.max_err_outside_px[ch]:.3f}"
                                        if math.isfinite(model.max_err_outside_px[ch]) else "")
                    for ch, v in model.max_err_px.items())
    dist = ("no distortion" if model.k1 is None else
            f"poly5 k1 {model.k1:.4g}, k2 {model.k2:.4g} about ({model.centre_px[0]:.1f}, {model.centre_px[1]:.1f}) px")
    where = ("fitted over the whole frame; px inside the board's field / beyond it" if model.k1 is not None
             else "px, the TCA fit")
    print(f"wrote {out} (Lensfun database version 1): geometry at z = {model.z_um:.1f} µm; source: "
          f"{model.source}; {dist}; largest error against the profile {fit or 'n/a'} ({where})")
    return 0
