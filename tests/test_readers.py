"""Scan readers: every format round-trips tiny files written here with struct and
NumPy (independently of the readers), bad files raise ScanReadError naming the
file, folders expand in natural order, and the real scans agree across formats."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.io.readers import FORMATS, guess_format, list_scans, natural_key, read_scan

# Five points with distinct, exactly representable coordinates and intensities.
XYZI = np.array(
    [
        [1.5, -2.25, 0.5, 0.125],
        [10.0, 20.0, -1.75, 0.5],
        [-3.0, 4.0, 2.0, 1.0],
        [0.0, 0.0, 0.0, 0.0],
        [-60.5, 33.25, -0.25, 0.75],
    ],
    dtype=np.float32,
)


def _scan_tail(n: int = 1200, seed: int = 0) -> np.ndarray:
    """`n` points such as a LiDAR scan holds (the ground 3-40 m around the sensor, walls),
    in quarter metres: exact in float32 and on NCLT's 5 mm grid. A headerless .bin must
    hold a whole scan to be read (plausible.MIN_POINTS), so the few points a test checks
    are followed by these."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3.0, 40.0, n), rng.uniform(-np.pi, np.pi, n)
    z = np.where(rng.random(n) < 0.7, -1.75, rng.uniform(-1.5, 6.0, n))
    xyzi = np.c_[r * np.cos(a), r * np.sin(a), z, rng.uniform(0.0, 1.0, n)]
    return (np.round(xyzi * 4) / 4).astype(np.float32)


def _assert_points(points: np.ndarray, xyz: np.ndarray, intensity: np.ndarray | None) -> None:
    assert points.dtype == np.float32
    assert points.shape == (len(xyz), 4)
    np.testing.assert_array_equal(points[:, :3], xyz.astype(np.float32))
    expected_i = np.zeros(len(xyz), np.float32) if intensity is None else intensity
    np.testing.assert_array_equal(points[:, 3], expected_i.astype(np.float32))


# -- KITTI ---------------------------------------------------------------------


def test_kitti_round_trip_and_no_copy(tmp_path: Path) -> None:
    path = tmp_path / "000007.bin"
    rows = np.vstack([XYZI, _scan_tail()])
    path.write_bytes(b"".join(struct.pack("<4f", *row) for row in rows.tolist()))
    points = read_scan(path)
    _assert_points(points, rows[:, :3], rows[:, 3])
    # Returned as np.fromfile(...).reshape(-1, 4) gives it: a view of the file's
    # buffer, C-contiguous, never a converted copy.
    assert points.base is not None and points.base.shape == (rows.size,)
    assert points.flags.c_contiguous


def test_explicit_format_overrides_the_extension(tmp_path: Path) -> None:
    path = tmp_path / "scan.dat"
    rows = np.vstack([XYZI, _scan_tail()])
    rows.tofile(path)
    _assert_points(read_scan(path, format="kitti"), rows[:, :3], rows[:, 3])
    with pytest.raises(ScanReadError, match="scan.dat"):
        read_scan(path)  # unknown extension, no format


# -- NCLT ----------------------------------------------------------------------


