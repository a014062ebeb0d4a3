"""The thread setting (`--threads N` > DISCO_THREADS > 1) reaches torch, the NumPy U-Net's
BLAS and the C++ core.

The truth is the value given: after `--threads 3` (or DISCO_THREADS=2) the command's
own work runs with torch.get_num_threads() == 3 (2) where it runs torch, a query's NumPy
U-Net multiplies on 3 (2) BLAS threads, and the compiled core's threaded calls receive
3 (2). Bad values give one line, never a traceback.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
from conftest import package_path
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DiscoError
from disco_cli.runtime import threads as disco_threads

runner = CliRunner()
COMPUTING = ["build-db", "query", "loops", "eval", "eval-loops", "train", "simulate", "serve"]


@pytest.fixture(autouse=True)
def _restore(monkeypatch: pytest.MonkeyPatch):
    """Each test leaves torch, the library variables and the setting as it found them."""
    before = torch.get_num_threads()
    for var in ("DISCO_THREADS", *disco_threads._LIBRARY_ENV):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(disco_threads, "_current", None)
    yield
    torch.set_num_threads(before)


def _threads_param(command: str):
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    found = [p for p in cmd.params if "--threads" in getattr(p, "opts", [])]
    assert len(found) == 1, f"{command}: no --threads"
    return found[0]


def test_every_computing_command_has_the_same_threads_option() -> None:
    params = [_threads_param(c) for c in COMPUTING]
    helps = {p.help for p in params}
    assert len(helps) == 1, helps
    for c, p in zip(COMPUTING, params):
        assert p.opts == ["--threads"], c
        assert p.min == 1, c
        assert p.default is None, c  # None: DISCO_THREADS, else 1
    cmds = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    workers = [c for c, cmd in cmds.items() if any("--workers" in p.opts for p in cmd.params)]
    assert workers == []  # one name for one setting


def test_resolution_order(monkeypatch: pytest.MonkeyPatch) -> None:
    assert disco_threads.resolve_threads(None) == 1
    monkeypatch.setenv("DISCO_THREADS", "2")
    assert disco_threads.resolve_threads(None) == 2
    assert disco_threads.resolve_threads(3) == 3  # the option wins over the variable


def test_api_set_threads_reaches_torch_and_the_library_variables() -> None:
    import disco_cli

    assert disco_cli.set_threads(2) == 2
    assert torch.get_num_threads() == 2
    assert disco_cli.get_threads() == 2

    assert os.environ["OMP_NUM_THREADS"] == "2"  # what torch and BLAS read when they load
    for bad in (0, -1, "abc", 1.5, True):
        with pytest.raises(DiscoError, match="thread"):
            disco_cli.set_threads(bad)  # type: ignore[arg-type]


def test_load_model_applies_the_setting_once(monkeypatch: pytest.MonkeyPatch) -> None:
    from disco_cli import load_model

    torch.set_num_threads(2)
    monkeypatch.setenv("DISCO_THREADS", "1")
    load_model("spectral")
    assert torch.get_num_threads() == 1
    torch.set_num_threads(2)  # a program's own choice after disco applied its setting
    load_model("spectral")
    assert torch.get_num_threads() == 2


class _RecordingCore:
    """Stands in for the compiled core: records the thread count each int8 call gets."""

    def __init__(self, core) -> None:
        self.core, self.threads = core, {}

    def __getattr__(self, name: str):
        fn = getattr(self.core, name)

        def call(*args):
            if name.startswith("int8_") and name != "int8_query_limit":
                self.threads[name] = int(args[-1])  # the last argument: threads
            return fn(*args)

        return call


def test_the_setting_reaches_the_c_core_search(monkeypatch: pytest.MonkeyPatch) -> None:
    import disco_cli
    from disco_cli import _core
    from disco_cli.query.search import SignatureIndex

    rec = _RecordingCore(_core)
    monkeypatch.setattr(disco_cli, "_core", rec)
    disco_threads.set_threads(3)
    sigs = np.random.default_rng(0).normal(size=(50, 16)).astype(np.float32)
    index = SignatureIndex(sigs, int8_min_rows=1)  # the int8 pass, however small
    rows, _ = index.search(sigs[7], 5)
    assert rows[0] == 7  # the search still finds the row itself
    assert rec.threads == {"int8_encode": 3, "int8_candidates": 3}


@pytest.fixture(scope="module")
def default_db(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of three sample scans by the shipped model (its NumPy U-Net: no torch)."""
    from disco_cli import Map
    from disco_cli.io.readers import list_scans, read_scan

    path = tmp_path_factory.mktemp("threads") / "default.db"
    with Map.create(path, "default") as m:
        m.add_many((read_scan(p), str(p), None) for p in list_scans(samples / "00")[:3])
    return path


