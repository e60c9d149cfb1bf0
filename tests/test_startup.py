"""The program's start-up: NumPy submodules no command uses load on first use, not with SciPy."""
import subprocess
import sys
import textwrap


def test_unused_numpy_modules_load_on_first_use_not_with_scipy():
    """In a fresh interpreter (pytest itself has numpy.testing loaded): after the deferral, importing SciPy's FFT
    and ndimage (whose array-API layer runs ``from numpy import *``) leaves numpy.testing and numpy.f2py
    unexecuted; their first use runs them and works as an ordinary import. A module already imported is left
    alone (the second call defers nothing)."""
    code = textwrap.dedent("""
        import sys
        from fieldcal._startup import defer_unused_numpy_modules
        assert defer_unused_numpy_modules() == ["numpy.f2py", "numpy.testing"]
        import numpy, scipy.fft, scipy.ndimage
        assert type(sys.modules["numpy.testing"]).__name__ == "_LazyModule", type(sys.modules["numpy.testing"])
        assert type(sys.modules["numpy.f2py"]).__name__ == "_LazyModule"
        assert "numpy.testing._private" not in sys.modules
        from numpy.testing import assert_allclose
        assert_allclose(numpy.ones(3), [1.0, 1.0, 1.0])
        assert type(sys.modules["numpy.testing"]) is type(sys), type(sys.modules["numpy.testing"])
        assert numpy.testing is sys.modules["numpy.testing"]
        assert defer_unused_numpy_modules() == []
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "ok"
