"""What the command line says: errors that name what to do, checks made before torch
loads, and progress lines where stderr is not a terminal (issue 26)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import package_path
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.runtime.console import progress_line


def _disco(*args: object, env: dict | None = None) -> subprocess.CompletedProcess:
    """The CLI in a fresh interpreter (stderr a pipe); its last stderr line says whether
    torch was imported."""
    code = (
        "import sys\n"
        "from disco_cli.cli import main\n"
        "sys.argv = ['disco', *sys.argv[1:]]\n"
        "try:\n"
        "    main()\n"
        "finally:\n"
        "    print('torch imported:', 'torch' in sys.modules, file=sys.stderr)\n"
    )
    import os

    full_env = {**os.environ, "PYTHONPATH": package_path(), **(env or {})}
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        capture_output=True,
        text=True,
        env=full_env,
        timeout=300,
    )


# -- cheap checks come before torch -------------------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ["query", "{tmp}/missing.bin", "--db", "{db}"],
        ["build-db", "{tmp}/missing", "-o", "{tmp}/out.db"],
        ["loops", "{tmp}/missing"],
        ["eval-loops", "{tmp}/missing"],
        ["eval", "{tmp}/missing.bin", "--db", "{db}"],
        ["bev", "{tmp}/missing.bin", "-o", "{tmp}/bev.png"],
    ],
)
def test_a_missing_scan_is_reported_before_torch_loads(
    args: list[str], samples_spectral_db: Path, tmp_path: Path
) -> None:
    argv = [a.format(tmp=tmp_path, db=samples_spectral_db) for a in args]
    proc = _disco(*argv)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 1, proc.stderr
    assert lines[-1] == "torch imported: False", proc.stderr
    assert len(lines) == 2 and lines[0].startswith("error: ") and "missing" in lines[0]


def test_an_unknown_extension_names_scan_format(tmp_path: Path) -> None:
    scan = tmp_path / "scan.dat"
    scan.write_bytes(b"\0" * 64)
    res = CliRunner().invoke(app, ["bev", str(scan), "-o", str(tmp_path / "b.npy")])
    assert res.exit_code == 1
    (line,) = res.stderr.splitlines()
    assert (
        line.startswith(f"error: {scan}: cannot tell the scan format") and "--scan-format" in line
    )


# -- models -------------------------------------------------------------------------------


def test_a_map_whose_checkpoint_moved_names_the_old_path(samples: Path, tmp_path: Path) -> None:
    from disco_cli.model import DEFAULT_WEIGHTS

    if not DEFAULT_WEIGHTS.is_file():
        pytest.skip("no shipped default weights")
    ckpt = tmp_path / "models" / "model.pt"
    ckpt.parent.mkdir()
    shutil.copy(DEFAULT_WEIGHTS, ckpt)
    scans = sorted((samples / "00" / "velodyne").glob("*.bin"))[:2]
    db = tmp_path / "map.db"
    res = CliRunner().invoke(app, ["build-db", *map(str, scans), "-o", str(db), "-m", str(ckpt)])
    assert res.exit_code == 0, res.output
    ckpt.rename(tmp_path / "moved.pt")
    res = CliRunner().invoke(app, ["query", str(scans[0]), "--db", str(db)])
    assert res.exit_code == 1
    assert res.stderr.splitlines() == [
        f"error: {db}: built with checkpoint {ckpt.resolve()}, which is gone; pass --model PATH"
    ]


def test_a_file_that_is_not_a_checkpoint_gets_no_advice_to_unpickle_it(
    samples: Path, tmp_path: Path
) -> None:
    import numpy as np
    import torch

    other = tmp_path / "other.pt"
    torch.save({"array": np.zeros(3)}, other)  # a pickle that a safe load refuses
    scan = next((samples / "00" / "velodyne").glob("*.bin"))
    args = ["bev", str(scan), "-o", str(tmp_path / "b.npy"), "--model", str(other)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1
    (line,) = res.stderr.splitlines()
    assert line.startswith(f"error: {other}: not a disco checkpoint (")
    assert "weights_only" not in line


# -- one line per message in a pipe --------------------------------------------------------


def test_simulate_says_what_it_wrote_in_one_line_in_a_pipe(tmp_path: Path) -> None:
    out = tmp_path / "a-folder-with-a-rather-long-name-so-that-the-line-passes-80-columns"
    proc = _disco("simulate", out, "--frames", "2", "--sessions", "1", "-q", env={"COLUMNS": "80"})
    assert proc.returncode == 0, proc.stderr
    wrote = [ln for ln in proc.stderr.splitlines() if ln.startswith("wrote ")]
    assert len(wrote) == 1 and len(wrote[0]) > 80, proc.stderr
    assert wrote[0].endswith("seed 0)") and str(out) in wrote[0]


# -- progress lines ------------------------------------------------------------------------


def test_progress_line_reads_done_rate_and_time_left() -> None:
    # 120 of 1000 in 10 s: 12 per second, 880 left -> 73 s.
    assert progress_line("build-db", 120, 1000, 10.0, 0, "scans") == (
        "build-db: 120/1000 (12%), 12.0 scans/s, 73 s left"
    )
    # The rate of what was done since counting began again (50 of the 80, in 5 s).
    assert progress_line("epoch 2/3", 80, 100, 5.0, 30, "steps") == (
        "epoch 2/3: 80/100 (80%), 10.0 steps/s, 2 s left"
    )
    assert progress_line("voxelizing", 7, None, 2.0, 0, "") == "voxelizing: 7, 3.5/s"
    # 3000 of 6000 in 1000 s: 3000 left at 3 per second, 1000 s.
    assert progress_line("x", 3000, 6000, 1000.0, 0, "scans").endswith(", 17 min left")


LINE = re.compile(r"^build-db: (\d+)/26 \((\d+)%\), \d+\.\d scans/s(, \d+ (s|min|h) left)?$")


def test_build_db_prints_progress_lines_in_a_pipe_and_quiet_silences_them(
    samples: Path, tmp_path: Path
) -> None:
    env = {"DISCO_PROGRESS_SECONDS": "0"}  # a line at every update
    args = ["build-db", str(samples / "00"), "-m", "spectral", "--batch", "4"]
    res = CliRunner().invoke(app, [*args, "-o", str(tmp_path / "a.db")], env=env)
    assert res.exit_code == 0, res.output
    found = [LINE.match(ln) for ln in res.stderr.splitlines() if ln.startswith("build-db:")]
    assert found and all(found), res.stderr
    done = [int(m.group(1)) for m in found]
    # 26 scans in batches of 4: a line per batch.
    assert done == [4, 8, 12, 16, 20, 24, 26]
    assert [int(m.group(2)) for m in found] == [round(100 * d / 26) for d in done]
    quiet = CliRunner().invoke(app, [*args, "-o", str(tmp_path / "b.db"), "-q"], env=env)
    assert quiet.exit_code == 0, quiet.output
    assert not [ln for ln in quiet.stderr.splitlines() if ln.startswith("build-db:")]
    # -q leaves results, warnings and errors: the summary line goes too (docs/cli.md)
    assert quiet.stderr == "" and (tmp_path / "b.db").is_file()


def test_train_prints_its_steps_and_losses_in_a_pipe(samples: Path, tmp_path: Path) -> None:
    args = ["train", str(samples / "00"), "-o", str(tmp_path / "m.pt"), "--epochs", "1"]
    args += ["--steps", "3", "--batch", "2", "--negatives", "2", "--width", "2"]
    res = CliRunner().invoke(app, args, env={"DISCO_PROGRESS_SECONDS": "0"})
    assert res.exit_code == 0, res.output
    steps = [ln for ln in res.stderr.splitlines() if ln.startswith("epoch 1/1: ")]
    assert [ln.split(",")[0] for ln in steps] == [
        "epoch 1/1: 1/3 (33%)",
        "epoch 1/1: 2/3 (67%)",
        "epoch 1/1: 3/3 (100%)",
    ]
    assert all(re.search(r" steps/s.*; \w+ \d+\.\d{3}", ln) for ln in steps), steps
