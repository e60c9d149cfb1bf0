"""DESIGN.md's public API, whatever was imported first."""

import subprocess
import sys


def test_calibrate_is_callable_after_importing_the_submodule(small_chart_stack):
    import fieldcal
    import fieldcal.calibration.pipeline  # noqa: F401  (must not shadow the function)
    import fieldcal.cli  # noqa: F401
    assert callable(fieldcal.calibrate)
    profile = fieldcal.calibrate(fieldcal.Stack.open(small_chart_stack), fs_cyc_per_mm=8.0, effort="quick",
                                 quiet=True)
    assert profile.channels == ("R", "G", "B")
    assert isinstance(profile, fieldcal.LensProfile)


def test_public_names_in_a_fresh_interpreter():
    # every stage package imported first must not shadow the public function
    code = ("import fieldcal, fieldcal.calibration, fieldcal.profile, fieldcal.formats, fieldcal.simulate;"
            "assert callable(fieldcal.calibrate) and fieldcal.calibrate is fieldcal.calibration.calibrate;"
            "assert hasattr(fieldcal.Stack, 'open') and hasattr(fieldcal.LensProfile, 'load');"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
