"""`fieldcal plan stack|sweep PROFILE`: make a focal-stack or focal-sweep plan (``fieldcal-plan/1``);
`fieldcal plan export-masks PLAN`: a sweep plan's masks as device files (``fieldcal-masks/1``)."""

from __future__ import annotations

from ..progress import status
from . import add_parser, parse_size

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"fs_cyc_per_mm": "--fs"}


def _channels(text):
    return None if not text else tuple(c for c in text.replace(" ", "").split(",") if c)


def _common(p):
    p.add_argument("profile", metavar="PROFILE", help="lens profile (fieldcal-profile/1) or lens spec (fieldcal-lens/1)")
    p.add_argument("--out", required=True, help="plan file to write (JSON)")
    p.add_argument("--roi", help="region of interest X,Y,W,H in pixels (default: whole image)")
    p.add_argument("--channels", help="comma-separated subset of channels, e.g. G or R,G,B (default: all)")
    p.add_argument("--object-distance-mm", type=float, help="refocus for this object distance (profile must know its own)")
    p.add_argument("--direction", choices=("+z", "-z"), default="+z", help="stage direction of travel: +z (default) or -z (write --direction=-z)")
    p.add_argument("--grid-step-px", type=int, default=8, help="surface sampling step in pixels (default 8)")
    p.add_argument("--size", help="plan a lens spec at another image size WxH (same sensor area)")
    p.add_argument("--plots", metavar="DIR", help="also write PNG pictures of the plan into DIR")
    p.add_argument("--overwrite", action="store_true", help="replace an existing plan (and its pictures)")


def register(sub):
    p = add_parser(sub, "plan", "make a focal-stack or focal-sweep plan from a lens profile",
                   "fieldcal plan stack lens.json --fs 80 --q 0.05 --out plan.json")
    ps = p.add_subparsers(dest="plan_kind", metavar="KIND")
    s = add_parser(ps, "stack", "fewest frames keeping every pixel within its focus tolerance (paper IV.B)",
                   "fieldcal plan stack models/triplet-uncorrected.json --fs 80 --q 0.05 --confidence 0.95 "
                   "--channels G --out stack-plan.json --plots plan-plots")
    _common(s)
    s.add_argument("--fs", type=float, required=True, help="spatial frequency to preserve (cycles/mm at the sensor)")
    s.add_argument("--q", type=float, required=True, help="allowed MTF loss at fs, in (0, 1)")
    s.add_argument("--confidence", type=float, help="cover every pixel with this probability (shrinks tolerances)")
    s.add_argument("--coverage", type=float, default=0.99,
                   help="add frames until this expected fraction of pixels is within tolerance under the "
                        "profile's uncertainty (default 0.99; 0 for the fewest frames)")
    s.add_argument("--max-frames", type=int, help="at most this many frames (then reports the q achieved)")
    s.add_argument("--max-time-ms", type=float, help="at most this much time (frames x (exposure + overhead))")
    s.add_argument("--exposure-ms", type=float, default=20.0, help="exposure per frame (default 20 ms)")
    s.add_argument("--frame-overhead-ms", type=float, default=0.0, help="stage move + settle per frame (default 0)")
    s.add_argument("--placement", choices=("optimal", "paper"), default="optimal",
                   help="optimal cover (default) or the paper's: first frame at the on-axis best focus")
    s.set_defaults(func=run_stack)
    w = add_parser(ps, "sweep", "focal sweep with per-pixel exposure windows and device masks (paper IV.C)",
                   "fieldcal plan sweep models/singlet-colour.json --alpha-um 20 --pixel-exposure-ms 16 "
                   "--device lcos --cfa RGGB --out sweep-plan.json --plots plan-plots")
    _common(w)
    w.add_argument("--alpha-um", type=float, required=True, help="half sweep range per pixel α (µm)")
    w.add_argument("--pixel-exposure-ms", type=float, required=True, help="exposure of each pixel t_s (ms)")
    w.add_argument("--device", choices=("pixel", "lcos"), default="pixel",
                   help="per-pixel start/stop sensor (default) or LCoS with a hold limit and complement")
    w.add_argument("--slot-ms", type=float, help="LCoS: time each mask is shown (default: t_s split to fit the hold limit)")
    w.add_argument("--max-hold-ms", type=float, default=20.0, help="LCoS: longest time one image may be shown (20)")
    w.add_argument("--clock-us", type=float, default=10.0, help="pixel device: register clock period (µs)")
    w.add_argument("--cfa", choices=("RGGB", "BGGR", "GRBG", "GBRG"), help="Bayer pattern of the sensor (CFA-aware masks)")
    w.add_argument("--fs", type=float, default=80.0, help="frequency for the IPSF MTF column (cycles/mm, default 80)")
    w.add_argument("--wiener-nsr", type=float, default=0.01, help="Wiener noise-to-signal ratio for the noise gain")
    w.add_argument("--confidence", type=float,
                   help="widen each pixel's window by the profile's credible band at this probability")
    w.set_defaults(func=run_sweep)
    e = add_parser(ps, "export-masks", "write a sweep plan's masks as device files (LCoS 1-bit PNGs or pixel-wise "
                   "16-bit start/stop TIFFs) with a masks.json manifest",
                   "fieldcal plan export-masks sweep-plan.json --out sweep-masks")
    e.add_argument("plan", metavar="PLAN", help="sweep plan (fieldcal-plan/1) with its .masks.npz beside it")
    e.add_argument("--out", required=True, help="folder to write (replaced as a whole with --overwrite)")
    e.add_argument("--format", choices=("lcos", "pixelwise"),
                   help="device format; must match the plan's --device (default: the plan's)")
    e.add_argument("--overwrite", action="store_true", help="replace an earlier export in --out")
    e.set_defaults(func=run_export_masks)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