def _query_records_threads(monkeypatch: pytest.MonkeyPatch) -> dict:
    """What a query's work runs on: the U-Net's BLAS threads (`blas_threads` around its
    products), the reading pool, and the setting the C++ search and FFTs read."""
    import disco_cli.model.disco as disco_model
    from disco_cli.maps.facade import Map

    seen: dict = {"blas": []}
    shipped = disco_model.blas_threads
    original = Map.query_files

    def blas_threads(n: int = 1):
        seen["blas"].append(n)
        return shipped(n)

    def query_files(self, paths, **kw):
        seen["pool"] = disco_threads.get_threads() if kw.get("threads") is None else kw["threads"]
        return original(self, paths, **kw)

    monkeypatch.setattr(disco_model, "blas_threads", blas_threads)
    monkeypatch.setattr(Map, "query_files", query_files)
    return seen


def test_query_threads_option_reaches_the_u_net_and_the_pools(
    default_db: Path, samples: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen = _query_records_threads(monkeypatch)
    scan = sorted((samples / "01" / "velodyne").iterdir())[0]
    res = runner.invoke(app, ["query", str(scan), "-d", str(default_db), "--threads", "3"])
    assert res.exit_code == 0, res.output
    assert seen["blas"] and set(seen["blas"]) == {3} and seen["pool"] == 3
    assert disco_threads.get_threads() == 3 and os.environ["OPENBLAS_NUM_THREADS"] == "3"


def test_query_takes_disco_threads_from_the_environment(
    default_db: Path, samples: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen = _query_records_threads(monkeypatch)
    scan = sorted((samples / "01" / "velodyne").iterdir())[0]
    res = runner.invoke(
        app, ["query", str(scan), "-d", str(default_db)], env={"DISCO_THREADS": "2"}
    )
    assert res.exit_code == 0, res.output
    assert set(seen["blas"]) == {2} and seen["pool"] == 2


def test_train_threads_reach_torch_and_the_voxelizer(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import disco_cli.training.data as data

    seen: dict = {}

    def load_training_data(paths, bev_config, **kw):
        seen.update(torch=torch.get_num_threads(), voxelizer=kw["threads"])
        raise DiscoError("stop here: the setting is what this test checks")

    monkeypatch.setattr(data, "load_training_data", load_training_data)
    out = tmp_path / "m.pt"
    res = runner.invoke(
        app, ["train", str(samples / "00"), "-o", str(out)], env={"DISCO_THREADS": "2"}
    )
    assert res.exit_code == 1 and "stop here" in res.output
    assert seen == {"torch": 2, "voxelizer": 2}


def test_simulate_threads_reach_the_ray_caster(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import disco_cli.simulator as sim

    seen: dict = {}

    def simulate(out, **kw):
        seen["threads"] = kw["threads"]
        raise DiscoError("stop here")

    monkeypatch.setattr(sim, "simulate", simulate)
    res = runner.invoke(app, ["simulate", str(tmp_path / "w"), "--threads", "2"])
    assert res.exit_code == 1
    assert seen == {"threads": 2}


@pytest.mark.parametrize("value", ["0", "-1", "abc"])
def test_bad_threads_option_is_one_usage_error(value: str, tmp_path: Path) -> None:
    res = runner.invoke(app, ["query", "x.bin", "-d", str(tmp_path / "m.db"), "--threads", value])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--threads" in lines[0], res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize("value", ["junk", "0", "-3", "2.5"])
def test_bad_disco_threads_is_one_line(value: str, tmp_path: Path) -> None:
    res = runner.invoke(
        app, ["query", "x.bin", "-d", str(tmp_path / "m.db")], env={"DISCO_THREADS": value}
    )
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "DISCO_THREADS" in lines[0], res.output
    assert "Traceback" not in res.output


CHECK_ORDER = """
import sys
from typer.testing import CliRunner
import disco_cli.runtime.threads as t
from disco_cli.cli import app
from disco_cli.errors import DiscoError

def first(n=None):
    loaded = sorted(m for m in ("numpy", "torch", "scipy") if m in sys.modules)
    print("loaded before set_threads:", ",".join(loaded) or "-", file=sys.__stdout__)
    raise DiscoError("stop")

t.set_threads = first
for args in sys.argv[1:]:
    CliRunner().invoke(app, args.split())
"""


def test_commands_apply_the_setting_before_numpy_or_torch_load(tmp_path: Path) -> None:
    """OpenBLAS and torch read their thread variables once, as they load: every command
    sets them first. A fresh interpreter shows what had loaded when it did."""
    import subprocess
    import sys

    runs = [
        "build-db x.bin",
        "query x.bin",
        "loops x",
        "eval x",
        "eval-loops x",
        f"train {tmp_path} -o {tmp_path / 'm.pt'}",
        f"simulate {tmp_path / 'w'}",
        "serve",
    ]
    assert {r.split()[0] for r in runs} == set(COMPUTING)
    env = {"PYTHONPATH": package_path(), "PATH": "/usr/bin:/bin"}
    res = subprocess.run(
        [sys.executable, "-c", CHECK_ORDER, *runs], capture_output=True, text=True, env=env
    )
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("loaded before")]
    assert lines == ["loaded before set_threads: -"] * len(runs), res.stdout