def test_nclt_round_trip_with_scale_and_offset(tmp_path: Path) -> None:
    folder = tmp_path / "2012-01-08" / "velodyne_sync"
    folder.mkdir(parents=True)
    # raw counts -> metres: raw * 0.005 - 100, by hand.
    raw = [(20000, 20000, 20000, 7, 3), (20200, 19800, 20001, 255, 31), (0, 65535, 21000, 0, 0)]
    metres = np.array(
        [[0.0, 0.0, 0.0], [1.0, -1.0, 0.005], [-100.0, 227.675, 5.0]], dtype=np.float64
    )
    # NCLT's z-down frame, returned turned 180 degrees about x: (x, -y, -z).
    metres *= [1.0, -1.0, -1.0]
    # A whole scan follows (a headerless .bin must hold one to be read): the tail's
    # points in NCLT's counts, z down.
    tail = _scan_tail(1200)[:, :3].astype(np.float64) * [1.0, -1.0, -1.0]
    raw += [(*np.round((p + 100.0) / 0.005).astype(int), 1, 2) for p in tail]
    path = folder / "1326030975726043.bin"
    path.write_bytes(b"".join(struct.pack("<HHHBB", *r) for r in raw))
    assert guess_format(path) == "nclt"
    points = read_scan(path)
    assert points.dtype == np.float32 and points.shape == (3 + 1200, 4)
    np.testing.assert_allclose(points[:3, :3], metres, atol=1e-5)
    np.testing.assert_allclose(points[3:, :3], tail * [1.0, -1.0, -1.0], atol=1e-5)
    np.testing.assert_array_equal(points[:4, 3], [7, 255, 0, 1])
    # Outside velodyne_sync the same bytes are read as KITTI only when they fit
    # 16-byte records, so the folder decides, and `format=` decides over both.
    other = tmp_path / "scan.bin"
    other.write_bytes(path.read_bytes() + b"\0" * 8)
    assert guess_format(other) == "kitti"
    np.testing.assert_allclose(read_scan(other, format="nclt")[:3, :3], metres, atol=1e-5)


def test_nclt_z_down_ground_reads_back_below_the_sensor(tmp_path: Path) -> None:
    """A ground plane 2 m below the Velodyne is z = +2 in NCLT's z-down frame; the reader
    returns it at z = -2 (within NCLT's 5 mm grid), and a wall 10 m ahead and 3 m to the
    right (NCLT: x forward, y right) comes back at y = -3 (z up: y left)."""
    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(-30, 30, (1500, 2)), np.full(1500, 2.0)]
    wall = np.c_[np.full(50, 10.0), np.full(50, 3.0), rng.uniform(-5.0, 1.0, 50)]
    ned = np.vstack([ground, wall])  # NCLT's z-down Velodyne frame
    raw = np.round((ned + 100.0) / 0.005).astype("<u2")
    rec = np.zeros(len(raw), dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"),
                                    ("l", "u1")])  # fmt: skip
    rec["x"], rec["y"], rec["z"] = raw.T
    folder = tmp_path / "velodyne_sync"
    folder.mkdir()
    rec.tofile(folder / "1326030975726043.bin")
    pts = read_scan(folder / "1326030975726043.bin")
    np.testing.assert_allclose(pts[:1500, 2], -2.0, atol=0.003)
    np.testing.assert_allclose(pts[1500:, :2], np.tile([10.0, -3.0], (50, 1)), atol=0.003)
    np.testing.assert_allclose(pts[:, 0], ned[:, 0], atol=0.003)  # x stays forward


# -- NumPy ---------------------------------------------------------------------


def test_npy_n_by_4_and_n_by_3(tmp_path: Path) -> None:
    np.save(tmp_path / "a.npy", XYZI.astype(np.float64))
    _assert_points(read_scan(tmp_path / "a.npy"), XYZI[:, :3], XYZI[:, 3])
    np.save(tmp_path / "b.npy", XYZI[:, :3])
    _assert_points(read_scan(tmp_path / "b.npy"), XYZI[:, :3], None)


def test_npy_structured_array(tmp_path: Path) -> None:
    fields = [("intensity", "<f4"), ("z", "<f8"), ("x", "<f4"), ("y", "<f4")]
    rec = np.zeros(len(XYZI), dtype=fields)
    for i, name in enumerate("xyz"):
        rec[name] = XYZI[:, i]
    rec["intensity"] = XYZI[:, 3]
    np.save(tmp_path / "s.npy", rec)
    _assert_points(read_scan(tmp_path / "s.npy"), XYZI[:, :3], XYZI[:, 3])


@pytest.mark.parametrize(
    "array, reason",
    [
        (np.zeros((5, 2), np.float32), "shape"),
        (np.zeros((2, 5, 4), np.float32), "shape"),
        (np.array([["a", "b", "c"]]), "dtype"),
        (np.zeros((0, 4), np.float32), "no points"),
        (np.full((3, 3), np.nan), "finite"),
    ],
)
def test_npy_bad_arrays(tmp_path: Path, array: np.ndarray, reason: str) -> None:
    path = tmp_path / "bad.npy"
    np.save(path, array)
    with pytest.raises(ScanReadError, match=reason) as info:
        read_scan(path)
    assert str(path) in str(info.value)


