"""The paper's protocols: `disco eval --protocol nclt` on a miniature NCLT tree (NCLT's
scan encoding, z-down Velodyne frame and body-frame ground truth CSV) gives the figures
that `disco eval` gives on the same scans in KITTI layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.evaluation.protocols import PROTOCOLS, oxford_in_test_squares
from disco_cli.io.poses import read_kitti_poses, write_kitti_poses
from disco_cli.io.poses.nclt import body_to_velo, write_nclt_poses
from disco_cli.io.poses.oxford import write_oxford_locations

SAMPLES = Path(__file__).resolve().parent.parent / "data" / "samples"
X = np.diag([1.0, -1.0, -1.0, 1.0])  # 180 degrees about x: z up <-> NCLT's z down


def run(*args) -> tuple[int, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.output


def moved(points: np.ndarray, yaw_deg: float, d: np.ndarray) -> np.ndarray:
    """The scan seen from a sensor moved by d and turned by yaw (in its own frame)."""
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    out = points.copy()
    out[:, :3] = (points[:, :3] - d) @ R  # R^T (p - d), row-wise
    return out


def write_nclt_session(root: Path, date: str, scans: list, poses: np.ndarray, t0: int) -> None:
    """Scans (z-up LiDAR frame) and LiDAR poses (z-up world) as an NCLT session."""
    (root / date / "velodyne_sync").mkdir(parents=True)
    utimes = t0 + 100_000 * np.arange(len(scans))
    for u, pts in zip(utimes, scans):
        p = pts[:, :3].astype(np.float64) * np.array([1.0, -1.0, -1.0])  # NCLT: z down
        p = p[np.all(np.abs(p) < 99.0, axis=1)]
        raw = np.round((p + 100.0) / 0.005).astype("<u2")
        rec = np.zeros(len(raw), dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"),
                                        ("i", "u1"), ("l", "u1")])  # fmt: skip
        rec["x"], rec["y"], rec["z"] = raw[:, 0], raw[:, 1], raw[:, 2]
        rec.tofile(root / date / "velodyne_sync" / f"{u}.bin")
    body = X @ poses @ X @ np.linalg.inv(body_to_velo())
    write_nclt_poses(root / date / f"groundtruth_{date}.csv", utimes, body)


@pytest.fixture(scope="module")
def nclt_tree(tmp_path_factory):
    from disco_cli.io.readers import read_scan

    root = tmp_path_factory.mktemp("nclt")
    files = sorted((SAMPLES / "00" / "velodyne").glob("*.bin"))
    map_scans = [read_scan(f) for f in files]
    map_poses = read_kitti_poses(SAMPLES / "00" / "poses.txt")
    # Queries: session 01 (the other lane, the other way), and session 00's places seen
    # again from up to 1.4 m aside and turned: true matches within the 1.5 m radius.
    q_files = sorted((SAMPLES / "01" / "velodyne").glob("*.bin"))
    q_scans = [read_scan(f) for f in q_files]
    q_poses = list(read_kitti_poses(SAMPLES / "01" / "poses.txt"))
    rng = np.random.default_rng(7)
    for pts, T in zip(map_scans[::2], map_poses[::2]):
        yaw, d = rng.uniform(-180, 180), np.r_[rng.uniform(-1.0, 1.0, 2), 0.0]
        q_scans.append(moved(pts, yaw, d))
        M = np.eye(4)
        a = np.radians(yaw)
        M[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        M[:3, 3] = d
        q_poses.append(T @ M)
    write_nclt_session(root, "2012-02-04", map_scans, map_poses, 1328388850000000)
    write_nclt_session(root, "2012-03-17", q_scans, np.array(q_poses), 1331989900000000)
    return root, map_poses, np.array(q_poses)


def kitti_copy(nclt_session: Path, poses: np.ndarray, out: Path) -> Path:
    """The same scans, decoded from NCLT's encoding by hand and turned z up, in KITTI
    layout."""
    (out / "velodyne").mkdir(parents=True)
    rec = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
    files = sorted((nclt_session / "velodyne_sync").glob("*.bin"), key=lambda f: int(f.stem))
    for i, f in enumerate(files):
        raw = np.fromfile(f, dtype=rec)
        xyz = np.stack([raw[c] * 0.005 - 100.0 for c in "xyz"], axis=1) * [1.0, -1.0, -1.0]
        pts = np.c_[xyz, raw["i"]]
        pts.astype("<f4").tofile(out / "velodyne" / f"{i:06d}.bin")
    write_kitti_poses(out / "poses.txt", poses)
    return out


def test_nclt_protocol_reproduces_disco_eval(nclt_tree, tmp_path):
    root, map_poses, q_poses = nclt_tree
    code, out = run("eval", "--protocol", "nclt", root, "--model", "spectral", "--format", "jsonl")
    assert code == 0, out
    lines = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    session = next(r for r in lines if r["session"] == "2012-03-17")
    assert session["approach"].startswith("disco") and session["queries"] == len(q_poses)
    # The five other evaluation runs are missing: named once each, skipped.
    assert out.count("skipped") == 5
    # The paper's own row stands beside ours.
    paper = next(r for r in lines if r["approach"] == "DiSCO-occupied (paper)")
    assert paper["recall@1"] == 89.08 and paper["auc"] == 92.91

    kmap = kitti_copy(root / "2012-02-04", map_poses, tmp_path / "map")
    kq = kitti_copy(root / "2012-03-17", q_poses, tmp_path / "query")
    assert run("build-db", kmap, "-o", tmp_path / "map.db", "--model", "spectral")[0] == 0
    code, out = run(
        "eval", kq, "--db", tmp_path / "map.db", "--radius", "1.5", "--topk", "10",
        "--format", "jsonl",
    )  # fmt: skip
    assert code == 0, out
    ref = json.loads(out.strip().splitlines()[-1])
    assert ref["num_queries_with_match"] >= 13  # the moved places, at least
    assert session["recall@1"] == pytest.approx(100 * ref["recall@1"], abs=0.006)
    assert session["recall@1%"] == pytest.approx(100 * ref["recall@1%"], abs=0.006)
    assert session["auc"] == pytest.approx(100 * ref["auc"], abs=0.006)
    # Plain build-db and eval on the NCLT session folders as downloaded (z-down scans and
    # body poses in groundtruth_*.csv) give the same figures: no conversion, no flag.
    db = tmp_path / "nclt.db"
    assert run("build-db", root / "2012-02-04", "-o", db, "--model", "spectral")[0] == 0
    code, out = run("eval", root / "2012-03-17", "--db", db, "--radius", "1.5", "--topk", "10",
                    "--format", "jsonl")  # fmt: skip
    assert code == 0, out
    plain = json.loads(out.strip().splitlines()[-1])
    for key in ("recall@1", "recall@1%", "auc"):
        assert plain[key] == pytest.approx(ref[key], abs=1e-9)


def test_nclt_protocol_needs_the_map_session(tmp_path):
    (tmp_path / "2012-03-17" / "velodyne_sync").mkdir(parents=True)
    code, out = run("eval", "--protocol", "nclt", tmp_path, "--model", "spectral")
    assert code == 1 and "2012-02-04" in out and "Traceback" not in out
    code, out = run("eval", "--protocol", "kitti", tmp_path)
    assert code == 1 and "unknown protocol" in out


def test_protocols_hold_the_papers_settings():
    nclt, mulran, oxford = PROTOCOLS["nclt"], PROTOCOLS["mulran"], PROTOCOLS["oxford"]
    assert nclt.map_sessions == ("2012-02-04",) and len(nclt.query_sessions) == 6
    assert (nclt.radius, nclt.topk, nclt.d_pos, nclt.d_neg) == (1.5, 10, 1.5, 2.0)
    assert mulran.map_sessions == ("DCC01",) and mulran.query_sessions == ("DCC02", "DCC03")
    assert (mulran.radius, mulran.topk) == (3.0, 10)
    assert (oxford.radius, oxford.topk, oxford.d_pos, oxford.d_neg) == (25.0, 25, 10.0, 50.0)
    # PointNetVLAD's test squares: 150 m around each of four centres.
    inside = oxford_in_test_squares(
        np.array([5735712.0, 5735712.0 + 151.0, 5734749.3]),
        np.array([620084.4, 620084.4, 619800.0]),
    )
    assert inside.tolist() == [True, False, True]


def test_train_protocol_uses_the_papers_session_and_distances(nclt_tree, tmp_path):
    import torch

    from disco_cli.io.readers import read_scan

    root, map_poses, _ = nclt_tree
    out = tmp_path / "nclt.pt"
    # On the evaluation tree: only 2012-02-04 is read (26 scans, not the queries' 39), and
    # its scans, several metres apart, hold no positive pair within the paper's 1.5 m.
    code, text = run("train", root, "--protocol", "nclt", "-o", out, "--epochs", "1")
    assert code == 1 and f"{len(map_poses)} scans from 1 sequences" in text
    assert "no positive pairs within 1.5 m" in text
    # A training session where each place is seen twice, up to 1.4 m apart.
    files = sorted((SAMPLES / "00" / "velodyne").glob("*.bin"))[:12]
    scans = [read_scan(f) for f in files]
    poses = list(map_poses[:12])
    rng = np.random.default_rng(8)
    for pts, T in zip(list(scans), list(poses)):
        d = np.r_[rng.uniform(-1.0, 1.0, 2), 0.0]
        scans.append(moved(pts, 0.0, d))
        M = np.eye(4)
        M[:3, 3] = d
        poses.append(T @ M)
    dense = tmp_path / "nclt"
    write_nclt_session(dense, "2012-02-04", scans, np.array(poses), 1328388850000000)
    code, text = run(
        "train", dense, "--protocol", "nclt", "-o", out, "--epochs", "1", "--steps", "1",
        "--batch", "2", "--negatives", "2", "--width", "2",
    )  # fmt: skip
    assert code == 0, text
    ckpt = torch.load(out, weights_only=True)
    opts = ckpt["train_state"]["options"]
    assert (opts["d_pos"], opts["d_neg"]) == (1.5, 2.0)
    assert "--d-pos 1.5 --d-neg 2.0" in ckpt["command"]
    assert str(dense / "2012-02-04") in ckpt["command"] and "--protocol" not in ckpt["command"]


def test_mulran_protocol_reads_ouster_scans_by_nanoseconds(tmp_path):
    """A miniature MulRan tree (DCC01 map, DCC02 queries; scans named by nanoseconds,
    base poses in global_pose.csv): the protocol keeps one place every 5 m and gives the
    figures of `disco eval --radius 3 --topk 10` on those scans in KITTI layout."""
    import shutil

    from disco_cli.io.poses.mulran import base_to_ouster, write_mulran_poses

    root = tmp_path / "mulran"
    kitti = {}
    for name, sample in (("DCC01", "00"), ("DCC02", "01")):
        files = sorted((SAMPLES / sample / "velodyne").glob("*.bin"))
        lidar = read_kitti_poses(SAMPLES / sample / "poses.txt")
        stamps = 1566535751292145922 + 100_000_000 * np.arange(len(files), dtype=np.int64)
        (root / name / "sensor_data" / "Ouster").mkdir(parents=True)
        # Each scan also 20 ms later (the same points): its pose is interpolated a fifth
        # of the way (2 to 3 m) to the next one, closer than 5 m, so the spacing drops it.
        xy = []
        for k, (s, f) in enumerate(zip(stamps, files)):
            shutil.copy(f, root / name / "sensor_data" / "Ouster" / f"{s}.bin")
            xy.append((k, lidar[k, :2, 3]))
            if k + 1 < len(files):
                shutil.copy(f, root / name / "sensor_data" / "Ouster" / f"{s + 20_000_000}.bin")
                xy.append((None, 0.8 * lidar[k, :2, 3] + 0.2 * lidar[k + 1, :2, 3]))
        write_mulran_poses(
            root / name / "global_pose.csv", stamps, lidar @ np.linalg.inv(base_to_ouster())
        )
        # The places the protocol keeps: one every 5 m of travel, written independently.
        kept = [xy[0]]
        for item in xy[1:]:
            if np.linalg.norm(item[1] - kept[-1][1]) >= 5.0:
                kept.append(item)
        keep = [k for k, _ in kept]
        assert None not in keep and len(keep) < len(xy)
        out = tmp_path / "kitti" / name
        (out / "velodyne").mkdir(parents=True)
        for j, i in enumerate(keep):
            shutil.copy(files[i], out / "velodyne" / f"{j:06d}.bin")
        write_kitti_poses(out / "poses.txt", lidar[keep])
        kitti[name] = (out, len(keep))

    code, out = run(
        "eval", "--protocol", "mulran", root, "--model", "spectral", "--format", "jsonl"
    )
    assert code == 0, out
    assert out.count("skipped") == 1  # DCC03 is missing
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    got = next(r for r in rows if r["session"] == "DCC02")
    assert got["queries"] == kitti["DCC02"][1]

    db = tmp_path / "dcc01.db"
    assert run("build-db", kitti["DCC01"][0], "-o", db, "--model", "spectral")[0] == 0
    code, out = run("eval", kitti["DCC02"][0], "--db", db, "--radius", "3", "--topk", "10",
                    "--format", "jsonl")  # fmt: skip
    assert code == 0, out
    ref = json.loads(out.strip().splitlines()[-1])
    assert ref["num_queries_with_match"] > 0
    for key in ("recall@1", "recall@1%", "auc"):
        assert got[key] == pytest.approx(100 * ref[key], abs=0.006)


def pointnetvlad_submap(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A scan (z-up LiDAR frame, metres) made into a submap as PointNetVLAD's published
    generate_submaps.m does: vehicle frame x forward, y right, z down; ground removed;
    4096 points; centred on their centroid, scaled by 0.5 / (mean distance), negated, and
    cropped to [-1, 1] (refilled with other points inside it); float64."""
    p = points[:, :3].astype(np.float64)
    p = p[(np.abs(p[:, 0]) < 40) & (np.abs(p[:, 1]) < 40) & (p[:, 2] > -1.4)]  # no ground
    ned = p * [1.0, -1.0, -1.0]
    pick = ned[rng.choice(len(ned), 4096, replace=len(ned) < 4096)]
    c = pick.mean(axis=0)
    s = 0.5 / np.linalg.norm(pick - c, axis=1).mean()
    out = -s * (pick - c)
    inside = np.all(np.abs(out) <= 1.0, axis=1)
    extra = -s * (ned[rng.permutation(len(ned))] - c)
    extra = extra[np.all(np.abs(extra) <= 1.0, axis=1)]
    return np.vstack([out[inside], extra])[:4096]


