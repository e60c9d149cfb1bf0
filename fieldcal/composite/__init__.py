"""Compositing: all-in-focus images from through-focus stacks and focal sweeps (docs/compositing.md).

``composite_stack`` (profile / depth-from-focus / hybrid), ``emulate_sweep`` + ``deconvolve_sweep`` for sweeps,
``write_composite_tiff`` for output; ``ArrayStack`` composites frames held in memory.
"""

from .api import METHODS, composite_stack
from .io import read_composite_metadata, write_composite_tiff
from .source import ArrayStack
from .stack_profile import CompositeResult, composite_profile
from .sweep import SweepResult, deconvolve_sweep, emulate_sweep

__all__ = ["METHODS", "ArrayStack", "CompositeResult", "SweepResult", "composite_profile", "composite_stack",
           "deconvolve_sweep", "emulate_sweep", "read_composite_metadata", "write_composite_tiff"]
