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
