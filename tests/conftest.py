"""Shared fixtures: real recordings under ../shared/data/real (skipped when absent), quiet progress."""
import os
from pathlib import Path

import pytest

os.environ.setdefault("TI_CMAX_NO_PROGRESS", "1")

PROJECT_ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = PROJECT_ROOT.parent / "shared" / "data" / "real"


@pytest.fixture(scope="session")
def real_data() -> Path:
    """Folder of real event recordings; tests using it skip cleanly when it is absent."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real data folder not found: {REAL_DATA}")
    return REAL_DATA


@pytest.fixture(scope="session")
def ti_runtime():
    """Initialize Taichi once for kernel tests."""
    from ti_cmax.kernels import runtime

    runtime.ensure_init()
    return runtime.ti
