"""The command line's small things (issue 34): a closed pipe on --help, Ctrl-C while
disco loads, what -q leaves, a bad DISCO_PROGRESS_SECONDS, the help's [ann], the
numbering of match_id and of loops' indices, and one default for the model."""

from __future__ import annotations

import csv
import io
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.runtime import console


def _disco() -> str:
    exe = shutil.which("disco") or str(Path(sys.executable).parent / "disco")
    assert Path(exe).exists(), "the disco executable is not installed"
    return exe


def _run(*args: str, env: dict | None = None):
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def _tsv(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text), delimiter="\t"))


@pytest.mark.parametrize("args", [["--help"], ["query", "--help"]])
def test_help_into_a_pipe_closed_early_exits_0(args: list[str]) -> None:
    cmd = " ".join([_disco(), *args]) + " | head -1 > /dev/null"
    res = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True)
    assert res.returncode == 0 and res.stderr == ""


def test_ctrl_c_while_disco_loads_is_one_line_and_status_130() -> None:
    # SIGINT arrives in the middle of cli.py's imports (as the first Ctrl-C does on a
    # slow start), deterministically: an import hook sends it.
    code = (
        "import importlib.abc, os, signal, sys\n"
        "class Hook(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name == 'disco_cli.commands.query':\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "sys.meta_path.insert(0, Hook())\n"
        "import disco_cli.cli\n"
        "print('loaded')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 130, res.stderr
    assert res.stderr == "error: interrupted\n" and res.stdout == ""


def test_ctrl_c_is_a_keyboard_interrupt_again_once_loaded() -> None:
    from disco_cli import cli

    assert signal.getsignal(signal.SIGINT) is not cli._interrupted_while_loading


def test_quiet_leaves_only_results_warnings_and_errors(samples: Path, tmp_path: Path) -> None:
    one = samples / "00" / "velodyne" / "000000.bin"
    posed = ["--poses", samples / "00" / "poses.txt", "--times", samples / "00" / "times.txt"]
    res = _run("build-db", one, "-o", tmp_path / "a.db", *posed)
    assert res.exit_code == 0
    assert res.stderr.startswith(f"{tmp_path / 'a.db'}: wrote 1 scan in ")  # one scan
    res = _run("build-db", one, "-o", tmp_path / "a.db", *posed)
    assert res.stderr.strip() == f"{tmp_path / 'a.db'}: all 1 scan are in it already"
    res = _run("build-db", samples / "00", "-o", tmp_path / "b.db", "-q")
    assert res.exit_code == 0 and res.stderr == "" and res.stdout == ""
    # a warning still prints under -q: a scan without a pose
    res = _run("build-db", one, "-o", tmp_path / "c.db", "-q")
    assert res.exit_code == 0 and res.stderr.startswith("warning: ")
    loops = _run("loops", samples / "00", "--exclude-frames", "5", "-q")
    assert loops.exit_code == 0 and loops.stderr == "" and len(_tsv(loops.stdout)) > 0


def test_a_bad_progress_seconds_gets_one_warning(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(console, "_bad_progress_seconds_told", False)
    env = {"DISCO_PROGRESS_SECONDS": "abc"}
    res = _run("build-db", samples / "00", "-o", tmp_path / "m.db", env=env)
    assert res.exit_code == 0
    warned = [ln for ln in res.stderr.splitlines() if "DISCO_PROGRESS_SECONDS" in ln]
    assert warned == ["warning: DISCO_PROGRESS_SECONDS='abc' is not a number of seconds >= 0; "
                      "using 5"]  # fmt: skip
    monkeypatch.setattr(console, "_bad_progress_seconds_told", False)
    env = {"DISCO_PROGRESS_SECONDS": "2"}
    res = _run("build-db", samples / "01", "-o", tmp_path / "n.db", env=env)
    assert "DISCO_PROGRESS_SECONDS" not in res.stderr


def test_query_help_shows_the_extra_in_brackets() -> None:
    res = _run("query", "--help", env={"COLUMNS": "300"})
    assert "pip install 'disco-cli[ann]'" in res.stdout


@pytest.fixture(scope="module")
def spectral_map(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("spectral") / "map.db"
    assert _run("build-db", samples / "00", "-o", db, "--model", "spectral", "-q").exit_code == 0
    return db


def test_match_id_counts_from_1_and_loop_indices_from_0(spectral_map: Path, samples: Path) -> None:
    # The map holds 00's scans in file order: NNNNNN.bin is the (N+1)-th stored.
    res = _run("query", samples / "01", "--db", spectral_map, "--topk", "3", "--format", "tsv")
    rows = _tsv(res.stdout)
    assert rows and all(int(r["match_id"]) == int(Path(r["match"]).stem) + 1 for r in rows)
    res = _run("loops", samples / "00", "--exclude-frames", "5")
    loops = _tsv(res.stdout)
    assert loops
    for r in loops:
        assert int(r["query_index"]) == int(Path(r["query"]).stem)
        assert int(r["match_index"]) == int(Path(r["match"]).stem)
    wide = {"COLUMNS": "400"}
    assert (
        "match_id is the scan's id in the map: 1 for the first"
        in _run("query", "--help", env=wide).stdout
    )
    assert "positions in the sequence, from 0" in _run("loops", "--help", env=wide).stdout


def test_commands_on_an_existing_map_use_its_model(spectral_map: Path, samples: Path) -> None:
    extra = samples / "01" / "velodyne" / "000003.bin"
    res = _run("build-db", extra, "-o", spectral_map, "--append", "-q")
    assert res.exit_code == 0, res.output
    res = _run("loops", samples / "00", "--db", spectral_map, "--exclude-frames", "5")
    assert res.exit_code == 0, res.output
    # the same as naming the map's model
    named = _run("loops", samples / "00", "--db", spectral_map, "--exclude-frames", "5", "-m",
                 "spectral")  # fmt: skip
    assert res.stdout == named.stdout
    for args in (["build-db", extra, "-o", spectral_map, "--append"], ["loops", samples / "00",
                 "--db", spectral_map], ["query", extra, "--db", spectral_map]):  # fmt: skip
        res = _run(*args, "--model", "default")
        assert res.exit_code == 1
        errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1 and "pass --model spectral" in errors[0], res.stderr
