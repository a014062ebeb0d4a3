"""The library API (`disco_cli.Map`, `LoopDetector`, `Match`, `Loop`) against the command
line built on it, and against truths computed here: a known rigid transform, NumPy brute
force over signatures, path lengths from poses.txt.
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import disco_cli
from disco_cli import DatabaseError, LoopDetector, Map, ScanReadError, list_scans, read_scan
from disco_cli.cli import app


def run(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def jsonl(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll), degrees."""
    r, p, y = np.radians([roll, pitch, yaw])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


@pytest.fixture(scope="module")
def seq_paths(samples: Path) -> list[str]:
    return [str(p) for p in list_scans(samples / "00")]


@pytest.fixture(scope="module")
def maps(samples: Path, seq_paths: list[str], tmp_path_factory) -> tuple[Path, Path]:
    """The same scans of data/samples/00 as a map, once by `disco build-db` and once by
    `Map.add_many` from arrays (default model)."""
    root = tmp_path_factory.mktemp("maps")
    cli_db, api_db = root / "cli.db", root / "api.db"
    code, _, err = run("build-db", samples / "00", "-o", cli_db)
    assert code == 0, err
    with Map.create(api_db) as m:
        ids = m.add_many((read_scan(p), p, None) for p in seq_paths)
        assert ids == list(range(1, len(seq_paths) + 1)) and len(m) == len(seq_paths)
    return cli_db, api_db


def test_api_map_equals_build_db(maps: tuple[Path, Path], samples: Path) -> None:
    cli_db, api_db = maps
    blobs = []
    for db in maps:
        with sqlite3.connect(db) as conn:
            blobs.append(conn.execute("SELECT path, signature FROM scans ORDER BY id").fetchall())
    assert blobs[0] == blobs[1]  # byte-identical signatures, same names, same order
    queries = [samples / "01" / "velodyne" / f"{i:06d}.bin" for i in (0, 5, 13, 21)]
    code, out, err = run("query", *queries, "--db", cli_db, "--topk", "5", "--format", "jsonl")
    assert code == 0, err
    want = jsonl(out)
    with Map.open(api_db) as m:
        assert m.model.name == "default" and len(m) == len(blobs[0])
        got = [mt for q in queries for mt in m.query(read_scan(q), topk=5)]
    # disco query prints a stored path relative to the current directory when it can.
    assert [(g.rank, g.match_id, g.name) for g in got] == [
        (w["rank"], w["match_id"], os.path.abspath(w["match"])) for w in want
    ]
    np.testing.assert_allclose([g.distance for g in got], [w["distance"] for w in want], atol=1e-6)
    np.testing.assert_allclose([g.yaw_deg for g in got], [w["yaw_deg"] for w in want], atol=1e-6)


def test_refined_pose_recovers_a_known_transform(maps: tuple[Path, Path], tmp_path: Path) -> None:
    """A map scan moved by a known roll, pitch, yaw and translation comes back with that
    transform as T, yaw_deg, roll_deg and pitch_deg, from the API and from `disco query`."""
    _, api_db = maps
    with Map.open(api_db) as m:
        match_path = m.names()[10]
    match = read_scan(match_path)
    cases = [(2.0, -1.5, 25.0, (1.0, -0.5, 0.2)), (-3.0, 2.0, -120.0, (-2.0, 1.5, -0.3))]
    for roll, pitch, yaw, t in cases:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rotation(roll, pitch, yaw), t
        # T is the query sensor's pose in the match's frame: query points are T^-1 p.
        inv = np.linalg.inv(T)
        query = match.copy()
        query[:, :3] = match[:, :3] @ inv[:3, :3].T + inv[:3, 3]
        with Map.open(api_db) as m:
            best = m.query(query, topk=1, pose=True)[0]
        assert best.name == match_path and best.accepted
        assert abs(best.roll_deg - roll) < 0.1 and abs(best.pitch_deg - pitch) < 0.1
        assert abs(best.yaw_deg - yaw) < 0.1
        np.testing.assert_allclose(best.T[:3, 3], t, atol=0.05)
        np.testing.assert_allclose(best.T[:3, :3], T[:3, :3], atol=2e-3)
        # The command line reports the same refined pose, with the full T in JSON lines.
        q_file = tmp_path / "q.bin"
        query.astype(np.float32).tofile(q_file)
        args = ["-d", api_db, "-k", "1", "--pose", "--format", "jsonl"]
        code, out, err = run("query", q_file, *args)
        assert code == 0, err
        row = jsonl(out)[0]
        assert row["match_id"] == best.match_id
        for key in ("yaw_deg", "roll_deg", "pitch_deg", "fitness"):
            assert abs(row[key] - getattr(best, key)) < 1e-9, key
        np.testing.assert_allclose(np.array(row["T"]), best.T, atol=1e-9)
        np.testing.assert_allclose([row["dx"], row["dy"], row["dz"]], best.T[:3, 3], atol=1e-9)


