"""ROS bags as inputs: PointCloud2 decoding, ROS 1 / ROS 2 (sqlite3) / MCAP bags, poses.

Bags are written here with rosbags' own writers from the sample's simulated scans, in
the point layouts of real drivers (packed here with NumPy, independently of disco's
decoder). The truth: the same scans as KITTI `.bin` files give the same matches, yaws
and relative poses; a pose topic gives the poses it was written from (an analytic
trajectory, and the sample's own poses).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

pytest.importorskip("rosbags", reason="the rosbags package (disco-cli[ros]) is absent")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from disco_cli.cli import app  # noqa: E402
from disco_cli.errors import ScanReadError  # noqa: E402
from disco_cli.io.readers import bags, list_scans, read_scan  # noqa: E402
from disco_cli.io.readers.pointcloud2 import PointField, decode_pointcloud2  # noqa: E402

SAMPLES = Path(__file__).resolve().parent.parent / "data" / "samples"
MAP_FRAMES = list(range(10))  # session 00
QUERY_FRAMES = [4, 5, 6]  # session 01: the reverse drive past 00's first scans
T0 = 1_700_000_000_000_000_000  # ns; scan i of a session is stamped T0 + i * 0.1 s
LOG_DELAY_NS = 5_000_000  # the recorder logs a message 5 ms after its stamp
CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
PC2 = "sensor_msgs/msg/PointCloud2"
# The bags decode to the .bin scans' very points (test_messages_read_back_...), so any
# model shows the whole path; the network-free one keeps this file fast.
MODEL = ["--model", "spectral"]


def stamp(i: int) -> int:
    return T0 + i * 100_000_000


def scan(session: str, i: int) -> np.ndarray:
    return np.fromfile(SAMPLES / session / "velodyne" / f"{i:06d}.bin", "<f4").reshape(-1, 4)


# -- point layouts of real drivers, packed with NumPy ---------------------------------


@dataclass(frozen=True)
class Layout:
    """Where each channel sits in a point: (name, offset, NumPy type)."""

    fields: list[tuple[str, int, str]]
    point_step: int
    bigendian: bool = False
    height: int = 1
    row_pad: int = 0  # bytes of padding after each row
    holes: bool = False  # NaN points among the real ones (organized clouds)
    scale: float = 1.0  # intensity [0, 1] -> stored value


LAYOUTS = {
    "xyzi": Layout([("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 12, "f4")], 16),
    # velodyne_pointcloud PointXYZIRT (PCL-aligned: 4 bytes after z).
    "velodyne": Layout(
        [
            ("x", 0, "f4"),
            ("y", 4, "f4"),
            ("z", 8, "f4"),
            ("intensity", 16, "f4"),
            ("ring", 20, "u2"),
            ("time", 24, "f4"),
        ],
        32,
        scale=255.0,
    ),
    # ouster-ros PointOS0: x, y, z, padding, intensity, t, reflectivity, ring, ambient, range.
    "ouster": Layout(
        [
            ("x", 0, "f4"),
            ("y", 4, "f4"),
            ("z", 8, "f4"),
            ("intensity", 16, "f4"),
            ("t", 20, "u4"),
            ("reflectivity", 24, "u2"),
            ("ring", 26, "u2"),
            ("ambient", 28, "u2"),
            ("range", 32, "u4"),
        ],
        48,
        scale=1000.0,
    ),
    # Ouster-like with no float intensity: uint16 reflectivity, uint8 ring, padding.
    "ouster_reflectivity": Layout(
        [
            ("x", 0, "f4"),
            ("y", 4, "f4"),
            ("z", 8, "f4"),
            ("reflectivity", 16, "u2"),
            ("ring", 18, "u1"),
        ],
        24,
        scale=65535.0,
    ),
    # HesaiLidar_ROS_2.0: uint8 intensity, uint16 ring, float64 timestamp.
    "hesai": Layout(
        [
            ("x", 0, "f4"),
            ("y", 4, "f4"),
            ("z", 8, "f4"),
            ("intensity", 12, "u1"),
            ("ring", 14, "u2"),
            ("timestamp", 16, "f8"),
        ],
        24,
        scale=255.0,
    ),
    # livox_ros_driver2 PointXYZRTLT: tag, line uint8 and an unaligned float64 timestamp.
    "livox": Layout(
        [
            ("x", 0, "f4"),
            ("y", 4, "f4"),
            ("z", 8, "f4"),
            ("intensity", 12, "f4"),
            ("tag", 16, "u1"),
            ("line", 17, "u1"),
            ("timestamp", 18, "f8"),
        ],
        26,
        scale=255.0,
    ),
    # Organized 8 x W, float64 x, y, z, uint8 intensity, rows padded, NaN holes.
    "organized": Layout(
        [("x", 0, "f8"), ("y", 8, "f8"), ("z", 16, "f8"), ("intensity", 24, "u1")],
        32,
        height=8,
        row_pad=16,
        holes=True,
        scale=255.0,
    ),
    # Big endian float32 x, y, z and uint16 intensity, 2 bytes of padding.
    "bigendian": Layout(
        [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 12, "u2")],
        16,
        bigendian=True,
        scale=65535.0,
    ),
}


@dataclass
class Packed:
    fields: list[PointField]
    data: bytes
    height: int
    width: int
    point_step: int
    row_step: int
    bigendian: bool
    expected: np.ndarray  # float32 N x 4 that decoding must give


def pack(points: np.ndarray, layout: Layout, seed: int = 0) -> Packed:
    """The points in `layout`'s bytes; padding and the other channels hold noise."""
    rng = np.random.default_rng(seed)
    n = len(points)
    valid = np.ones(n, bool)
    if layout.holes:
        valid = np.ones(n + n // 10, bool)
        valid[rng.choice(len(valid), n // 10, replace=False)] = False
    total = -(-len(valid) // layout.height) * layout.height
    valid = np.r_[valid, np.zeros(total - len(valid), bool)]
    order = ">" if layout.bigendian else "<"
    dtype = np.dtype(
        {
            "names": [f[0] for f in layout.fields],
            "formats": [order + f[2] for f in layout.fields],
            "offsets": [f[1] for f in layout.fields],
            "itemsize": layout.point_step,
        }
    )
    raw = rng.integers(0, 256, total * layout.point_step, dtype=np.uint8)
    cloud = raw.view(dtype)
    for name, _, code in layout.fields:
        if name in "xyz":
            continue
        kind = np.dtype(code)
        cloud[name] = rng.integers(0, 100, total).astype(kind)
    inten_name = next((f for f, _, _ in layout.fields if f in ("intensity", "reflectivity")), None)
    expected = points.copy()
    inten_code = dict((f, c) for f, _, c in layout.fields)[inten_name]
    stored = points[:, 3].astype(np.float64) * layout.scale
    if np.dtype(inten_code).kind != "f":
        stored = np.round(stored)
    stored = stored.astype(inten_code)
    expected[:, 3] = stored.astype(np.float32)
    for k, c in enumerate("xyz"):
        col = np.full(total, np.nan)
        col[valid] = points[:, k]
        cloud[c] = col
    inten = np.zeros(total, inten_code)
    inten[valid] = stored
    cloud[inten_name] = inten
    width = total // layout.height
    rows = raw.reshape(layout.height, width * layout.point_step)
    pad = rng.integers(0, 256, (layout.height, layout.row_pad), dtype=np.uint8)
    data = np.concatenate([rows, pad], axis=1).tobytes()
    fields = [PointField(name, off, CODES[code], 1) for name, off, code in layout.fields]
    return Packed(
        fields,
        data,
        layout.height,
        width,
        layout.point_step,
        width * layout.point_step + layout.row_pad,
        layout.bigendian,
        expected,
    )


def decode(p: Packed, name: str = "test.bag#/points@1") -> np.ndarray:
    return decode_pointcloud2(
        p.fields,
        p.data,
        height=p.height,
        width=p.width,
        point_step=p.point_step,
        row_step=p.row_step,
        is_bigendian=p.bigendian,
        name=name,
    )


# -- the decoder against hand-packed bytes ----------------------------------------------


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_decoder_reads_each_driver_layout(layout: str) -> None:
    points = scan("00", 3)[:5000]
    packed = pack(points, LAYOUTS[layout], seed=7)
    got = decode(packed)
    assert got.dtype == np.float32 and got.shape == (len(points), 4)
    np.testing.assert_array_equal(got, packed.expected)
    # x, y, z are the scan's own values, whatever the layout.
    np.testing.assert_array_equal(got[:, :3], points[:, :3])


def test_decoder_without_intensity_gives_zero() -> None:
    points = scan("00", 1)[:100]
    layout = Layout([("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4")], 12)
    data = np.ascontiguousarray(points[:, :3]).tobytes()
    fields = [PointField(c, o, 7) for c, o in (("x", 0), ("y", 4), ("z", 8))]
    got = decode_pointcloud2(
        fields, data, height=1, width=100, point_step=layout.point_step, row_step=1200,
        is_bigendian=False, name="b.bag#/p@1",
    )  # fmt: skip
    np.testing.assert_array_equal(got[:, :3], points[:, :3])
    assert not got[:, 3].any()


def test_decoder_one_hand_written_point_each_endianness() -> None:
    # One point, bytes written out by hand: x=1.5, y=-2, z=0.25 (float32), intensity 300
    # (uint16), two bytes of padding.
    little = bytes.fromhex("0000c03f 000000c0 0000803e 2c01 abcd")
    big = bytes.fromhex("3fc00000 c0000000 3e800000 012c abcd")
    fields = [PointField("x", 0, 7), PointField("y", 4, 7), PointField("z", 8, 7),
              PointField("intensity", 12, 4)]  # fmt: skip
    for data, be in ((little, False), (big, True)):
        got = decode_pointcloud2(
            fields, data, height=1, width=1, point_step=16, row_step=16, is_bigendian=be,
            name="x.bag#/p@1",
        )  # fmt: skip
        np.testing.assert_array_equal(got, [[1.5, -2.0, 0.25, 300.0]])


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(fields=[PointField("y", 4, 7), PointField("z", 8, 7)]), "no x field"),
        (
            dict(fields=[PointField("x", 0, 3), PointField("y", 4, 7), PointField("z", 8, 7)]),
            "field 'x' is INT16; x, y, z must be FLOAT32 or FLOAT64",
        ),
        (
            dict(fields=[PointField("x", 0, 7), PointField("y", 4, 7), PointField("z", 14, 7)]),
            "outside the 16-byte point",
        ),
        (
            dict(fields=[PointField("x", 0, 9), PointField("y", 4, 7), PointField("z", 8, 7)]),
            "unknown datatype 9",
        ),
        (dict(data=b"\0" * 100), "truncated"),
        (dict(row_step=10), "row_step 10 is less than"),
        (dict(width=0), "no points"),
        (dict(data=np.full(40, np.nan, "<f4").tobytes()), "none of its 10 points"),
    ],
)
def test_decoder_rejects_bad_messages_naming_them(change: dict, message: str) -> None:
    args = dict(
        fields=[PointField("x", 0, 7), PointField("y", 4, 7), PointField("z", 8, 7)],
        data=np.zeros(40, "<f4").tobytes(),
        height=1,
        width=10,
        point_step=16,
        row_step=160,
        is_bigendian=False,
    )
    args.update(change)
    fields, data = args.pop("fields"), args.pop("data")
    with pytest.raises(ScanReadError) as err:
        decode_pointcloud2(fields, data, name="run.bag#/points@42", **args)
    assert message in str(err.value)
    assert str(err.value).startswith("run.bag#/points@42: ")


# -- bags written with rosbags' writers ------------------------------------------------


def header(ts, ns: int, ros1: bool):
    T = ts.types
    t = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    if ros1:
        return T["std_msgs/msg/Header"](seq=0, stamp=t, frame_id="lidar")
    return T["std_msgs/msg/Header"](stamp=t, frame_id="lidar")


def cloud_msg(ts, points: np.ndarray, layout: str, ns: int, ros1: bool, seed: int):
    T = ts.types
    p = pack(points, LAYOUTS[layout], seed)
    fields = [
        T["sensor_msgs/msg/PointField"](name=f.name, offset=f.offset, datatype=f.datatype, count=1)
        for f in p.fields
    ]
    return T[PC2](
        header=header(ts, ns, ros1),
        height=p.height,
        width=p.width,
        fields=fields,
        is_bigendian=p.bigendian,
        point_step=p.point_step,
        row_step=p.row_step,
        data=np.frombuffer(p.data, np.uint8),
        is_dense=False,
    )


def pose_parts(ts, T4: np.ndarray):
    T = ts.types
    q = Rotation.from_matrix(T4[:3, :3]).as_quat()  # x, y, z, w
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=T4[0, 3], y=T4[1, 3], z=T4[2, 3]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def odometry_msg(ts, T4: np.ndarray, ns: int, ros1: bool):
    T = ts.types
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header(ts, ns, ros1),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose_parts(ts, T4), covariance=np.zeros(36)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            covariance=np.zeros(36),
        ),
    )


