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


@pytest.fixture(scope="session")
def samples_spectral_db(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map database of data/samples/00 (spectral model, absolute input paths), built
    once per session. Tests must not write to it: copy it first."""
    from typer.testing import CliRunner

    from disco_cli.cli import app

    out = tmp_path_factory.mktemp("samples_db") / "s00.db"
    args = ["build-db", str(samples / "00"), "-o", str(out), "-m", "spectral"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return out