def test_loop_detector_streams_the_loops_of_disco_loops(samples: Path, seq_paths) -> None:
    args = ["--exclude-frames", "5", "--verify", "--format", "jsonl"]
    code, out, err = run("loops", samples / "00", *args)
    assert code == 0, err
    want = jsonl(out)
    assert want, "no loops in data/samples/00"
    det = LoopDetector(exclude_frames=5, verify=True)
    got = []
    for i, p in enumerate(seq_paths):
        new = det.add(read_scan(p), name=p)
        assert all(lp.query_index == i for lp in new)  # each loop as its scan arrives
        got += new
    assert len(det) == len(seq_paths)
    assert [(g.query_index, g.match_index) for g in got] == [
        (w["query_index"], w["match_index"]) for w in want
    ]
    for g, w in zip(got, want):
        assert g.accepted and g.query == w["query"] and g.match == w["match"]
        assert abs(g.distance - w["distance"]) < 1e-6 and abs(g.yaw_deg - w["yaw_deg"]) < 1e-6
        assert abs(g.confidence - w["confidence"]) < 1e-9 and g.confidence >= 0.9
        np.testing.assert_allclose(g.T, np.array(w["T"]), atol=1e-6)


def test_loop_detector_by_seconds_equals_disco_loops(samples: Path, seq_paths) -> None:
    args = ["--exclude-seconds", "2.5", "--topk", "2", "-m", "spectral", "--format", "jsonl"]
    code, out, err = run("loops", samples / "00", *args)
    assert code == 0, err
    times = np.loadtxt(samples / "00" / "times.txt")
    det = LoopDetector("spectral", exclude_frames=None, exclude_seconds=2.5, topk=2, verify=False)
    got = [lp for p, t in zip(seq_paths, times) for lp in det.add(read_scan(p), time=t)]
    want = jsonl(out)
    assert [(g.query_index, g.match_index) for g in got] == [
        (w["query_index"], w["match_index"]) for w in want
    ]
    assert all(times[g.query_index] - times[g.match_index] >= 2.5 for g in got)
    np.testing.assert_allclose([g.distance for g in got], [w["distance"] for w in want], atol=1e-6)


def test_exclude_distance_against_numpy(samples: Path, seq_paths) -> None:
    """Each scan's loop is its nearest signature among the scans at least D metres of
    travel back (path lengths from poses.txt, signatures from the model itself)."""
    from disco_cli.io.poses import read_kitti_poses
    from disco_cli.model.bev import polar_bev

    poses = read_kitti_poses(samples / "00" / "poses.txt")
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    det = LoopDetector("spectral", exclude_frames=None, exclude_distance=30.0, verify=False)
    loops = [lp for p, T in zip(seq_paths, poses) for lp in det.add(read_scan(p), pose=T)]
    bevs = np.stack([polar_bev(read_scan(p), det.model.bev_config) for p in seq_paths])
    sigs, _ = det.model.embed(bevs)
    sigs = sigs.astype(np.float64)
    want = []
    for i in range(len(seq_paths)):
        allowed = np.flatnonzero(travelled[:i] <= travelled[i] - 30.0)
        if len(allowed):
            d = np.linalg.norm(sigs[allowed] - sigs[i], axis=1)
            want.append((i, int(allowed[np.argmin(d)]), float(d.min())))
    assert want and [(lp.query_index, lp.match_index) for lp in loops] == [w[:2] for w in want]
    np.testing.assert_allclose([lp.distance for lp in loops], [w[2] for w in want], rtol=1e-5)