def pose_stamped_msg(ts, T4: np.ndarray, ns: int, ros1: bool):
    return ts.types["geometry_msgs/msg/PoseStamped"](
        header=header(ts, ns, ros1), pose=pose_parts(ts, T4)
    )


# The analytic trajectory of the ROS 1 bag's /odom: straight line, constant yaw rate.
def odom_truth(tau: np.ndarray) -> np.ndarray:
    """x, y, z, yaw at tau seconds after T0."""
    tau = np.asarray(tau, float)
    return np.stack([1.0 + 2.0 * tau, 0.5 * tau, np.full_like(tau, 0.1), 0.3 * tau], -1)


def odom_T(tau: float) -> np.ndarray:
    x, y, z, yaw = odom_truth(np.array([tau]))[0]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    T[:3, 3] = x, y, z
    return T


# Odometry every 50 ms from -37 ms to 863 ms: map scan 9 (900 ms) lies past its end.
ODOM_TAUS = [0.013 + 0.05 * k for k in range(-1, 18)]


def kitti_poses(session: str) -> np.ndarray:
    rows = np.loadtxt(SAMPLES / session / "poses.txt").reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows
    return T


def write_bag(path: Path, kind: str, topics: dict) -> Path:
    """A bag of `kind` (ros1, sqlite3, mcap) at `path`; `topics`: name -> (msgtype,
    [(stamp_ns, message)]). An mcap bag is written as a ROS 2 bag and its .mcap file
    taken out of the folder: a plain MCAP file."""
    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    target = path.with_suffix("") if kind == "mcap" else path
    if ros1:
        writer = Writer1(target)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(target, version=9, storage_plugin=plugin)
    with writer as w:
        conns = {t: w.add_connection(t, mt, typestore=ts) for t, (mt, _) in topics.items()}
        items = [(ns, t, m) for t, (_, msgs) in topics.items() for ns, m in msgs]
        for ns, t, msg in sorted(items, key=lambda x: x[0]):
            w.write(conns[t], ns + LOG_DELAY_NS, ser(msg, topics[t][0]))
    if kind == "mcap":
        (mcap,) = target.glob("*.mcap")
        shutil.move(str(mcap), path)
        shutil.rmtree(target)
    return path


