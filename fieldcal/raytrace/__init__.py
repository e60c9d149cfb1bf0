"""Independent optical check of the simulator: prescription tables, paraxial validation, ray-traced best focus.

``prescription`` and ``paraxial`` need only numpy; ``optiland_backend``, ``bestfocus`` and ``build`` trace real
rays with optiland, the optional ``raytrace`` extra (``pip install -e ".[raytrace]"``). See docs/raytrace.md.
"""

from .paraxial import ParaxialData, paraxial
from .prescription import GLASS_CATALOGUE, Prescription, Surface, load_prescription, model_glass_index

__all__ = ["GLASS_CATALOGUE", "ParaxialData", "Prescription", "Surface", "load_prescription",
           "model_glass_index", "paraxial"]
