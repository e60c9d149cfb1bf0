"""fieldcal: calibrate a lens's field curvature and emulate a curved sensor with focal stacks and sweeps.

The public API (docs/architecture.md)::

    import fieldcal
    stack = fieldcal.Stack.open("STACK")
    profile = fieldcal.calibrate(stack)
    profile.save("lens.json"); profile = fieldcal.LensProfile.load("lens.json")
    profile.best_focus_um(x, y, "G"); profile.best_focus_interval_um(x, y, "G", level=0.9)
    profile.magnification(z_um, "G"); profile.shift_px(z_um, "G")

Attributes are imported lazily so that ``import fieldcal`` stays fast and light.
"""

from __future__ import annotations

__version__ = "0.1.0"

from ._lazy import lazy_names

#: public name -> the module it lives in (imported on first use)
_LAZY = {
    "Stack": "fieldcal.formats.stack",
    "StackWriter": "fieldcal.formats.stack",
    "LensSpec": "fieldcal.simulate.lens",
    "LensProfile": "fieldcal.profile.lens_profile",
    "TruthProfile": "fieldcal.simulate.truth",
    "LensModel": "fieldcal.optics.model",
    "MTFCriterion": "fieldcal.optics.criterion",
    "calibrate": "fieldcal.calibration.pipeline",
    "measure_mtf": "fieldcal.measure.mtf",
    "import_stack": "fieldcal.formats.importer",
    "FieldcalError": "fieldcal.errors",
}

__all__ = ["__version__", *_LAZY]

__getattr__, __dir__ = lazy_names(__name__, _LAZY, globals())
