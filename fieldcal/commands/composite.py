"""`fieldcal composite`: an all-in-focus image from a through-focus stack, or a deconvolved focal sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ParameterError, SpecError, StackError
from ..progress import status
from . import add_parser

EXAMPLE = ("fieldcal composite STACK --profile lens.json --out image.tiff\n"
           "  fieldcal composite STACK --out image.tiff                      (no profile: depth from focus)\n"
           "  fieldcal composite STACK --profile lens.json --method hybrid --plan plan.json --out image.tiff\n"
           "  fieldcal composite STACK --profile lens.json --sweep-alpha-um 20 --out sweep.tiff  (emulated sweep)\n"
           "  fieldcal composite sweep.tiff --profile lens.json --sweep-alpha-um 20 --out restored.tiff")


def register(sub):
    p = add_parser(sub, "composite", "composite a stack into an all-in-focus image (or deconvolve a focal sweep)",
                   EXAMPLE,
                   description="Composite a through-focus stack into an all-in-focus image in the geometry of "
                               "the profile's z_ref, same channels, dtype and scale as the input (TIFF with "
                               "metadata). With --sweep-alpha-um, emulate a focal sweep from the stack (or take "
                               "a captured sweep image given instead of STACK) and deconvolve it with the "
                               "integrated PSF.")
    p.add_argument("stack", metavar="STACK", help="stack folder (fieldcal-stack/1), or a captured sweep image "
                                                  "(TIFF/PNG) with --sweep-alpha-um")
    p.add_argument("--profile", metavar="PROFILE",
                   help="lens profile (fieldcal-profile/1) or, for simulated data, a lens spec (fieldcal-lens/1)")
    p.add_argument("--out", required=True, metavar="IMAGE", help="output TIFF")
    p.add_argument("--method", choices=["profile", "dff", "hybrid"],
                   help="where each pixel is in focus: the profile's surfaces, depth from focus, or the profile "
                        "refined by depth from focus (default: profile with --profile, dff without)")
    p.add_argument("--plan", metavar="PLAN", help="stack plan (fieldcal-plan/1): use its frames and tolerance")
    p.add_argument("--sweep-alpha-um", type=float, metavar="ALPHA",
                   help="focal sweep of half-range ALPHA µm around each pixel's best focus (paper: 20)")
    p.add_argument("--deconvolve", choices=["wiener", "rl", "none"], default="wiener",
                   help="sweep deconvolution with the integrated PSF (default wiener)")
    p.add_argument("--rl-iterations", type=int, default=30, metavar="N", help="Richardson-Lucy iterations")
    p.add_argument("--fs", type=float, dest="fs_cyc_per_mm", metavar="CYC_PER_MM",
                   help="frequency of the focus tolerance that sets seam width (default: plan's, or Nyquist/4)")
    p.add_argument("--q", type=float, default=None, help="allowed MTF drop of the focus tolerance (default 0.05)")
    p.add_argument("--z-ref-um", type=float, metavar="Z",
                   help="without a profile: output in the geometry of stage position Z (default: the middle "
                        "frame); breathing and shift are measured from the stack")
    p.add_argument("--no-register", action="store_true",
                   help="without a profile: take the frames as registered (no breathing/shift measurement)")
    p.add_argument("--lateral-colour", action="store_true",
                   help="also undo lateral colour (register every channel to the reference channel)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--no-verify", action="store_true",
                   help="use frames whose content no longer matches the sha256 stack.json records")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def load_profile_for(path: str | Path, size_px: tuple[int, int]):
    """A lens profile (fieldcal-profile/1) or a lens spec's truth (fieldcal-lens/1) at the stack's size."""
    from fieldcal.profile.lens_profile import load_profile_or_truth
    return load_profile_or_truth(path, size_px)

def plan_frames(stack, plan_path: str | Path) -> tuple[np.ndarray, dict, dict]:
    """Stack frames matching a stack plan's positions, the plan's parameters and its metadata block."""
    from ..plan.planfile import read_plan

    doc = read_plan(plan_path)
    if doc["kind"] != "stack":
        raise SpecError(f"a {doc['kind']} plan cannot select stack frames", path=plan_path, field="kind",
                        fix="give the stack plan the stack was captured with (or no --plan)")
    z_plan = np.array([f["z_um"] for f in doc["frames"]], dtype=np.float64)
    z = np.asarray(stack.z_um, dtype=np.float64)
    spacing = float(np.min(np.abs(np.diff(np.sort(z_plan))))) if len(z_plan) > 1 else np.inf
    tol = max(1.0, 0.25 * spacing) if np.isfinite(spacing) else 1.0
    idx = []
    for zp in z_plan:
        k = int(np.argmin(np.abs(z - zp)))
        if abs(z[k] - zp) > tol:
            raise StackError(f"the plan's frame at z = {zp:g} µm is not in the stack (nearest {z[k]:g} µm)",
                             path=getattr(stack, "path", None), field="frames",
                             fix="composite without --plan, or capture the stack with this plan")
        idx.append(k)
    params = doc.get("parameters", {})
    return np.array(sorted(set(idx))), params, {"path": str(plan_path), "kind": "stack",
                                                "n_frames": len(z_plan), "refocus_um": doc.get("refocus_um", 0.0)}


def run(args) -> int:
    from ..composite import (composite_stack, deconvolve_sweep, emulate_sweep, write_composite_tiff)
    from ..composite.io import check_composite_output, read_single_image
    from ..composite.stack_profile import to_input_dtype

    out = check_composite_output(args.out, stack=args.stack, profile=args.profile, plan=args.plan,
                                 overwrite=args.overwrite)
    src = Path(args.stack)
    q = 0.05 if args.q is None else args.q
    if not 0.0 < q < 1.0:
        raise ParameterError(f"--q must be in (0, 1), got {q}", field="--q", fix="e.g. --q 0.05")
    if args.fs_cyc_per_mm is not None and not args.fs_cyc_per_mm > 0:
        raise ParameterError(f"--fs must be > 0, got {args.fs_cyc_per_mm}", field="--fs", fix="e.g. --fs 80")
    if args.sweep_alpha_um is not None and not (np.isfinite(args.sweep_alpha_um) and args.sweep_alpha_um > 0):
        raise ParameterError(f"--sweep-alpha-um must be > 0, got {args.sweep_alpha_um}", field="--sweep-alpha-um",
                             fix="e.g. --sweep-alpha-um 20")
    meta: dict = {"input": str(src)}

    if src.is_file():  # a captured sweep image
        if args.sweep_alpha_um is None or not args.profile:
            raise ParameterError("a single image is a captured sweep: it needs --sweep-alpha-um and --profile",
                                 path=src, field="STACK",
                                 fix="give a stack folder, or add --profile PROFILE --sweep-alpha-um ALPHA")
        if args.deconvolve == "none":
            raise ParameterError("nothing to do for a captured sweep with --deconvolve none", field="--deconvolve",
                                 fix="use --deconvolve wiener or rl")
        img = read_single_image(src)
        h, w = img.shape[:2]
        profile, pinfo = load_profile_for(args.profile, (w, h))
        channels = tuple(profile.channels)
        if len(channels) != img.shape[2]:
            raise ParameterError(f"the image has {img.shape[2]} channel(s), the profile {len(channels)}",
                                 path=src, field="channels", fix="use the profile of the camera that took it")
        if tuple(profile.image_size_px) != (w, h):
            raise ParameterError(f"the profile is for {profile.image_size_px} px images, the image is {w}x{h}",
                                 path=src, field="image_size_px", fix="use the profile of this camera")
        white = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
        res = deconvolve_sweep(img.astype(np.float32), profile, args.sweep_alpha_um, channels, black=0.0,
                               white=white, method=args.deconvolve, rl_iterations=args.rl_iterations)
        final = to_input_dtype(res.image, img.dtype, white)
        meta.update({"method": "sweep-captured", "profile": pinfo, "sweep": res.info})
        write_composite_tiff(out, final, channels, meta)
        _report_sweep(res.info, out, args.quiet)
        return 0

    from fieldcal.formats.stack import Stack
    stack = Stack.open(src, verify=not args.no_verify)
    if stack.cfa is not None:
        raise StackError(f"a raw {stack.cfa} mosaic stack cannot be composited per channel", path=src,
                         field="cfa", fix="demosaic the frames first (H x W x 3)")
    w, h = stack.shape[1], stack.shape[0]
    profile, pinfo = (None, None)
    if args.profile:
        profile, pinfo = load_profile_for(args.profile, (w, h))
    meta["profile"] = pinfo
    frames, fs = None, args.fs_cyc_per_mm
    if args.plan:
        frames, params, plan_meta = plan_frames(stack, args.plan)
        meta["plan"] = plan_meta
        fs = fs or params.get("fs_cyc_per_mm")
        if args.q is None and isinstance(params.get("q"), (int, float)):
            q = float(params["q"])
    if args.sweep_alpha_um is not None:
        if profile is None:
            raise ParameterError("sweep emulation needs a profile (each pixel's best focus and the PSF)",
                                 field="--profile", fix="add --profile PROFILE")
        stack.require_frames(2, "sweep emulation")
        sw = emulate_sweep(stack, profile, args.sweep_alpha_um, frames=frames, lateral_colour=args.lateral_colour,
                           quiet=args.quiet)
        info = dict(sw.info)
        img = sw.image
        if args.deconvolve != "none":
            res = deconvolve_sweep(img, profile, args.sweep_alpha_um, stack.channels, black=stack.black_level,
                                   white=stack.white_level, method=args.deconvolve,
                                   rl_iterations=args.rl_iterations, noise_sigma=sw.info["noise_sigma"])
            img = res.image
            info.update(res.info)
        meta.update({"method": "sweep-emulated", "sweep": info, "z_ref_um": float(profile.z_ref_um)})
        write_composite_tiff(out, to_input_dtype(img, stack.dtype, stack.white_level), stack.channels, meta)
        _report_sweep(info, out, args.quiet)
        return 0

    offset = float(meta.get("plan", {}).get("refocus_um") or 0.0) if args.plan else 0.0
    res = composite_stack(stack, profile, args.method, frames=frames, fs_cyc_per_mm=fs, q=q,
                          lateral_colour=args.lateral_colour, focus_offset_um=offset,
                          register=not args.no_register, z_ref_um=args.z_ref_um, quiet=args.quiet)
    z_ref = float(profile.z_ref_um) if profile is not None else res.info.get("registration", {}).get("z_ref_um")
    meta.update({"method": res.method, "z_ref_um": z_ref,
                 "lateral_colour_corrected": bool(args.lateral_colour), **res.info})
    write_composite_tiff(out, res.image, stack.channels, meta)
    status(f"wrote {out} ({res.method}, {res.info.get('frames_used')} frames)", args.quiet)
    return 0


def _report_sweep(info: dict, out: Path, quiet: bool) -> None:
    gains = {c: round(v.get("noise_gain", float("nan")), 2) for c, v in info.get("channels", {}).items()
             if "noise_gain" in v}
    extra = f", noise gain {gains}" if gains else ""
    status(f"wrote {out} (sweep, alpha {info.get('alpha_um')} µm{extra})", quiet)
