"""Plans from files to files: what ``fieldcal plan stack|sweep`` does, as Python.

:func:`stack_plan_file` and :func:`sweep_plan_file` load a lens profile (or a lens spec's truth), plan, draw the
optional pictures and write the ``fieldcal-plan/1`` document; each returns the document written.
"""

from __future__ import annotations

from pathlib import Path

from .load import load_profile
from .planfile import write_plan
from .stack_plan import StackRequest, plan_stack
from .sweep_plan import SweepRequest, plan_sweep, write_sweep_plan


def stack_plan_file(profile, request: StackRequest, out: str | Path, *, size_px: tuple[int, int] | None = None,
                    plots: str | Path | None = None) -> dict:
    """Plan a focal stack for the lens in ``profile`` (a ``fieldcal-profile/1`` or ``fieldcal-lens/1`` file).

    Parameters
    ----------
    profile : path
        Lens profile, or a lens spec (planned from its true surfaces; ``size_px`` renders it at another size).
    request : StackRequest
        The criterion (``fs_cyc_per_mm``, ``q``), confidence, limits and scene.
    out : path
        The plan file (JSON) to write.
    plots : path, optional
        Folder for ``stack-plan.png``.
    """
    prof, info = load_profile(profile, size_px)
    plan = plan_stack(prof, request)
    doc = plan.to_dict(info)
    doc["parameters"]["profile_source"] = info["source"]
    if plots:
        from .plots import plot_stack_plan
        plot_stack_plan(prof, plan, Path(plots) / "stack-plan.png")
    write_plan(out, doc)
    return doc


def sweep_plan_file(profile, request: SweepRequest, out: str | Path, *, size_px: tuple[int, int] | None = None,
                    plots: str | Path | None = None) -> dict:
    """Plan a focal sweep (exposure windows and device masks) for the lens in ``profile``; see
    :func:`stack_plan_file`. ``plots`` gets ``sweep-masks.png``, ``sweep-windows.png`` and ``alpha-trade.png``."""
    prof, info = load_profile(profile, size_px)
    plan = plan_sweep(prof, request)
    if plots:
        from .plots import plot_alpha_trade, plot_masks, plot_windows
        d = Path(plots)
        plot_masks(plan, d / "sweep-masks.png")
        plot_windows(plan, d / "sweep-windows.png")
        plot_alpha_trade(prof, plan, d / "alpha-trade.png")
    return write_sweep_plan(plan, out, info, extra_parameters={"profile_source": info["source"]})
