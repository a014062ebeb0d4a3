"""Shared test fixtures. Tests find data through this file's location, never the cwd."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "data" / "samples"
# ../shared/realdata beside the checkout: real scans that must never be committed.
REALDATA = REPO.parent / "shared" / "realdata"


def package_path() -> str:
    """The folder holding the `disco_cli` these tests import (site-packages after an
    install, src/ in a checkout whose compiled core lies there): PYTHONPATH for test
    subprocesses, so that they run the same code with its compiled core."""
    import disco_cli

    return str(Path(disco_cli.__file__).resolve().parent.parent)


def socket_listening(sock: Path) -> bool:
    """Whether a Unix socket at `sock` listens yet, without connecting to it (a test may
    count the server's clients). The server binds under a private name and moves the
    file into place after listen() (test_serve_limits checks that), so the file's
    existence says it listens; /proc/net/unix would name the private path instead."""
    return sock.is_socket()


# A shell's background job (CI's, say) inherits SIGINT ignored, and Python keeps it so.
# A `disco` child started by a test sets Python's own handler (KeyboardInterrupt) back,
# as a terminal's Ctrl-C would find it, in its first line. `preexec_fn` would run Python
# between fork and exec, which breaks a child forked while gRPC's threads run (the
# Milvus tests load it): it died with "epoll_wait error: Bad file descriptor".
DISCO_WITH_DEFAULT_SIGINT = [
    sys.executable,
    "-c",
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv[0] = 'disco'; runpy.run_module('disco_cli.cli', run_name='__main__')",
]


# pytest-xdist's workers (`make test` runs -n auto) find COLUMNS=80 and LINES=24 in their
# environment, which the shell and a serial run did not have (set as a worker starts). With
# both, rich sizes a dumb terminal by them instead of its 80 columns, and `disco query`'s
# table in the README's check came out wider. The workers get the shell's own values.
_TERMINAL_VARS = ("COLUMNS", "LINES")


def pytest_configure(config: pytest.Config) -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # the controller, or a serial run
        os.environ["DISCO_TEST_SHELL_TERMINAL"] = ",".join(
            f"{k}={os.environ[k]}" for k in _TERMINAL_VARS if k in os.environ
        )


@pytest.fixture(autouse=True)
def _shell_terminal_size() -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    given = dict(
        kv.split("=", 1) for kv in os.environ.get("DISCO_TEST_SHELL_TERMINAL", "").split(",") if kv
    )
    for key in _TERMINAL_VARS:
        if key in given:
            os.environ[key] = given[key]
        else:
            os.environ.pop(key, None)


KERNEL_LEVELS = {3: "level3", 2: "level2", 1: "level1", 0: "plain"}


@contextmanager
def kernel_level(level: int) -> Iterator[int]:
    """The compiled core's SIMD level capped at `level` within the block (the cap that
    the BEV kernels, the U-Net convolutions, the int8 signature scan and the polar
    resampling share); skips the test where this CPU or build has no such level."""
    from disco_cli import _core  # deferred: only the tests that ask for a level need the core

    previous = _core._set_bev_kernel_level(level)
    try:
        if _core._bev_kernel_level() != level:
            pytest.skip(f"this CPU or build has no kernel level {level}")
        yield level
    finally:
        _core._set_bev_kernel_level(previous)


# Every level up to the CPU's best is forced in turn, so that an AVX-512 machine also
# checks the AVX2, SSE2 and plain kernels, and an aarch64 one NEON and plain. Levels
# above the CPU's best are skipped: nothing here needs AVX-512.
@pytest.fixture(params=list(KERNEL_LEVELS), ids=list(KERNEL_LEVELS.values()))
def kernel(request: pytest.FixtureRequest) -> Iterator[int]:
    """Run a test on each SIMD kernel level the CPU has (each must agree with the
    test's reference)."""
    with kernel_level(request.param) as level:
        yield level


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


def _format1(db: Path, rel_paths: bool = True) -> None:
    """Rewrite the map at `db` in place as disco's format 1 (before checksums), as that
    version wrote it: one `scans` table with float32 signatures and raw float16 features
    beside them, `side_views` with float32 signatures, and no row checksums. Written
    here with sqlite3 and NumPy alone, not by disco's code. Its values are the format-2
    map's (float16 signatures widened to float32), so migrating it back loses nothing:
    tests/test_database_migration.py writes format-1 maps from float32 values instead."""
    import json
    import os
    import sqlite3
    import zlib

    import numpy as np

    src = sqlite3.connect(db)
    meta = dict(src.execute("SELECT key, value FROM meta"))
    scans = src.execute(
        "SELECT s.id, s.path, s.rel_path, s.time, s.x, s.y, s.z, s.yaw, s.signature, "
        "s.signature_scale, f.scale, f.data FROM scans s JOIN features f ON f.id = s.id "
        "ORDER BY s.id"
    ).fetchall()
    offsets = json.loads(meta.get("side_views_m", "[]"))
    views = (
        src.execute(
            "SELECT scan_id, offset_m, signature, signature_scale FROM side_views"
        ).fetchall()
        if offsets
        else []
    )
    src.close()
    for suffix in ("", "-wal", "-shm"):
        Path(f"{db}{suffix}").unlink(missing_ok=True)
    meta = {k: v for k, v in meta.items() if k not in ("generation", "signature_dtype")}
    meta.pop("feature_codec", None)
    meta["format_version"] = "1"

    def f32(sig: bytes, scale: float) -> bytes:
        return (np.frombuffer(sig, "<f2").astype(np.float32) * np.float32(scale)).tobytes()

    conn = sqlite3.connect(db)
    with conn:
        conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        rel = ", rel_path TEXT" if rel_paths else ""
        conn.execute(
            "CREATE TABLE scans (id INTEGER PRIMARY KEY, path TEXT NOT NULL UNIQUE, time REAL, "
            "x REAL, y REAL, z REAL, yaw REAL, signature BLOB NOT NULL, features BLOB NOT NULL, "
            f"feature_scale REAL NOT NULL{rel})"
        )
        if offsets:
            conn.execute(
                "CREATE TABLE side_views (scan_id INTEGER NOT NULL, offset_m REAL NOT NULL, "
                "signature BLOB NOT NULL, PRIMARY KEY (scan_id, offset_m))"
            )
        conn.executemany("INSERT INTO meta VALUES (?, ?)", sorted(meta.items()))
        for rid, path, relp, t, x, y, z, yaw, sig, ss, fs, data in scans:
            row = [rid, path, t, x, y, z, yaw, f32(sig, ss), zlib.decompress(data, -15), fs]
            marks = ",".join("?" * (len(row) + rel_paths))
            conn.execute(f"INSERT INTO scans VALUES ({marks})", row + ([relp] if rel_paths else []))
        for rid, off, sig, ss in views:
            conn.execute("INSERT INTO side_views VALUES (?, ?, ?)", (rid, off, f32(sig, ss)))
    conn.execute("PRAGMA journal_mode=WAL")
    conn.close()
    assert not os.path.exists(f"{db}-wal") or os.path.getsize(f"{db}-wal") == 0


@pytest.fixture
def to_format1():
    """`to_format1(db, rel_paths=True)`: the map rewritten in place as format 1."""
    return _format1


@pytest.fixture()
def one_thread():
    """One torch thread: on a shared 2-core CI box two threads fight and run far slower."""
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def short_training(train_data, held_out, out: Path, radius: float, max_queries: int, **options):
    """A few steps of training of a small plain U-Net (width 4, no residual path to the
    spectral floor, so that it must learn) on `train_data`, written to `out`: (its
    TrainOptions, Recall@1 metrics on `held_out` before, the training history, the
    metrics after). `options` completes the TrainOptions (steps, d_pos, d_neg, ...)."""
    import torch

    from disco_cli.model import load_model
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.disco import DiscoModel, build_net, default_model_config
    from disco_cli.training.evaluate import retrieval_metrics
    from disco_cli.training.loop import TrainOptions, train

    opts = TrainOptions(
        epochs=2, batch=4, negatives=2, width=4, lr=3e-3, residual=False, hard_after=1,
        seed=0, **options,
    )  # fmt: skip
    torch.manual_seed(opts.seed)
    config = {**default_model_config(20, 4), "residual": False}
    untrained = DiscoModel(build_net(config), BEVConfig(), config)
    before = retrieval_metrics(untrained, held_out, radius, max_queries=max_queries, seed=0)
    history = train(train_data, BEVConfig(), opts, out, command="test", log=lambda s: None)
    trained = load_model(str(out))
    after = retrieval_metrics(trained, held_out, radius, max_queries=max_queries, seed=0)
    return opts, before, history, after
