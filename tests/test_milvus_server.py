"""A map on a Milvus server over the network (issue 33): `python -m milvus_lite server`
(Milvus Lite's engine behind Milvus's gRPC protocol, on a free local port) reached at
`milvus://127.0.0.1:PORT/NAME`. The answers against the SQLite map of the same scans,
appends by two processes at once, `info --check`, and copies both ways; the writers'
lock (`milvus_lock.py`).

This is not Milvus standalone (no container runs here): it checks disco's client side
of a server (the network address, separate processes, collections named NAME_*), not
Milvus's own server. Skipped where pymilvus or milvus-lite is not installed."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymilvus")
pytest.importorskip("milvus_lite")

from conftest import package_path  # noqa: E402
from test_serve import start_server  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

import disco_cli.maps.milvus_lock as milvus_lock  # noqa: E402
from disco_cli.cli import app  # noqa: E402
from disco_cli.maps.database import ScanBatch  # noqa: E402
from disco_cli.maps.milvus_lock import WriteLock  # noqa: E402
from disco_cli.maps.milvus_store import MilvusDatabase  # noqa: E402
from disco_cli.service.client import Client  # noqa: E402


def _cli(*args: object) -> str:
    res = CliRunner().invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res.output


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> str:
    """`milvus://127.0.0.1:PORT`: a Milvus Lite gRPC server in a temporary folder."""
    data = tmp_path_factory.mktemp("milvus_server")
    port = _free_port()
    log = open(data / "server.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "milvus_lite", "server", "--data-dir", str(data / "d")]
        + ["--host", "127.0.0.1", "--port", str(port)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, (data / "server.log").read_text()
            assert time.monotonic() < deadline, "the Milvus Lite server did not start in 60 s"
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.2)
        yield f"milvus://127.0.0.1:{port}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def _answers(db: object, scans: list[str]) -> list[tuple]:
    """Each query's top 3: (query, rank, match, yaw) from `disco query --format jsonl`."""
    out = _cli("query", *scans, "--db", db, "-k", "3", "--format", "jsonl")
    rows = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
    return [(r["query"], r["rank"], r["match"], r["yaw_deg"]) for r in rows]


def _same(got: list[tuple], want: list[tuple]) -> None:
    assert [r[:3] for r in got] == [r[:3] for r in want]
    np.testing.assert_allclose([r[3] for r in got], [r[3] for r in want], atol=1e-3)