# PointNetVLAD's benchmark has 45 run folders; these names sort in this order.
OXFORD_RUNS = [f"2014-{i // 28 + 5:02d}-{i % 28 + 1:02d}-10-00-00" for i in range(45)]


def oxford_run_folders(root: Path) -> list[Path]:
    """The 45 run folders of a PointNetVLAD Oxford tree, each with a test-split locations
    CSV holding no submap (a run then gets submaps with `write_oxford_split`)."""
    folders = []
    for name in OXFORD_RUNS:
        (root / name).mkdir(parents=True)
        (root / name / "pointcloud_locations_20m.csv").write_text("timestamp,northing,easting\n")
        folders.append(root / name)
    return folders


def write_oxford_split(run: Path, split: str, stamps, submaps, north, east) -> None:
    """Submaps (float64) and their locations CSV as one split of a run: "20m" (test) or
    "20m_10overlap" (training)."""
    (run / f"pointcloud_{split}").mkdir()
    for t, sub in zip(stamps, submaps):
        sub.astype("<f8").tofile(run / f"pointcloud_{split}" / f"{t}.bin")
    ne = np.c_[np.broadcast_to(north, len(stamps)), np.broadcast_to(east, len(stamps))]
    write_oxford_locations(run / f"pointcloud_locations_{split}.csv", stamps, ne)


