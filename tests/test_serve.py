"""`disco serve` end to end: a real server process on a Unix socket answers exactly what
`disco query --format jsonl` prints for the same scans, refuses bad requests with one
error reply each and keeps serving, and sees scans another process appends."""

from __future__ import annotations

import base64
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import DISCO_WITH_DEFAULT_SIGINT, socket_listening
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.service.client import Client, ServerError

QUERIES = ["01/velodyne/000005.bin", "01/velodyne/000012.bin", "01/velodyne/000018.bin"]


def cli(*args) -> str:
    res = CliRunner().invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res.stdout


def start_server(
    db: Path, sock: Path, *extra: str, wait_for: Path | None = None
) -> subprocess.Popen:
    """A server of `db` on `sock` (or on the `--port` in `extra`) that may read the
    sample scans, once `wait_for` (default: the socket) exists."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    root = Path(__file__).resolve().parent.parent / "data" / "samples"
    where = [] if "--port" in extra else ["--socket", str(sock)]
    if "--scan-root" not in extra:
        where += ["--scan-root", str(root)]
    proc = subprocess.Popen(
        [*DISCO_WITH_DEFAULT_SIGINT, "serve", "--db", str(db), *where, *extra],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    wait_for = wait_for or sock
    deadline = time.monotonic() + 120
    while not wait_for.exists() or (wait_for == sock and not socket_listening(sock)):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"the server did not start: {proc.stderr.read()}")
        time.sleep(0.1)
    return proc


@pytest.fixture(scope="module")
def served(samples: Path, tmp_path_factory):
    """A map of session 00 (26 scans) and a server of it."""
    tmp = tmp_path_factory.mktemp("serve")
    db = tmp / "map.db"
    paths = sorted(str(p) for p in (samples / "00" / "velodyne").glob("*.bin"))
    cli("build-db", *paths[:20], "-o", db)
    sock = tmp / "disco.sock"
    proc = start_server(db, sock, "--topk", "4")
    yield db, sock, paths
    proc.terminate()
    proc.wait(timeout=30)


def raw_exchange(sock: Path, payload: bytes, replies: int) -> list[dict]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(60)
    s.connect(str(sock))
    s.sendall(payload)
    f = s.makefile("rb")
    out = []
    for _ in range(replies):
        line = f.readline()
        if not line:
            break
        out.append(json.loads(line))
    s.close()
    return out


def test_replies_equal_disco_query_rows(served, samples: Path) -> None:
    db, sock, _ = served
    scans = [str(samples / q) for q in QUERIES]
    out = cli("query", *scans, "--db", db, "-k", "4", "--format", "jsonl")
    expected = [json.loads(x) for x in out.splitlines()]
    got = []
    with Client(sock) as c:
        for scan in scans:
            got += c.query(scan)
    assert got == expected
    # With --pose, the pose columns and T too.
    out = cli("query", scans[0], "--db", db, "-k", "2", "--pose", "--format", "jsonl")
    expected = [json.loads(x) for x in out.splitlines()]
    with Client(sock) as c:
        assert c.query(scans[0], topk=2, pose=True) == expected


def test_inline_points_match_the_file(served, samples: Path) -> None:
    db, sock, _ = served
    from disco_cli.io.readers import read_scan

    scan = samples / QUERIES[1]
    pts = read_scan(str(scan))
    with Client(sock) as c:
        by_file = c.query(str(scan))
        by_points = c.query(pts)
    keys = ["rank", "match", "match_id", "distance", "yaw_deg"]

    def picked(rows: list[dict]) -> list[dict]:
        return [{k: r[k] for k in keys} for r in rows]

    assert picked(by_points) == picked(by_file)


BAD = [
    (b"not json\n", "not JSON"),
    (b"[1, 2]\n", "JSON object"),
    (b'{"scan": 5}\n', "'scan' must be a file path"),
    (b'{"scan": "/nonexistent/x.bin"}\n', "/nonexistent/x.bin"),
    (b'{"scan": "a.bin", "topk": 0}\n', "'topk'"),
    (b'{"scan": "a.bin", "topk": true}\n', "'topk'"),
    (b'{"scan": "a.bin", "rm": "-rf"}\n', "unknown field 'rm'"),
    (b'{"op": "shutdown"}\n', "unknown op"),
    (b'{"scan": "a.bin", "points": {}}\n', "exactly one"),
    (b'{"points": {"shape": [10, 4], "data": "AAAA"}}\n', "not 10 x 4 float32"),
    (b'{"points": {"shape": [1e12, 4], "data": ""}}\n', "'points.shape'"),
    (b'{"points": {"shape": [2, 4], "data": "@@@"}}\n', "base64"),
    (b'{"scan": "a.bin", "max_distance": -1}\n', "max_distance"),
    (b'{"scan": "a.bin", "id": [1]}\n', "'id'"),
    (b"\xff\xfe\n", "not JSON"),
]


def test_bad_requests_get_one_error_each_and_the_server_goes_on(served, samples: Path) -> None:
    db, sock, _ = served
    nan = np.full((100, 4), np.nan, np.float32)
    nan_req = {"points": {"shape": [100, 4], "data": base64.b64encode(nan.tobytes()).decode()}}
    payload = b"".join(p for p, _ in BAD) + json.dumps(nan_req).encode() + b"\n"
    good = json.dumps({"id": "last", "scan": str(samples / QUERIES[0])}).encode() + b"\n"
    replies = raw_exchange(sock, payload + good, len(BAD) + 2)
    assert len(replies) == len(BAD) + 2
    for (_, needle), reply in zip(BAD, replies):
        assert reply["ok"] is False and needle in reply["error"], reply
        assert "\n" not in reply["error"] and "Traceback" not in reply["error"]
    assert replies[-2]["ok"] is False and replies[-2]["error"]  # NaN points: refused
    assert replies[-1]["ok"] is True and replies[-1]["id"] == "last" and replies[-1]["rows"]
    with Client(sock) as c:
        with pytest.raises(ServerError, match="no such file"):
            c.query(samples / "00" / "velodyne" / "missing.bin")
        assert c.ping()  # the same connection still works


def test_an_oversized_request_is_refused(samples: Path, tmp_path: Path, served) -> None:
    db, _, _ = served
    sock = tmp_path / "small.sock"
    proc = start_server(db, sock, "--max-request-mb", "0.01")
    try:
        big = json.dumps({"scan": "x" * 20000}).encode() + b"\n"
        replies = raw_exchange(sock, big, 1)
        assert replies[0]["ok"] is False and "longer than" in replies[0]["error"]
        with Client(sock) as c:  # the server is still up for others
            assert c.query(str(samples / QUERIES[0]), topk=1)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert proc.returncode is not None
    assert not sock.exists()  # removed on the way out


def test_server_sees_scans_appended_by_another_process(served) -> None:
    db, sock, paths = served
    with Client(sock) as c:
        before = c.request({"op": "info"})["scans"]
        cli("build-db", *paths, "-o", db, "--append")
        after = c.request({"op": "info"})["scans"]
        # The appended scan 000024 is now found for itself.
        rows = c.query(paths[24], topk=1)
    assert (before, after) == (20, len(paths))
    assert rows[0]["match"].endswith("000024.bin") and rows[0]["distance"] < 0.05


def test_a_live_socket_is_not_taken_over(served) -> None:
    db, sock, _ = served
    res = CliRunner().invoke(app, ["serve", "--db", str(db), "--socket", str(sock)])
    assert res.exit_code == 1
    assert "another server is listening" in res.output