def _scene(args):
    from ..plan.scene import Scene, parse_roi
    return Scene(roi=parse_roi(args.roi) if args.roi else None, channels=_channels(args.channels),
                 object_distance_mm=args.object_distance_mm)


def _check_outputs(args, files: tuple[str, ...], masks: bool = False) -> None:
    """Refuse --out/--plots before planning: not the profile (or its sidecar), not an existing file."""
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files
    inputs = profile_files(args.profile)
    out = check_output(args.out, inputs=inputs, overwrite=args.overwrite)
    if masks:
        # write_sweep_plan puts the masks in PLAN.masks.npz beside the plan
        check_output(out.with_name(out.stem + ".masks.npz"), inputs=inputs, overwrite=args.overwrite)
    if args.plots:
        check_output(args.plots, inputs=inputs, overwrite=args.overwrite, kind="dir", files=files,
                     field="plots")


def run_stack(args) -> int:
    _check_outputs(args, ("stack-plan.png",))
    from ..plan.files import stack_plan_file
    from ..plan.stack_plan import StackRequest
    req = StackRequest(fs_cyc_per_mm=args.fs, q=args.q, confidence=args.confidence, scene=_scene(args),
                       coverage=None if args.coverage == 0 else args.coverage, max_frames=args.max_frames, max_time_ms=args.max_time_ms, exposure_ms=args.exposure_ms,
                       frame_overhead_ms=args.frame_overhead_ms, placement=args.placement,
                       direction=args.direction, grid_step_px=args.grid_step_px)
    status(f"planning a focal stack from {args.profile} ...")
    doc = stack_plan_file(args.profile, req, args.out, size_px=parse_size(args.size), plots=args.plots)
    print(f"{args.out}: {doc['n_frames']} frames over D = {doc['D_um']:.1f} µm ({doc['direction']}), "
          f"q achieved {doc['q_achieved']:.4f}, total exposure {doc['total_exposure_ms']:.0f} ms, "
          f"coverage probability {doc['coverage']['probability']:.4f}")
    for wmsg in doc["warnings"]:
        print(f"note: {wmsg}")
    return 0


def run_sweep(args) -> int:
    _check_outputs(args, ("sweep-masks.png", "sweep-windows.png", "alpha-trade.png"), masks=True)
    from ..plan.files import sweep_plan_file
    from ..plan.sweep_plan import SweepRequest
    req = SweepRequest(alpha_um=args.alpha_um, pixel_exposure_ms=args.pixel_exposure_ms, device=args.device,
                       slot_ms=args.slot_ms, max_hold_ms=args.max_hold_ms, clock_us=args.clock_us, cfa=args.cfa,
                       scene=_scene(args), direction=args.direction, grid_step_px=args.grid_step_px,
                       fs_cyc_per_mm=args.fs, wiener_nsr=args.wiener_nsr, confidence=args.confidence)
    status(f"planning a focal sweep from {args.profile} ...")
    doc = sweep_plan_file(args.profile, req, args.out, size_px=parse_size(args.size), plots=args.plots)
    print(f"{args.out}: sweep {doc['start_um']:.1f} -> {doc['stop_um']:.1f} µm at {doc['velocity_um_per_ms']:.3f} µm/ms, "
          f"T = {doc['total_time_ms']:.1f} ms (D = {doc['range_um']:.1f} µm), masks in {doc['masks']['file']}")
    print("  alpha_um    T_ms  MTF@fs  Wiener_gain  restored@fs  gain_to_in_focus")
    for r in doc["alpha_trade"]:
        print(f"  {r['alpha_um']:8.1f} {r['total_time_ms']:7.1f} {r['mtf_at_fs']:7.3f} {r['noise_gain']:12.3f} "
              f"{r['restored_mtf_at_fs']:12.3f} {r['noise_gain_to_in_focus']:17.3f}")
    return 0


def run_export_masks(args) -> int:
    from ..plan.device_masks import export_plan_file
    status(f"exporting the masks of {args.plan} ...")
    man = export_plan_file(args.plan, args.out, fmt=args.format, overwrite=args.overwrite)
    print(f"{args.out}: {len(man['files'])} {man['device']} files for {', '.join(man['planes'])}, "
          f"{man['total_bytes'] / 1e6:.3f} MB, manifest masks.json")
    return 0
