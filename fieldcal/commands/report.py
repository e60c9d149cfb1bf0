"""`fieldcal report PROFILE --out DIR`: PNG plots and an HTML page for a lens profile."""

from __future__ import annotations

from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"fs_cyc_per_mm": "--fs"}


def register(sub):
    p = add_parser(sub, "report", "plots and an HTML page for a lens profile (or a simulated lens's truth)",
                   "fieldcal report lens.json --out report/")
    p.add_argument("profile", help="lens profile (.json from `fieldcal calibrate`) or a fieldcal-lens/1 spec")
    p.add_argument("--out", required=True, help="folder for index.html and the PNGs")
    p.add_argument("--fs", type=float, default=None, help="frequency of the tolerance map (default: calibration's)")
    p.add_argument("--q", type=float, default=None, help="MTF loss of the tolerance map (default: calibration's)")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier report in --out")
    p.set_defaults(func=run)


def run(args) -> int:
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files
    from fieldcal.report.calibration_report import REPORT_FILES, self_check_summary, write_report
    from fieldcal.optics import valid_fs_cyc_per_mm, valid_q
    # before any work or write: a bad --fs/--q found while plotting left the first pictures of a report behind
    if args.fs is not None:
        valid_fs_cyc_per_mm(args.fs)
    if args.q is not None:
        valid_q(args.q)
    check_output(args.out, inputs=profile_files(args.profile), overwrite=args.overwrite, kind="dir",
                 files=REPORT_FILES)
    from fieldcal.profile.lens_profile import load_profile_or_truth
    profile, _ = load_profile_or_truth(args.profile)
    print(f"wrote {write_report(profile, args.out, fs=args.fs, q=args.q)}")
    line, warn = self_check_summary(profile)
    if line:
        print(f"self-check: {line}")
    if warn:
        print(f"warning: {warn}")
    return 0