def clouds(ts_kind: str, session: str, frames: list[int], layout: str) -> tuple[str, list]:
    ros1 = ts_kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    return PC2, [
        (stamp(i), cloud_msg(ts, scan(session, i), layout, stamp(i), ros1, seed=i)) for i in frames
    ]


# Per bag kind: (map file name, map layout, query file name, query layout).
KINDS = {
    "ros1": ("map.bag", "xyzi", "query.bag", "ouster"),
    "sqlite3": ("map_db3", "organized", "query_db3", "bigendian"),
    "mcap": ("map.mcap", "ouster", "query.mcap", "organized"),
}


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not (SAMPLES / "00" / "velodyne").is_dir():
        pytest.skip("data/samples is empty")
    root = tmp_path_factory.mktemp("bags")
    # The same scans as KITTI .bin: the map folder (with its poses) and the query files.
    (root / "bin" / "velodyne").mkdir(parents=True)
    for i in MAP_FRAMES:
        shutil.copy(SAMPLES / "00" / "velodyne" / f"{i:06d}.bin", root / "bin" / "velodyne")
    T00 = kitti_poses("00")
    np.savetxt(root / "bin" / "poses.txt", T00[MAP_FRAMES, :3, :].reshape(-1, 12))
    T01 = kitti_poses("01")
    np.savetxt(root / "query_poses.txt", T01[QUERY_FRAMES, :3, :].reshape(-1, 12))

    for kind, (map_name, map_layout, query_name, query_layout) in KINDS.items():
        ros1 = kind == "ros1"
        ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
        topics = {"/points": clouds(kind, "00", MAP_FRAMES, map_layout)}
        qtopics = {"/points": clouds(kind, "01", QUERY_FRAMES, query_layout)}
        if ros1:
            # A second cloud topic (so --topic is needed) and odometry to pose by time.
            topics["/os_cloud_node/points"] = clouds(kind, "00", MAP_FRAMES, "ouster")
            odom = []
            for tau in ODOM_TAUS:
                ns = T0 + round(tau * 1e9)
                odom.append((ns, odometry_msg(ts, odom_T(tau), ns, True)))
            topics["/odom"] = ("nav_msgs/msg/Odometry", odom)
        else:
            # The scans' own poses at their stamps, as PoseStamped.
            topics["/pose"] = (
                "geometry_msgs/msg/PoseStamped",
                [(stamp(i), pose_stamped_msg(ts, T00[i], stamp(i), False)) for i in MAP_FRAMES],
            )
            qtopics["/pose"] = (
                "geometry_msgs/msg/PoseStamped",
                [(stamp(i), pose_stamped_msg(ts, T01[i], stamp(i), False)) for i in QUERY_FRAMES],
            )
        write_bag(root / map_name, kind, topics)
        write_bag(root / query_name, kind, qtopics)
    return root


