"""`fieldcal composite`: an all-in-focus image from a through-focus stack, or a deconvolved focal sweep."""

from __future__ import annotations

from ..progress import status
from . import add_parser

# the API fields composite_to_file's errors name, where the flag is spelt differently
FIELD_FLAGS = {"fs_cyc_per_mm": "--fs", "breathing": "--breathing", "zone_px": "--zone-px",
               "camera_noise": "--camera-noise", "max_memory": "--max-memory", "z_ref_um": "--z-ref-um"}

EXAMPLE = ("fieldcal composite STACK --profile lens.json --out image.tiff\n"
           "  fieldcal composite STACK --out image.tiff                      (no profile: depth from focus)\n"
           "  fieldcal composite STACK --profile lens.json --method hybrid --plan plan.json --out image.tiff\n"
           "  fieldcal composite STACK --profile lens.json --sweep-alpha-um 20 --out sweep.tiff  (emulated sweep)\n"
           "  fieldcal composite sweep.tiff --profile lens.json --sweep-alpha-um 20 --out restored.tiff\n"
           "  fieldcal composite sweep.tiff --profile lens.json --sweep-alpha-um 20 --breathing blind --out b.tiff")


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
    p.add_argument("--out", required=True, metavar="IMAGE", help="output image: .tiff keeps the stack's bit depth; .png (8/16-bit) or .jpg for viewing")
    p.add_argument("--method", choices=["profile", "dff", "hybrid"],
                   help="where each pixel is in focus: the profile's surfaces, depth from focus, or the profile "
                        "refined by depth from focus (default: profile with --profile, dff without)")
    p.add_argument("--plan", metavar="PLAN", help="stack plan (fieldcal-plan/1): use its frames and tolerance")
    p.add_argument("--sweep-alpha-um", type=float, metavar="ALPHA",
                   help="focal sweep of half-range ALPHA µm around each pixel's best focus (paper: 20)")
    p.add_argument("--deconvolve", choices=["wiener", "rl", "none"], default="wiener",
                   help="sweep deconvolution with the integrated PSF (default wiener)")
    p.add_argument("--rl-iterations", type=int, default=30, metavar="N", help="Richardson-Lucy iterations")
    p.add_argument("--breathing", choices=["aware", "blind"], default=None,
                   help="captured sweep image: deconvolve per field zone with the image motion (breathing, shift) "
                        "during each pixel's window and register to the profile's z_ref geometry (aware), or per "
                        "zone without the motion (blind). Default: aware when the profile breathes or has geometry "
                        "maps and --deconvolve is wiener, else one kernel for the whole image")
    p.add_argument("--zone-px", type=int, metavar="PX",
                   help="captured sweep image: size of the deconvolution zones (default 64)")
    p.add_argument("--camera-noise", type=float, nargs=2, metavar=("GAIN_DN_PER_E", "READ_NOISE_E"),
                   help="captured sweep image: the camera's gain (DN per electron) and read noise (electrons), from "
                        "its photon-transfer calibration, for the Wiener filter's noise (default: estimated from "
                        "the image, which texture inflates)")
    p.add_argument("--fs", type=float, dest="fs_cyc_per_mm", metavar="CYC_PER_MM",
                   help="frequency of the focus tolerance that sets seam width (default: plan's, or Nyquist/4)")
    p.add_argument("--q", type=float, default=None, help="allowed MTF drop of the focus tolerance (default 0.05)")
    p.add_argument("--z-ref-um", type=float, metavar="Z",
                   help="without a profile: output in the geometry of the frame nearest stage position Z, within the "
                        "frames' z range (default: the middle frame); breathing and shift are measured from the "
                        "stack")
    p.add_argument("--no-register", action="store_true",
                   help="without a profile: take the frames as registered (no breathing/shift measurement)")
    p.add_argument("--lateral-colour", action="store_true",
                   help="also undo lateral colour (register every channel to the reference channel)")
    p.add_argument("--depth", choices=["auto", "flat", "3d"], default="auto",
                   help="dff/hybrid: a flat scene (best focus from a smooth surface) or one with depth (per pixel, "
                        "edge-aware); auto decides from how well a surface fits the measured depths (default)")
    p.add_argument("--defocus", choices=["measured", "none"], default="measured",
                   help="a scene with depth and no profile with an F-number: measure the blur's growth per frame "
                        "from the stack and combine the frames by its Wiener filter where that is reliable "
                        "(default), or choose frames per pixel (none)")
    p.add_argument("--max-memory", metavar="SIZE",
                   help="without a profile (dff, hybrid): the memory the composite may take, e.g. 8G (default: "
                        "the memory available now); a composite that would need more is refused before any work")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--no-verify", action="store_true",
                   help="use frames whose content no longer matches the sha256 stack.json records")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    import os

    from ..composite import source
    from ..composite.memory import single_threaded_blas, tune_allocator

    tune_allocator()  # planes reused from the heap, not mapped and zeroed afresh (composite/memory.py)
    if (os.path.isdir(args.stack) and args.profile is None and args.sweep_alpha_um is None and args.plan is None
            and not args.no_register):
        # the first frames decoded (GIL released) while the compositor's modules import on this core
        source.prefetch_frames(args.stack)
    try:
        return _run(args)
    finally:
        source.end_prefetch()


def _run(args) -> int:
    from ..composite.api import composite_to_file
    from ..composite.memory import single_threaded_blas, single_threaded_opencv

    single_threaded_blas()
    single_threaded_opencv()

    res = composite_to_file(args.stack, args.out, profile=args.profile, method=args.method, plan=args.plan,
                            sweep_alpha_um=args.sweep_alpha_um, deconvolve=args.deconvolve,
                            rl_iterations=args.rl_iterations, fs_cyc_per_mm=args.fs_cyc_per_mm, q=args.q,
                            z_ref_um=args.z_ref_um, register=not args.no_register,
                            lateral_colour=args.lateral_colour, depth=args.depth, overwrite=args.overwrite,
                            verify=not args.no_verify, quiet=args.quiet,
                            breathing=args.breathing or "auto", zone_px=args.zone_px,
                            camera_noise=tuple(args.camera_noise) if args.camera_noise else None,
                            max_memory=args.max_memory, measured_defocus=args.defocus == "measured")
    if "sweep" in res.metadata:
        info = res.metadata["sweep"]
        gains = {c: round(v.get("noise_gain", float("nan")), 2) for c, v in info.get("channels", {}).items()
                 if "noise_gain" in v}
        extra = f", noise gain {gains}" if gains else ""
        if info.get("breathing"):
            extra += f", breathing {info['breathing']}"
        status(f"wrote {res.path} (sweep, alpha {info.get('alpha_um')} µm{extra})", args.quiet)
    else:
        status(f"wrote {res.path} ({res.method}, {res.metadata.get('frames_used')} frames)", args.quiet)
    return 0
