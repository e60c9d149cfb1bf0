"""Planning: focal-stack plans and focal-sweep plans (``fieldcal-plan/1``) from a lens profile.

See docs/planning.md for the method and the file format.
"""

from .planfile import read_plan, validate_plan, write_plan
from .scene import Scene
from .stack_plan import StackPlan, StackRequest, check_coverage, plan_stack
from .sweep_plan import SweepPlan, SweepRequest, plan_sweep, write_sweep_plan

__all__ = ["Scene", "StackPlan", "StackRequest", "SweepPlan", "SweepRequest", "check_coverage", "plan_stack",
           "plan_sweep", "read_plan", "validate_plan", "write_plan", "write_sweep_plan"]
