"""`disco serve --allow-append` (issue 33: robots as clients): several writers append
scans through one server at once, and afterwards the map holds exactly the original
scans plus every appended one, with the poses and times `disco build-db` records,
passes `disco info --check`, answers the earlier queries as before and finds each
appended scan for itself. Appends are refused without the option; a bad one gets one
error reply, writes nothing, and the server goes on."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from test_serve import cli, raw_exchange, start_server
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.io.readers import read_scan
from disco_cli.maps.facade import Map
from disco_cli.service.client import Client, ServerError

# The original map is session 00; writer k appends session 01's scans 5k .. 5k+4.
WRITERS, EACH = 4, 5
# Earlier queries: scans of the original map, whose true match is themselves there.
EARLIER = ["00/velodyne/000003.bin", "00/velodyne/000010.bin", "00/velodyne/000017.bin"]


def _session(samples: Path, name: str) -> list[Path]:
    return sorted((samples / name / "velodyne").glob("*.bin"))


@pytest.fixture(scope="module")
def recorded(samples: Path, tmp_path_factory) -> dict[str, tuple[np.ndarray, float]]:
    """What `disco build-db` records for each scan of session 01 (from its poses.txt and
    times.txt): `{absolute path: (x, y, z, yaw rad), time}`."""
    ref = tmp_path_factory.mktemp("ref") / "ref.db"
    cli("build-db", samples / "01", "-o", ref)
    with Map.open(ref) as m:
        poses, times = m.database.poses()
        names = m.names()
    return {str(Path(n).resolve()): (p, float(t)) for n, p, t in zip(names, poses, times)}


def _pose(row: np.ndarray) -> list[list[float]]:
    """The 4 x 4 sensor pose of a stored x, y, z, yaw row."""
    x, y, z, yaw = (float(v) for v in row)
    c, s = np.cos(yaw), np.sin(yaw)
    return [[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]]


def _jsonl(text: str) -> list[dict]:
    return [json.loads(x) for x in text.splitlines() if x.startswith("{")]


def _writer(k: int, sock: Path, scans: list[Path], recorded: dict, start, out: dict) -> None:
    """Writer k's appends, each in its own way: 0 files one by one, 1 files in one
    request, 2 inline points one by one, 3 inline points in one request (named by
    their file's path, so that they are stored as a build would store the file)."""
    items = []
    for p in scans:
        row, t = recorded[str(p.resolve())]
        scan = str(p) if k < 2 else read_scan(str(p))
        items.append({"scan": scan, "pose": _pose(row), "time": t})
        if k >= 2:
            items[-1]["name"] = str(p.resolve())
    try:
        with Client(sock, timeout=300) as c:
            start.wait()
            if k % 2 == 0:
                out[k] = [c.append(**item) for item in items]
            else:
                out[k] = [c.append_many(items)]
    except BaseException as exc:  # the test's thread says what went wrong
        out[k] = exc


@pytest.mark.parametrize("store", ["sqlite", "milvus"])
def test_concurrent_writers_lose_no_row(
    store: str, samples: Path, recorded: dict, tmp_path: Path
) -> None:
    if store == "milvus":
        pytest.importorskip("pymilvus")
        pytest.importorskip("milvus_lite")
    db = str(tmp_path / "map.db") if store == "sqlite" else f"milvus:{tmp_path / 'fleet.db'}"
    original = _session(samples, "00")
    cli("build-db", samples / "00", "-o", db)
    earlier = [str(samples / q) for q in EARLIER]
    before = _jsonl(cli("query", *earlier, "--db", db, "-k", "1", "--format", "jsonl"))
    # The earlier answers found the query's own scan: their true match is in the map.
    assert [Path(r["match"]).name for r in before] == [Path(q).name for q in EARLIER]

    appended = _session(samples, "01")[: WRITERS * EACH]
    sock = tmp_path / "disco.sock"
    proc = start_server(Path(db), sock, "--allow-append")
    try:
        start = threading.Barrier(WRITERS + 1)
        out: dict = {}
        threads = [
            threading.Thread(
                target=_writer,
                args=(k, sock, appended[k * EACH : (k + 1) * EACH], recorded, start, out),
            )
            for k in range(WRITERS)
        ]
        for t in threads:
            t.start()
        with Client(sock, timeout=300) as reader:
            start.wait()
            # Queries are answered between the appends, as before them.
            during = [row for q in earlier for row in reader.query(q, topk=1)]
        for t in threads:
            t.join(timeout=600)
        for k in range(WRITERS):
            assert not isinstance(out[k], BaseException), out[k]
        ids_of = {}
        for k in range(WRITERS):
            ids = [i for reply in out[k] for i in reply["scan_ids"]]
            assert sum(reply["added"] for reply in out[k]) == EACH
            ids_of.update(zip(appended[k * EACH : (k + 1) * EACH], ids))
        # Every appended scan got an id of its own, after the original scans'.
        n0, n = len(original), len(original) + len(appended)
        assert sorted(ids_of.values()) == list(range(n0 + 1, n + 1))
        with Client(sock, timeout=300) as c:
            assert c.request({"op": "info"})["scans"] == n
            for scan, sid in ids_of.items():
                top = c.query(str(scan), topk=1)[0]
                assert top["match_id"] == sid and Path(top["match"]).resolve() == scan.resolve()
                assert top["distance"] < 1e-3 and abs(top["yaw_deg"]) < 0.5, top
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert proc.returncode == 0
    assert f"and {len(appended)} scans appended" in proc.stderr.read()

    res = CliRunner().invoke(app, ["info", db, "--check"])
    assert res.exit_code == 0 and "check\tok" in res.stdout, res.output
    with Map.open(db) as m:
        names, ids = m.names(), m.database.ids()
        poses, times = m.database.poses()
    assert list(ids) == list(range(1, n + 1))
    # The original scans keep their ids; the appended ones are stored by absolute path.
    assert [Path(p).resolve() for p in names[:n0]] == [p.resolve() for p in original]
    assert {names[i - 1] for i in ids_of.values()} == {str(p.resolve()) for p in appended}
    for scan, sid in ids_of.items():
        row, t = recorded[str(scan.resolve())]
        np.testing.assert_allclose(poses[sid - 1], row, atol=1e-5)
        assert times[sid - 1] == pytest.approx(t)
    after = _jsonl(cli("query", *earlier, "--db", db, "-k", "1", "--format", "jsonl"))
    assert after == before and during == before


@pytest.fixture(scope="module")
def small_map(samples: Path, tmp_path_factory) -> Path:
    """A map of session 00's first 10 scans (tests copy it before writing)."""
    db = tmp_path_factory.mktemp("append") / "map.db"
    cli("build-db", *_session(samples, "00")[:10], "-o", db)
    return db


def _copy(db: Path, tmp_path: Path) -> Path:
    out = tmp_path / "map.db"
    out.write_bytes(db.read_bytes())
    return out


def test_appends_are_refused_without_the_option(small_map: Path, samples: Path, tmp_path: Path):
    db = _copy(small_map, tmp_path)
    sock = tmp_path / "disco.sock"
    proc = start_server(db, sock)
    try:
        with Client(sock) as c:
            with pytest.raises(ServerError, match="disco serve --allow-append"):
                c.append(_session(samples, "01")[0])
            info = c.request({"op": "info"})
            assert c.query(_session(samples, "00")[3], topk=1)  # still answering
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert (info["scans"], info["appends"], info["appended"]) == (10, False, 0)
    with Map.open(db) as m:
        assert len(m) == 10


def _points(pts: np.ndarray) -> dict:
    import base64

    pts = np.ascontiguousarray(pts, dtype="<f4")
    return {"shape": list(pts.shape), "data": base64.b64encode(pts.tobytes()).decode()}


def test_bad_appends_get_one_error_each_and_write_nothing(
    small_map: Path, samples: Path, tmp_path: Path
) -> None:
    db = _copy(small_map, tmp_path)
    good, other = (str(p) for p in _session(samples, "01")[:2])
    missing = str(samples / "01" / "velodyne" / "missing.bin")
    pts = read_scan(good)
    (tmp_path / "outside.bin").write_bytes(Path(good).read_bytes())
    bad = [
        ({"scan": missing}, "missing.bin: no such file"),
        ({"scan": str(tmp_path / "outside.bin")}, "outside the folder"),
        ({"scan": str(samples / "01")}, "a folder, not a scan file"),
        ({"points": _points(np.full((50, 4), np.nan)), "name": "nan"}, "nan: none of its 50"),
        ({"points": _points(pts)}, "need a 'name'"),
        ({"scan": good, "name": "x"}, "'name' names inline points"),
        ({"scan": good, "pose": True}, "'pose' must be the sensor's 4 x 4 pose"),
        ({"scan": good, "pose": np.eye(4)[:3].tolist()}, "'pose' must be"),
        ({"scan": good, "time": "noon"}, "'time' must be a finite number"),
        ({"scan": good, "topk": 3}, "unknown field 'topk'"),
        ({"scans": []}, "non-empty list"),
        ({"scans": [{"scan": good}], "time": 1.0}, "goes inside each of 'scans'"),
        ({"scans": [{"scan": good}, {"scan": good}]}, "given twice in one request"),
        ({"scans": [{"scan": good}, {"points": _points(pts), "name": "p"}]}, "all files or all"),
        # One bad scan refuses the whole request: the good one before it is not written.
        ({"scans": [{"scan": good}, {"scan": str(tmp_path / "outside.bin")}]}, "scans[1]: "),
        ({"scans": [{"scan": good}, {"scan": missing}]}, "missing.bin: no such file"),
        (
            {
                "scans": [
                    {"points": _points(pts), "name": "a"},
                    {"points": _points(pts[:0]), "name": "b"},
                ]
            },
            "scans[1]: 'points.shape'",
        ),
    ]
    sock = tmp_path / "disco.sock"
    proc = start_server(db, sock, "--allow-append")
    try:
        payload = b"".join(
            json.dumps({"op": "append", "id": k, **req}).encode() + b"\n"
            for k, (req, _) in enumerate(bad)
        )
        payload += json.dumps({"op": "info", "id": "info"}).encode() + b"\n"
        replies = raw_exchange(sock, payload, len(bad) + 1)
        assert len(replies) == len(bad) + 1
        for k, ((_, needle), reply) in enumerate(zip(bad, replies)):
            assert reply["id"] == k and reply["ok"] is False, reply
            assert needle in reply["error"] and "\n" not in reply["error"], (needle, reply)
        assert replies[-1]["scans"] == 10 and replies[-1]["appended"] == 0
        with Client(sock) as c:
            # The scans of the refused requests were not stored: now they are added.
            first = c.append(good, time=2.5)
            again = c.append(good)  # a resend adds nothing and names the same scan
            named = c.append(pts, name="robot-1/000000")
            resent = c.append(pts, name="robot-1/000000")
            batch = c.append_many([good, other])
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert first == {"scan_ids": [11], "added": 1, "scans": 11}
    assert again == {"scan_ids": [11], "added": 0, "scans": 11}
    assert named == {"scan_ids": [12], "added": 1, "scans": 12}
    assert resent == {"scan_ids": [12], "added": 0, "scans": 12}
    assert batch == {"scan_ids": [11, 13], "added": 1, "scans": 13}
    with Map.open(db) as m:
        names = m.names()
    assert names[10:] == [str(Path(good).resolve()), "robot-1/000000", str(Path(other).resolve())]
