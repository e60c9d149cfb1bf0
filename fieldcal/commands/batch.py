"""`fieldcal batch calibrate STACK... --out DIR`: one calibration per stack on Dask, and a fleet report.

Exit status: 0 when every stack was calibrated; otherwise the exit status of the failed units' errors (the
largest when they differ: 2 a bad stack, 4 the machine, 5 a bug), after every other unit has finished. 4 also
when Dask is not installed (``pip install -e ".[dask]"``) or its scheduler cannot be reached. docs/batch.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import add_parser

# library fields whose flag has another name (the rest map by each option's dest)
FIELD_FLAGS = {"fs_cyc_per_mm": "--fs"}
# the options `batch calibrate` takes over from `calibrate` (same flags, defaults and help)
SHARED_CALIBRATE = ("fs", "q", "effort", "z_ref_um", "tile_px", "measure", "chart", "seed",
                    "stage_repeatability_um", "no_verify")

EXAMPLE = ("fieldcal batch calibrate unit-*/ --out profiles --fs 10 --effort quick   "
           "# a LocalCluster, one worker per CPU\n"
           "  fieldcal batch calibrate unit-*/ --out profiles --scheduler tcp://10.0.0.5:8786   # an existing cluster")


def add_scheduler_options(p: argparse.ArgumentParser, default: str | None = "local") -> None:
    """``--scheduler`` and ``--workers`` (batch commands and ``validate --lenses``)."""
    from fieldcal.batch.engine import SCHEDULER_HELP
    p.add_argument("--scheduler", default=default, metavar="local|threads|tcp://HOST:PORT",
                   help=SCHEDULER_HELP + (f" (default {default})" if default else ""))
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of a local cluster (default: one per CPU); each uses one thread")


def _inherit(p: argparse.ArgumentParser, command: str, dests: tuple[str, ...]) -> None:
    """Give ``p`` the options ``dests`` of ``fieldcal COMMAND`` as that command defines them."""
    import importlib

    tmp = argparse.ArgumentParser(add_help=False)
    importlib.import_module(f"fieldcal.commands.{command}").register(tmp.add_subparsers())
    src = next(a for a in tmp._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    actions = {a.dest: a for a in src._actions}
    for d in dests:
        p._add_action(actions[d])


def register(sub):
    p = add_parser(sub, "batch", "run a command over many inputs on Dask distributed (a fleet of lenses)", EXAMPLE,
                   description="Run one task per input on Dask distributed: a LocalCluster by default, or an "
                               "existing scheduler (--scheduler tcp://HOST:PORT). A failed unit is reported with "
                               "its error and the others finish. Needs the optional extra: pip install -e "
                               "\".[dask]\" (docs/batch.md).")
    bs = p.add_subparsers(dest="batch_command", metavar="COMMAND")
    c = add_parser(bs, "calibrate", "calibrate many stacks, one Dask task each, and report the fleet's spread",
                   EXAMPLE, description="Calibrate every STACK as `fieldcal calibrate STACK --out DIR/NAME.json` "
                   "would (NAME: the stack folder's name, -2, -3 ... after a name already taken), one Dask task "
                   "per stack, and write DIR/fleet.json (fieldcal-fleet/1) and DIR/fleet.png: the spread of the "
                   "best-focus surfaces and tolerances across the units and the units that differ significantly "
                   "from the fleet. A stack that fails is reported (name and error) and the others finish; the "
                   "exit status is then that of the failure (2 bad input, 4 the machine, 5 a bug).")
    c.add_argument("stacks", nargs="+", metavar="STACK", help="fieldcal-stack/1 folders of chart stacks")
    c.add_argument("--out", required=True, help="folder of the profiles (NAME.json each) and the fleet report")
    add_scheduler_options(c)
    _inherit(c, "calibrate", SHARED_CALIBRATE)
    c.add_argument("--no-plots", action="store_true", help="write fleet.json only, no fleet.png")
    c.add_argument("--overwrite", action="store_true", help="replace existing profiles and fleet report in --out")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    c.set_defaults(func=run_calibrate)


def exit_status(results) -> int:
    """0 when every unit finished, else the failed units' exit status (the largest when they differ)."""
    return max((r.exit_code for r in results if not r.ok), default=0)


def report_units(command: str, results, debug: bool = False) -> None:
    """The failed units, each with its error, on stderr (always: this is the batch's result)."""
    failed = [r for r in results if not r.ok]
    if not failed:
        return
    lines = [f"fieldcal {command}: {len(failed)} of {len(results)} unit(s) FAILED (the others finished):"]
    for r in failed:
        msg = str(r.error).replace("\n", "\n      ")
        lines.append(f"  {r.name}: error (exit {r.exit_code}): {msg}")
        if debug and r.trace:
            lines.append(r.trace)
    print("\n".join(lines), file=sys.stderr, flush=True)


