"""Fuzzing every scan reader, the PointCloud2 decoder and every pose reader.

Each example writes a valid file of random layout (its contents known here, written
with struct and NumPy, not by the readers), then damages it: truncation, byte flips,
inserted or deleted bytes, header numbers made huge, negative, NaN or empty, header
words (types, field names, formats) swapped, or the whole file replaced by random
bytes. The reader must either return a well-formed result or raise the project's one
error type with a message naming the file; nothing else may escape, no read may run
for long, and none may allocate far more than the file's size (a header that claims
10^12 points is refused before allocating). An undamaged file must read back exactly.

DISCO_FUZZ_EXAMPLES=N runs N examples per reader (default 120).
"""

from __future__ import annotations

import io
import os
import re
import signal
import struct
import subprocess
import sys
import tracemalloc
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from test_readers import _pcd_header, _ply_header, _scan_tail, lzf_compress  # noqa: E402

from disco_cli.errors import DiscoError, PoseFileError, ScanReadError  # noqa: E402
from disco_cli.io.poses import (  # noqa: E402
    kitti360,
    read_calib_tr,
    read_extrinsic,
    read_poses,
    read_times,
    scan_times,
)
from disco_cli.io.readers import read_scan  # noqa: E402
from disco_cli.io.readers.pointcloud2 import PointField, decode_message  # noqa: E402

# A reader must not print NumPy's RuntimeWarnings (overflow, invalid cast) either.
pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")
EXAMPLES = int(os.environ.get("DISCO_FUZZ_EXAMPLES", "120"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# Far more than any reader needs here (files are a few kB), far less than a read
# that believed a damaged count would take.
TIME_LIMIT_S = 30


def _memory_bound(size: int) -> int:
    """Bytes a read of a `size`-byte file may allocate at its peak: Python's text
    parsing (a str and a list entry per token) costs tens of bytes per input byte."""
    return (1 << 20) + 200 * size


@contextmanager
def _bounded(size: int):
    """Fail a read that runs past TIME_LIMIT_S or allocates past `_memory_bound`."""

    def timeout(signum, frame):
        raise TimeoutError(f"a read ran for more than {TIME_LIMIT_S} s")

    previous = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(TIME_LIMIT_S)
    tracemalloc.start()
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        assert peak <= _memory_bound(size), f"the read allocated {peak} bytes"


# -- damage ---------------------------------------------------------------------------

NUMBERS = [b"0", b"-1", b"-7", b"1", b"2", b"3", b"8", b"65535", b"4294967295", b"4294967296",
           b"2147483648", b"1000000000000", b"-1000000000000", b"99999999999999999999999",
           b"nan", b"NaN", b"inf", b"-inf", b"1e3", b"1e400", b"1.5", b"", b"x", b"0x10",
           b"-0", b"1" * 400]  # fmt: skip
WORDS = [b"float", b"double", b"uchar", b"char", b"int", b"uint", b"short", b"list",
         b"int64", b"F", b"U", b"I", b"x", b"y", b"z", b"intensity", b"_", b"ascii",
         b"binary", b"binary_compressed", b"binary_big_endian", b"vertex", b"face",
         b"element", b"property", b"DATA", b"POINTS", b"COUNT", b"SIZE", b"TYPE",
         b"FIELDS", b"WIDTH", b"HEIGHT", b"end_header", b"descr", b"shape", b"", b"\n",
         b"#", b","]  # fmt: skip
_NUMBER = re.compile(rb"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|nan|inf", re.IGNORECASE)
_WORD = re.compile(rb"[A-Za-z_]+")

damage_ops = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(0, 255)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 16)),
    st.tuples(st.just("number"), st.integers(0, 10**6), st.sampled_from(NUMBERS)),
    st.tuples(st.just("word"), st.integers(0, 10**6), st.sampled_from(WORDS)),
)


def _replace_match(content: bytes, head: int, pattern: re.Pattern, which: int, new: bytes):
    matches = list(pattern.finditer(content, 0, min(head, len(content))))
    if not matches:
        return content
    m = matches[which % len(matches)]
    return content[: m.start()] + new + content[m.end() :]


def damage(content: bytes, head: int, ops: list[tuple]) -> bytes:
    """`content` after `ops`; number and word swaps hit the first `head` bytes (the
    header, where counts, types and names live)."""
    for op in ops:
        kind = op[0]
        at = int(op[1] * len(content)) if isinstance(op[1], float) else 0
        if kind == "truncate":
            content = content[:at]
        elif kind == "flip" and content:
            at = min(at, len(content) - 1)
            content = content[:at] + bytes([op[2]]) + content[at + 1 :]
        elif kind == "insert":
            content = content[:at] + op[2] + content[at:]
        elif kind == "delete":
            content = content[:at] + content[at + op[2] :]
        elif kind == "number":
            content = _replace_match(content, head, _NUMBER, op[1], op[2])
        elif kind == "word":
            content = _replace_match(content, head, _WORD, op[1], op[2])
    return content


