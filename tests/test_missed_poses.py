"""No silent drops: poses and times the input could have given are said, in one line,
and an evaluation with nothing to score exits non-zero with the reason.

The truths: data/samples/00 holds 26 scans with poses.txt and times.txt spanning 2.5 s,
so scans given one by one are 26 scans without poses that poses.txt would give; a
30 s exclusion window leaves none of them a scan to search. (ROS bags: test_bags.py.)
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app

runner = CliRunner()


def _warnings(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.startswith("warning:")]


def _joined(text: str) -> str:
    return " ".join(text.split())  # rich wraps long lines at the terminal width


@pytest.fixture
def seq(samples: Path, tmp_path: Path) -> Path:
    """A copy of data/samples/00 (so that paths in messages are this test's)."""
    dst = tmp_path / "seq"
    shutil.copytree(samples / "00", dst)
    return dst


def test_stdin_scans_beside_a_pose_file_are_counted_with_the_way_to_pose_them(
    seq: Path, tmp_path: Path
) -> None:
    scans = sorted((seq / "velodyne").glob("*.bin"))
    stdin = "".join(f"{p}\n" for p in scans)
    db = tmp_path / "m.db"
    res = runner.invoke(app, ["build-db", "-", "-o", str(db), "-m", "spectral"], input=stdin)
    assert res.exit_code == 0, res.output
    lines = _warnings(res)
    assert len(lines) == 1, res.stderr
    line = _joined(lines[0])
    assert f"{len(scans)} of {len(scans)} scans have no pose" in line
    assert f"--poses {seq / 'poses.txt'}" in line
    assert f"--times {seq / 'times.txt'}" in line


def test_the_velodyne_folder_given_instead_of_the_sequence_is_said(
    seq: Path, tmp_path: Path
) -> None:
    res = runner.invoke(
        app, ["build-db", str(seq / "velodyne"), "-o", str(tmp_path / "m.db"), "-m", "spectral"]
    )
    assert res.exit_code == 0, res.output
    line = _joined(" ".join(_warnings(res)))
    assert "26 of 26 scans have no pose" in line and f"--poses {seq / 'poses.txt'}" in line


def test_no_line_when_the_poses_are_used_or_given(seq: Path, tmp_path: Path) -> None:
    res = runner.invoke(app, ["build-db", str(seq), "-o", str(tmp_path / "a.db"), "-m", "spectral"])
    assert res.exit_code == 0 and _warnings(res) == [], res.output
    scans = [str(p) for p in sorted((seq / "velodyne").glob("*.bin"))]
    args = ["build-db", *scans, "-o", str(tmp_path / "b.db"), "-m", "spectral"]
    args += ["--poses", str(seq / "poses.txt"), "--times", str(seq / "times.txt")]
    res = runner.invoke(app, args)
    assert res.exit_code == 0 and _warnings(res) == [], res.output


def test_a_lone_scan_folder_gets_no_line(tmp_path: Path, seq: Path) -> None:
    """Nothing beside the scans could have posed them: nothing to say."""
    lone = tmp_path / "lone"
    lone.mkdir()
    for p in sorted((seq / "velodyne").glob("*.bin"))[:3]:
        shutil.copy(p, lone)
    res = runner.invoke(
        app, ["build-db", str(lone), "-o", str(tmp_path / "m.db"), "-m", "spectral"]
    )
    assert res.exit_code == 0 and _warnings(res) == [], res.output


# -- evaluations with nothing to score ---------------------------------------------------


@pytest.fixture
def no_embedding(monkeypatch: pytest.MonkeyPatch) -> list:
    from disco_cli.embedding import batches

    calls: list = []

    def embed_paths(*args, **kwargs):
        calls.append(args)
        raise AssertionError("embedded scans of an evaluation that cannot be scored")

    monkeypatch.setattr(batches, "embed_paths", embed_paths)
    return calls


def _one_error_line(res) -> str:
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    return _joined(lines[0])


def test_eval_loops_with_the_default_window_on_a_short_sequence(
    seq: Path, no_embedding: list
) -> None:
    res = runner.invoke(app, ["eval-loops", str(seq), "-m", "spectral"])
    line = _one_error_line(res)
    assert "0 of 26 scans can be scored" in line
    assert "--exclude-seconds (now 30 s; the sequence spans 2.5 s)" in line
    assert "--exclude-frames" in line
    assert no_embedding == []


def test_eval_loops_with_frames_longer_than_the_sequence(seq: Path, no_embedding: list) -> None:
    res = runner.invoke(app, ["eval-loops", str(seq), "-m", "spectral", "--exclude-frames", "40"])
    line = _one_error_line(res)
    assert "0 of 26 scans can be scored" in line and "--exclude-frames (now 40" in line
    assert no_embedding == []


def test_eval_loops_without_any_revisit_in_the_radius_says_so(seq: Path) -> None:
    """A straight drive, poses 100 m apart: the queries score precision only (every
    detection is false); one warning says that recall, AUC and F1 stay blank."""
    import json

    n = 26
    T = np.tile(np.eye(4)[:3].reshape(1, 12), (n, 1))
    T[:, 3] = 100.0 * np.arange(n)  # x
    np.savetxt(seq / "poses.txt", T)
    args = ["eval-loops", str(seq), "-m", "spectral", "--exclude-frames", "5", "--format", "jsonl"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    lines = _warnings(res)
    assert len(lines) == 1 and "none of the 21 queries returns within 3 m" in _joined(lines[0])
    metrics = json.loads(res.stdout)
    assert metrics["num_queries"] == 21 and metrics["num_queries_with_match"] == 0


def test_eval_with_queries_nowhere_near_the_map(
    samples: Path, samples_spectral_db: Path, tmp_path: Path, no_embedding: list
) -> None:
    T = np.loadtxt(samples / "01" / "poses.txt")
    T[:, 3] += 1e5  # every query 100 km from the map
    poses = tmp_path / "far.txt"
    np.savetxt(poses, T)
    args = ["eval", str(samples / "01"), "-d", str(samples_spectral_db), "--poses"]
    res = runner.invoke(app, [*args, str(poses), "--calib", "none"])
    line = _one_error_line(res)
    assert "0 of 26 queries can be scored" in line and "--radius" in line
    assert no_embedding == []
