"""The edges of the command line: a closed stdout, no loop found, Ctrl-C in build-db,
a folder given to query, `info` as one JSON object.

Truths come from outside the command: the files in data/samples, the database read
back with `Database`, the model's own BEV configuration.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.maps.database import Database


def _disco() -> str:
    exe = shutil.which("disco") or str(Path(sys.executable).parent / "disco")
    assert Path(exe).exists(), "the disco executable is not installed"
    return exe


def _scans(folder: Path) -> list[str]:
    return sorted(str(p) for p in (folder / "velodyne").glob("*.bin"))


# -- a closed stdout (`| head`) is a normal end ------------------------------------


def _closed_stdout_run(args: list[str]) -> subprocess.CompletedProcess:
    """Run disco with a stdout whose reader has gone already: every write fails (EPIPE)."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run(
            [_disco(), *args], stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120
        )
    finally:
        os.close(write_end)


@pytest.mark.parametrize("command", ["query", "loops", "gt-loops", "info", "eval", "eval-loops"])
def test_closed_stdout_is_a_normal_end(
    command: str, samples: Path, samples_spectral_db: Path
) -> None:
    db = str(samples_spectral_db)
    q = str(samples / "01" / "velodyne" / "000005.bin")
    args = {
        "query": ["query", q, "-d", db, "--format", "tsv"],
        "loops": ["loops", str(samples / "00"), "-m", "spectral", "--exclude-frames", "5"],
        "gt-loops": ["gt-loops", str(samples / "00"), str(samples / "01")],
        "info": ["info", db],
        "eval": ["eval", str(samples / "01"), "-d", db, "-k", "2"],
        "eval-loops": ["eval-loops", str(samples / "00"), "-m", "spectral"]
        + ["--exclude-frames", "5"],
    }[command]
    proc = _closed_stdout_run(args)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "Broken pipe" not in proc.stderr, proc.stderr
    assert "Exception ignored" not in proc.stderr, proc.stderr


# -- no loop found -----------------------------------------------------------------


def test_loops_says_so_when_it_finds_no_loop(samples: Path) -> None:
    args = ["loops", str(samples / "00"), "-m", "spectral", "--max-distance", "0"]
    args += ["--format", "tsv"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    # A distance of 0 is never reached between two different scans: no row, but the header.
    header = "query_index\tquery\tmatch_index\tmatch\tdistance\tconfidence\tyaw_deg\tyaw_conf"
    assert res.stdout.splitlines() == [header]
    n = len(_scans(samples / "00"))
    assert f"0 loop candidates among {n} scans" in res.stderr


def test_loops_count_line_counts_the_rows(samples: Path) -> None:
    args = ["loops", str(samples / "00"), "-m", "spectral", "--exclude-frames", "5"]
    res = CliRunner().invoke(app, [*args, "--format", "jsonl"])
    assert res.exit_code == 0, res.output
    rows = [json.loads(line) for line in res.stdout.splitlines()]
    n = len(_scans(samples / "00"))
    # Top-1 for every scan that has scans 5 frames before it, each with its yaw's
    # confidence (spectral's parallax-free yaw gives one).
    assert len(rows) == n - 5
    assert all(0.0 <= r["yaw_conf"] <= 1.0 for r in rows)
    assert f"{len(rows)} loop candidates among {n} scans" in res.stderr


def test_gt_loops_says_so_when_there_is_no_revisit(samples: Path) -> None:
    res = CliRunner().invoke(
        app, ["gt-loops", str(samples / "00"), "--radius", "0", "--format", "tsv"]
    )
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines() == ["query_seq\tquery\tmatch_seq\tmatch\tdistance_m\tyaw_deg"]
    assert "0 revisit pairs" in res.stderr


# -- Ctrl-C in build-db -------------------------------------------------------------


def test_ctrl_c_in_build_db_says_what_is_stored(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    original = Database.append
    calls = {"n": 0}

    def append_then_ctrl_c(self, batch):  # noqa: ANN001
        calls["n"] += 1
        if calls["n"] == 3:  # the first two batches are committed, then Ctrl-C
            raise KeyboardInterrupt
        return original(self, batch)

    monkeypatch.setattr(Database, "append", append_then_ctrl_c)
    out = tmp_path / "map.db"
    args = ["build-db", str(samples / "00"), "-o", str(out), "-m", "spectral", "--batch", "4"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 130, res.output
    with Database.open(out) as db:
        stored = len(db)
        assert db.check() == []
    assert stored == 8
    total = len(_scans(samples / "00"))
    assert f"holds {stored} of the {total} scans" in res.stderr
    assert "run the same command again to resume" in res.stderr
    monkeypatch.setattr(Database, "append", original)
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert f"{stored} were in it already" in res.stderr
    with Database.open(out) as db:
        assert len(db) == total


def test_ctrl_c_before_the_first_batch_leaves_no_file(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def ctrl_c(self, batch):  # noqa: ANN001
        raise KeyboardInterrupt

    monkeypatch.setattr(Database, "append", ctrl_c)
    out = tmp_path / "map.db"
    args = ["build-db", str(samples / "00"), "-o", str(out), "-m", "spectral"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 130
    assert "nothing written" in res.stderr and not out.exists()
    assert list(tmp_path.iterdir()) == []


# -- query takes a folder ---------------------------------------------------------------


def test_query_takes_a_folder_like_build_db(samples: Path, samples_spectral_db: Path) -> None:
    args = ["query", str(samples / "01"), "-d", str(samples_spectral_db), "-k", "1"]
    res = CliRunner().invoke(app, [*args, "--format", "jsonl"])
    assert res.exit_code == 0, res.output
    rows = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["query"] for r in rows] == _scans(samples / "01")
    # The same rows as asking for each file.
    files = CliRunner().invoke(
        app,
        ["query", *_scans(samples / "01"), "-d", str(samples_spectral_db), "-k", "1"]
        + ["--format", "jsonl"],
    )
    assert [json.loads(line) for line in files.stdout.splitlines()] == rows


def test_query_an_empty_folder_is_one_line(tmp_path: Path, samples_spectral_db: Path) -> None:
    (tmp_path / "empty").mkdir()
    args = ["query", str(tmp_path / "empty"), "-d", str(samples_spectral_db)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1 and res.stderr.count("\n") == 1
    assert f"{tmp_path / 'empty'}: no scan files" in res.stderr
    assert "scan format" not in res.stderr


# -- info --format jsonl --------------------------------------------------------------


def test_info_jsonl_is_one_object(samples: Path, samples_spectral_db: Path) -> None:
    from disco_cli.model import load_model

    res = CliRunner().invoke(app, ["info", str(samples_spectral_db), "--format", "jsonl"])
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert len(lines) == 1
    info = json.loads(lines[0])
    assert info["scans"] == len(_scans(samples / "00"))
    assert info["model"] == "spectral" and info["poses"] == "yes"
    want = json.loads(json.dumps(load_model("spectral").bev_config.to_dict()))
    assert info["bev_config"] == want
    # A table and TSV keep one row per field.
    res = CliRunner().invoke(app, ["info", str(samples_spectral_db), "--format", "tsv"])
    tsv = res.stdout.splitlines()
    assert tsv[0] == "field\tvalue" and len(tsv) == 1 + len(info)