def test_oxford_protocol_reads_normalized_submaps_in_metres(tmp_path):
    """A miniature PointNetVLAD Oxford tree: 45 run folders (the 23 test runs with
    submaps, the others only their CSV). Run A's submaps lie inside a test square (the
    queries), every other test run holds the same places 15 m away, just outside it (maps
    only), as one of two different sets of submaps (B, C; C swaps some places).
    `eval --protocol oxford` reads them at --oxford-scale metres per unit and gives, for
    A, the mean of what `disco eval --radius 25 --topk 25` gives on the same rescaled
    submaps in KITTI layout against B and against C."""
    from disco_cli.evaluation.protocols import OXFORD_TEST_CENTRES, OXFORD_TEST_RUNS
    from disco_cli.io.readers import read_scan

    scale = 25.0
    files = sorted((SAMPLES / "00" / "velodyne").glob("*.bin"))[:8]
    scans = [read_scan(f) for f in files]
    n0, e0 = OXFORD_TEST_CENTRES[0]
    east = e0 - 100.0 + 30.0 * np.arange(len(scans))  # places 30 m apart
    root = tmp_path / "benchmark_datasets" / "oxford"
    folders = oxford_run_folders(root)
    test_runs = [OXFORD_RUNS[i] for i in OXFORD_TEST_RUNS]
    query_run = test_runs[0]
    contents: dict[str, list[np.ndarray]] = {}
    # C holds the scans of places 4-7 at one another's locations: fewer true matches.
    order = {"A": range(8), "B": range(8), "C": (0, 1, 2, 3, 5, 4, 7, 6)}
    for seed, name in enumerate(("A", "B", "C")):
        rng = np.random.default_rng(100 + seed)
        contents[name] = [pointnetvlad_submap(scans[i], rng) for i in order[name]]
    which = {}
    for k, folder in enumerate(folders):
        if folder.name not in test_runs:
            continue
        name = "A" if folder.name == query_run else "BC"[k % 2]
        which[folder.name] = name
        north = n0 + (140.0 if name == "A" else 155.0)  # in / just outside the square
        stamps = 1400000000000000 + 10**9 * k + 10**6 * np.arange(len(scans))
        write_oxford_split(folder, "20m", stamps, contents[name], north, east)
    assert set(which.values()) == {"A", "B", "C"}

    code, out = run(
        "eval", "--protocol", "oxford", tmp_path / "benchmark_datasets", "--model", "spectral",
        "--oxford-scale", scale, "--format", "jsonl",
    )  # fmt: skip
    assert code == 0, out
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    got = next(r for r in rows if r["session"] == query_run)
    assert got["queries"] == 22 * len(scans)  # A's places, against each of 22 maps

    # The same submaps rescaled by hand (x negated back: x forward, y left, z up), in
    # KITTI layout with their locations as poses.
    def kitti(name: str, north: float) -> Path:
        out = tmp_path / "kitti" / name
        (out / "velodyne").mkdir(parents=True)
        for i, sub in enumerate(contents[name]):
            pts = np.c_[sub * [-scale, scale, scale], np.zeros(len(sub))]
            pts.astype("<f4").tofile(out / "velodyne" / f"{i:06d}.bin")
        T = np.tile(np.eye(4), (len(scans), 1, 1))
        T[:, 0, 3], T[:, 1, 3] = north, east
        write_kitti_poses(out / "poses.txt", T)
        return out

    kq = kitti("A", n0 + 140.0)
    ref = {}
    for name in ("B", "C"):
        db = tmp_path / f"{name}.db"
        assert run("build-db", kitti(name, n0 + 155.0), "-o", db, "--model", "spectral")[0] == 0
        code, text = run("eval", kq, "--db", db, "--radius", "25", "--topk", "25",
                         "--format", "jsonl")  # fmt: skip
        assert code == 0, text
        ref[name] = json.loads(text.strip().splitlines()[-1])
        assert ref[name]["num_queries_with_match"] == len(scans)
    n_b = sum(1 for n in which.values() if n == "B")
    for key in ("recall@1", "recall@1%", "auc"):
        want = (n_b * ref["B"][key] + (22 - n_b) * ref["C"][key]) / 22
        assert got[key] == pytest.approx(100 * want, abs=0.006)
    # The places are recognised, and the two kinds of map differ, so the mean is tested.
    assert ref["B"]["recall@1"] > 0.5 and ref["C"]["recall@1"] < ref["B"]["recall@1"]

    # Without a scale in metres the submaps fall inside the 3 m blind radius.
    code, out = run("eval", "--protocol", "oxford", root, "--model", "spectral",
                    "--oxford-scale", "1")  # fmt: skip
    assert code == 1 and "no points in range" in out and "Traceback" not in out