@st.composite
def damaged(draw, valid):
    """(bytes, None) for a damaged file, or (bytes, expected N x 4) for an intact one;
    `valid` draws (bytes, header length, expected points)."""
    content, head, expected = draw(valid)
    how = draw(st.sampled_from(["intact", "damaged", "damaged", "damaged", "random"]))
    if how == "intact":
        return content, expected
    if how == "random":
        magic = draw(st.sampled_from([b"", b"ply\n", b"# .PCD v0.7\n", b"\x93NUMPY\x01\x00"]))
        return magic + draw(st.binary(max_size=600)), None
    return damage(content, head, draw(st.lists(damage_ops, min_size=1, max_size=4))), None


def check_scan(path: Path, content: bytes, expected, fmt: str) -> None:
    path.write_bytes(content)
    with _bounded(len(content)):
        try:
            points = read_scan(path, format=fmt)
        except ScanReadError as exc:
            message = str(exc)
            assert message.startswith(f"{path}: ") and "\n" not in message, message
            assert expected is None, f"an intact file was refused: {message}"
            return
    assert isinstance(points, np.ndarray) and points.dtype == np.float32
    assert points.ndim == 2 and points.shape[1] == 4 and len(points) > 0
    if fmt != "kitti":
        # KITTI's .bin goes to the voxelizer as read (no copy); it drops NaN itself.
        assert np.isfinite(points[:, :3]).all()
    if expected is not None:
        np.testing.assert_array_equal(points, expected)


# -- valid files of each format ---------------------------------------------------------

# Small integers and quarters: exact in every type below, so the expected points are exact.
small = st.integers(0, 100)


def values(n: int, integer: bool):
    return st.lists(small if integer else small.map(lambda v: v / 4), min_size=n, max_size=n)


# A headerless .bin is read only when it holds a whole scan (plausible.MIN_POINTS): the
# drawn points of a KITTI, NCLT or Oxford file are followed by these.
TAIL = _scan_tail(1100, seed=5)


@st.composite
def kitti_files(draw):
    n = draw(st.integers(1, 30))
    pts = np.array(draw(values(4 * n, False)), np.float32).reshape(n, 4)
    pts = np.vstack([pts, TAIL])
    return pts.tobytes(), 0, pts


@st.composite
def nclt_files(draw):
    from disco_cli.io.readers.nclt import RECORD

    n = draw(st.integers(1, 30))
    raw = np.zeros(n + len(TAIL), RECORD)
    for c, hi in (("x", 65535), ("y", 65535), ("z", 65535), ("intensity", 255), ("laser", 31)):
        raw[c][:n] = draw(st.lists(st.integers(0, hi), min_size=n, max_size=n))
    # The tail in NCLT's counts (z down); its laser ids are 0.
    raw["x"][n:], raw["y"][n:], raw["z"][n:] = np.round((TAIL[:, :3] * [1, -1, -1] + 100) / 0.005).T
    raw["intensity"][n:] = 9
    # NCLT's published conversion (5 mm per count, -100 m), turned z up: (x, -y, -z).
    xyz = [raw[c].astype(np.float64) * 0.005 - 100.0 for c in "xyz"]
    expected = np.stack([xyz[0], -xyz[1], -xyz[2], raw["intensity"]], axis=1)
    return raw.tobytes(), 0, expected.astype(np.float32)


@st.composite
def oxford_files(draw):
    from disco_cli.io.readers.oxford import DEFAULT_SCALE

    n = draw(st.integers(1, 30))
    xyz = np.array(draw(values(3 * n, False)), np.float64).reshape(n, 3) / 100
    xyz = np.vstack([xyz, TAIL[:, :3] / 40.0])  # a submap's points within [-1, 1]
    n = len(xyz)
    m = DEFAULT_SCALE  # x negated back: x forward, y left, z up
    expected = np.stack([-m * xyz[:, 0], m * xyz[:, 1], m * xyz[:, 2], np.zeros(n)], axis=1)
    return xyz.astype("<f8").tobytes(), 0, expected.astype(np.float32)


@st.composite
def npy_files(draw):
    n = draw(st.integers(1, 30))
    structured = draw(st.booleans())
    code = draw(st.sampled_from(["<f4", "<f8", "<i2", "u1", ">f4"]))
    cols = draw(st.sampled_from([3, 4]))
    table = np.array(draw(values(cols * n, code[-2] != "f")), np.float64).reshape(n, cols)
    if structured:
        names = draw(st.permutations(["x", "y", "z"] + (["intensity"] if cols == 4 else [])))
        arr = np.zeros(n, [(name, code) for name in names])
        for k, name in enumerate(["x", "y", "z", "intensity"][:cols]):
            arr[name] = table[:, k]
    else:
        arr = table.astype(code)
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    expected = np.zeros((n, 4), np.float32)
    expected[:, :cols] = table
    content = buf.getvalue()
    head = 10 + struct.unpack_from("<H", content, 8)[0]
    return content, head, expected


