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