def run(*args: object) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def jsonl(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def bin_db(data: Path) -> Path:
    """The map of the .bin scans, with their poses (poses.txt beside them)."""
    db = data / "bin.db"
    code, _, err = run("build-db", data / "bin", "-o", db, *MODEL)
    assert code == 0, err
    return db


@pytest.fixture(scope="module")
def bin_results(data: Path, bin_db: Path) -> list[dict]:
    db = bin_db
    queries = [SAMPLES / "01" / "velodyne" / f"{i:06d}.bin" for i in QUERY_FRAMES]
    code, out, err = run("query", *queries, "--db", db, "-k", "1", "--pose", "--format", "jsonl")
    assert code == 0, err
    rows = jsonl(out)
    assert len(rows) == len(QUERY_FRAMES)
    return rows


def map_args(kind: str) -> list[str]:
    return ["--topic", "/points"] if kind == "ros1" else []


def test_list_scans_names_each_message(data: Path) -> None:
    for kind, (map_name, *_rest) in KINDS.items():
        names = [str(p) for p in list_scans(data / map_name, topic="/points")]
        assert names == [f"{data / map_name}#/points@{stamp(i)}" for i in MAP_FRAMES], kind
        # A ROS 2 bag has one cloud topic: no --topic needed.
        if kind != "ros1":
            assert [str(p) for p in list_scans(data / map_name)] == names


@pytest.mark.parametrize("kind", list(KINDS))
def test_messages_read_back_by_name_in_any_order(data: Path, kind: str) -> None:
    map_name, map_layout = KINDS[kind][:2]
    bags._close_all()  # a fresh process: no index of the bag yet
    rng = np.random.default_rng(1)
    for i in rng.permutation(MAP_FRAMES):
        got = read_scan(f"{data / map_name}#/points@{stamp(i)}")
        want = pack(scan("00", i), LAYOUTS[map_layout], seed=i).expected
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ScanReadError, match="no message with this header stamp"):
        read_scan(f"{data / map_name}#/points@{stamp(3) + 1}")
    # Reading threads (build-db --threads) share the bag and its cursor.
    from concurrent.futures import ThreadPoolExecutor

    bags._close_all()
    names = list_scans(data / map_name, topic="/points")
    with ThreadPoolExecutor(4) as pool:
        for i, got in zip(MAP_FRAMES, pool.map(read_scan, names)):
            want = pack(scan("00", i), LAYOUTS[map_layout], seed=i).expected
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("kind", list(KINDS))
def test_build_and_query_match_the_bin_scans(
    data: Path, kind: str, bin_results: list[dict]
) -> None:
    map_name, _, query_name, _ = KINDS[kind]
    db = data / f"{kind}.db"
    code, _, err = run("build-db", data / map_name, *map_args(kind), "-o", db, *MODEL)
    assert code == 0, err
    code, out, err = run(
        "query", data / query_name, "--db", db, "-k", "1", "--pose", "--format", "jsonl"
    )
    assert code == 0, err
    rows = jsonl(out)
    assert [r["query"] for r in rows] == [f"{data / query_name}#/points@{stamp(i)}"
                                          for i in QUERY_FRAMES]  # fmt: skip
    for got, want in zip(rows, bin_results):
        assert got["match_id"] == want["match_id"]
        frame = MAP_FRAMES[want["match_id"] - 1]
        assert got["match"] == f"{data / map_name}#/points@{stamp(frame)}"
        assert got["yaw_deg"] == pytest.approx(want["yaw_deg"], abs=1e-3)
        assert got["distance"] == pytest.approx(want["distance"], abs=1e-5)
        for k in ("dx", "dy", "dz"):
            assert got[k] == pytest.approx(want[k], abs=1e-3)
    # One scan of a bag, named: the same row again.
    code, out, err = run(
        "query", rows[1]["query"], "--db", db, "-k", "1", "--pose", "--format", "jsonl"
    )
    assert code == 0, err
    (again,) = jsonl(out)
    assert again["match"] == rows[1]["match"]
    assert again["yaw_deg"] == pytest.approx(rows[1]["yaw_deg"], abs=1e-6)
    assert again["dx"] == pytest.approx(rows[1]["dx"], abs=1e-6)


