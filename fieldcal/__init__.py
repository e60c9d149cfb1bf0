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

_LAZY = {
    "Stack": ("fieldcal.formats.stack", "Stack"),
    "StackWriter": ("fieldcal.formats.stack", "StackWriter"),
    "LensSpec": ("fieldcal.simulate.lens", "LensSpec"),
    "LensProfile": ("fieldcal.profile.lens_profile", "LensProfile"),
    "TruthProfile": ("fieldcal.simulate.truth", "TruthProfile"),
    "LensModel": ("fieldcal.optics.model", "LensModel"),
    "MTFCriterion": ("fieldcal.optics.criterion", "MTFCriterion"),
    "calibrate": ("fieldcal.calibration.pipeline", "calibrate"),
    "measure_mtf": ("fieldcal.measure.mtf", "measure_mtf"),
    "import_stack": ("fieldcal.formats.importer", "import_stack"),
    "FieldcalError": ("fieldcal.errors", "FieldcalError"),
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib
        mod, attr = _LAZY[name]
        value = getattr(importlib.import_module(mod), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'fieldcal' has no attribute {name!r}")