_PCD_TYPES = [("F", 4, "f"), ("F", 8, "d"), ("U", 1, "B"), ("U", 2, "H"), ("I", 2, "h"),
              ("U", 4, "I"), ("I", 4, "i"), ("I", 8, "q"), ("U", 8, "Q"),
              ("I", 1, "b")]  # fmt: skip


@st.composite
def pcd_files(draw):
    n = draw(st.integers(1, 20))
    names = ["x", "y", "z"] + (["intensity"] if draw(st.booleans()) else [])
    names += [f"extra{k}" for k in range(draw(st.integers(0, 2)))] + ["_"] * draw(st.integers(0, 1))
    names = draw(st.permutations(names))
    kinds = [draw(st.sampled_from(_PCD_TYPES)) for _ in names]
    counts = [1 if m in ("x", "y", "z", "intensity") else draw(st.integers(1, 3)) for m in names]
    cols = [
        np.array(draw(values(n * c, k[0] != "F")), np.float64).reshape(n, c)
        for k, c in zip(kinds, counts)
    ]
    data = draw(st.sampled_from(["ascii", "binary", "binary_compressed"]))
    head = _pcd_header(names, [k[1] for k in kinds], [k[0] for k in kinds], counts, n, data)
    if data == "ascii":
        body = "".join(
            " ".join(
                repr(float(v)) if k[0] == "F" else str(int(v))
                for col, k in zip(cols, kinds)
                for v in col[i]
            )  # fmt: skip
            + "\n"
            for i in range(n)
        ).encode()
    elif data == "binary":
        body = b"".join(
            struct.pack(
                "<" + "".join(k[2] * c for k, c in zip(kinds, counts)),
                *[v for col, k in zip(cols, kinds) for v in _typed(col[i], k)],
            )  # fmt: skip
            for i in range(n)
        )
    else:  # field by field, then LZF
        raw = b"".join(
            struct.pack("<" + k[2] * col.size, *_typed(col.reshape(-1), k))
            for col, k in zip(cols, kinds)
        )
        packed = lzf_compress(raw)
        body = struct.pack("<II", len(packed), len(raw)) + packed
    expected = np.zeros((n, 4), np.float32)
    for col, name in zip(cols, names):
        if name in ("x", "y", "z", "intensity"):
            expected[:, "xyz".find(name) if name != "intensity" else 3] = col[:, 0]
    return head + body, len(head), expected


def _typed(row: np.ndarray, kind) -> list:
    return [float(v) if kind[0] == "F" else int(v) for v in row]


_PLY_TYPES = [("float", "f"), ("double", "d"), ("uchar", "B"), ("ushort", "H"),
              ("short", "h"), ("int", "i"), ("uint", "I"), ("char", "b")]  # fmt: skip


@st.composite
def ply_files(draw):
    n = draw(st.integers(1, 20))
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    order = ">" if fmt == "binary_big_endian" else "<"
    names = ["x", "y", "z"] + (["intensity"] if draw(st.booleans()) else [])
    names += [f"extra{k}" for k in range(draw(st.integers(0, 2)))]
    names = draw(st.permutations(names))
    kinds = {m: draw(st.sampled_from(_PLY_TYPES)) for m in names}
    lists = {m: m.startswith("extra") and draw(st.booleans()) for m in names}
    vals = {m: np.array(draw(values(n, kinds[m][0] not in ("float", "double"))))
            for m in names}  # fmt: skip
    list_len = draw(st.integers(0, 3))
    props = [f"list uchar {kinds[m][0]} {m}" if lists[m] else f"{kinds[m][0]} {m}" for m in names]
    before = draw(st.booleans())
    elements = ([("camera", 1, ["float px", "float py"])] if before else []) + [
        ("vertex", n, props),
        ("face", 1, ["list uchar int vertex_indices"]),
    ]
    head = _ply_header(fmt, elements)

    def number(v, kind) -> str:
        return repr(float(v)) if kind in ("float", "double") else str(int(v))

    if fmt == "ascii":
        rows = ["0.5 1.5\n"] if before else []
        for i in range(n):
            fields = []
            for m in names:
                if lists[m]:
                    fields += [str(list_len)] + [number(vals[m][i], kinds[m][0])] * list_len
                else:
                    fields.append(number(vals[m][i], kinds[m][0]))
            rows.append(" ".join(fields) + "\n")
        rows.append("3 0 1 2\n")
        body = "".join(rows).encode()
    else:
        body = struct.pack(order + "ff", 0.5, 1.5) if before else b""
        for i in range(n):
            for m in names:
                code = kinds[m][1]
                v = float(vals[m][i]) if code in "fd" else int(vals[m][i])
                if lists[m]:
                    body += struct.pack(order + "B" + code * list_len, list_len, *[v] * list_len)
                else:
                    body += struct.pack(order + code, v)
        body += struct.pack(order + "B3i", 3, 0, 1, 2)
    expected = np.zeros((n, 4), np.float32)
    for k, m in enumerate(["x", "y", "z", "intensity"]):
        if m in vals:
            expected[:, k] = vals[m]
    return head + body, len(head), expected