def test_topic_errors_list_the_topics(data: Path) -> None:
    bag = data / "map.bag"
    code, out, err = run("build-db", bag, "-o", data / "x.db")
    assert code != 0 and not (data / "x.db").exists()
    line = err.strip()
    assert "\n" not in line
    assert "2 sensor_msgs/PointCloud2 topics (/os_cloud_node/points, /points)" in line
    assert "--topic" in line
    code, _, err = run("build-db", bag, "--topic", "/nope", "-o", data / "x.db")
    assert code != 0 and "no topic '/nope'" in err
    code, _, err = run("build-db", bag, "--topic", "/odom", "-o", data / "x.db")
    assert code != 0 and "is nav_msgs/Odometry, not sensor_msgs/PointCloud2" in err
    code, _, err = run(
        "build-db", bag, "--topic", "/points", "--pose-topic", "/points", "-o", data / "x.db"
    )
    assert code != 0 and "is sensor_msgs/PointCloud2, not nav_msgs/Odometry" in err
    assert not (data / "x.db").exists()
    (db3,) = (data / "map_db3").glob("*.db3")
    code, _, err = run("build-db", db3, "-o", data / "x.db")
    assert code != 0 and "give the bag's folder (metadata.yaml)" in err


def test_odometry_topic_poses_by_time(data: Path) -> None:
    from disco_cli.maps.database import Database

    db = data / "odom.db"
    bag = data / "map.bag"
    code, _, err = run(
        "build-db", bag, "--topic", "/points", "--pose-topic", "/odom", "-o", db, *MODEL
    )
    assert code == 0, err
    # Scan 9 (900 ms) lies past the last odometry message (863 ms): one warning, no pose.
    err = " ".join(err.split())  # rich wraps long lines
    assert "/odom: 1 of 10 scans have no pose near their stamp" in err
    assert "1 without a pose" in err
    with Database.open(db) as d:
        poses, times = d.poses()
    taus = np.array([stamp(i) - T0 for i in MAP_FRAMES]) * 1e-9
    np.testing.assert_allclose(times, (T0 * 1e-9) + taus, rtol=0, atol=1e-6)
    truth = odom_truth(taus)
    np.testing.assert_allclose(poses[:9], truth[:9], rtol=0, atol=1e-6)
    assert np.isnan(poses[9]).all()


