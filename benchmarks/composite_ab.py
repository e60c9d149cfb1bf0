"""One composite function of two checkouts, timed against each other inside one composite run, and compared.

``python benchmarks/composite_ab.py BASE_CHECKOUT MODULE FUNCTION STACK [Z_REF_UM]`` (with ``PYTHONPATH`` at the
checkout to measure): composites ``STACK`` with this checkout; when ``fieldcal.composite.MODULE.FUNCTION`` is
called, it is called three times in alternating order with this checkout's code and with ``BASE_CHECKOUT``'s
``fieldcal/composite/MODULE.py`` (executed as a module of this package, so its relative imports take this
checkout's modules), printing each call's wall and CPU (all threads) seconds, and then whether the two returned
the same numbers (arrays: ``np.array_equal`` and the largest difference; other results: their ``repr``). Both
calls get the same inputs, made once, so a phase's change is timed without the rest of the composite's noise.
Only a function that does not change its inputs can be compared this way.

Example (session 20's fine detail)::

    PYTHONPATH=. python benchmarks/composite_ab.py ../main-checkout detail fine_detail /tmp/s13speed/stack 0
"""
from __future__ import annotations

import importlib
import sys
import time
import types
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> None:
    if len(argv) not in (4, 5):
        sys.exit(__doc__)
    base, module, name, stack = argv[:4]
    z_ref = float(argv[4]) if len(argv) == 5 else None
    import fieldcal.composite.api as api
    from fieldcal.composite import memory

    for setup in ("tune_allocator", "single_threaded_blas", "single_threaded_opencv"):  # as `fieldcal composite`
        if hasattr(memory, setup):
            getattr(memory, setup)()
    new_mod = importlib.import_module(f"fieldcal.composite.{module}")
    old_mod = types.ModuleType(f"fieldcal.composite._base_{module}")
    old_mod.__package__ = "fieldcal.composite"
    sys.modules[old_mod.__name__] = old_mod
    path = Path(base) / "fieldcal" / "composite" / f"{module}.py"
    exec(compile(path.read_text(), str(path), "exec"), old_mod.__dict__)  # noqa: S102 (the base checkout's own module)
    new_fn, old_fn = getattr(new_mod, name), getattr(old_mod, name)

    def first(r):
        return r[0] if isinstance(r, tuple) else r

    def compared(*args, **kwargs):
        got = {}
        for rnd in range(3):
            pair = (("base", old_fn), ("this", new_fn)) if rnd % 2 == 0 else (("this", new_fn), ("base", old_fn))
            for tag, fn in pair:
                w0, c0 = time.perf_counter(), time.process_time()
                got[tag] = fn(*args, **kwargs)
                print(f"{name} {tag}: wall {time.perf_counter() - w0:.3f} s, CPU {time.process_time() - c0:.3f} s",
                      flush=True)
        a, b = first(got["base"]), first(got["this"])
        if isinstance(a, np.ndarray):
            diff = float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64)))) if a.size else 0.0
            print(f"equal: {np.array_equal(a, b)} (largest difference {diff:.3g})")
        else:
            print(f"equal: {repr(a) == repr(b)}")
        return got["this"]

    setattr(new_mod, name, compared)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="composite_ab-") as tmp:  # the composite itself is not kept
        api.composite_to_file(stack, Path(tmp) / "composite.tiff", z_ref_um=z_ref, quiet=True)


if __name__ == "__main__":
    main(sys.argv[1:])