SCAN_FILES = {
    "kitti": (kitti_files(), "scan.bin"),
    "nclt": (nclt_files(), "scan.bin"),
    "oxford": (oxford_files(), "scan.bin"),
    "npy": (npy_files(), "scan.npy"),
    "pcd": (pcd_files(), "scan.pcd"),
    "ply": (ply_files(), "scan.ply"),
}


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.mark.parametrize("fmt", list(SCAN_FILES))
def test_scan_reader_survives_damage(fmt: str, fuzz_dir: Path) -> None:
    strategy, name = SCAN_FILES[fmt]

    @FUZZ
    @given(case=damaged(strategy))
    def check(case) -> None:
        content, expected = case
        check_scan(fuzz_dir / name, content, expected, fmt)

    check()


def test_header_claiming_a_trillion_points_is_refused_before_allocating(fuzz_dir: Path) -> None:
    """Each format's count field set to 10^12 (and 2^62): a one-line error, no huge
    allocation (tracemalloc's peak stays near the file's size)."""
    head = _pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], [1, 1, 1], 2, "binary")
    pcd = head + bytes(24)
    ply = _ply_header("binary_little_endian", [("vertex", 2, ["float x", "float y", "float z"])])
    buf = io.BytesIO()
    np.save(buf, np.zeros((2, 4), np.float32))
    for huge in (b"1000000000000", str(2**62).encode()):
        cases = {
            "pcd": pcd.replace(b"POINTS 2", b"POINTS " + huge),
            "pcd ": pcd.replace(b"WIDTH 2", b"WIDTH " + huge).replace(b"POINTS 2\n", b""),
            "pcdc": pcd.replace(b"binary", b"binary_compressed").replace(
                b"POINTS 2", b"POINTS " + huge
            ),  # fmt: skip
            "ply": ply.replace(b"vertex 2", b"vertex " + huge) + bytes(24),
            "npy": buf.getvalue().replace(b"(2, 4)", b"(" + huge + b", 4)"),
        }
        for fmt, content in cases.items():
            check_scan(fuzz_dir / f"huge.{fmt.strip()[:3]}", content, None, fmt.strip()[:3])
            with pytest.raises(ScanReadError):
                read_scan(fuzz_dir / f"huge.{fmt.strip()[:3]}")


# -- files that are no scan: random bytes, text, truncated scans --------------------------

RECORD_BYTES = {"kitti": 16, "nclt": 8, "oxford": 24}
WORDS_TEXT = np.array(["the", "scan", "Größe", "x", "y", "z", "intensity", "ERROR", "at",
                       "0", "1", "-12.5", "3.14159", "1e-3", "nan", "inf", "\u5730\u56fe",
                       ",", ";", ".", "#", "\t", "\n", "\r\n", " ", "  "])  # fmt: skip


