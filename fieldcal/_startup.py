"""Start-up of the ``fieldcal`` program: what the process loads before any command runs."""
from __future__ import annotations

import importlib.util
import sys

#: NumPy submodules that no fieldcal command uses but that SciPy's array-API layer (SciPy >= 1.14: its
#: ``array_api_compat.numpy`` clones NumPy's namespace with ``from numpy import *``, which imports every public
#: submodule NumPy's ``__all__`` names) would load on every ``import scipy.fft`` / ``scipy.ndimage``: ~70 ms of
#: the composite's start-up on one core (docs/benchmarks.md ``bench_composite_speed_s20``).
UNUSED_NUMPY_MODULES = ("numpy.f2py", "numpy.testing")


def defer_unused_numpy_modules(names=UNUSED_NUMPY_MODULES) -> list[str]:
    """Make ``names`` (NumPy submodules not yet imported) load on first use instead of at ``import scipy``.

    Each is put in ``sys.modules`` (and on its parent) as the standard library's lazy module
    (:class:`importlib.util.LazyLoader`): the module object exists, and its code runs the first time one of its
    attributes is read, so ``import numpy.testing`` and ``numpy.testing.assert_allclose(...)`` work as before;
    a ``from numpy import *`` only binds the object. Modules already imported, absent or not NumPy's are left
    alone. Returns the names deferred.
    """
    import numpy

    deferred = []
    for name in names:
        parent, _, child = name.rpartition(".")
        if parent != "numpy" or name in sys.modules or child in vars(numpy):
            continue
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        # on the parent too: NumPy's module __getattr__ imports its lazy submodules with `import numpy.x as x`,
        # which reads the attribute back (and would recurse into __getattr__ without it)
        setattr(numpy, child, module)
        spec.loader.exec_module(module)
        deferred.append(name)
    return deferred
