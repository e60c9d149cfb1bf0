"""`fieldcal validate LENS`: the whole pipeline on a simulated lens, every stage compared with the truth.

`fieldcal validate --lenses N` does it for N random simulated lenses, one Dask task each (fieldcal.batch).

Exit status: 0 when every check passes, 1 when a check fails (the report says which), 2 for a user error
(bad lens file or parameter), 4 when a pipeline stage is not available yet (or, with --lenses, Dask is not
installed). With --lenses, a lens whose run failed gives that failure's status after the others finished.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ParameterError
from . import add_parser, parse_size

EXAMPLE = ("fieldcal validate models/triplet-uncorrected.json --out validation   "
           "# 640 px wide, fs = 0.4 Nyquist; open validation/index.html\n"
           "  fieldcal validate models/triplet-uncorrected.json --size 256x144 --effort quick --out v   "
           "# a quick try\n"
           "  fieldcal validate --lenses 8 --size 256x192 --effort quick --out fleet-validation   "
           "# 8 random lenses on a LocalCluster")

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"size_px": "--size", "fs_cyc_per_mm": "--fs"}


def _confidence(text: str):
    if text.lower() in ("none", "off", "0"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise ParameterError(f"confidence must be a number in (0, 1) or 'none', got {text!r}", field="confidence",
                             fix="e.g. 0.9") from None
    return v


def register(sub):
    p = add_parser(sub, "validate", "end-to-end check against a simulated lens's truth", EXAMPLE,
                   description="Simulate a chart stack from the lens, calibrate, plan a stack, simulate a scene at the "
                               "planned positions and composite it; compare every step with the simulator's truth "
                               "(surface errors, band coverage, geometry, plan coverage, composite PSNR against a "
                               "one-shot frame and the true-surface oracle) and write a report (PNG plots, "
                               "index.html, report.md, summary.json). Exit 0 when every check passes, 1 when one "
                               "fails, 2 for a user error. With --lenses N, N random simulated lenses instead, "
                               "one Dask task each (OUT/lens-KKK/ per lens, OUT/fleet.json; docs/batch.md).")
    p.add_argument("lens", nargs="?", default=None,
                   help="simulated lens spec (fieldcal-lens/1 JSON), e.g. models/triplet-uncorrected.json")
    p.add_argument("--lenses", type=int, default=None, metavar="N",
                   help="validate N random simulated lenses (fieldcal.fit.synthetic.random_lens, drawn from "
                        "--seed) instead of LENS, one Dask task each")
    from .batch import add_scheduler_options
    add_scheduler_options(p, default=None)
    p.add_argument("--out", default="validation", help="report folder (default: validation)")
    p.add_argument("--size", type=str, default=None,
                   help="render size WxH over the same sensor area (default 640 px wide at the sensor's aspect, "
                        "e.g. 640x360)")
    p.add_argument("--fs", type=float, default=None,
                   help="target frequency, cycles/mm (default 0.4 x Nyquist of the render size)")
    p.add_argument("--q", type=float, default=0.05, help="allowed MTF loss at fs (default 0.05)")
    p.add_argument("--effort", choices=("quick", "standard", "thorough"), default="standard",
                   help="calibration effort (default standard)")
    p.add_argument("--seed", type=int, default=0, help="seed of charts, noise and samplers (default 0)")
    p.add_argument("--scene", default="chart",
                   help="scene to composite: chart (dead leaves), texture (colour dead leaves) or an image file")
    p.add_argument("--confidence", type=str, default="0.9",
                   help="coverage probability the plan asks of the profile's band, or 'none' (default 0.9)")
    p.add_argument("--profile", default="calibrate",
                   help="calibrate (the full pipeline, default), truth (skip calibration; checks planning and "
                        "compositing) or PROFILE.json (judge a saved fieldcal-profile/1 calibrated at --size)")
    p.add_argument("--keep-stacks", action="store_true", help="keep the chart and scene stacks in OUT/stacks/")
    p.add_argument("--no-plots", action="store_true", help="write only summary.json, report.md and index.html")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..progress import status

    if args.lenses is not None or args.scheduler is not None or args.workers is not None:
        return run_lenses(args)
    if args.lens is None:
        raise ParameterError("give a lens spec, or --lenses N for random lenses", field="lens",
                             fix="e.g. fieldcal validate models/triplet-uncorrected.json --out validation")
    from fieldcal.validation.run import ValidateConfig, validate
    from fieldcal.validation.report import write_report

    given = None if args.profile in ("calibrate", "truth") else args.profile  # a profile file to judge
    cfg = _config(args, given)
    from fieldcal.formats.atomic import check_output
    from fieldcal.profile.lens_profile import profile_files
    scene_file = args.scene if Path(args.scene).is_file() else None
    inputs = [args.lens, scene_file, *(profile_files(given) if given else [])]
    out = check_output(args.out, inputs=inputs, kind="dir", overwrite=True,
                       files=("index.html", "report.md", "summary.json"))
    workdir = out / "stacks" if args.keep_stacks else None
    result = validate(args.lens, cfg, workdir=workdir, profile=given)
    write_report(result, out, plots=not args.no_plots)
    for c in result.checks:
        status(f"  {'pass' if c.passed else 'FAIL'}  {c.name}: {c.value:.4g} {c.op} {c.limit:.4g}")
    verdict = "all checks pass" if result.passed else f"{len(result.failed)} check(s) FAILED"
    print(f"fieldcal validate: {result.lens}: {verdict}; report in {out / 'index.html'}")
    return 0 if result.passed else 1


def _config(args, given=None):
    from fieldcal.validation.run import ValidateConfig
    return ValidateConfig(size_px=parse_size(args.size, minimum=1), fs_cyc_per_mm=args.fs, q=args.q,
                          effort=args.effort, seed=args.seed, scene=args.scene,
                          confidence=_confidence(args.confidence),
                          profile="calibrate" if given else args.profile)


def run_lenses(args) -> int:
    """``--lenses N``: one validation per random lens on Dask; OUT/lens-KKK/ each and OUT/fleet.json."""
    import os

    from fieldcal.batch.engine import check_scheduler, require_dask, run_units
    from fieldcal.batch.fleet import fleet_document, write_fleet_report
    from fieldcal.batch.lenses import REPORT_FILES, LensJob, unit_name, validate_unit
    from fieldcal.formats.atomic import check_output
    from fieldcal.progress import status

    from .batch import exit_status, report_units, unit_status, _debug

    if args.lenses is None:
        raise ParameterError("--scheduler and --workers apply to --lenses N", field="lenses",
                             fix="add --lenses N, or drop --scheduler/--workers to validate one lens")
    if args.lens is not None:
        raise ParameterError(f"give a lens spec or --lenses N, not both (got {args.lens!r})", field="lenses",
                             fix="drop LENS to validate random lenses, or --lenses to validate LENS")
    if args.lenses < 1:
        raise ParameterError(f"--lenses must be at least 1, got {args.lenses}", field="lenses", fix="e.g. --lenses 8")
    if args.profile not in ("calibrate", "truth"):
        raise ParameterError("a profile file belongs to one lens; random lenses are calibrated or use their truth",
                             field="profile", fix="use --profile calibrate or --profile truth with --lenses")
    scheduler = check_scheduler(args.scheduler or "local", args.workers)
    require_dask()
    cfg = _config(args)
    names = [unit_name(k) for k in range(args.lenses)]
    scene_file = args.scene if Path(args.scene).is_file() else None
    out = check_output(args.out, inputs=[scene_file], kind="dir", overwrite=True,
                       files=["fleet.json", *(f"{n}/{f}" for n in names for f in REPORT_FILES)])
    out_abs = Path(os.path.abspath(out))
    if scene_file:  # workers may run elsewhere: give them the absolute path
        from dataclasses import replace
        cfg = replace(cfg, scene=os.path.abspath(scene_file))
    jobs = [(n, LensJob(index=k, seed=args.seed, config=cfg, out=str(out_abs / n), keep_stacks=args.keep_stacks,
                        plots=not args.no_plots)) for k, n in enumerate(names)]
    status(f"validate: {len(jobs)} random lens(es) on {scheduler}"
           + (f" ({args.workers} worker(s))" if args.workers else ""))
    results = run_units(validate_unit, jobs, scheduler=scheduler, workers=args.workers, desc="validating",
                        unit="lens", on_result=unit_status)
    units = []
    for (n, job), r in zip(jobs, results):
        v = r.value or {}
        units.append({**r.summary(), "input": v.get("lens"), "output": job.out if r.ok else None,
                      "passed": v.get("passed"), "failed_checks": v.get("failed_checks", [])})
    doc = fleet_document("validate", units, None, scheduler=scheduler, workers=args.workers)
    written = write_fleet_report(doc, None, out)
    report_units("validate", results, debug=_debug())
    for u in units:
        if u["ok"]:
            status(f"  {'pass' if u['passed'] else 'FAIL'}  {u['name']}"
                   + (f": {', '.join(u['failed_checks'])}" if u["failed_checks"] else ""))
    n_pass = sum(bool(u["passed"]) for u in units)
    print(f"fieldcal validate: {n_pass} of {len(units)} random lens(es) pass every check; reports in "
          f"{out}/lens-*/index.html, summary {written[0]}")
    code = exit_status(results)
    return code if code else (0 if n_pass == len(units) else 1)
