"""`fieldcal capture`: a thin CLI over :func:`fieldcal.capture.run_capture`."""

from __future__ import annotations

import json
import re
import sys

from . import add_parser

EXAMPLE = ("fieldcal capture --z -100 100 10 --stage sim --camera sim:models/triplet-uncorrected.json,size=320x180 "
           "--out S\n  fieldcal capture --plan plan.json --stage gcs:/dev/ttyUSB0,zero_mm=7.5 --camera pylon,pixel_pitch_um=3.45 --out S\n"
           "  fieldcal capture --z -100 100 10 --stage sim:fail_after=7 --camera sim:models/triplet-uncorrected.json "
           "--out S   (injected fault; re-run without it to resume)\n"
           "  fieldcal capture --plan sweep.json --stage sim --camera sim:models/triplet-uncorrected.json,size=320x180 "
           "--exposure-device sim:sweep-masks --out swept   (a focal sweep: one exposure over a constant-velocity "
           "move)")

# library field -> the flag that sets it (library errors name API fields; the user sees flags)
FLAGS = {"start_um": "--z", "stop_um": "--z", "step_um": "--z", "exposure_ms": "--exposure-ms",
         "overshoot_um": "--overshoot-um", "approach": "--approach", "settle_ms": "--settle-ms",
         "on_target_timeout_ms": "--on-target-timeout-ms", "retries": "--retries", "frames": "--z",
         "z_um": "--z / --plan", "focal_length_mm": "--focal-length-mm",
         "object_distance_mm": "--object-distance-mm", "exposure_device": "--exposure-device",
         "velocity_um_s": "--plan"}


def register(sub):
    p = add_parser(sub, "capture", "run a plan on a stage and camera into a crash-safe, resumable stack", EXAMPLE,
                   description="Move the stage to every planned position (approached from one side), snap a frame, "
                               "and commit it to a fieldcal-stack/1 folder (frame fsynced and renamed, then a "
                               "journal line fsynced). Re-running the same command resumes: intact frames are "
                               "kept, torn ones re-taken; a changed plan is refused; a second capture into the "
                               "same folder is refused while the first runs. A sweep plan (`fieldcal plan sweep "
                               "--device pixel`) runs as one exposure over a constant-velocity move, the per-pixel "
                               "windows applied by --exposure-device. Device strings: docs/hardware.md.")
    # argparse takes "-1e3" for an option (its negative-number pattern has no exponent): widen it, so that
    # `--z -1e3 1e3 100` parses and out-of-range values get a message naming --z
    if hasattr(p, "_negative_number_matcher"):
        p._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)(e[+-]?\d+)?$|^-(inf|infinity|nan)$", re.I)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--plan", metavar="PLAN.json", help="a fieldcal-plan/1 stack or sweep plan")
    src.add_argument("--z", nargs=3, type=float, metavar=("START", "STOP", "STEP"),
                     help="positions START, START+STEP, ... STOP in um")
    p.add_argument("--stage", default="sim", help="sim | sim:OPTIONS | gcs:PORT[,OPTIONS] | pi:PORT | a plug-in "
                                                  "(default: sim)")
    p.add_argument("--camera", required=True, help="sim:LENS.json[,size=WxH] | pylon[:SERIAL] | a plug-in")
    p.add_argument("--exposure-device", metavar="DEVICE", help="per-pixel exposure device for a sweep plan: "
                                                               "sim:MASKS (the folder `fieldcal plan export-masks` "
                                                               "wrote) | a plug-in")
    p.add_argument("--out", required=True, metavar="STACK", help="output stack folder (created or resumed)")
    p.add_argument("--exposure-ms", type=float, help="exposure for every frame (overrides the plan's)")
    p.add_argument("--approach", choices=["+z", "-z"], help="side every position is approached from "
                                                            "(default: the plan's direction of travel)")
    p.add_argument("--overshoot-um", type=float, default=20.0, help="back-off distance before approaching "
                                                                    "a position; more than the backlash (default 20)")
    p.add_argument("--settle-ms", type=float, default=0.0, help="extra wait after on-target (default 0)")
    p.add_argument("--on-target-timeout-ms", type=float, default=30000.0, help="per move (default 30000)")
    p.add_argument("--retries", type=int, default=2, help="resync-and-retry attempts per frame after a link "
                                                          "error (default 2)")
    p.add_argument("--focal-length-mm", type=float, help="the lens's focal length, recorded in stack.json (and by "
                                                         "calibration in the profile) where the camera does not "
                                                         "state it; overrides the camera's")
    p.add_argument("--object-distance-mm", type=float, help="the chart's distance from the lens, recorded like "
                                                            "--focal-length-mm (refocusing a plan needs both)")
    p.add_argument("--chart", metavar="TARGETS.json", help="record the ChArUco board in view (targets.json of "
                   "`fieldcal targets`) in stack.json, for `calibrate`'s geometry maps")
    p.add_argument("--dry-run", action="store_true", help="print the acquisition stream, positions, time and disk "
                                                          "needed; move nothing")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _with_flag(exc):
    flag = FLAGS.get((exc.field or "").split("[")[0].split(".")[-1]) if exc.path is None else None
    if flag:
        exc.field = flag
        exc.args = (exc._format(),)
    return exc


def run(args) -> int:
    from ..capture import CapturePlan, Interrupted, LensRecord, RunOptions, run_capture
    from ..errors import ParameterError
    from ..progress import status

    try:
        options = RunOptions(retries=args.retries, on_target_timeout_ms=args.on_target_timeout_ms,
                             settle_ms=args.settle_ms, quiet=args.quiet)
        lens = LensRecord(focal_length_mm=args.focal_length_mm, object_distance_mm=args.object_distance_mm)
        common = dict(exposure_ms=args.exposure_ms, approach=args.approach, overshoot_um=args.overshoot_um)
        plan = (CapturePlan.from_file(args.plan, **common) if args.plan
                else CapturePlan.from_range(*args.z, **common))
        chart = None
        if args.chart:  # read before the stage moves: a bad chart file costs no capture
            from ..charts.targets import chart_record_from_targets
            chart = chart_record_from_targets(args.chart)
    except ParameterError as exc:
        raise _with_flag(exc) from None
    from ..formats.atomic import check_output
    # the shared output checks (a path through a file, the plan or chart as --out): capture's own rules on the
    # folder (new, or a capture folder to resume; never a folder it did not create) follow in run_capture
    check_output(args.out, inputs=[args.plan, args.chart], kind="dir", overwrite=True, field="--out")
    try:
        r = run_capture(plan, args.stage, args.camera, args.out, options=options, dry_run=args.dry_run, lens=lens,
                        exposure_device=args.exposure_device)
    except Interrupted as exc:
        print(f"fieldcal capture: interrupted ({exc}); the stage was stopped and {args.out} is resumable: re-run "
              "the same command", file=sys.stderr)
        return 130
    if args.dry_run:
        print(json.dumps(r, indent=2))
        print(f"{r['n_frames']} frames, {r['n_moves']} moves, about {r['time_s']:.1f} s, "
              f"{r['disk_bytes'] / 1e6:.1f} MB" + ("" if r["fits_travel"] else
                                                  "; the plan does NOT fit the stage's travel"), file=sys.stderr)
        return 0 if r["fits_travel"] else 2
    if chart is not None:
        from ..formats.stack import record_chart
        record_chart(r.path, chart)
    status(f"capture: {r.path}: {r.n_frames} frames ({r.taken} taken, {r.skipped} already there, "
           f"{r.retaken} torn re-taken)", args.quiet)
    return 0