def test_loop_detector_feature_store_across_blocks() -> None:
    """The detector's features live in fixed blocks (no copy as it grows, for the
    soak): rows asked for in any order, across block edges, are the arrays added."""
    from disco_cli.query.loop_detector import _Features

    rng = np.random.default_rng(5)
    added = rng.normal(size=(3 * _Features.BLOCK + 7, 2, 3)).astype(np.float32)
    store = _Features()
    for i, f in enumerate(added):
        store.append(f, f"scan-{i}")
    ids = np.array(
        [0, _Features.BLOCK - 1, _Features.BLOCK, len(added) - 1, 5, 2 * _Features.BLOCK]
    )
    rows = store.rows(ids)
    np.testing.assert_array_equal(rows.features, added[ids])
    assert rows.paths == [f"scan-{i}" for i in ids]
    assert store.nbytes() == added.nbytes and store.rows(np.array([], int)).features.shape == (
        0,
        2,
        3,
    )
    # Handed out in place and read-only, while the store itself takes more rows.
    assert rows.feature_rows is not None
    with pytest.raises(ValueError, match="read-only"):
        rows.feature_rows[0][...] = 0.0
    store.append(added[0] + 1.0, "one more")
    np.testing.assert_array_equal(
        store.rows(np.array([0, len(added)])).features, [added[0], added[0] + 1.0]
    )


@pytest.mark.parametrize(
    "array",
    [
        np.zeros((0, 4), np.float32),  # empty
        np.full((50, 4), np.nan, np.float32),  # NaN only
        np.zeros((10, 5), np.float32),  # wrong shape
        np.zeros((10, 4), np.complex64),  # wrong dtype
    ],
    ids=["empty", "nan-only", "wrong-shape", "wrong-dtype"],
)
def test_bad_arrays_raise_the_cli_message(array: np.ndarray, maps, tmp_path: Path) -> None:
    _, api_db = maps
    bad = tmp_path / "bad.npy"
    np.save(bad, array)
    code, _, err = run("query", bad, "--db", api_db)
    assert code == 1 and "Traceback" not in err
    line = " ".join(err.split())  # the console may wrap
    assert line.startswith(f"error: {bad}: ")
    reason = line[len(f"error: {bad}: ") :]
    with Map.open(api_db) as m:
        with pytest.raises(ScanReadError) as exc:
            m.query(array)
    assert exc.value.reason == reason and str(exc.value) == f"points: {reason}"
    with pytest.raises(ScanReadError, match="^scan-a: ") as exc:
        LoopDetector("spectral").add(array, name="scan-a")
    assert exc.value.reason == reason


def test_closed_map_and_another_model(maps, samples: Path, tmp_path: Path) -> None:
    _, api_db = maps
    m = Map.open(api_db)
    m.close()
    with pytest.raises(DatabaseError, match="the map is closed"):
        m.query(read_scan(samples / "01" / "velodyne" / "000000.bin"))
    with pytest.raises(DatabaseError, match="the map is closed"):
        len(m)
    q = samples / "01" / "velodyne" / "000000.bin"
    code, _, err = run("query", q, "--db", api_db, "-m", "spectral")
    assert code == 1
    with pytest.raises(DatabaseError) as exc:
        Map.open(api_db, model="spectral")
    assert " ".join(err.split()) == f"error: {exc.value}"
    assert "built with model 'default'" in str(exc.value)
    with pytest.raises(DatabaseError, match="already exists"):
        Map.create(api_db)
    with pytest.raises(DatabaseError, match="read-only"):
        with Map.open(api_db) as ro:
            ro.add(read_scan(q))


