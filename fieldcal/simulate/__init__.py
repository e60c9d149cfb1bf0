"""Simulated frames and stacks: :class:`Renderer` (a scene through a ``fieldcal-lens/1`` lens at a stage
position) and :func:`simulate_stack` (a ``fieldcal-stack/1`` folder plus its ground truth).

See docs/simulator.md for the physics and its assumptions.
"""

from .render import RENDERER_VERSION, Renderer

__all__ = ["Renderer", "RENDERER_VERSION", "simulate_stack"]


def __getattr__(name):
    if name == "simulate_stack":  # lazy: pulls in the stack writer and the chart generator
        from .stackgen import simulate_stack
        return simulate_stack
    raise AttributeError(f"module 'fieldcal.simulate' has no attribute {name!r}")