def test_npy_object_array_is_refused_without_unpickling(tmp_path: Path) -> None:
    path = tmp_path / "obj.npy"
    np.save(path, np.array([object()] * 3, dtype=object), allow_pickle=True)
    with pytest.raises(ScanReadError, match="obj.npy"):
        read_scan(path)


# -- PCD -----------------------------------------------------------------------


def _pcd_header(fields, sizes, types, counts, n, data) -> bytes:
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(map(str, sizes)),
        "TYPE " + " ".join(types),
        "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n}",
        f"DATA {data}",
    ]
    return ("\n".join(lines) + "\n").encode()


def test_pcd_ascii(tmp_path: Path) -> None:
    # Fields out of order, an rgb field to skip and intensity as an integer.
    head = _pcd_header(
        ["z", "rgb", "y", "x", "intensity"],
        [4, 4, 4, 4, 2],
        "F F F F U".split(),
        [1] * 5,
        len(XYZI),
        "ascii",
    )
    body = "".join(f"{z} 0.0 {y} {x} {int(i * 8)}\n" for x, y, z, i in XYZI.tolist())
    (tmp_path / "a.pcd").write_bytes(head + body.encode())
    _assert_points(read_scan(tmp_path / "a.pcd"), XYZI[:, :3], XYZI[:, 3] * 8)


def test_pcd_binary_with_count_padding_and_doubles(tmp_path: Path) -> None:
    # x as double, a 3-wide normal field (COUNT 3), a 1-byte padding field `_`,
    # y, z as float, intensity as float; records packed, little-endian.
    head = _pcd_header(
        ["x", "normal", "_", "y", "z", "intensity"],
        [8, 4, 1, 4, 4, 4],
        "F F U F F F".split(),
        [1, 3, 1, 1, 1, 1],
        len(XYZI),
        "binary",
    )
    body = b"".join(
        struct.pack("<d3fB3f", x, 9.0, 9.0, 9.0, 0xAB, y, z, i) for x, y, z, i in XYZI.tolist()
    )
    (tmp_path / "b.pcd").write_bytes(head + body)
    _assert_points(read_scan(tmp_path / "b.pcd"), XYZI[:, :3], XYZI[:, 3])


def test_pcd_binary_without_intensity_drops_nan_points(tmp_path: Path) -> None:
    # An organized cloud: missing returns are NaN and carry no geometry.
    rows = XYZI[:, :3].tolist() + [[float("nan")] * 3]
    head = _pcd_header(["x", "y", "z"], [4, 4, 4], "F F F".split(), [1, 1, 1], len(rows), "binary")
    body = b"".join(struct.pack("<3f", *r) for r in rows)
    (tmp_path / "n.pcd").write_bytes(head + body)
    _assert_points(read_scan(tmp_path / "n.pcd"), XYZI[:, :3], None)


def test_pcd_integer_coordinates(tmp_path: Path) -> None:
    head = _pcd_header(["x", "y", "z"], [2, 4, 1], "I I U".split(), [1, 1, 1], 2, "binary")
    body = struct.pack("<hiB", -300, 70000, 5) + struct.pack("<hiB", 12, -1, 255)
    (tmp_path / "i.pcd").write_bytes(head + body)
    expected = np.array([[-300, 70000, 5], [12, -1, 255]])
    _assert_points(read_scan(tmp_path / "i.pcd"), expected, None)


