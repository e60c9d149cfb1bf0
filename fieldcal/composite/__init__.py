"""Compositing: all-in-focus images from through-focus stacks and focal sweeps (docs/compositing.md).

``composite_stack`` (profile / depth-from-focus / hybrid); ``select_plan_frames`` (a stack plan's frames);
``composite_sweep`` (emulate + deconvolve) and ``restore_sweep_image`` (a captured sweep) for sweeps, built on
``emulate_sweep`` + ``deconvolve_sweep``; ``composite_to_file`` is the whole ``fieldcal composite`` path;
``write_composite`` (TIFF, PNG or JPEG by extension) for output; ``ArrayStack`` composites frames held in memory.
"""

from .._lazy import lazy_names

# The names below are imported on first use (PEP 562): ``fieldcal composite`` starts decoding the first frames
# (composite/source.py, :func:`~fieldcal.composite.source.prefetch_frames`) before the compositor's modules and
# SciPy import, which importing this package would otherwise do first.
_WHERE = {"METHODS": ".api", "CompositeOutput": ".api", "PlanSelection": ".api", "SweepComposite": ".api",
          "composite_stack": ".api", "composite_sweep": ".api", "composite_to_file": ".api",
          "restore_sweep_image": ".api", "select_plan_frames": ".api", "read_composite_metadata": ".io",
          "write_composite": ".io", "write_composite_tiff": ".io", "ArrayStack": ".source",
          "CompositeResult": ".stack_profile", "composite_profile": ".stack_profile", "SweepResult": ".sweep",
          "deconvolve_sweep": ".sweep", "emulate_sweep": ".sweep"}

__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())


__all__ = ["METHODS", "ArrayStack", "CompositeOutput", "CompositeResult", "PlanSelection", "SweepComposite",
           "SweepResult", "composite_profile", "composite_stack", "composite_sweep", "composite_to_file",
           "deconvolve_sweep", "emulate_sweep", "read_composite_metadata", "restore_sweep_image",
           "select_plan_frames", "write_composite", "write_composite_tiff"]
