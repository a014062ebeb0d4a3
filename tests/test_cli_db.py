"""build-db, query, loops and info from the command line, on small scans made here.

Every scene is a random set of boxes seen from its centre; a query is a scene turned
by a known angle, so the right match and its yaw are known without disco. Search
results are checked against a plain NumPy brute force over the stored signatures.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import DISCO_WITH_DEFAULT_SIGINT, package_path
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.maps.database import FORMAT_VERSION, Database

N_SCENES = 8
TURN_DEG = 30.0  # a whole number of 3-degree sectors


def _disco() -> str:
    exe = shutil.which("disco") or str(Path(sys.executable).parent / "disco")
    assert Path(exe).exists(), "the disco executable is not installed"
    return exe


def scene(seed: int, n: int = 4000) -> np.ndarray:
    """Points on random boxes around the sensor, float32 N x 4."""
    rng = np.random.default_rng(seed)
    boxes = 30
    r = rng.uniform(4.0, 35.0, boxes)
    a = rng.uniform(0.0, 2 * np.pi, boxes)
    centre = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    size = rng.uniform(0.5, 4.0, (boxes, 2))
    height = rng.uniform(0.5, 6.0, boxes)
    k = rng.integers(0, boxes, n)
    xy = centre[k] + (rng.random((n, 2)) - 0.5) * size[k]
    z = rng.random(n) * height[k] - 1.7
    return np.column_stack([xy, z, rng.random(n)]).astype(np.float32)


def turn(points: np.ndarray, deg: float) -> np.ndarray:
    """The points turned by +deg about z: the sensor turned by -deg."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def kitti_line(x: float, y: float, yaw: float) -> str:
    c, s = np.cos(yaw), np.sin(yaw)
    return f"{c} {-s} 0 {x} {s} {c} 0 {y} 0 0 1 0\n"


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A KITTI-style folder: velodyne/*.bin, poses.txt, times.txt."""
    root = tmp_path_factory.mktemp("seq")
    (root / "velodyne").mkdir()
    lines, times = [], []
    for i in range(N_SCENES):
        scene(i).tofile(root / "velodyne" / f"{i:06d}.bin")
        lines.append(kitti_line(10.0 * i, 2.0 * i, 0.1 * i))
        times.append(f"{0.5 * i}\n")
    (root / "poses.txt").write_text("".join(lines))
    (root / "times.txt").write_text("".join(times))
    return root


@pytest.fixture(scope="module")
def queries(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """q3.bin = scene 3 turned by TURN_DEG; q5.bin = scene 5 turned by -60 degrees."""
    root = tmp_path_factory.mktemp("queries")
    turn(scene(3), TURN_DEG).tofile(root / "q3.bin")
    turn(scene(5), -60.0).tofile(root / "q5.bin")
    far = scene(9)
    far[:, :2] += 1000.0  # every point far outside any BEV range
    far.tofile(root / "empty.bin")
    (root / "bad.bin").write_bytes(b"\x00" * 10)  # not a whole number of points
    return root


@pytest.fixture(scope="module")
def map_db(seq: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("db") / "map.db"
    res = CliRunner().invoke(
        app, ["build-db", str(seq), "-o", str(out), "--model", "spectral", "--batch", "3"]
    )
    assert res.exit_code == 0, res.output
    return out


def run(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, list(args))
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def jsonl(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def query_signature(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    model = load_model("spectral")
    sig, feat = model.embed(polar_bev(read_scan(path), model.bev_config)[None])
    return sig[0], feat[0]


# -- build-db ----------------------------------------------------------------


def test_build_db_stores_scans_poses_and_times(map_db: Path, seq: Path) -> None:
    with Database.open(map_db) as db:
        assert len(db) == N_SCENES
        assert db.paths() == [str(seq / "velodyne" / f"{i:06d}.bin") for i in range(N_SCENES)]
        assert db.model.name == "spectral"
        poses, times = db.poses()
        i = np.arange(N_SCENES)
        np.testing.assert_allclose(poses[:, 0], 10.0 * i)
        np.testing.assert_allclose(poses[:, 1], 2.0 * i)
        np.testing.assert_allclose(poses[:, 3], 0.1 * i)
        np.testing.assert_allclose(times, 0.5 * i)
        assert db.check() == []


def test_rerun_is_a_no_op_and_other_scans_need_append(
    map_db: Path, seq: Path, tmp_path: Path
) -> None:
    before = map_db.read_bytes()
    code, _, err = run("build-db", str(seq), "-o", str(map_db), "--model", "spectral")
    assert code == 0 and "in it already" in err
    extra = tmp_path / "extra.bin"
    scene(42).tofile(extra)
    db = tmp_path / "copy.db"
    db.write_bytes(before)
    code, _, err = run("build-db", str(extra), "-o", str(db), "--model", "spectral")
    assert code == 1 and "--append" in err
    code, _, err = run("build-db", str(extra), "-o", str(db), "--model", "spectral", "--append")
    assert code == 0, err
    with Database.open(db) as d:
        assert len(d) == N_SCENES + 1 and d.paths()[-1] == str(extra)
    # Another model is refused even with --append, and the database is untouched.
    snapshot = db.read_bytes()
    code, _, err = run("build-db", str(extra), "-o", str(db), "--model", "scancontext", "--append")
    assert code == 1 and "model 'spectral'" in err and "Traceback" not in err
    assert db.read_bytes() == snapshot


def test_build_from_stdin_with_the_installed_executable(seq: Path, tmp_path: Path) -> None:
    files = sorted((seq / "velodyne").glob("*.bin"))[:3]
    out = tmp_path / "stdin.db"
    proc = subprocess.run(
        [_disco(), "build-db", "-", "-o", str(out), "--model", "spectral"],
        input="".join(f"{f}\n" for f in files),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    with Database.open(out) as db:
        assert db.paths() == [str(f) for f in files]
        assert not db.has_poses()


def test_unreadable_scan_stops_the_build_and_leaves_no_file(
    seq: Path, queries: Path, tmp_path: Path
) -> None:
    out = tmp_path / "new.db"
    code, _, err = run("build-db", str(queries / "bad.bin"), "-o", str(out), "--model", "spectral")
    assert code == 1 and "bad.bin" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # no half-initialized database
    # With --skip-bad: a warning, a count, and the good scans stored.
    good = seq / "velodyne" / "000001.bin"
    code, _, err = run(
        "build-db",
        str(good),
        str(queries / "bad.bin"),
        str(queries / "empty.bin"),
        "-o",
        str(out),
        "--model",
        "spectral",
        "--skip-bad",
    )
    assert code == 0, err
    assert "bad.bin" in err and "empty.bin" in err and "2 unreadable scans skipped" in err
    with Database.open(out) as db:
        assert db.paths() == [str(good)]


def test_missing_input_and_model_without_weights(tmp_path: Path) -> None:
    code, _, err = run(
        "build-db", str(tmp_path / "nope"), "-o", str(tmp_path / "m.db"), "--model", "spectral"
    )
    assert code == 1 and "nope" in err and "Traceback" not in err
    scene(0).tofile(tmp_path / "a.bin")
    code, _, err = run(
        "build-db",
        str(tmp_path / "a.bin"),
        "-o",
        str(tmp_path / "m.db"),
        "--model",
        str(tmp_path / "missing.pt"),
    )
    assert code == 1 and "missing.pt" in err
    assert not (tmp_path / "m.db").exists()


def test_output_in_a_missing_folder(tmp_path: Path) -> None:
    scene(0).tofile(tmp_path / "a.bin")
    out = tmp_path / "no" / "such" / "map.db"
    code, _, err = run("build-db", str(tmp_path / "a.bin"), "-o", str(out), "--model", "spectral")
    # Refused before any scan is embedded (the same rule as every -o: tests/test_output_paths.py).
    assert code == 1 and "does not exist" in err and str(out) in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_refuses_to_overwrite_a_non_database(tmp_path: Path) -> None:
    scene(0).tofile(tmp_path / "a.bin")
    target = tmp_path / "notes.txt"
    target.write_text("my precious notes\n")
    code, _, err = run(
        "build-db", str(tmp_path / "a.bin"), "-o", str(target), "--model", "spectral"
    )
    assert code == 1 and "notes.txt" in err and "not a disco database" in err
    assert target.read_text() == "my precious notes\n"


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_resume_after_kill(tmp_path: Path, sig: signal.Signals) -> None:
    # Many paths (links to a few scans) so that the build is still running when killed.
    src = tmp_path / "src"
    src.mkdir()
    for k in range(4):
        scene(100 + k, n=30000).tofile(src / f"s{k}.bin")
    scans = tmp_path / "scans"
    scans.mkdir()
    n = 400
    for i in range(n):
        (scans / f"{i:06d}.bin").symlink_to(src / f"s{i % 4}.bin")
    out = tmp_path / "map.db"
    args = ["build-db", str(scans), "-o", str(out), "--model", "spectral", "--batch", "2"]
    cmd, env = [*DISCO_WITH_DEFAULT_SIGINT, *args], {**os.environ, "PYTHONPATH": package_path()}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 120
    while not out.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    proc.send_signal(sig)
    code = proc.wait(timeout=60)
    err = proc.stderr.read().decode()
    if sig == signal.SIGINT:  # Ctrl-C: exit 130, no traceback, what is safe and what next
        assert code == 130 and "Traceback" not in err, err
        assert "safely stored; run the same command again to resume" in err, err
    with Database.open(out) as db:
        assert db.check() == []
        done = db.paths()
    assert 0 < len(done) < n, "the build was not interrupted mid-way"
    if sig == signal.SIGINT:
        assert f"holds {len(done)} of the {n} scans given" in err, err
    assert done == [str(scans / f"{i:06d}.bin") for i in range(len(done))]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    assert f"{len(done)} were in it already" in proc.stderr
    with Database.open(out) as db:
        assert db.paths() == [str(scans / f"{i:06d}.bin") for i in range(n)]
        ids, sigs = db.signatures()
        # Links to the same scan give the same signature, killed or not.
        np.testing.assert_array_equal(sigs[4:], sigs[:-4])


# -- query -------------------------------------------------------------------


def test_query_finds_the_turned_scene_with_its_yaw(map_db: Path, seq: Path, queries: Path) -> None:
    code, out, err = run(
        "query",
        str(queries / "q3.bin"),
        str(queries / "q5.bin"),
        "--db",
        str(map_db),
        "--topk",
        "3",
        "--format",
        "jsonl",
    )
    assert code == 0, err
    rows = jsonl(out)
    assert [r["rank"] for r in rows] == [1, 2, 3, 1, 2, 3]
    first = [r for r in rows if r["rank"] == 1]
    assert first[0]["match"] == str(seq / "velodyne" / "000003.bin") and first[0]["match_id"] == 4
    assert first[1]["match"] == str(seq / "velodyne" / "000005.bin") and first[1]["match_id"] == 6
    # Points turned by +a: the query sensor is turned by -a in the match's frame.
    assert abs(first[0]["yaw_deg"] - (-TURN_DEG)) <= 3.0
    assert abs(first[1]["yaw_deg"] - 60.0) <= 3.0
    assert all(-180.0 < r["yaw_deg"] <= 180.0 for r in rows)
    assert set(rows[0]) == {
        "query", "rank", "match", "match_id", "distance", "confidence", "yaw_deg", "yaw_conf"
    }  # fmt: skip
    # Every row rates its yaw (yaw_refine.py): an unambiguous scene here.
    assert all(0.0 <= r["yaw_conf"] <= 1.0 for r in rows)
    assert first[0]["yaw_conf"] > 0.5


def test_query_equals_numpy_brute_force(map_db: Path, queries: Path) -> None:
    sig, _ = query_signature(queries / "q5.bin")
    with Database.open(map_db) as db:
        ids, sigs = db.signatures()
        paths = db.paths()
    d = np.sqrt(((sigs.astype(np.float64) - sig.astype(np.float64)) ** 2).sum(1))
    order = np.argsort(d, kind="stable")
    code, out, _ = run(
        "query",
        str(queries / "q5.bin"),
        "--db",
        str(map_db),
        "--topk",
        str(N_SCENES),
        "--format",
        "jsonl",
    )
    rows = jsonl(out)
    assert [r["match"] for r in rows] == [paths[i] for i in order]
    assert [r["match_id"] for r in rows] == [int(ids[i]) for i in order]
    np.testing.assert_allclose([r["distance"] for r in rows], d[order], rtol=1e-6)
    # --max-distance keeps exactly the brute-force rows within it.
    cut = float((d[order[2]] + d[order[3]]) / 2)
    code, out, _ = run(
        "query",
        str(queries / "q5.bin"),
        "--db",
        str(map_db),
        "--topk",
        "10",
        "--max-distance",
        str(cut),
        "--format",
        "jsonl",
    )
    assert [r["match_id"] for r in jsonl(out)] == [int(ids[i]) for i in order[:3]]


def test_exclude_radius_drops_nearby_map_scans(map_db: Path, queries: Path, tmp_path: Path) -> None:
    # The query stands where scene 3 was (x=30, y=6): scenes within 15 m (2, 3, 4) go.
    poses = tmp_path / "qposes.txt"
    poses.write_text(kitti_line(30.0, 6.0, 0.0))
    code, out, err = run(
        "query",
        str(queries / "q3.bin"),
        "--db",
        str(map_db),
        "--topk",
        "10",
        "--exclude-radius",
        "15",
        "--poses",
        str(poses),
        "--format",
        "jsonl",
    )
    assert code == 0, err
    got = {r["match_id"] for r in jsonl(out)}
    xy = np.stack([10.0 * np.arange(N_SCENES), 2.0 * np.arange(N_SCENES)], 1)
    keep = {i + 1 for i in range(N_SCENES) if np.hypot(*(xy[i] - [30.0, 6.0])) > 15.0}
    assert got == keep and 4 not in got
    # --query-poses, the old name of --poses in query and eval, still works.
    args = ["query", str(queries / "q3.bin"), "--db", str(map_db), "--exclude-radius", "15"]
    code, out, err = run(*args, "--query-poses", str(poses), "--format", "jsonl")
    assert code == 0 and {r["match_id"] for r in jsonl(out)} == keep
    assert "--query-poses is now --poses" in err
    code, _, err = run(
        "query", str(queries / "q3.bin"), "--db", str(map_db), "--exclude-radius", "15"
    )
    assert code != 0 and "--poses" in err


def test_tsv_has_a_header_and_the_same_columns(map_db: Path, queries: Path) -> None:
    code, out, _ = run(
        "query", str(queries / "q3.bin"), "--db", str(map_db), "--topk", "2", "--format", "tsv"
    )
    lines = out.splitlines()
    assert lines[0].split("\t") == [
        "query",
        "rank",
        "match",
        "match_id",
        "distance",
        "confidence",
        "yaw_deg",
        "yaw_conf",
    ]
    assert len(lines) == 3 and lines[1].split("\t")[1] == "1"
    code, out, _ = run(
        "query", str(queries / "q3.bin"), "--db", str(map_db), "--topk", "2", "--format", "table"
    )
    # A table titled by its query, with one row per match: long paths wrap inside their
    # cells, so a row is a line whose rank cell holds a number.
    assert code == 0 and out.startswith(str(queries / "q3.bin"))
    header = next(ln for ln in out.splitlines() if ln.startswith("┃"))
    names = [c.strip() for c in header.split("┃")[1:-1]]
    assert "query" not in names and "match" in names
    col = names.index("rank") + 1
    ranks = [ln.split("│")[col].strip() for ln in out.splitlines() if ln.startswith("│")]
    assert [r for r in ranks if r] == ["1", "2"]


def test_bad_query_scans_are_reported_and_the_rest_go_on(map_db: Path, queries: Path) -> None:
    code, out, err = run(
        "query",
        str(queries / "bad.bin"),
        str(queries / "nope.bin"),
        str(queries / "empty.bin"),
        str(queries / "q3.bin"),
        "--db",
        str(map_db),
        "--topk",
        "1",
        "--format",
        "jsonl",
    )
    assert code == 1
    assert [r["query"] for r in jsonl(out)] == [str(queries / "q3.bin")]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 3 and "Traceback" not in err
    assert "bad.bin" in lines[0] and "nope.bin" in lines[1]
    assert "empty.bin" in lines[2] and "no points" in lines[2]


def test_bad_databases(map_db: Path, queries: Path, tmp_path: Path) -> None:
    q = str(queries / "q3.bin")
    cases = {}
    text = tmp_path / "text.db"
    text.write_text("not a database\n")
    cases[text] = "not a disco database"
    cases[tmp_path / "missing.db"] = "no such database"
    newer = tmp_path / "newer.db"
    newer.write_bytes(map_db.read_bytes())
    with sqlite3.connect(newer) as conn:
        conn.execute(
            "UPDATE meta SET value=? WHERE key='format_version'", (str(FORMAT_VERSION + 1),)
        )
    cases[newer] = "newer"
    empty = tmp_path / "empty.db"
    empty.write_bytes(map_db.read_bytes())
    with sqlite3.connect(empty) as conn:
        conn.execute("DELETE FROM scans")
    cases[empty] = "empty"
    for path, reason in cases.items():
        before = path.read_bytes() if path.exists() else None
        code, out, err = run("query", q, "--db", str(path))
        assert code == 1 and str(path) in err and reason in err, (path, err)
        assert out == "" and "Traceback" not in err
        if before is not None:
            assert path.read_bytes() == before
    code, _, err = run("query", q, "--db", str(map_db), "--model", "scancontext")
    assert code == 1 and "model 'spectral'" in err and "scancontext" in err


def test_scancontext_rerank_through_the_database(seq: Path, queries: Path, tmp_path: Path) -> None:
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    out = tmp_path / "sc.db"
    code, _, err = run("build-db", str(seq), "-o", str(out), "--model", "scancontext")
    assert code == 0, err
    code, text, err = run(
        "query", str(queries / "q3.bin"), "--db", str(out), "--topk", "3", "--format", "jsonl"
    )
    assert code == 0, err
    rows = jsonl(text)
    assert rows[0]["match_id"] == 4
    assert abs(rows[0]["yaw_deg"] - (-TURN_DEG)) <= 6.0
    # The truth: rerank every map scan with the model's full comparison.
    model = load_model("scancontext")
    sig, feat = model.embed(polar_bev(read_scan(queries / "q3.bin"), model.bev_config)[None])
    with Database.open(out) as db:
        ids, _ = db.signatures()
        stored = db.rows(ids)
    if model.rerank_candidates >= N_SCENES:
        d, _ = model.rerank(feat[0], stored.features)
        order = np.argsort(d, kind="stable")[:3]
        assert [r["match_id"] for r in rows] == [int(ids[i]) for i in order]


def test_default_model_reranks_the_nearest_signatures(
    seq: Path, queries: Path, tmp_path: Path
) -> None:
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    out = tmp_path / "default.db"
    code, _, err = run("build-db", str(seq), "-o", str(out), "--model", "default")
    assert code == 0, err
    model = load_model("default")
    sig, feat = model.embed(polar_bev(read_scan(queries / "q3.bin"), model.bev_config)[None])
    with Database.open(out) as db:
        ids, sigs = db.signatures()
        stored = db.rows(ids)
    d_sig = ((sigs.astype(np.float64) - sig[0]) ** 2).sum(1)
    near = np.argsort(d_sig, kind="stable")[:4]
    # The query's side views (its feature images re-centred to either side): each map
    # scan counts at its nearest signature over the query and its views.
    policy = model.query_policy
    view_sigs, view_images = model.query_views(feat[0], policy.view_offsets)
    d_views = ((sigs[:, None].astype(np.float64) - view_sigs[None]) ** 2).sum(2).min(1)
    d_best = np.sqrt(np.minimum(d_sig, d_views))
    near_views = np.argsort(d_best, kind="stable")[:4]

    def corr(a: np.ndarray, b: np.ndarray) -> float:
        # Truth by a plain loop: best centred, normalized correlation over all rolls.
        a, b = a - a.mean(), b - b.mean()
        return max(
            float((a * np.roll(b, k, axis=1)).sum() / (np.linalg.norm(a) * np.linalg.norm(b)))
            for k in range(b.shape[1])
        )

    # Re-ranking the 4 nearest by the query's own signature and the 4 nearest over the
    # query and its views by the learned images (channel 1), each at its best over the
    # query's and its views' (a view's distance plus the model's penalty), in the order
    # of re-rank distance minus 0.3 over the signature distance; the best 4 are shown.
    cand = np.array(sorted(set(near.tolist()) | set(near_views.tolist())))
    rerank = np.array(
        [
            min(
                [1 - corr(feat[0, 1], stored.features[i, 1])]
                + [1 + policy.view_penalty - corr(v, stored.features[i, 1]) for v in view_images]
            )
            for i in cand
        ]
    )
    assert rerank.min() <= policy.rerank_wider_above  # no wider pass
    score = rerank - 0.3 / d_best[cand]
    order = np.lexsort((cand, score))[:4]
    args = ["query", str(queries / "q3.bin"), "--db", str(out), "--format", "jsonl"]
    code, text, err = run(*args, "--topk", "4", "--rerank", "4")
    assert code == 0, err
    rows = jsonl(text)
    assert [r["match_id"] for r in rows] == [int(ids[i]) for i in cand[order]]
    # The distance shown is that score, bounded: r + 0.3 (1/0.05 - 1/max(s, 0.05)), each
    # row's own.
    bounded = rerank + 0.3 * (1 / 0.05 - 1 / np.maximum(d_best[cand], 0.05))
    shown = bounded[order]
    np.testing.assert_allclose([r["distance"] for r in rows], shown, atol=2e-3)
    # --rerank 0: the signature order of the paper.
    code, text, err = run(*args, "--topk", "4", "--rerank", "0")
    assert [r["match_id"] for r in jsonl(text)] == [int(ids[i]) for i in near]
    # The turned scene is still found, with its yaw.
    code, text, err = run(*args, "--topk", "1")
    assert jsonl(text)[0]["match_id"] == 4 and abs(jsonl(text)[0]["yaw_deg"] + TURN_DEG) <= 3


def test_rerank_with_a_model_that_cannot(map_db: Path, queries: Path) -> None:
    code, _, err = run("query", str(queries / "q3.bin"), "--db", str(map_db), "--rerank", "5")
    assert code == 1 and "spectral cannot re-rank" in err and len(err.strip().splitlines()) == 1


def test_streaming_first_result_before_stdin_closes(map_db: Path, queries: Path) -> None:
    proc = subprocess.Popen(
        [_disco(), "query", "-", "--db", str(map_db), "--topk", "1", "--format", "tsv"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True)
    reader.start()
    try:
        proc.stdin.write(f"{queries / 'q3.bin'}\n")
        proc.stdin.flush()
        header = lines.get(timeout=60)
        first = lines.get(timeout=60)  # stdin is still open: the result came on its own
        assert header.startswith("query\trank")
        assert first.split("\t")[0] == str(queries / "q3.bin")
        assert first.split("\t")[3] == "4"
        assert proc.poll() is None
        proc.stdin.write(f"{queries / 'q5.bin'}\n")
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
        reader.join(timeout=10)
        assert lines.get(timeout=1).split("\t")[3] == "6"
        assert lines.empty()
    finally:
        proc.kill()
        proc.wait()


def test_closed_pipe_is_quiet(map_db: Path, queries: Path) -> None:
    # `... | disco query - | head -1`: the reader goes away after one line.
    shell = (
        f"yes {queries / 'q3.bin'} | head -200 | {_disco()} query - --db {map_db} "
        "--topk 5 --format tsv | head -1"
    )
    proc = subprocess.run(
        ["bash", "-o", "pipefail", "-c", shell], capture_output=True, text=True, timeout=120
    )
    header = "query\trank\tmatch\tmatch_id\tdistance\tconfidence\tyaw_deg\tyaw_conf"
    assert proc.stdout.splitlines() == [header]
    assert "Traceback" not in proc.stderr and "Error" not in proc.stderr, proc.stderr


# -- loops and info ----------------------------------------------------------


def test_loops_finds_the_revisit(tmp_path: Path) -> None:
    seq = tmp_path / "loop"
    (seq / "velodyne").mkdir(parents=True)
    for i in range(6):
        scene(200 + i).tofile(seq / "velodyne" / f"{i:06d}.bin")
    turn(scene(201), 90.0).tofile(seq / "velodyne" / "000006.bin")  # back at scene 1, turned
    (seq / "times.txt").write_text("".join(f"{0.1 * i}\n" for i in range(7)))
    code, out, err = run(
        "loops", str(seq), "--model", "spectral", "--exclude-frames", "3", "--format", "jsonl"
    )
    assert code == 0, err
    rows = jsonl(out)
    # Query i searches frames [0, i - 3]: frames 3.. have candidates, top-1 each.
    assert [r["query_index"] for r in rows] == [3, 4, 5, 6]
    assert all(r["match_index"] <= r["query_index"] - 3 for r in rows)
    last = rows[-1]
    assert last["match_index"] == 1 and abs(last["yaw_deg"] - (-90.0)) <= 3.0
    # A threshold between the revisit and the other pairs keeps only the revisit.
    others = [r["distance"] for r in rows[:-1]]
    assert last["distance"] < min(others)
    cut = (last["distance"] + min(others)) / 2
    args = ["loops", str(seq), "--model", "spectral", "--exclude-seconds", "0.25"]
    args += ["--max-distance", str(cut), "--format", "jsonl"]
    code, out, _ = run(*args)
    rows = jsonl(out)
    assert [(r["query_index"], r["match_index"]) for r in rows] == [(6, 1)]
    # The old name of the cut still works, with one warning line naming the new one.
    code, out_old, err_old = run(*["--threshold" if a == "--max-distance" else a for a in args])
    assert code == 0 and jsonl(out_old) == rows
    said = [line for line in err_old.splitlines() if "--threshold" in line]
    assert said == ["warning: --threshold is now --max-distance; the old name will go"]
    # The same answer from a database of the sequence.
    db = tmp_path / "loop.db"
    assert run("build-db", str(seq), "-o", str(db), "--model", "spectral")[0] == 0
    code, out2, _ = run(*args, "--db", str(db))
    # The map stores float16 signatures and features: the same loops, distances within
    # their rounding, and the yaw's confidence (a ratio of two correlation peaks) within
    # a few thousandths.
    got = jsonl(out2)
    same = [{**r, "distance": 0, "yaw_conf": 0} for r in got]
    assert same == [{**r, "distance": 0, "yaw_conf": 0} for r in rows]
    assert all(abs(g["distance"] - r["distance"]) < 1e-4 for g, r in zip(got, rows))
    assert all(abs(g["yaw_conf"] - r["yaw_conf"]) < 0.01 for g, r in zip(got, rows))


def test_info_and_check(map_db: Path, tmp_path: Path) -> None:
    code, out, err = run("info", str(map_db), "--check", "--format", "jsonl")
    assert code == 0, err
    (fields,) = jsonl(out)
    assert fields["scans"] == N_SCENES and fields["model"] == "spectral"
    assert fields["poses"] == "yes" and fields["check"] == "ok"
    assert fields["bev_config"]["rings"] > 0
    broken = tmp_path / "broken.db"
    broken.write_bytes(map_db.read_bytes())
    with sqlite3.connect(broken) as conn:
        conn.execute("UPDATE features SET data = x'00' WHERE id = 2")
    code, out, err = run("info", str(broken), "--check")
    assert code == 1 and "scan 2" in err
    code, _, err = run("info", str(tmp_path / "none.db"))
    assert code == 1 and "no such database" in err


# -- relative pose: query --pose/--verify, loops --verify -o ----------------------


def _gt_relative(samples: Path, query: tuple[str, int], match: tuple[str, int]) -> np.ndarray:
    """T_match<-query from the sessions' poses.txt (the simulator's truth)."""
    from disco_cli.io.poses import read_kitti_poses

    Tq = read_kitti_poses(samples / query[0] / "poses.txt")[query[1]]
    Tm = read_kitti_poses(samples / match[0] / "poses.txt")[match[1]]
    return np.linalg.inv(Tm) @ Tq


def _yaw_of(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_quaternion_of_known_rotations() -> None:
    from disco_cli.io.loop_export import quaternion

    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(-np.pi, np.pi)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K  # Rodrigues
        want = np.append(axis * np.sin(angle / 2), np.cos(angle / 2))
        want = -want if want[3] < 0 else want
        np.testing.assert_allclose(quaternion(R), want, atol=1e-12)
    np.testing.assert_allclose(quaternion(np.diag([1.0, -1.0, -1.0])), [1, 0, 0, 0], atol=1e-12)


@pytest.fixture(scope="module")
def samples_db(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("samples") / "s00.db"
    assert run("build-db", str(samples / "00"), "-o", str(out), "--model", "spectral")[0] == 0
    return out


def test_query_pose_matches_the_simulator_truth(samples: Path, samples_db: Path) -> None:
    # 01/000005 drives past 00/000004 in the opposite direction, about 1.9 m away.
    q = samples / "01" / "velodyne" / "000005.bin"
    code, out, err = run(
        "query", str(q), "--db", str(samples_db), "--topk", "5", "--pose", "--format", "jsonl"
    )
    assert code == 0, err
    rows = jsonl(out)
    assert len(rows) == 5 and {"dx", "dy", "dz", "fitness", "accepted"} <= set(rows[0])
    hit = [r for r in rows if r["match"].endswith("00/velodyne/000004.bin")]
    assert hit and hit[0]["accepted"]
    T = _gt_relative(samples, ("01", 5), ("00", 4))
    assert np.hypot(hit[0]["dx"] - T[0, 3], hit[0]["dy"] - T[1, 3]) < 0.3
    # --verify keeps exactly the accepted ones, in the same order.
    code, out, _ = run(
        "query", str(q), "--db", str(samples_db), "--topk", "5", "--verify", "--format", "jsonl"
    )
    assert [r["match_id"] for r in jsonl(out)] == [r["match_id"] for r in rows if r["accepted"]]


def test_loops_export_g2o_tum_csv(samples: Path, tmp_path: Path) -> None:
    seq = samples / "00"
    args = [
        "loops",
        str(seq),
        "--model",
        "spectral",
        "--exclude-frames",
        "5",
        "--max-distance",
        "0.5",
        "--verify",
        "--format",
        "jsonl",
    ]
    code, out, err = run(*args, "-o", str(tmp_path / "loops.g2o"))
    assert code == 0, err
    rows = jsonl(out)
    assert rows, "no verified loops in data/samples/00"
    # With a pose, yaw_deg is the refined yaw of T; roll, pitch and the full T come along.
    base = {"query_index", "query", "match_index", "match", "distance", "yaw_deg", "yaw_conf"}
    assert set(rows[0]) == base | {"confidence", "roll_deg", "pitch_deg", "T"}
    for r in rows:
        T = np.array(r["T"])
        assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
        assert abs(r["yaw_deg"] - _yaw_of(T)) < 1e-9
        assert abs(r["pitch_deg"] - np.degrees(np.arcsin(-T[2, 0]))) < 1e-6
        assert abs(r["roll_deg"] - np.degrees(np.arctan2(T[2, 1], T[2, 2]))) < 1e-9
    edges = [ln.split() for ln in (tmp_path / "loops.g2o").read_text().splitlines()]
    assert len(edges) == len(rows)
    for e, r in zip(edges, rows):
        assert e[0] == "EDGE_SE3:QUAT" and len(e) == 3 + 7 + 21
        assert (int(e[1]), int(e[2])) == (r["match_index"], r["query_index"])
        t, q = np.array(e[3:6], float), np.array(e[6:10], float)
        np.testing.assert_allclose(t, np.array(r["T"])[:3, 3], atol=1e-6)  # the same pose
        T = _gt_relative(samples, ("00", r["query_index"]), ("00", r["match_index"]))
        assert np.linalg.norm(t - T[:3, 3]) < 0.3
        assert abs(np.linalg.norm(q) - 1.0) < 1e-6
        yaw = np.degrees(2 * np.arctan2(q[2], q[3]))  # near-planar: rotation about z
        assert _angle_diff(yaw, _yaw_of(T)) < 1.0
        info = np.array(e[10:], float)
        assert info[0] > 0 and info[[1, 2, 3, 4, 5]].tolist() == [0, 0, 0, 0, 0]
    code, _, _ = run(*args, "-o", str(tmp_path / "loops.tum"))
    tum = (tmp_path / "loops.tum").read_text().splitlines()
    assert tum[0].startswith("#") and len(tum) == len(rows) + 1
    times = np.loadtxt(seq / "times.txt")
    first = tum[1].split()
    assert float(first[0]) == pytest.approx(times[rows[0]["query_index"]], abs=1e-6)
    assert float(first[1]) == pytest.approx(times[rows[0]["match_index"]], abs=1e-6)
    code, _, _ = run(*args, "-o", str(tmp_path / "loops.csv"))
    import csv

    with open(tmp_path / "loops.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [int(t["query_index"]) for t in table] == [r["query_index"] for r in rows]
    assert all(t["accepted"] == "true" for t in table)
    code, _, err = run(*args, "-o", str(tmp_path / "loops.txt"))
    assert code == 1 and "loops.txt" in err
    # --verbose without --verify: every pair with its pose; the accepted ones are the above.
    verbose = [a for a in args if a != "--verify"] + ["--verbose"]
    code, out, _ = run(*verbose)
    every = jsonl(out)
    assert {"dx", "dy", "dz", "fitness", "rmse", "accepted", "reason"} <= set(every[0])
    assert [(r["query_index"], r["match_index"]) for r in every if r["accepted"]] == [
        (r["query_index"], r["match_index"]) for r in rows
    ]
    assert all(r["reason"] for r in every if not r["accepted"])


def test_bad_device_is_one_line(seq: Path, tmp_path: Path) -> None:
    import torch

    out = tmp_path / "m.db"
    code, _, err = run(
        "build-db", str(seq), "-o", str(out), "--model", "spectral", "--device", "tpu"
    )
    assert code == 1 and "'tpu'" in err and "Traceback" not in err
    if not torch.cuda.is_available():
        code, _, err = run(
            "build-db", str(seq), "-o", str(out), "--model", "spectral", "--device", "cuda"
        )
        assert code == 1 and "no CUDA device" in err
    assert not out.exists()


def test_real_kitti_folder_with_a_few_frames(realdata: Path, tmp_path: Path) -> None:
    """KITTI 00 with 12 of its 4541 frames: poses, calibration and times come from the
    folder by frame number; a turned copy of frame 15 finds frame 15 with its yaw."""
    from disco_cli.io.poses import read_kitti_poses, read_times

    seq = realdata / "kitti00"
    out = tmp_path / "kitti.db"
    code, _, err = run("build-db", str(seq), "-o", str(out), "--model", "spectral")
    assert code == 0, err
    frames = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 15]
    T = read_kitti_poses(seq / "poses.txt", seq / "calib.txt")[frames]
    with Database.open(out) as db:
        assert db.paths() == [str(seq / "velodyne" / f"{i:06d}.bin") for i in frames]
        poses, times = db.poses()
    np.testing.assert_allclose(poses[:, :3], T[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(poses[:, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0]), atol=1e-9)
    np.testing.assert_allclose(times, read_times(seq / "times.txt")[frames])
    from disco_cli.io.readers import read_scan

    turn(read_scan(seq / "velodyne" / "000015.bin"), 90.0).tofile(tmp_path / "q.bin")
    code, out_text, err = run(
        "query", str(tmp_path / "q.bin"), "--db", str(out), "--topk", "1", "--format", "jsonl"
    )
    assert code == 0, err
    row = jsonl(out_text)[0]
    assert row["match"].endswith("000015.bin") and abs(row["yaw_deg"] - (-90.0)) <= 3.0


def test_loops_go_on_past_a_pair_without_pose(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # One pair whose relative pose cannot be estimated (here forced) is named on stderr;
    # the other loops are still printed and exported, and the exit status says it.
    import disco_cli.query.relative_pose as rp_module
    from disco_cli.errors import DiscoError

    real = rp_module.estimate_relative_pose
    calls = []

    def flaky(query_points, match_points, yaw_deg, config=None):
        calls.append(yaw_deg)
        if len(calls) == 1:
            raise rp_module.PoseError("query points: the scan is empty")
        return real(query_points, match_points, yaw_deg, config)

    assert issubclass(rp_module.PoseError, DiscoError)
    monkeypatch.setattr(rp_module, "estimate_relative_pose", flaky)
    out_file = tmp_path / "loops.g2o"
    code, out, err = run(
        "loops", str(samples / "00"), "--model", "spectral", "--exclude-frames", "5",
        "--max-distance", "0.5", "--verify", "--format", "jsonl", "-o", str(out_file),
    )  # fmt: skip
    assert code == 1
    assert "no relative pose" in err and "the scan is empty" in err
    rows = jsonl(out)
    assert len(calls) >= 2 and len(rows) >= 1
    assert len(out_file.read_text().splitlines()) == len(rows)