_WRITER = """
import sys, time
import numpy as np
from disco_cli import Map, read_scan
scans = [read_scan(p) for p in sys.argv[2:]]
with Map.open(sys.argv[1], writable=True) as m:
    for k in range(6):
        m.add_many([(s, f"w{k}-{j}", None) for j, s in enumerate(scans)], batch=len(scans))
        time.sleep(0.15)
"""


def test_read_only_map_sees_a_consistent_snapshot(seq_paths, tmp_path: Path) -> None:
    batch = seq_paths[:4]
    path = tmp_path / "grow.db"
    with Map.create(path, "spectral") as m:
        m.add_many([(read_scan(p), p, None) for p in batch])
    writer = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(_WRITER), str(path), *batch],
        stderr=subprocess.PIPE,
        text=True,
    )
    probe = read_scan(seq_paths[2])
    seen = set()
    try:
        deadline = time.time() + 120
        while writer.poll() is None and time.time() < deadline:
            with Map.open(path) as m:
                n = len(m)
                # Whole batches only, and every answer comes from the same snapshot.
                assert n % len(batch) == 0
                for _ in range(3):
                    found = m.query(probe, topk=n)
                    assert len(found) == n and max(f.match_id for f in found) == n
                    time.sleep(0.05)
                assert len(m) == n
                seen.add(n)
    finally:
        writer.wait(timeout=120)
    assert writer.returncode == 0, writer.stderr.read()
    with Map.open(path) as m:
        assert len(m) == 7 * len(batch)
        before = len(m)
        m.refresh()
        assert len(m) == before
    assert len(seen) >= 2, seen  # the reader saw the map grow between its snapshots


def test_public_names() -> None:
    for name in ("Map", "Match", "LoopDetector", "Loop", "load_model", "signature"):
        assert hasattr(disco_cli, name)
    model = disco_cli.load_model("spectral")
    scan = np.random.default_rng(0).uniform(-20, 20, (2000, 3)).astype(np.float32)
    sig, feat = disco_cli.signature(model, scan)
    sig2, _ = model.embed(disco_cli.polar_bev(scan, model.bev_config)[None])
    np.testing.assert_array_equal(sig, sig2[0])
    assert abs(float(model.yaw(feat, feat[None])[0])) < 1e-6


def test_poses_near_exclude_overwrite_and_query_many(samples: Path, seq_paths, tmp_path) -> None:
    from disco_cli.io.poses import read_kitti_poses

    poses = read_kitti_poses(samples / "00" / "poses.txt")
    path = tmp_path / "posed.db"
    with Map.create(path, "spectral") as m:
        ids = m.add_many((read_scan(p), p, T) for p, T in zip(seq_paths, poses))
        assert len(m) == len(seq_paths) and ids[-1] == len(seq_paths)
    with Map.open(path) as m:
        # near(): the stored x, y against a NumPy distance over poses.txt.
        here = poses[3]
        d = np.hypot(*(poses[:, :2, 3] - here[:2, 3]).T)
        np.testing.assert_array_equal(m.near(here, 30.0), np.flatnonzero(d <= 30.0) + 1)
        # Excluding those ids leaves only matches farther than 30 m.
        found = m.query(read_scan(seq_paths[3]), topk=5, exclude=m.near(here, 30.0))
        assert found and all(d[f.match_id - 1] > 30.0 for f in found)
        assert m.query(read_scan(seq_paths[3]), topk=1)[0].match_id == 4  # itself, unexcluded
        many = list(m.query_many([read_scan(p) for p in seq_paths[:3]], topk=2))
        assert [r[0].match_id for r in many] == [1, 2, 3]
    # overwrite=True replaces the old map with its first batch; without it, refused.
    with Map.create(path, "spectral", overwrite=True) as m:
        assert len(m) == 0
        m.add(read_scan(seq_paths[0]), name="only")
    with Map.open(path) as m:
        assert m.names() == ["only"] and len(m) == 1
