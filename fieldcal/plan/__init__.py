"""Planning: focal-stack plans and focal-sweep plans (``fieldcal-plan/1``) from a lens profile."""

from .scene import Scene
from .stack_plan import StackPlan, StackRequest, plan_stack

__all__ = ["Scene", "StackPlan", "StackRequest", "plan_stack"]