def _run(*args: object) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": package_path()}
    return subprocess.Popen(
        [sys.executable, "-m", "disco_cli.cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def test_server_map_as_the_sqlite_map(server: str, samples: Path, tmp_path: Path) -> None:
    """Built, queried, appended to by two `build-db --append` processes at once, checked,
    and copied to SQLite and back: the answers are the SQLite map's throughout."""
    town = f"{server}/town"
    sqlite_map = tmp_path / "map.db"
    _cli("build-db", samples / "00", "-o", sqlite_map)
    _cli("build-db", samples / "00", "-o", town)
    scans = sorted(str(p) for p in (samples / "01" / "velodyne").iterdir())
    _same(_answers(town, scans), _answers(sqlite_map, scans))

    # Session 01 in two halves (files, so without poses): to the SQLite map in turn, to
    # the server map by two processes at once.
    halves = (scans[: len(scans) // 2], scans[len(scans) // 2 :])
    for part in halves:
        _cli("build-db", *part, "-o", sqlite_map, "--append")
    procs = [_run("build-db", *part, "-o", town, "--append") for part in halves]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    check = _cli("info", town, "--check")
    assert "\ncheck\tok" in check and "\nscans\t52" in check, check
    with MilvusDatabase.open(town) as db:
        stored = db.paths()
    assert sorted(stored[26:]) == sorted(os.path.abspath(s) for s in scans)
    # The two appends came in some order: compare with the SQLite map by scan, not id.
    _same(_answers(town, scans[::5]), _answers(sqlite_map, scans[::5]))

    copy, back = tmp_path / "copy.db", f"{server}/back"
    _cli("build-db", "--from", town, "-o", copy)
    _cli("build-db", "--from", copy, "-o", back)
    assert "\ncheck\tok" in _cli("info", back, "--check")
    want = _answers(town, scans[::5])
    _same(_answers(copy, scans[::5]), want)
    _same(_answers(back, scans[::5]), want)


# Two processes, each appending one scan at a time to the same server map, started on
# the same instant: without the lock, appends reading the same next_id took the same
# ids and the later rows replaced the earlier ones (16 of 40 rows lost in one run).
_WRITER = """
import json, sys, time
import numpy as np
from disco_cli.maps.database import ScanBatch
from disco_cli.maps.milvus_store import MilvusDatabase
address, tag, n, start = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
db = MilvusDatabase.open(address, writable=True)
rng = np.random.default_rng(ord(tag))
feats = np.zeros((1, *db.feature_shape), np.float32)
time.sleep(max(0.0, start - time.time()))
ids = []
for i in range(n):
    sig = rng.standard_normal((1, db.signature_dim)).astype(np.float32)
    sig /= np.linalg.norm(sig)
    batch = ScanBatch(paths=[f"/robot-{tag}/{i}"], signatures=sig, features=feats)
    ids += db.append(batch)
db.close()
print(json.dumps(ids))
"""


def test_two_writer_processes_lose_no_rows(server: str, samples: Path, tmp_path: Path) -> None:
    fleet = f"{server}/fleet"
    _cli("build-db", samples / "00", "-o", fleet)
    env = {**os.environ, "PYTHONPATH": package_path()}
    start = time.time() + 8  # both open the map first, then start together
    procs = {
        tag: subprocess.Popen(
            [sys.executable, "-c", _WRITER, fleet, tag, "15", str(start)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for tag in "ab"
    }
    given = {}
    for tag, p in procs.items():
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        given[tag] = json.loads(out.splitlines()[-1])
    assert not set(given["a"]) & set(given["b"])
    with MilvusDatabase.open(fleet) as db:
        assert db.check() == []  # ids 1..next_id-1, none missing, every row sound
        names = db.stored_names(given["a"] + given["b"])
        assert len(db) == 26 + 30 and db.next_id() == 57
    for tag, ids in given.items():
        assert [names[i][0] for i in ids] == [f"/robot-{tag}/{i}" for i in range(15)]


def _one_scan(db: MilvusDatabase, path: str) -> ScanBatch:
    sig = np.ones((1, db.signature_dim), np.float32) / np.sqrt(db.signature_dim)
    feats = np.zeros((1, *db.feature_shape), np.float32)
    return ScanBatch(paths=[path], signatures=sig, features=feats)


def _claim(db: MilvusDatabase, key: str) -> None:
    db._client.insert(db._meta_c, [{"key": key, "value": "{}", "v": [0.0, 0.0]}])


def test_append_waits_for_another_writers_claim(server: str, samples: Path) -> None:
    """An append does not write while another writer's claim stands, and writes once
    it is gone; the claim is no meta of the map."""
    lock_map = f"{server}/held"
    _cli("build-db", samples / "00", "-o", lock_map)
    with MilvusDatabase.open(lock_map, writable=True) as db:
        _claim(db, "lock:other")
        got: list = []
        writer = threading.Thread(target=lambda: got.append(db.append(_one_scan(db, "/x"))))
        writer.start()
        time.sleep(1.5)
        assert writer.is_alive() and got == []
        with MilvusDatabase.open(lock_map) as other:
            assert len(other) == 26 and "lock:other" not in other.meta
        db._client.delete(db._meta_c, filter='key in ["lock:other"]')
        writer.join(timeout=30)
        assert got == [[27]]
        assert WriteLock(db._client, db._meta_c).claims() == {}


def test_leftover_claim_taken_after_the_lease(
    server: str, samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A claim a killed writer left is deleted once watched unchanged for the lease; in
    Milvus Lite (one process per folder) at once, when the map is opened for writing."""
    monkeypatch.setattr(milvus_lock, "LEASE_S", 1.0)
    dead_map = f"{server}/dead"
    _cli("build-db", samples / "00", "-o", dead_map)
    with MilvusDatabase.open(dead_map, writable=True) as db:
        _claim(db, "lock:dead")
        assert db.append(_one_scan(db, "/x")) == [27]
        assert WriteLock(db._client, db._meta_c).claims() == {}

    monkeypatch.setattr(milvus_lock, "LEASE_S", 3600.0)  # the lite map must not wait it out
    lite = f"milvus:{tmp_path / 'lite.db'}"
    _cli("build-db", samples / "00", "-o", lite)
    with MilvusDatabase.open(lite, writable=True) as db:
        _claim(db, "lock:dead")
    with MilvusDatabase.open(lite, writable=True) as db:
        assert WriteLock(db._client, db._meta_c).claims() == {}
        assert db.append(_one_scan(db, "/x")) == [27]


def test_serve_appends_beside_a_direct_writer(server: str, samples: Path, tmp_path: Path) -> None:
    """A robot's appends through `disco serve --allow-append` on a server map, while a
    second process appends to the same map directly: the writers' lock keeps their ids
    apart, every row stays, and each scan appended through the server is its own top 1."""
    relay = f"{server}/relay"
    _cli("build-db", samples / "00", "-o", relay)
    robot_scans = sorted((samples / "01" / "velodyne").glob("*.bin"))[:8]
    sock = tmp_path / "disco.sock"
    proc = start_server(Path(relay), sock, "--allow-append")
    env = {**os.environ, "PYTHONPATH": package_path()}
    start = time.time() + 8  # the direct writer opens the map first
    direct = subprocess.Popen(
        [sys.executable, "-c", _WRITER, relay, "d", "10", str(start)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        with Client(sock, timeout=300) as c:
            time.sleep(max(0.0, start - time.time()))
            robot_ids = [c.append(str(p))["scan_ids"][0] for p in robot_scans]
            out, err = direct.communicate(timeout=180)
            assert direct.returncode == 0, err
            direct_ids = json.loads(out.splitlines()[-1])
            assert not set(robot_ids) & set(direct_ids)
            for sid, scan in zip(robot_ids, robot_scans):
                top = c.query(str(scan), topk=1)[0]
                assert top["match_id"] == sid and abs(top["yaw_deg"]) < 0.5, top
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        direct.kill()
    with MilvusDatabase.open(relay) as db:
        assert db.check() == []
        assert len(db) == 26 + 8 + 10 and db.next_id() == 45
        names = db.stored_names(direct_ids)
    assert [names[i][0] for i in direct_ids] == [f"/robot-d/{i}" for i in range(10)]
