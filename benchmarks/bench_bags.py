"""Benchmark: reading scans out of ROS bags (ROS 1, ROS 2 sqlite3, MCAP) by name.

Writes, into a temporary folder, one bag of each kind holding N PointCloud2 messages
(the sample's scans of session 00, over and over; float32 x, y, z, intensity) and the
same scans as KITTI .bin files. Then times, per kind, in a fresh state: listing the
bag's scans (one pass over the topic), reading every scan by name in bag order (the
way build-db and loops read), the first and the second half of that separately (equal
per-message times: no cost grows with the position in the bag), and 100 names in a
random order (each a seek). `--build-db` also runs `disco build-db` on each bag and on
the .bin folder and prints the scans/s it reports.

Run: `.venv/bin/python benchmarks/bench_bags.py` (`--messages 400 --build-db`).
Needs the rosbags package (`pip install 'disco-cli[ros]'`).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import print_header

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "data" / "samples" / "00" / "velodyne"
T0 = 1_700_000_000_000_000_000
PC2 = "sensor_msgs/msg/PointCloud2"


def cloud(ts, points: np.ndarray, ns: int, ros1: bool):
    T = ts.types
    t = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    extra = {"seq": 0} if ros1 else {}
    header = T["std_msgs/msg/Header"](stamp=t, frame_id="lidar", **extra)
    fields = [
        T["sensor_msgs/msg/PointField"](name=c, offset=4 * k, datatype=7, count=1)
        for k, c in enumerate(("x", "y", "z", "intensity"))
    ]
    data = np.ascontiguousarray(points, dtype="<f4").view(np.uint8).reshape(-1)
    return T[PC2](
        header=header, height=1, width=len(points), fields=fields, is_bigendian=False,
        point_step=16, row_step=16 * len(points), data=data, is_dense=True,
    )  # fmt: skip


def write_bags(root: Path, scans: list[np.ndarray], n: int) -> dict[str, Path]:
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    out = {}
    for kind in ("ros1", "sqlite3", "mcap"):
        ros1 = kind == "ros1"
        ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
        ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
        path = root / {"ros1": "run.bag", "sqlite3": "run_db3", "mcap": "run_mcap"}[kind]
        if ros1:
            writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(path, version=9, storage_plugin=plugin)
        with writer as w:
            conn = w.add_connection("/points", PC2, typestore=ts)
            for i in range(n):
                ns = T0 + i * 100_000_000
                w.write(conn, ns + 5_000_000, ser(cloud(ts, scans[i % len(scans)], ns, ros1), PC2))
        if kind == "mcap":  # a plain .mcap file
            (mcap,) = path.glob("*.mcap")
            shutil.move(str(mcap), root / "run.mcap")
            shutil.rmtree(path)
            path = root / "run.mcap"
        out[kind] = path
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=400)
    parser.add_argument("--build-db", action="store_true", help="also time disco build-db")
    args = parser.parse_args()

    from disco_cli.io.readers import bags, list_scans, read_scan

    print_header("bench_bags")
    scans = [np.fromfile(p, "<f4").reshape(-1, 4) for p in sorted(SAMPLE.glob("*.bin"))]
    n = args.messages
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "bin" / "velodyne").mkdir(parents=True)
        files = sorted(SAMPLE.glob("*.bin"))
        for i in range(n):
            shutil.copy(files[i % len(files)], root / "bin" / "velodyne" / f"{i:06d}.bin")
        paths = write_bags(root, scans, n)
        points = sum(len(scans[i % len(scans)]) for i in range(n)) / n
        print(f"{n} messages of {points:.0f} points (16 bytes each) per bag")

        t = time.perf_counter()
        for p in sorted((root / "bin" / "velodyne").iterdir()):
            read_scan(p).copy()
        print(f"  .bin files: read all {1e3 * (time.perf_counter() - t) / n:.2f} ms/scan")
        rng = np.random.default_rng(0)
        for kind, path in paths.items():
            bags._close_all()
            t = time.perf_counter()
            names = list_scans(path)
            t_list = time.perf_counter() - t
            halves = []
            for part in (names[: n // 2], names[n // 2 :]):
                t = time.perf_counter()
                for name in part:
                    read_scan(name)
                halves.append(1e3 * (time.perf_counter() - t) / len(part))
            bags._close_all()
            list_scans(path)
            pick = rng.choice(n, size=min(100, n), replace=False)
            t = time.perf_counter()
            for i in pick:
                read_scan(names[i])
            t_rand = 1e3 * (time.perf_counter() - t) / len(pick)
            size = sum(f.stat().st_size for f in ([path] if path.is_file() else path.iterdir()))
            print(
                f"  {kind:8s} ({size / 2**20:.0f} MiB): list {t_list:.2f} s; in order "
                f"{np.mean(halves):.2f} ms/scan (1st half {halves[0]:.2f}, 2nd {halves[1]:.2f}); "
                f"random order {t_rand:.2f} ms/scan"
            )
        if args.build_db:
            disco = str(Path(sys.executable).parent / "disco")
            for name, src in [("bin", root / "bin"), *paths.items()]:
                res = subprocess.run(
                    [disco, "build-db", str(src), "-o", str(root / f"{name}.db")],
                    capture_output=True,
                    text=True,
                )
                print(f"  build-db {name}: {res.stderr.strip().splitlines()[-1]}")


if __name__ == "__main__":
    main()