def unit_status(r) -> None:
    """One status line per finished unit (fieldcal.progress conventions)."""
    from fieldcal.progress import enabled
    if not enabled():
        return
    from tqdm import tqdm
    head = str(r.error).splitlines()[0] if r.error else ""
    # tqdm.write prints above the progress bar instead of through it
    tqdm.write(f"  {'ok  ' if r.ok else 'FAIL'}  {r.name} ({r.time_s:.1f} s)" + (f": {head}" if not r.ok else ""),
               file=sys.stderr)


def _validate_options(args) -> None:
    from fieldcal.optics import valid_fs_cyc_per_mm, valid_q
    valid_fs_cyc_per_mm(args.fs)
    valid_q(args.q)


def run_calibrate(args) -> int:
    import os

    from fieldcal.batch.calibrate import CALIBRATE_OPTIONS, CalibrateJob, calibrate_unit, unit_names
    from fieldcal.batch.engine import check_scheduler, require_dask, run_units
    from fieldcal.batch.fleet import GRID, REPORT_FILES, fleet_document, fleet_statistics, write_fleet_report
    from fieldcal.formats.atomic import check_output
    from fieldcal.progress import status

    scheduler = check_scheduler(args.scheduler, args.workers)
    require_dask()  # before any work: exit 4 with the install command
    _validate_options(args)
    stacks = [Path(s).parent if Path(s).name == "stack.json" else Path(s) for s in args.stacks]
    _refuse_repeats(stacks)
    names = unit_names(stacks)
    files = [f"{n}.json" for n in names] + list(REPORT_FILES)
    out = check_output(args.out, inputs=stacks, kind="dir", overwrite=args.overwrite, files=files)
    out_abs = Path(os.path.abspath(out))
    options = {kw: getattr(args, dest) for kw, dest in CALIBRATE_OPTIONS.items()}
    jobs = [(n, CalibrateJob(stack=os.path.abspath(s), out=str(out_abs / f"{n}.json"), options=options,
                             verify=not args.no_verify, grid=GRID)) for n, s in zip(names, stacks)]
    status(f"batch calibrate: {len(jobs)} stack(s) on {scheduler}"
           + (f" ({args.workers} worker(s))" if args.workers else ""), args.quiet)
    results = run_units(calibrate_unit, jobs, scheduler=scheduler, workers=args.workers, desc="calibrating",
                        unit="stack", quiet=args.quiet, on_result=None if args.quiet else unit_status)
    _name_unit_flags(results)
    units = []
    for (n, job), r in zip(jobs, results):
        units.append({**r.summary(), "input": job.stack, "output": job.out if r.ok else None})
    maps = {r.name: r.value["maps"] for r in results if r.ok}
    stats = fleet_statistics(maps, GRID) if maps else None
    doc = fleet_document("batch calibrate", units, stats, grid=GRID, fs_cyc_per_mm=args.fs, q=args.q,
                         scheduler=scheduler, workers=args.workers)
    written = write_fleet_report(doc, stats, out, plot=not args.no_plots)
    report_units("batch calibrate", results, debug=_debug())
    n_ok = sum(r.ok for r in results)
    sig = (doc["fleet"] or {}).get("significant", [])
    print(f"fieldcal batch calibrate: {n_ok} of {len(results)} stack(s) calibrated into {out}; "
          f"{len(sig)} unit(s) differ significantly from the fleet"
          + (f" ({', '.join(s['unit'] for s in sig)})" if sig else "") + f"; report {written[0]}")
    return exit_status(results)


def _refuse_repeats(stacks: list[Path]) -> None:
    """One stack given twice (by two spellings of its path, or a link) would be two identical units: the fleet's
    spread would shrink and its mean lean towards that unit."""
    from fieldcal.errors import ParameterError

    seen: dict[Path, Path] = {}
    for s in stacks:
        key = s.resolve()
        if key in seen:
            same = "" if str(seen[key]) == str(s) else f" (as {seen[key]})"
            raise ParameterError(f"is given twice{same}: one unit would count as two in the fleet's statistics",
                                 path=s, field="STACK", fix="give each stack once")
        seen[key] = s


def _debug() -> bool:
    """``--debug`` (which the CLI takes off the command line) or FIELDCAL_DEBUG=1: show failed units' tracebacks."""
    import os
    return "--debug" in sys.argv or os.environ.get("FIELDCAL_DEBUG", "") not in ("", "0")


def _name_unit_flags(results) -> None:
    """A unit's error that names an API field (``fs_cyc_per_mm``) names the flag instead (``--fs``)."""
    for r in results:
        if r.ok or not r.field:
            continue
        for api, flag in FIELD_FLAGS.items():
            if r.field.split(" ", 1)[0] == api and r.error:
                r.error = r.error.replace(f"field '{r.field}'", f"field '{flag}{r.field[len(api):]}'", 1)