def lzf_compress(raw: bytes) -> bytes:
    """A plain greedy LZF encoder (liblzf's stream format), for the tests: literal
    runs of up to 32 bytes, back references of 3 to 264 bytes up to 8192 back."""
    out, literals, last = bytearray(), bytearray(), {}
    i = 0

    def flush() -> None:
        for k in range(0, len(literals), 32):
            chunk = literals[k : k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        literals.clear()

    while i < len(raw):
        key = raw[i : i + 3]
        ref = last.get(key)
        last[key] = i
        if len(key) == 3 and ref is not None and 0 < i - ref <= 8192:
            length = 3
            while length < 264 and i + length < len(raw) and raw[ref + length] == raw[i + length]:
                length += 1  # may run into bytes the copy itself writes (ref + length >= i)
            flush()
            offset, extra = i - ref - 1, length - 2
            if extra < 7:
                out += bytes([(extra << 5) | (offset >> 8), offset & 0xFF])
            else:
                out += bytes([(7 << 5) | (offset >> 8), extra - 7, offset & 0xFF])
            i += length
        else:
            literals.append(raw[i])
            i += 1
    flush()
    return bytes(out)


def test_pcd_binary_compressed(tmp_path: Path) -> None:
    # Fields one after another after expansion: all x, then all normal (COUNT 2), ...
    n = 300
    rng = np.random.default_rng(3)
    x = np.round(rng.uniform(-50, 50, n), 2).astype(np.float32)
    y = np.zeros(n, np.float32)  # long runs of zeros: overlapping copies
    z = np.repeat(np.float32([0.5, -1.25, 2.0]), n // 3)
    normal = np.tile(np.float32([1.0, 0.0]), (n, 1))
    intensity = (np.arange(n) % 7).astype(np.uint8)
    raw = x.tobytes() + normal.tobytes() + y.tobytes() + z.tobytes() + intensity.tobytes()
    packed = lzf_compress(raw)
    assert len(packed) < len(raw)  # the encoder really used back references
    head = _pcd_header(
        ["x", "normal", "y", "z", "intensity"],
        [4, 4, 4, 4, 1],
        "F F F F U".split(),
        [1, 2, 1, 1, 1],
        n,
        "binary_compressed",
    )
    path = tmp_path / "c.pcd"
    path.write_bytes(head + struct.pack("<II", len(packed), len(raw)) + packed)
    _assert_points(read_scan(path), np.stack([x, y, z], axis=1), intensity)

    bad = {
        "short.pcd": head + struct.pack("<II", len(packed), len(raw)) + packed[:-5],
        "size.pcd": head + struct.pack("<II", len(packed), len(raw) - 4) + packed,
        "nosize.pcd": head + b"\1\2",
        "damaged.pcd": head + struct.pack("<II", 4, len(raw)) + bytes([0xE0, 0xFF, 0x10, 0x00]),
    }
    for name, content in bad.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ScanReadError) as info:
            read_scan(tmp_path / name)
        assert str(tmp_path / name) in str(info.value), name


def test_pcd_bad_files(tmp_path: Path) -> None:
    head = _pcd_header(["x", "y", "z"], [4, 4, 4], "F F F".split(), [1, 1, 1], 3, "binary")
    cases = {
        "truncated.pcd": head + struct.pack("<3f", 1, 2, 3) * 2 + b"\0\0",
        "compressed.pcd": head.replace(b"DATA binary", b"DATA binary_compressed") + b"\0" * 40,
        "noxyz.pcd": _pcd_header(["a", "b"], [4, 4], "F F".split(), [1, 1], 1, "ascii") + b"1 2\n",
        "badtype.pcd": _pcd_header(
            ["x", "y", "z"], [3, 4, 4], "F F F".split(), [1, 1, 1], 1, "ascii"
        )
        + b"1 2 3\n",
        "zero.pcd": _pcd_header(["x", "y", "z"], [4, 4, 4], "F F F".split(), [1, 1, 1], 0, "ascii"),
        "shortascii.pcd": _pcd_header(
            ["x", "y", "z"], [4, 4, 4], "F F F".split(), [1, 1, 1], 2, "ascii"
        )
        + b"1 2 3\n4 5\n",
        "words.pcd": _pcd_header(["x", "y", "z"], [4, 4, 4], "F F F".split(), [1, 1, 1], 1, "ascii")
        + b"1 two 3\n",
        "garbage.pcd": bytes(range(256)) * 8,
        "empty.pcd": b"",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ScanReadError) as info:
            read_scan(tmp_path / name)
        assert str(tmp_path / name) in str(info.value), name
    (tmp_path / "lzma.pcd").write_bytes(head.replace(b"DATA binary", b"DATA lzma") + b"\0" * 40)
    with pytest.raises(ScanReadError, match="'lzma' is not supported"):
        read_scan(tmp_path / "lzma.pcd")


# -- PLY -----------------------------------------------------------------------


def _ply_header(fmt: str, elements: list[tuple[str, int, list[str]]]) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment written by test_readers"]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {p}" for p in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode()


def test_ply_ascii_with_other_elements(tmp_path: Path) -> None:
    # A camera element before the vertices and faces after: both skipped.
    head = _ply_header(
        "ascii",
        [
            ("camera", 1, ["float px", "float py"]),
            (
                "vertex",
                len(XYZI),
                ["uchar red", "float x", "float y", "float z", "float reflectance"],
            ),
            ("face", 1, ["list uchar int vertex_indices"]),
        ],
    )
    body = "0.5 0.25\n" + "".join(f"200 {x} {y} {z} {i}\n" for x, y, z, i in XYZI.tolist())
    body += "3 0 1 2\n"
    (tmp_path / "a.ply").write_bytes(head + body.encode())
    _assert_points(read_scan(tmp_path / "a.ply"), XYZI[:, :3], XYZI[:, 3])


def test_ply_binary_little_endian_with_lists_before_vertices(tmp_path: Path) -> None:
    # A list element before the vertices can only be skipped by reading its counts.
    head = _ply_header(
        "binary_little_endian",
        [
            ("tag", 2, ["list uchar int ids", "short k"]),
            (
                "vertex",
                len(XYZI),
                ["double x", "double y", "float z", "ushort ring", "float intensity"],
            ),
            ("face", 1, ["list uchar int vertex_indices"]),
        ],
    )
    tags = struct.pack("<B3ih", 3, 1, 2, 3, -4) + struct.pack("<Bh", 0, 5)
    verts = b"".join(struct.pack("<ddfHf", x, y, z, 17, i) for x, y, z, i in XYZI.tolist())
    faces = struct.pack("<B3i", 3, 0, 1, 2)
    (tmp_path / "b.ply").write_bytes(head + tags + verts + faces)
    _assert_points(read_scan(tmp_path / "b.ply"), XYZI[:, :3], XYZI[:, 3])


def test_ply_binary_vertex_with_a_list_property(tmp_path: Path) -> None:
    head = _ply_header(
        "binary_big_endian",
        [
            ("vertex", len(XYZI), ["float x", "list uchar float extra", "float y", "float z"]),
        ],
    )
    verts = b"".join(
        struct.pack(">fB", x, k % 3)
        + struct.pack(f">{k % 3}f", *([7.0] * (k % 3)))
        + struct.pack(">ff", y, z)
        for k, (x, y, z, _) in enumerate(XYZI.tolist())
    )
    (tmp_path / "l.ply").write_bytes(head + verts)
    _assert_points(read_scan(tmp_path / "l.ply"), XYZI[:, :3], None)


def test_ply_bad_files(tmp_path: Path) -> None:
    xyz = ["float x", "float y", "float z"]
    good_head = _ply_header("binary_little_endian", [("vertex", 3, xyz)])
    cases = {
        "truncated.ply": good_head + struct.pack("<3f", 1, 2, 3) * 2,
        "noz.ply": _ply_header("ascii", [("vertex", 1, ["float x", "float y"])]) + b"1 2\n",
        "novertex.ply": _ply_header("ascii", [("face", 0, ["list uchar int i"])]),
        "zero.ply": _ply_header("ascii", [("vertex", 0, ["float x", "float y", "float z"])]),
        "badtype.ply": _ply_header("ascii", [("vertex", 1, ["float16 x", "float y", "float z"])]),
        "shortascii.ply": _ply_header("ascii", [("vertex", 2, ["float x", "float y", "float z"])])
        + b"1 2 3\n",
        "words.ply": _ply_header("ascii", [("vertex", 1, ["float x", "float y", "float z"])])
        + b"1 2 three\n",
        "noend.ply": b"ply\nformat ascii 1.0\nelement vertex 1\n",
        "garbage.ply": b"\x00\xff" * 500,
        "empty.ply": b"",
        "hugecount.ply": _ply_header(
            "binary_little_endian",
            [
                ("vertex", 10**15, ["float x", "float y", "float z", "list uchar float e"]),
            ],
        )
        + struct.pack("<3fB", 1, 2, 3, 0),
        "listtrunc.ply": _ply_header(
            "binary_little_endian",
            [
                ("vertex", 2, ["float x", "float y", "float z", "list uchar float e"]),
            ],
        )
        + struct.pack("<3fB", 1, 2, 3, 200),
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ScanReadError) as info:
            read_scan(tmp_path / name)
        assert str(tmp_path / name) in str(info.value), name


# -- bad .bin and missing files ----------------------------------------------------


@pytest.mark.parametrize("fmt, record", [("kitti", 16), ("nclt", 8)])
def test_bin_misaligned_empty_and_missing(tmp_path: Path, fmt: str, record: int) -> None:
    cases = {"misaligned.bin": b"\1" * (3 * record + 5), "empty.bin": b""}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ScanReadError) as info:
            read_scan(tmp_path / name, format=fmt)
        assert str(info.value).startswith(str(tmp_path / name) + ": ")
    with pytest.raises(ScanReadError, match="multiple of the 16-byte record"):
        read_scan(tmp_path / "misaligned.bin")
    with pytest.raises(ScanReadError, match="no such file"):
        read_scan(tmp_path / "absent.bin", format=fmt)


