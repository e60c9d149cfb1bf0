"""Import a benchmark script (benchmarks/*.py, not a package) as a module, for tests of its pure helpers."""

import importlib
import sys
from pathlib import Path

BENCH_DIR = str(Path(__file__).resolve().parents[1] / "benchmarks")


def import_bench(name: str):
    """``benchmarks/<name>.py`` as a module; the folder is on sys.path only while it is imported."""
    sys.path.insert(0, BENCH_DIR)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(BENCH_DIR)
