"""Shared test fixtures. Tests find data through this file's location, never the cwd."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "data" / "samples"
# ../shared/realdata beside the checkout: real scans that must never be committed.
REALDATA = REPO.parent / "shared" / "realdata"


@pytest.fixture(scope="session")
def realdata() -> Path:
    """The real-scan folder, or skip when this machine does not have it."""
    if not REALDATA.is_dir():
        pytest.skip("../shared/realdata is absent")
    return REALDATA


@pytest.fixture(scope="session")
def samples() -> Path:
    if not SAMPLES.is_dir() or not any(SAMPLES.iterdir()):
        pytest.skip("data/samples is empty")
    return SAMPLES