def test_every_format_refuses_a_missing_file_and_unknown_format(tmp_path: Path) -> None:
    for name, fmt in FORMATS.items():
        with pytest.raises(ScanReadError, match="no such file"):
            read_scan(tmp_path / f"absent{fmt.extensions[0]}", format=name)
    with pytest.raises(ScanReadError, match="unknown scan format 'las'"):
        read_scan(tmp_path / "x.bin", format="las")
    # A folder is not a scan file.
    with pytest.raises(ScanReadError, match="not a file"):
        read_scan(tmp_path, format="kitti")
    assert issubclass(ScanReadError, DiscoError)


# -- folders and natural order ----------------------------------------------------


def test_natural_key_orders_numbers_by_value() -> None:
    names = ["10.bin", "2.bin", "1.bin", "scan_10_b.pcd", "scan_9_b.pcd", "scan_9_a.pcd", "a.bin"]
    ordered = sorted(names, key=natural_key)
    assert ordered == [
        "1.bin",
        "2.bin",
        "10.bin",
        "a.bin",
        "scan_9_a.pcd",
        "scan_9_b.pcd",
        "scan_10_b.pcd",
    ]


def test_list_scans_layouts(tmp_path: Path) -> None:
    # DIR/velodyne/*.bin wins over files at the top of DIR.
    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    for i in (10, 2, 1):
        XYZI.tofile(seq / "velodyne" / f"{i}.bin")
    (seq / "velodyne" / "notes.txt").write_text("not a scan")
    (seq / "velodyne" / "._1.bin").write_bytes(b"\0" * 4096)  # a macOS resource fork
    (seq / "poses.npy").write_bytes(b"")
    assert [p.name for p in list_scans(seq)] == ["1.bin", "2.bin", "10.bin"]
    # A file gives itself, whatever it holds.
    assert list_scans(seq / "velodyne" / "2.bin") == [seq / "velodyne" / "2.bin"]

    # Files at the top of DIR, filtered by extension and format.
    flat = tmp_path / "flat"
    flat.mkdir()
    for name in ("s11.pcd", "s3.pcd", "readme.md"):
        (flat / name).write_text("x")
    assert [p.name for p in list_scans(flat)] == ["s3.pcd", "s11.pcd"]
    assert [p.name for p in list_scans(flat, format="pcd")] == ["s3.pcd", "s11.pcd"]
    with pytest.raises(ScanReadError, match="no scan files"):
        list_scans(flat, format="ply")

    # NCLT's velodyne_sync folder.
    nclt = tmp_path / "2012-01-08"
    (nclt / "velodyne_sync").mkdir(parents=True)
    (nclt / "velodyne_sync" / "100.bin").write_bytes(b"\0" * 8)
    scans = list_scans(nclt)
    assert [p.name for p in scans] == ["100.bin"] and guess_format(scans[0]) == "nclt"


