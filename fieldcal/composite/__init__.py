"""Compositing: all-in-focus images from through-focus stacks and focal sweeps (docs/compositing.md)."""

from .source import ArrayStack
from .stack_profile import CompositeResult, composite_profile

__all__ = ["ArrayStack", "CompositeResult", "composite_profile"]
