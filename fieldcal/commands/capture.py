"""`fieldcal capture`: run a stack plan (or a --z range) on a stage and a camera into a resumable stack."""

from __future__ import annotations

import json
import signal
import sys

from . import add_parser

EXAMPLE = ("fieldcal capture --z -100 100 10 --stage sim --camera sim:models/triplet-uncorrected.json,size=320x180 "
           "--out S\n  fieldcal capture --plan plan.json --stage gcs:/dev/ttyUSB0,zero_mm=7.5 --camera pylon,pixel_pitch_um=3.45 --out S\n"
           "  fieldcal capture --z -100 100 10 --stage sim:fail_after=7 --camera sim:models/triplet-uncorrected.json "
           "--out S   (injected fault; re-run without it to resume)")


def register(sub):
    p = add_parser(sub, "capture", "run a plan on a stage and camera into a crash-safe, resumable stack", EXAMPLE,
                   description="Move the stage to every planned position (approached from one side), snap a frame, "
                               "and commit it to a fieldcal-stack/1 folder (frame fsynced and renamed, then a "
                               "journal line fsynced). Re-running the same command resumes: intact frames are "
                               "kept, torn ones re-taken; a changed plan is refused. Device strings: "
                               "docs/hardware.md.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--plan", metavar="PLAN.json", help="a fieldcal-plan/1 stack plan")
    src.add_argument("--z", nargs=3, type=float, metavar=("START", "STOP", "STEP"),
                     help="positions START, START+STEP, ... STOP in um")
    p.add_argument("--stage", default="sim", help="sim | sim:OPTIONS | gcs:PORT[,OPTIONS] | pi:PORT | a plug-in "
                                                  "(default: sim)")
    p.add_argument("--camera", required=True, help="sim:LENS.json[,size=WxH] | pylon[:SERIAL] | a plug-in")
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
    p.add_argument("--dry-run", action="store_true", help="print positions, time and disk needed; move nothing")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _plan(args):
    from fieldcal.capture.acquire import CapturePlan
    if args.plan:
        return CapturePlan.from_file(args.plan, exposure_ms=args.exposure_ms, approach=args.approach,
                                     overshoot_um=args.overshoot_um)
    start, stop, step = args.z
    return CapturePlan.from_range(start, stop, step, exposure_ms=args.exposure_ms, approach=args.approach,
                                  overshoot_um=args.overshoot_um)


def _frame_bytes(cam: dict) -> int:
    w, h = cam.get("size_px") or (0, 0)
    if cam.get("roi"):
        w, h = cam["roi"][2], cam["roi"][3]
    return int(w) * int(h) * len(cam.get("channels") or ["Y"]) * (1 if (cam.get("bit_depth") or 16) <= 8 else 2)


def _sigterm(signum, frame):  # a `kill` is handled like Ctrl-C: stop the stage, leave a resumable folder
    raise KeyboardInterrupt


def run(args) -> int:
    from fieldcal.capture.acquire import capture
    from ..errors import ParameterError
    from ..hardware.registry import make_device
    from ..progress import status

    if args.retries < 0:
        raise ParameterError(f"--retries {args.retries} must be >= 0", field="--retries", fix="e.g. --retries 2")
    plan = _plan(args)
    stage = make_device("stage", args.stage)
    camera = make_device("camera", args.camera)
    old = signal.signal(signal.SIGTERM, _sigterm) if hasattr(signal, "SIGTERM") else None
    try:
        stage.connect()
        camera.connect()
        if hasattr(camera, "observe_stage"):
            camera.observe_stage(stage)
        if args.dry_run:
            cam = camera.describe()
            s = plan.summary(velocity_um_per_s=stage.velocity_um_per_s(), frame_bytes=_frame_bytes(cam),
                             exposure_ms=args.exposure_ms)
            lo, hi = stage.limits_um()
            s["stage_travel_um"] = [lo, hi]
            s["fits_travel"] = lo <= s["motion_range_um"][0] and s["motion_range_um"][1] <= hi
            print(json.dumps(s, indent=2))
            print(f"{s['n_frames']} frames, about {s['time_s']:.1f} s, {s['disk_bytes'] / 1e6:.1f} MB"
                  + ("" if s["fits_travel"] else "; the plan does NOT fit the stage's travel"), file=sys.stderr)
            return 0 if s["fits_travel"] else 2
        r = capture(plan, stage, camera, args.out, retries=args.retries,
                    on_target_timeout_ms=args.on_target_timeout_ms, settle_ms=args.settle_ms, quiet=args.quiet)
        status(f"capture: {r.path}: {r.n_frames} frames ({r.taken} taken, {r.skipped} already there, "
               f"{r.retaken} torn re-taken)", args.quiet)
        return 0
    except KeyboardInterrupt:
        print(f"fieldcal capture: interrupted; the stage was stopped and {args.out} is resumable: re-run the same "
              "command", file=sys.stderr)
        return 130
    finally:
        for dev in (camera, stage):
            try:
                dev.close()
            except Exception:  # closing must not replace the error being reported
                pass
        if old is not None:
            signal.signal(signal.SIGTERM, old)
