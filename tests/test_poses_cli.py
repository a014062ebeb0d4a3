"""The one pose rule through the command line: a partial KITTI sequence, calib.txt beside
poses.txt applied with an explicit --poses too, --calib none, the self-match excluded,
and a scan beyond --max-time-gap (TUM poses) stored without a pose and named once."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.io.poses import read_kitti_poses, write_kitti_poses, xy_yaw
from disco_cli.maps.database import Database

SAMPLES = Path(__file__).resolve().parent.parent / "data" / "samples"
FRAMES = [3, 4, 5, 6, 7, 8]

# LiDAR -> camera 0, KITTI's axes (x right, y down, z forward) and an offset.
TR = np.array(
    [[0, -1, 0, 0.1], [0, 0, -1, -0.08], [1, 0, 0, -0.27], [0, 0, 0, 1.0]], dtype=np.float64
)


def run(*args) -> tuple[int, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, res.output


@pytest.fixture(scope="module")
def kitti_seq(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """Six scans of sample 00 under their own frame numbers, the whole sequence's poses
    in KITTI's camera frame and a calib.txt: the LiDAR poses are the sample's own."""
    root = tmp_path_factory.mktemp("kitti") / "00"
    (root / "velodyne").mkdir(parents=True)
    for f in FRAMES:
        name = f"{f:06d}.bin"
        shutil.copy(SAMPLES / "00" / "velodyne" / name, root / "velodyne" / name)
    velo = read_kitti_poses(SAMPLES / "00" / "poses.txt")
    write_kitti_poses(root / "poses.txt", TR @ velo @ np.linalg.inv(TR))
    row = " ".join(f"{v:.12g}" for v in TR[:3].ravel())
    (root / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {row}\n")
    return root, velo


def stored_poses(db: Path) -> np.ndarray:
    with Database.open(db) as d:
        return d.poses()[0]


def want_rows(T: np.ndarray) -> np.ndarray:
    x, y, yaw = xy_yaw(T)
    return np.c_[x, y, T[:, 2, 3], yaw]


def test_partial_sequence_and_calib_with_explicit_poses(kitti_seq, tmp_path):
    root, velo = kitti_seq
    # The folder: poses.txt (26 rows) for 6 scans, by frame number; calib.txt applied.
    code, out = run("build-db", root, "-o", tmp_path / "a.db", "--model", "spectral")
    assert code == 0, out
    np.testing.assert_allclose(stored_poses(tmp_path / "a.db"), want_rows(velo[FRAMES]), atol=1e-6)
    # The same with an explicit --poses: calib.txt beside it still applies.
    files = sorted((root / "velodyne").glob("*.bin"))
    code, out = run(
        "build-db", *files, "-o", tmp_path / "b.db", "--model", "spectral",
        "--poses", root / "poses.txt",
    )  # fmt: skip
    assert code == 0, out
    np.testing.assert_allclose(stored_poses(tmp_path / "b.db"), want_rows(velo[FRAMES]), atol=1e-6)
    # --calib none: the camera-frame poses as stored in the file.
    code, out = run(
        "build-db", root, "-o", tmp_path / "c.db", "--model", "spectral", "--calib", "none"
    )
    assert code == 0, out
    cam = TR @ velo[FRAMES] @ np.linalg.inv(TR)
    np.testing.assert_allclose(stored_poses(tmp_path / "c.db"), want_rows(cam), atol=1e-6)


def test_eval_on_a_partial_sequence_and_self_match_excluded(kitti_seq, tmp_path):
    root, velo = kitti_seq
    db = tmp_path / "map.db"
    assert run("build-db", root, "-o", db, "--model", "spectral")[0] == 0
    # eval and eval-loops take the partial sequence (rows by frame number) too.
    code, out = run("eval", root, "--db", db, "--format", "jsonl", "--topk", "3")
    assert code == 0, out
    metrics = json.loads(out.strip().splitlines()[-1])
    assert metrics["recall@1"] == pytest.approx(1.0)  # every scan finds itself
    code, out = run("eval-loops", root, "--model", "spectral", "--exclude-frames", "2",
                    "--format", "jsonl")  # fmt: skip
    assert code == 0, out
    # query --exclude-radius with explicit --poses: the scan's own entry (and its
    # neighbours within 1 m) are gone; without the option it is the top match.
    scan = root / "velodyne" / "000005.bin"
    code, out = run("query", scan, "--db", db, "--format", "jsonl", "--topk", "6")
    assert json.loads(out.splitlines()[0])["match"] == str(scan)
    code, out = run(
        "query", scan, "--db", db, "--format", "jsonl", "--topk", "6",
        "--exclude-radius", "1", "--poses", root / "poses.txt",
    )  # fmt: skip
    assert code == 0, out
    matches = [json.loads(line)["match"] for line in out.splitlines()]
    assert str(scan) not in matches and len(matches) == 5
    # The others stay: each is farther than 1 m from frame 5 (the sample's spacing).
    d = np.linalg.norm(velo[FRAMES, :2, 3] - velo[5, :2, 3], axis=1)
    assert sorted(matches) == sorted(
        str(root / "velodyne" / f"{f:06d}.bin") for f, di in zip(FRAMES, d) if di > 1.0
    )


def test_scan_beyond_max_time_gap_has_no_pose(tmp_path):
    from disco_cli.io.poses.tum import write_tum_poses

    velo = read_kitti_poses(SAMPLES / "00" / "poses.txt")
    folder = tmp_path / "run"
    folder.mkdir()
    stamps = 100.0 + 0.1 * np.arange(len(velo))
    # Scans named by their time; the last one 5 s after the last pose.
    scan_times = [stamps[2], stamps[3] + 0.05, stamps[-1] + 5.0]
    sources = [2, 3, 25]
    for t, f in zip(scan_times, sources):
        shutil.copy(SAMPLES / "00" / "velodyne" / f"{f:06d}.bin", folder / f"{t:.3f}.bin")
    write_tum_poses(tmp_path / "traj.tum", stamps, velo)
    code, out = run(
        "build-db", folder, "-o", tmp_path / "m.db", "--model", "spectral",
        "--poses", tmp_path / "traj.tum", "--poses-format", "tum",
    )  # fmt: skip
    assert code == 0, out
    assert out.count("no pose") == 1 and "1 of 3 scans have no pose" in out
    assert f"{scan_times[2]:.3f}.bin" in out and "1 without a pose" in out
    got = stored_poses(tmp_path / "m.db")
    assert np.isnan(got[2]).all()
    np.testing.assert_allclose(got[0], want_rows(velo[[2]])[0], atol=1e-6)
    # The second scan lies halfway between poses 3 and 4.
    mid = (velo[3, :3, 3] + velo[4, :3, 3]) / 2
    np.testing.assert_allclose(got[1, :3], mid, atol=1e-6)
    # With a gap of 10 s the last scan... still has none: it is past the last pose.
    code, out = run(
        "build-db", folder, "-o", tmp_path / "n.db", "--model", "spectral",
        "--poses", tmp_path / "traj.tum", "--max-time-gap", "10",
    )  # fmt: skip
    assert code == 0 and "1 of 3 scans have no pose" in out