def test_list_scans_errors(tmp_path: Path) -> None:
    with pytest.raises(ScanReadError, match="no such file or folder") as info:
        list_scans(tmp_path / "nowhere")
    assert "nowhere" in str(info.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanReadError, match="no scan files"):
        list_scans(tmp_path / "empty")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "a.bin").write_bytes(b"")
    (mixed / "a.ply").write_bytes(b"")
    with pytest.raises(ScanReadError, match="several scan formats"):
        list_scans(mixed)
    assert [p.name for p in list_scans(mixed, format="ply")] == ["a.ply"]


# -- real scans ---------------------------------------------------------------------


def test_real_kitti_scan(realdata: Path) -> None:
    path = realdata / "kitti00" / "velodyne" / "000000.bin"
    points = read_scan(path)
    assert points.shape == (path.stat().st_size // 16, 4)
    # An HDL-64E on a car: returns out to tens of metres, reflectance in [0, 1],
    # the ground about 1.7 m below the sensor.
    r = np.hypot(points[:, 0], points[:, 1])
    assert 100_000 < len(points) < 130_000
    assert r.max() > 50 and 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0
    assert -2.0 < np.median(points[:, 2]) < 0.0
    assert [p.name for p in list_scans(realdata / "kitti00")][:3] == [
        "000000.bin",
        "000001.bin",
        "000002.bin",
    ]


@pytest.mark.parametrize("name", ["source", "target"])
def test_real_ply_agrees_with_its_bin_conversion(realdata: Path, name: str) -> None:
    ply = read_scan(realdata / "hdl32_pair" / f"{name}.ply")
    bin_ = read_scan(realdata / "hdl32_pair" / f"{name}.bin")
    assert len(ply) > 60_000
    np.testing.assert_array_equal(ply[:, :3], bin_[:, :3])


# -- random layouts -------------------------------------------------------------------

_PCD_TYPES = [
    ("F", 4, "f"),
    ("F", 8, "d"),
    ("U", 1, "B"),
    ("U", 2, "H"),
    ("I", 2, "h"),
    ("I", 4, "i"),
    ("U", 4, "I"),
    ("I", 8, "q"),
]


def test_pcd_and_ply_binary_random_layouts(tmp_path: Path) -> None:
    """x, y, z, intensity among extra fields of random types, counts and order; the
    expected values are written with struct, field by field."""
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies

    @hypothesis.settings(max_examples=40, deadline=None)
    @hypothesis.given(data=st.data())
    def check(data) -> None:
        n = data.draw(st.integers(1, 6))
        extras = data.draw(st.integers(0, 3))
        names = ["x", "y", "z"] + (["intensity"] if data.draw(st.booleans()) else [])
        names += [f"extra{k}" for k in range(extras)]
        names = data.draw(st.permutations(names))
        kinds = {name: data.draw(st.sampled_from(_PCD_TYPES)) for name in names}
        counts = {
            name: 1 if name in ("x", "y", "z", "intensity") else data.draw(st.integers(1, 3))
            for name in names
        }
        # Small integers fit every type, signed or not.
        values = {
            name: data.draw(
                st.lists(st.integers(0, 100), min_size=n * counts[name], max_size=n * counts[name])
            )
            for name in names
        }
        expected = np.zeros((n, 4))
        for col, name in enumerate(["x", "y", "z", "intensity"]):
            if name in values:
                expected[:, col] = values[name]

        rows = []
        for i in range(n):
            row = b""
            for name in names:
                c = counts[name]
                row += struct.pack("<" + kinds[name][2] * c, *values[name][i * c : (i + 1) * c])
            rows.append(row)
        head = _pcd_header(
            names,
            [kinds[m][1] for m in names],
            [kinds[m][0] for m in names],
            [counts[m] for m in names],
            n,
            "binary",
        )
        (tmp_path / "r.pcd").write_bytes(head + b"".join(rows))
        np.testing.assert_array_equal(read_scan(tmp_path / "r.pcd"), expected.astype(np.float32))

        # The same records as PLY vertices: a list property stands in for COUNT > 1.
        ply_type = {
            "f": "float",
            "d": "double",
            "B": "uchar",
            "H": "ushort",
            "h": "short",
            "i": "int",
            "I": "uint",
            "q": None,
        }
        props, ply_rows = [], []
        for name in names:
            t = ply_type[kinds[name][2]] or "int"
            props.append(f"list uchar {t} {name}" if counts[name] > 1 else f"{t} {name}")
        for i in range(n):
            row = b""
            for name in names:
                c, code = counts[name], kinds[name][2] if kinds[name][2] != "q" else "i"
                if c > 1:
                    row += struct.pack("<B", c)
                row += struct.pack("<" + code * c, *values[name][i * c : (i + 1) * c])
            ply_rows.append(row)
        ply = _ply_header("binary_little_endian", [("vertex", n, props)]) + b"".join(ply_rows)
        (tmp_path / "r.ply").write_bytes(ply)
        np.testing.assert_array_equal(read_scan(tmp_path / "r.ply"), expected.astype(np.float32))

    check()


def test_damaged_files_raise_only_scan_read_error(tmp_path: Path) -> None:
    """Every prefix and many byte-flipped copies of a valid file of each format
    either read as N x 4 float32 or raise ScanReadError; nothing else escapes."""
    valid: dict[str, bytes] = {}
    scan = np.vstack([XYZI, _scan_tail()])  # a headerless .bin is read when it is a scan
    valid["kitti.bin"] = scan.tobytes()
    np.save(tmp_path / "v.npy", XYZI)
    valid["v.npy"] = (tmp_path / "v.npy").read_bytes()
    head = _pcd_header(
        ["x", "y", "z", "intensity"], [4] * 4, "F F F F".split(), [1] * 4, len(XYZI), "binary"
    )
    valid["b.pcd"] = head + XYZI.tobytes()
    raw = XYZI.T.tobytes() + bytes(40)  # field by field, then a zero run
    head = _pcd_header(
        ["x", "y", "z", "intensity", "_"],
        [4] * 5,
        "F F F F U".split(),
        [1, 1, 1, 1, 2],
        len(XYZI),
        "binary_compressed",
    )
    packed = lzf_compress(raw)
    valid["c.pcd"] = head + struct.pack("<II", len(packed), len(raw)) + packed
    head = _pcd_header(
        ["x", "y", "z", "intensity"], [4] * 4, "F F F F".split(), [1] * 4, len(XYZI), "ascii"
    )
    valid["a.pcd"] = head + "".join(" ".join(map(str, r)) + "\n" for r in XYZI.tolist()).encode()
    props = ["float x", "float y", "float z", "float intensity", "list uchar int e"]
    head = _ply_header("binary_little_endian", [("vertex", len(XYZI), props)])
    valid["b.ply"] = head + b"".join(struct.pack("<4fB2i", *r, 2, 7, 8) for r in XYZI.tolist())
    valid["a.ply"] = (
        _ply_header("ascii", [("vertex", len(XYZI), props)])
        + "".join(" ".join(map(str, r)) + " 2 7 8\n" for r in XYZI.tolist()).encode()
    )
    rng = np.random.default_rng(7)
    for name, content in valid.items():
        path = tmp_path / name
        step = 5 if len(content) < 999 else 83  # the KITTI scan: 19 kB
        variants = [content[:cut] for cut in range(0, len(content), step)]
        for _ in range(60):
            damaged = bytearray(content)
            for pos in rng.integers(0, len(content), size=rng.integers(1, 4)):
                damaged[pos] = int(rng.integers(0, 256))
            variants.append(bytes(damaged))
        for variant in variants:
            path.write_bytes(variant)
            try:
                points = read_scan(path)
            except ScanReadError as exc:
                assert str(exc).startswith(f"{path}: ")
            else:
                assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 4
                assert len(points) > 0
        path.write_bytes(content)
        assert read_scan(path).shape == (len(scan if name == "kitti.bin" else XYZI), 4), name