def test_train_protocol_oxford_uses_pointnetvlad_training_split(tmp_path):
    """`train --protocol oxford` trains on PointNetVLAD's training split: the
    pointcloud_20m_10overlap submaps listed in each run's locations CSV, for every run but
    the last (sorted), without those inside the four test squares, pooled across runs;
    10 m / 50 m, and no yaw loss (the locations have no heading)."""
    import torch

    from disco_cli.evaluation.protocols import OXFORD_TEST_CENTRES, training_setup
    from disco_cli.io.readers import read_scan

    files = sorted((SAMPLES / "00" / "velodyne").glob("*.bin"))[:8]
    scans = [read_scan(f) for f in files]
    n0, e0 = OXFORD_TEST_CENTRES[0]
    # Eight places around the first test square (150 m half-width): three inside it, five
    # outside it (60 m or more apart, all far from the other three squares).
    offsets = np.array(
        [(140, -100), (-145, -40), (0, 140), (156, -100), (160, -40), (165, 20), (-160, 80),
         (0, 160)], float
    )  # fmt: skip
    root = tmp_path / "benchmark_datasets" / "oxford"
    folders = oxford_run_folders(root)
    # Runs 0, 1 and 5 (a test run: PointNetVLAD trains on those too, outside the squares)
    # hold the places a few metres apart (positives across runs); the last run (44) holds
    # them too but is not in the split.
    expected: dict[Path, tuple[float, float]] = {}
    for j, k in enumerate((0, 1, 5, 44)):
        rng = np.random.default_rng(200 + k)
        subs = [pointnetvlad_submap(p, rng) for p in scans]
        north = n0 + offsets[:, 0] + j
        east = e0 + offsets[:, 1] + 2 * j
        stamps = 1400000000000000 + 10**9 * k + 10**6 * np.arange(len(subs))
        write_oxford_split(folders[k], "20m_10overlap", stamps, subs, north, east)
        # A submap without a row in the CSV is not in the split.
        subs[0].astype("<f8").tofile(folders[k] / "pointcloud_20m_10overlap" / "1399999999.bin")
        if k == 44:
            continue
        for t, n, e in zip(stamps, north, east):
            # Square 0 only: the test's places lie hundreds of metres from the other three.
            if not (abs(n - n0) < 150 and abs(e - e0) < 150):
                path = folders[k] / "pointcloud_20m_10overlap" / f"{t}.bin"
                expected[path] = (n, e)
    assert len(expected) == 3 * 5
    # Run 1's test-split submaps are not training data either.
    rng = np.random.default_rng(9)
    subs = [pointnetvlad_submap(p, rng) for p in scans[:3]]
    write_oxford_split(folders[1], "20m", 1500000000000000 + np.arange(3), subs, n0 + 400, e0)

    setup = training_setup("oxford", tmp_path / "benchmark_datasets")
    assert (setup.d_pos, setup.d_neg, setup.lambda_yaw) == (10.0, 50.0, 0.0)
    assert [s.name for s in setup.sessions] == [OXFORD_RUNS[k] for k in (0, 1, 5)]
    got = {p: tuple(T[:2, 3]) for s in setup.sessions for p, T in zip(s.scans, s.poses)}
    assert set(got) == set(expected)
    for path, (n, e) in expected.items():
        assert got[path] == pytest.approx((n, e), abs=1e-6)
    assert len({s.world for s in setup.sessions}) == 1  # pooled: positives across runs

    out = tmp_path / "ox.pt"
    code, text = run(
        "train", tmp_path / "benchmark_datasets", "--protocol", "oxford", "-o", out,
        "--epochs", "1", "--steps", "1", "--batch", "2", "--negatives", "2", "--width", "2",
    )  # fmt: skip
    assert code == 0, text
    assert f"training data: {len(expected)} scans from 3 sequences" in text
    assert text.count("skipped") == 1 and "41 of 44 training runs" in text
    ckpt = torch.load(out, weights_only=True)
    opts = ckpt["train_state"]["options"]
    assert (opts["d_pos"], opts["d_neg"], opts["lambda_yaw"]) == (10.0, 50.0, 0.0)
    command = ckpt["command"]
    assert "--protocol oxford" in command and "--oxford-scale 20.0" in command
    assert "--d-pos 10.0 --d-neg 50.0" in command and "--lambda-yaw 0.0" in command

    # The yaw loss cannot be asked for, and a tree without its 45 runs is named.
    code, text = run("train", root, "--protocol", "oxford", "-o", tmp_path / "b.pt",
                     "--lambda-yaw", "0.1")  # fmt: skip
    assert code == 1 and "--lambda-yaw" in text and "Traceback" not in text
    code, text = run("train", folders[0], "--protocol", "oxford", "-o", tmp_path / "c.pt")
    assert code == 1 and "found 0" in text and "Traceback" not in text