def _text(rng: np.random.Generator, size: int) -> bytes:
    """`size` bytes of text: prose and numbers, CSV rows, or a point cloud's ASCII
    export ("x y z i" a line), the kinds of text a .bin name ends up on."""
    kind = rng.integers(0, 3)
    tokens = max(1, size // 2)
    if kind == 0:
        text = " ".join(rng.choice(WORDS_TEXT, tokens))
    elif kind == 1:
        rows = rng.normal(0.0, 20.0, (tokens // 8 + 1, 4))
        text = "x,y,z,intensity\n" + "".join(",".join(f"{v:.3f}" for v in r) + "\n" for r in rows)
    else:
        rows = rng.normal(0.0, 20.0, (tokens // 8 + 1, 4))
        text = "".join(" ".join(f"{v:.6g}" for v in r) + "\n" for r in rows)
    content = text.encode()
    while len(content) < size:
        content += content
    return content[:size]


@FUZZ
@given(fmt=st.sampled_from(list(SCAN_FILES)), text=st.booleans(), seed=st.integers(0, 2**32 - 1),
       records=st.one_of(st.integers(1, 1100), st.integers(1100, 12_000)))  # fmt: skip
def test_random_bytes_and_text_are_never_answered(
    fmt: str, text: bool, seed: int, records: int, fuzz_dir: Path
) -> None:
    """Random bytes, or text, of a size that fits the layout's record (so the size check
    does not catch it), under each format's name: refused in one line naming the file,
    never read as points, at every size from one record to 12,000 (300 kB)."""
    rng = np.random.default_rng(seed)
    size = records * RECORD_BYTES.get(fmt, 16)
    content = _text(rng, size) if text else rng.bytes(size)
    path = fuzz_dir / SCAN_FILES[fmt][1]
    path.write_bytes(content)
    with _bounded(len(content)):
        with pytest.raises(ScanReadError) as info:
            read_scan(path, format=fmt)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message


@FUZZ
@given(scan=st.integers(0, 51), cut=st.floats(0.0, 1.0), aligned=st.booleans(),
       fmt=st.sampled_from(["kitti", "nclt", "oxford"]))  # fmt: skip
def test_a_scan_cut_anywhere_is_answered_only_when_whole_enough(
    samples: Path, scan: int, cut: float, aligned: bool, fmt: str, fuzz_dir: Path
) -> None:
    """A bundled sample scan (17k points, written in each headerless layout) cut at any
    byte: refused in one line when the cut splits a record or leaves fewer than
    plausible.MIN_POINTS points, else answered with exactly the points before the cut."""
    from disco_cli.io.readers.plausible import MIN_POINTS

    files = sorted(samples.glob("0[01]/velodyne/*.bin"))
    pts = np.fromfile(files[scan % len(files)], "<f4").reshape(-1, 4)
    if fmt == "kitti":
        content = pts.tobytes()
    elif fmt == "nclt":
        content = _as_nclt_records(pts).tobytes()
    else:  # a submap's float64 x, y, z, in [-1, 1] at 40 m a unit
        content = (pts[:, :3].astype(np.float64) / 40.0).tobytes()
    record = RECORD_BYTES[fmt]
    at = int(cut * len(content))
    if aligned:
        at -= at % record
    path = fuzz_dir / f"cut_{fmt}.bin"
    path.write_bytes(content[:at])
    whole = at % record == 0 and at // record >= MIN_POINTS
    try:
        points = read_scan(path, format=fmt)
    except ScanReadError as exc:
        message = str(exc)
        assert message.startswith(f"{path}: ") and "\n" not in message, message
        assert not whole, f"a scan of {at // record} whole points was refused: {message}"
        return
    assert whole, f"{at} bytes ({at / record:.2f} records) were answered"
    assert len(points) == at // record


def _as_nclt_records(pts: np.ndarray) -> np.ndarray:
    from disco_cli.io.readers.nclt import RECORD

    keep = np.all(np.abs(pts[:, :3]) < 99.0, axis=1)
    rec = np.zeros(int(keep.sum()), RECORD)
    raw = np.round((pts[keep, :3].astype(np.float64) * [1, -1, -1] + 100.0) / 0.005)
    rec["x"], rec["y"], rec["z"] = raw.astype("<u2").T
    rec["laser"] = np.arange(len(rec)) % 32
    return rec


# -- PointCloud2 -----------------------------------------------------------------------

_PC2_TYPES = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
HEADER_VALUES = [0, 1, -1, 3, 7, 2**31, 2**32 + 1, 10**12, -(10**12), 2**63]


@st.composite
def pointclouds(draw):
    """(message, expected N x 4 or None): a valid cloud of random layout, maybe damaged."""
    names = ["x", "y", "z"] + draw(
        st.sampled_from([[], ["intensity"], ["reflectivity"], ["intensity", "reflectivity"]])
    )
    names += ["ring", "time"][: draw(st.integers(0, 2))]
    names = draw(st.permutations(names))
    types = {
        m: draw(st.sampled_from([7, 8])) if m in "xyz" else draw(st.sampled_from(list(_PC2_TYPES)))
        for m in names
    }
    fields, offset = [], 0
    for m in names:
        offset += draw(st.integers(0, 3))  # padding between fields
        fields.append(PointField(m, offset, types[m], 1))
        offset += struct.calcsize(_PC2_TYPES[types[m]])
    point_step = offset + draw(st.integers(0, 4))
    height, width = draw(st.integers(1, 3)), draw(st.integers(1, 6))
    row_step = width * point_step + draw(st.sampled_from([0, 0, 3, 16]))
    big = draw(st.booleans())
    order = ">" if big else "<"
    vals = {m: draw(values(height * width, types[m] not in (7, 8))) for m in names}
    data = bytearray(height * row_step)
    for r in range(height):
        for c in range(width):
            i = r * width + c
            for f in fields:
                at = r * row_step + c * point_step + f.offset
                struct.pack_into(order + _PC2_TYPES[f.datatype], data, at, vals[f.name][i])
    expected = np.zeros((height * width, 4), np.float32)
    for k, m in enumerate("xyz"):
        expected[:, k] = vals[m]
    inten = (
        "intensity" if "intensity" in names else "reflectivity" if "reflectivity" in names else None
    )
    if inten:
        expected[:, 3] = vals[inten]
    header = dict(height=height, width=width, point_step=point_step, row_step=row_step)
    how = draw(st.sampled_from(["intact", "header", "field", "data", "data"]))
    if how == "header":
        header[draw(st.sampled_from(list(header)))] = draw(st.sampled_from(HEADER_VALUES))
    elif how == "field":
        k = draw(st.integers(0, len(fields) - 1))
        f = fields[k]
        what = draw(st.sampled_from(["offset", "datatype", "count", "name"]))
        if what == "name":
            fields[k] = PointField(draw(st.sampled_from(["", "x", "y", "i", "X"])), f.offset,
                                   f.datatype, f.count)  # fmt: skip
        else:
            new = draw(st.sampled_from(HEADER_VALUES + [9, 255]))
            fields[k] = PointField(
                f.name,
                new if what == "offset" else f.offset,
                new if what == "datatype" else f.datatype,
                new if what == "count" else f.count,
            )
    elif how == "data":
        ops = draw(st.lists(damage_ops.filter(lambda op: op[0] in ("truncate", "flip",
                                                                    "insert", "delete")),
                            min_size=1, max_size=3))  # fmt: skip
        data = bytearray(damage(bytes(data), 0, ops))
    msg = SimpleNamespace(
        fields=[SimpleNamespace(**f.__dict__) for f in fields],
        data=np.frombuffer(bytes(data), np.uint8),
        is_bigendian=big,
        **header,
    )
    return msg, expected if how == "intact" else None


@FUZZ
@given(case=pointclouds())
def test_pointcloud2_decoder_survives_damage(case) -> None:
    msg, expected = case
    name = "bag.mcap#/points@42"
    with _bounded(msg.data.nbytes):
        try:
            points = decode_message(msg, name)
        except ScanReadError as exc:
            assert str(exc).startswith(f"{name}: ") and "\n" not in str(exc)
            assert expected is None, f"an intact cloud was refused: {exc}"
            return
    assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 4
    assert 0 < len(points) <= msg.height * msg.width
    assert np.isfinite(points[:, :3]).all()
    if expected is not None:
        np.testing.assert_array_equal(points, expected)


# -- pose files --------------------------------------------------------------------------


def _rotations(draw, n: int) -> np.ndarray:
    q = np.array(draw(st.lists(st.integers(-9, 9), min_size=4 * n, max_size=4 * n)), float)
    q = q.reshape(n, 4)
    q[np.linalg.norm(q, axis=1) == 0] = [0, 0, 0, 1]
    from disco_cli.io.poses.geometry import quat_to_matrix

    return quat_to_matrix(q)


def _rows12(draw, n: int) -> np.ndarray:
    T = np.zeros((n, 3, 4))
    T[:, :, :3] = _rotations(draw, n)
    T[:, :, 3] = np.array(draw(values(3 * n, False))).reshape(n, 3)
    return T.reshape(n, 12)


def _line(values_) -> str:
    return " ".join(f"{v:.9e}" for v in values_)


@st.composite
def pose_files(draw):
    """(format, file name, text bytes)."""
    fmt = draw(st.sampled_from(["kitti", "tum", "nclt", "mulran", "oxford", "kitti360"]))
    n = draw(st.integers(1, 8))
    t0 = draw(st.integers(0, 10**6))
    if fmt == "kitti":
        name, text = "poses.txt", "".join(_line(r) + "\n" for r in _rows12(draw, n))
    elif fmt == "tum":
        q = np.array(draw(st.lists(st.integers(-9, 9), min_size=4 * n, max_size=4 * n)), float)
        q = q.reshape(n, 4) + [0, 0, 0, 10]
        xyz = np.array(draw(values(3 * n, False))).reshape(n, 3)
        name = "traj.txt"
        text = "# timestamp tx ty tz qx qy qz qw\n" + "".join(
            f"{t0 + 0.1 * i:.6f} " + _line([*xyz[i], *q[i]]) + "\n" for i in range(n)
        )
    elif fmt == "nclt":
        name = "groundtruth_2012-01-08.csv"
        rows = np.array(draw(values(6 * n, False))).reshape(n, 6) / 10
        text = "".join(f"{t0 + 100000 * i}," + ",".join(repr(float(v)) for v in r) + "\n"
                       for i, r in enumerate(rows))  # fmt: skip
        text += f"{t0 + 100000 * n},nan,nan,nan,nan,nan,nan\n"
    elif fmt == "mulran":
        name = "global_pose.csv"
        text = "".join(f"{t0 + 10**8 * i}," + ",".join(repr(float(v)) for v in r) + "\n"
                       for i, r in enumerate(_rows12(draw, n)))  # fmt: skip
    elif fmt == "oxford":
        name = "pointcloud_locations_20m.csv"
        ne = np.array(draw(values(2 * n, False))).reshape(n, 2) + 5.7e6
        text = "timestamp,northing,easting\n" + "".join(
            f"{t0 + 10**6 * i},{float(a)!r},{float(b)!r}\n" for i, (a, b) in enumerate(ne)
        )
    else:
        name = "poses.txt"
        text = "".join(f"{3 * i + 1} " + _line(r) + "\n" for i, r in enumerate(_rows12(draw, n)))
    return fmt, name, n, text.encode()


TEXT_NUMBERS = NUMBERS + [b"1e308", b"-1e308", b"1e-320", b"\xd9\xa1", b"1_0", b"+5", b" "]
text_ops = st.one_of(
    damage_ops,
    st.tuples(st.just("number"), st.integers(0, 10**6), st.sampled_from(TEXT_NUMBERS)),
)


@st.composite
def damaged_text(draw, valid):
    fmt, name, n, content = draw(valid)
    how = draw(st.sampled_from(["intact", "damaged", "damaged", "damaged", "random"]))
    if how == "random":
        content = draw(st.binary(max_size=400))
    elif how == "damaged":
        content = damage(content, len(content), draw(st.lists(text_ops, min_size=1, max_size=4)))
    return fmt, name, (n if how == "intact" else None), content


def _expect_pose_error(exc: DiscoError, *paths: Path) -> None:
    """A PoseFileError of one line naming one of `paths`."""
    message = str(exc)
    assert isinstance(exc, PoseFileError), f"{type(exc).__name__}: {message}"
    assert any(str(p) in message for p in paths) and "\n" not in message, message


@FUZZ
@given(case=damaged_text(pose_files()), named=st.booleans())
def test_pose_readers_survive_damage(case, named: bool, fuzz_dir: Path) -> None:
    """read_poses with the format given or guessed: finite keys and poses of the right
    shapes, or a PoseFileError naming the file."""
    fmt, name, n, content = case
    folder = fuzz_dir / "poses"
    folder.mkdir(exist_ok=True)
    path = folder / name
    path.write_bytes(content)
    with _bounded(len(content)):
        try:
            keys, T, got, _ = read_poses(path, fmt if named else None, calib="none")
        except DiscoError as exc:
            _expect_pose_error(exc, path)
            assert n is None, f"an intact {fmt} file was refused: {exc}"
            return
    assert got in ("kitti", "tum", "nclt", "mulran", "oxford", "kitti360")
    assert keys.shape == (len(T),) and T.shape == (len(T), 4, 4) and len(T) > 0
    assert np.isfinite(keys).all() and np.isfinite(T).all()
    if n is not None:
        assert got == fmt and len(T) == n
        np.testing.assert_array_equal(T[:, 3], np.tile([0.0, 0, 0, 1], (n, 1)))


@st.composite
def calibration_files(draw):
    """(kind, text): a KITTI calib.txt, an extrinsic, a times.txt or KITTI-360's two
    calibration files (kind 'kitti360', text of calib_cam_to_pose.txt + '\\0' + velo)."""
    kind = draw(st.sampled_from(["calib", "extrinsic", "times", "kitti360"]))
    R = _rows12(draw, 2)
    if kind == "calib":
        text = "".join(f"P{k}: " + _line(R[0]) + "\n" for k in range(4)) + "Tr: " + _line(R[1])
    elif kind == "extrinsic":
        text = "\n".join(_line(r) for r in R[0].reshape(3, 4)) + "\n0 0 0 1\n"
    elif kind == "times":
        n = draw(st.integers(1, 8))
        text = "".join(f"{0.1 * i:.6e}\n" for i in range(n))
    else:
        text = "image_00: " + _line(R[0]) + "\nimage_01: " + _line(R[0]) + "\n\0" + _line(R[1])
    return kind, text.encode()


@FUZZ
@given(case=calibration_files(), how=st.sampled_from(["intact", "damaged", "damaged"]),
       ops=st.lists(text_ops, min_size=1, max_size=4))  # fmt: skip
def test_calibration_and_times_survive_damage(case, how: str, ops, fuzz_dir: Path) -> None:
    kind, content = case
    if how == "damaged":
        content = damage(content, len(content), ops)
    folder = fuzz_dir / "calibration"
    folder.mkdir(exist_ok=True)
    if kind == "kitti360":
        pose_text, _, velo_text = content.partition(b"\0")
        (folder / "calib_cam_to_pose.txt").write_bytes(pose_text)
        (folder / "calib_cam_to_velo.txt").write_bytes(velo_text)
        path, read = folder, lambda p: kitti360.imu_to_velo(p)
    else:
        path = folder / {"calib": "calib.txt", "extrinsic": "ext.txt", "times": "times.txt"}[kind]
        path.write_bytes(content)
        read = {"calib": read_calib_tr, "extrinsic": read_extrinsic, "times": read_times}[kind]
    with _bounded(len(content)):
        try:
            out = read(path)
        except DiscoError as exc:
            _expect_pose_error(exc, path)
            assert how == "damaged", f"an intact {kind} file was refused: {exc}"
            return
    assert np.isfinite(out).all()
    assert out.shape == ((len(out),) if kind == "times" else (4, 4))
    if kind == "calib":
        # KITTI poses through this Tr: finite, or refused naming the calibration file.
        poses = fuzz_dir / "calibration" / "poses.txt"
        poses.write_text("1 0 0 1 0 1 0 2 0 0 1 3\n")
        try:
            _, T, _, _ = read_poses(poses, "kitti", calib=path)
        except DiscoError as exc:
            _expect_pose_error(exc, path, poses)  # a Tr that overflows the poses: either
            return
        assert np.isfinite(T).all()


@FUZZ
@given(names=st.lists(st.one_of(st.text(max_size=30), st.from_regex(r"\A[0-9]{1,500}\.bin\Z"),
                                st.from_regex(r"\Ab\.bag#/p@[0-9]{1,500}\Z")),
                      max_size=5),
       fmt=st.sampled_from(["kitti", "tum", "nclt", "mulran", "oxford", "kitti360"]))  # fmt: skip
def test_scan_times_from_any_name(names: list[str], fmt: str) -> None:
    """A scan name gives a finite time or NaN (no time), never an exception."""
    t = scan_times(names, fmt)
    assert t.shape == (len(names),) and not np.isinf(t).any()


# -- through the command line ----------------------------------------------------------


def _disco(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "disco_cli.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )


def test_corrupt_scans_through_the_command_line(tmp_path: Path, samples_spectral_db: Path) -> None:
    """`disco bev` and `disco query` given damaged files: one line naming the file,
    exit status 1, no traceback."""
    head = _pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], [1, 1, 1], 2, "binary")
    pcd = tmp_path / "huge.pcd"
    pcd.write_bytes(head.replace(b"POINTS 2", b"POINTS 1000000000000") + bytes(24))
    ply = tmp_path / "cut.ply"
    ply.write_bytes(
        _ply_header("binary_little_endian", [("vertex", 3, ["float x", "float y", "float z"])])
        + bytes(20)
    )
    npy = tmp_path / "bad.npy"
    npy.write_bytes(b"\x93NUMPY\x01\x00\x20\x00{'descr': '<f4', 'shape': (1e12, 4)}\n")
    runs = [
        (pcd, _disco("bev", str(pcd), "-o", str(tmp_path / "b.png"))),
        (ply, _disco("query", str(ply), "--db", str(samples_spectral_db))),
        (npy, _disco("query", str(npy), "--db", str(samples_spectral_db))),
    ]
    for path, res in runs:
        assert res.returncode == 1, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and str(path) in lines[0], res.stderr
        assert "Traceback" not in res.stderr + res.stdout
    assert not (tmp_path / "b.png").exists()


# -- what the fuzzing found, pinned ---------------------------------------------------


def test_degenerate_pose_files_are_refused(tmp_path: Path) -> None:
    """A zero quaternion (TUM), a singular Tr (KITTI calib.txt) and a frame number past
    2^53 (KITTI-360) used to give NaN poses, a LinAlgError or a silent wrap-around."""
    tum = tmp_path / "traj.txt"
    tum.write_text("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 0\n")
    poses = tmp_path / "poses.txt"
    poses.write_text("1 0 0 1 0 1 0 2 0 0 1 3\n")
    calib = tmp_path / "calib.txt"
    calib.write_text("Tr: " + " ".join(["0"] * 12) + "\n")
    k360 = tmp_path / "k360" / "poses.txt"
    k360.parent.mkdir()
    k360.write_text("1e23 1 0 0 0 0 1 0 0 0 0 1 0\n")
    cases = [
        (tum, lambda: read_poses(tum, "tum")),
        (calib, lambda: read_poses(poses, "kitti", calib=calib)),
        (k360, lambda: read_poses(k360, "kitti360", calib="none")),
    ]
    for path, read in cases:
        with pytest.raises(PoseFileError) as info:
            read()
        assert str(path) in str(info.value)


def test_scan_names_with_other_scripts_digits_hold_no_time() -> None:
    # '²' passes str.isdigit but not int(); 400 digits and 1e400 overflow a float.
    names = ["²", "1" * 400 + ".bin", "1e400.bin", "000012.bin"]
    t = scan_times(names, "tum")
    assert np.isnan(t[:3]).all() and t[3] == 12.0
    assert np.isnan(scan_times(["b.bag#/p@²"], "nclt")).all()


def test_pcd_with_a_huge_count_and_pointcloud2_beyond_float32(fuzz_dir: Path) -> None:
    head = _pcd_header(["x", "y", "z", "h"], [4] * 4, ["F"] * 4, [1, 1, 1, 4294967295], 1, "ascii")
    check_scan(fuzz_dir / "count.pcd", head + b"1 2 3 4\n", None, "pcd")
    # y is FLOAT64 1e300: finite there, Inf as float32; that point is dropped.
    fields = [PointField("x", 0, 7), PointField("y", 4, 8), PointField("z", 12, 7)]
    data = struct.pack("<fdf", 1, 1e300, 2) + struct.pack("<fdf", 3, 4, 5)
    msg = SimpleNamespace(fields=fields, data=data, height=1, width=2, point_step=16,
                          row_step=32, is_bigendian=False)  # fmt: skip
    np.testing.assert_array_equal(decode_message(msg, "b#t@1"), [[3, 4, 5, 0]])
    # One row and a row_step of 2^63 (a damaged header): its padding is never read.
    msg.data, msg.width, msg.row_step = struct.pack("<fdf", 3, 4, 5), 1, 2**63
    np.testing.assert_array_equal(decode_message(msg, "b#t@1"), [[3, 4, 5, 0]])


def test_a_tum_quaternion_that_overflows_is_refused_in_one_line(tmp_path: Path) -> None:
    # Found by the fuzz test above: qx = 1e308 overflowed the norm (a RuntimeWarning).
    path = tmp_path / "traj.txt"
    path.write_text("0.0 0 0 0 1e308 0 0 10\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(DiscoError) as info:
        read_poses(path, "tum", calib="none")
    _expect_pose_error(info.value, path)
