"""Compositing: all-in-focus images from through-focus stacks and focal sweeps (docs/compositing.md).

``composite_stack`` (profile / depth-from-focus / hybrid); ``select_plan_frames`` (a stack plan's frames);
``composite_sweep`` (emulate + deconvolve) and ``restore_sweep_image`` (a captured sweep) for sweeps, built on
``emulate_sweep`` + ``deconvolve_sweep``; ``composite_to_file`` is the whole ``fieldcal composite`` path;
``write_composite`` (TIFF, PNG or JPEG by extension) for output; ``ArrayStack`` composites frames held in memory.
"""

from .api import (METHODS, CompositeOutput, PlanSelection, SweepComposite, composite_stack, composite_sweep,
                  composite_to_file, restore_sweep_image, select_plan_frames)
from .io import read_composite_metadata, write_composite, write_composite_tiff
from .source import ArrayStack
from .stack_profile import CompositeResult, composite_profile
from .sweep import SweepResult, deconvolve_sweep, emulate_sweep

__all__ = ["METHODS", "ArrayStack", "CompositeOutput", "CompositeResult", "PlanSelection", "SweepComposite",
           "SweepResult", "composite_profile", "composite_stack", "composite_sweep", "composite_to_file",
           "deconvolve_sweep", "emulate_sweep", "read_composite_metadata", "restore_sweep_image",
           "select_plan_frames", "write_composite", "write_composite_tiff"]