def test_tum_file_poses_bag_scans_by_time(data: Path) -> None:
    from disco_cli.maps.database import Database

    # The odometry's trajectory as a TUM file: t tx ty tz qx qy qz qw.
    lines = []
    for tau in ODOM_TAUS:
        T = odom_T(tau)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        ns = T0 + round(tau * 1e9)
        t = f"{ns // 10**9}.{ns % 10**9:09d}"  # seconds, to the nanosecond
        lines.append(" ".join([t, *(repr(float(v)) for v in (*T[:3, 3], *q))]))
    tum = data / "trajectory.tum"
    tum.write_text("\n".join(lines) + "\n")
    db = data / "tum.db"
    code, _, err = run(
        "build-db", data / "map.bag", "--topic", "/points", "--poses", tum,
        "--poses-format", "tum", "-o", db, *MODEL,
    )  # fmt: skip
    assert code == 0, err
    with Database.open(db) as d:
        poses, _ = d.poses()
    taus = np.array([stamp(i) - T0 for i in MAP_FRAMES]) * 1e-9
    np.testing.assert_allclose(poses[:9], odom_truth(taus)[:9], rtol=0, atol=1e-5)
    assert np.isnan(poses[9]).all()


def test_pose_stamped_topic_and_eval(data: Path, bin_db: Path) -> None:
    from disco_cli.io.poses import xy_yaw
    from disco_cli.maps.database import Database

    db = data / "posed_db3.db"
    code, _, err = run("build-db", data / "map_db3", "--pose-topic", "/pose", "-o", db, *MODEL)
    assert code == 0, err
    T = kitti_poses("00")[MAP_FRAMES]
    x, y, yaw = xy_yaw(T)
    with Database.open(db) as d:
        poses, _ = d.poses()
    np.testing.assert_allclose(poses, np.stack([x, y, T[:, 2, 3], yaw], 1), atol=1e-6)

    # eval on the query bag with its pose topic == eval on the .bin files with poses.
    code, out_bag, err = run(
        "eval", data / "query_db3", "--db", db, "--pose-topic", "/pose", "--format", "jsonl"
    )
    assert code == 0, err
    queries = [SAMPLES / "01" / "velodyne" / f"{i:06d}.bin" for i in QUERY_FRAMES]
    code, out_bin, err = run(
        "eval", *queries, "--db", bin_db, "--poses", data / "query_poses.txt",
        "--format", "jsonl",
    )  # fmt: skip
    assert code == 0, err
    got, want = json.loads(out_bag), json.loads(out_bin)
    assert got["recall@1"] == want["recall@1"]
    assert got["recall@N"] == want["recall@N"]


