import os
from pathlib import Path

import pytest

os.environ.setdefault("FIELDCAL_PROGRESS", "0")
os.environ.setdefault("MPLBACKEND", "Agg")

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"


@pytest.fixture
def models_dir() -> Path:
    return MODELS


@pytest.fixture
def triplet_path() -> Path:
    return MODELS / "triplet-uncorrected.json"


@pytest.fixture(scope="session")
def small_chart_stack(tmp_path_factory):
    """A small simulated chart stack of the paper's triplet (256x144 px, same sensor area), with its truth.

    Shared by the calibration tests: fs must stay below this size's Nyquist (20 cycles/mm at 24.5 µm pixels).
    """
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack, z_grid

    spec = LensSpec.load(MODELS / "triplet-uncorrected.json")
    out = tmp_path_factory.mktemp("chart") / "stack"
    simulate_stack(spec, out, z_grid(-360.0, 50.0, 10.0), scene="chart", seed=3, size=(256, 144), progress=False)
    return out


@pytest.fixture(scope="session")
def hostile_world(tmp_path_factory):
    """A small chart stack S and its profile lens.json (256x144 px, 21 frames), built once for the hostile-input
    suites (tests/test_hostile_*.py); tests use a private copy (``w``)."""
    from fieldcal.cli import main

    root = tmp_path_factory.mktemp("hostile-world")
    assert main(["simulate", str(MODELS / "triplet-uncorrected.json"), str(root / "S"), "--z", "-360", "50", "20",
                 "--size", "256x144", "--quiet"]) == 0
    assert main(["calibrate", str(root / "S"), "--out", str(root / "lens.json"), "--fs", "16", "--effort",
                 "quick", "-q"]) == 0
    return root


def private_copy(world: Path, tmp_path: Path, name: str) -> Path:
    """A private copy of a session-built world for one test (links copied as links)."""
    import shutil

    dst = tmp_path / name
    shutil.copytree(world, dst, symlinks=True)
    return dst


@pytest.fixture
def w(hostile_world, tmp_path):
    """A private copy of the hostile-input world for one test."""
    return private_copy(hostile_world, tmp_path, "w")