def test_without_rosbags_one_line_with_the_install_hint(
    data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    bags._close_all()
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails
    code, _, err = run("build-db", data / "map_db3", "-o", data / "none.db")
    assert code != 0 and not (data / "none.db").exists()
    assert err.strip().endswith("pip install 'disco-cli[ros]'")
    assert "\n" not in err.strip()


def test_loops_on_a_bag_times_scans_by_their_stamps(data: Path) -> None:
    # The .bin copy of the map with times.txt = the bag's stamps (0.1 s apart).
    seq = data / "bin_timed"
    if not seq.exists():
        shutil.copytree(data / "bin", seq)
        np.savetxt(seq / "times.txt", [0.1 * i for i in MAP_FRAMES])
    args = ["--exclude-seconds", "0.35", "--format", "jsonl", *MODEL]
    code, out_bin, err = run("loops", seq, *args)
    assert code == 0, err
    code, out_bag, err = run("loops", data / "map.bag", "--topic", "/points", *args)
    assert code == 0, err
    want, got = jsonl(out_bin), jsonl(out_bag)
    assert len(got) == len(want) == len(MAP_FRAMES) - 4  # scans 4.. have a scan 0.35 s back
    for g, w in zip(got, want):
        assert (g["query_index"], g["match_index"]) == (w["query_index"], w["match_index"])
        assert g["yaw_deg"] == pytest.approx(w["yaw_deg"], abs=1e-4)


def test_bev_of_a_bag_is_its_first_scan(data: Path) -> None:
    from disco_cli.model.bev import BEVConfig, polar_bev

    out = data / "bev.npy"
    code, _, err = run("bev", data / "map.bag", "--topic", "/os_cloud_node/points", "-o", out)
    assert code == 0, err
    assert f"map.bag#/os_cloud_node/points@{stamp(0)}" in err
    np.testing.assert_array_equal(np.load(out), polar_bev(scan("00", 0), BEVConfig()))


def test_a_bad_message_is_named_and_skippable(tmp_path: Path) -> None:
    ts = get_typestore(Stores.LATEST)
    good = [(stamp(i), cloud_msg(ts, scan("00", i), "xyzi", stamp(i), False, i)) for i in (0, 1)]
    bad = cloud_msg(ts, scan("00", 2), "xyzi", stamp(2), False, 2)
    bad.width += 1  # the cloud claims one point more than the data holds
    bad.row_step += 16
    bag = write_bag(tmp_path / "bad.mcap", "mcap", {"/points": (PC2, [*good, (stamp(2), bad)])})
    db = tmp_path / "bad.db"
    code, _, err = run("build-db", bag, "-o", db, *MODEL)
    assert code != 0
    assert f"bad.mcap#/points@{stamp(2)}: data holds" in err and "truncated" in err
    code, _, err = run("build-db", bag, "-o", tmp_path / "skip.db", "--skip-bad", *MODEL)
    assert code == 0, err
    err = " ".join(err.split())  # rich wraps long lines
    assert "wrote 2 scans" in err and "1 unreadable scan skipped" in err


@pytest.mark.parametrize(
    ("name", "topic", "kind"),
    [("map.bag", "/odom", "nav_msgs/Odometry"), ("map_db3", "/pose", "geometry_msgs/PoseStamped")],
)
def test_a_pose_topic_left_unused_is_said_in_one_line(
    data: Path, name: str, topic: str, kind: str
) -> None:
    """The bag could have posed its scans: build-db says how many went without, and how."""
    db = data / f"unposed-{name}.db"
    args = ["--topic", "/points"] if name == "map.bag" else []
    code, _, err = run("build-db", data / name, *args, "-o", db, *MODEL)
    assert code == 0, err
    lines = [" ".join(ln.split()) for ln in err.split("warning:")[1:]]
    assert len(lines) == 1, err
    n = len(MAP_FRAMES)
    assert f"{n} of {n} scans have no pose" in lines[0]
    assert f"the bag has {topic} ({kind}): pass --pose-topic {topic}" in lines[0]


def test_eval_of_a_bag_without_poses_names_its_pose_topic(data: Path, bin_db: Path) -> None:
    code, _, err = run("eval", data / "query_db3", "--db", bin_db)
    err = " ".join(err.split())
    assert code == 1 and "Traceback" not in err
    assert "no query poses" in err and "pass --pose-topic /pose" in err
