"""`disco serve` under requests it should not trust: every malformed line gets exactly
one error line; slow, idle and greedy connections are closed; a query whose client
has left stops; SIGTERM ends the server as Ctrl-C does; the map's warnings reach the
client in its reply."""

from __future__ import annotations

import json
import select
import shutil
import signal
import socket
import sqlite3
import time
import warnings
from pathlib import Path

import pytest
from test_serve import cli, start_server

from disco_cli.service.client import Client, ClientError


@pytest.fixture(scope="module")
def small_map(samples: Path, tmp_path_factory) -> Path:
    """A map of 20 scans of session 00, read from copies in its own folder."""
    tmp = tmp_path_factory.mktemp("limits")
    scans = tmp / "scans"
    scans.mkdir()
    for p in sorted((samples / "00" / "velodyne").glob("*.bin"))[:20]:
        shutil.copy(p, scans / p.name)
    cli("build-db", scans, "-o", tmp / "map.db")
    return tmp / "map.db"


@pytest.fixture(scope="module")
def strict(small_map: Path):
    """A server with short timeouts and a small request budget."""
    sock = small_map.parent / "strict.sock"
    proc = start_server(
        small_map, sock, "--read-timeout", "4", "--idle-timeout", "2",
        "--max-request-mb", "0.5", "--max-buffer-mb", "1", "--scan-root", str(small_map.parent),
        "--max-poses", "10000",
    )  # fmt: skip
    yield sock
    proc.terminate()
    proc.wait(timeout=30)


def connect(sock: Path, timeout: float = 60) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(sock))
    return s


def read_all(s: socket.socket) -> list[dict]:
    """Every reply line until the server closes the connection."""
    data = b""
    while True:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    return [json.loads(x) for x in data.splitlines()]


MALFORMED = [
    b"",  # an empty line
    b"   ",
    b"[" * 100000,  # nested far past Python's recursion limit
    b'{"a": ' * 5000 + b"1" + b"}" * 5000,
    b"{",
    b'"just a string"',
    b"null",
    b'{"scan": "a.bin", "topk": "3"}',
    b'{"scan": "a.bin", "topk": 2.5}',
    b'{"scan": "a.bin", "pose": "yes"}',
    b'{"scan": "a.bin", "scan_format": 5}',
    b'{"points": {"shape": [1, 4], "data": "AAAAAAAAAAAAAAAAAAAAAA=="}, "name": 5}',
    b'{"points": "AAAA"}',
    b'{"scan": ["a.bin"]}',
    b'{"scan": "a.bin", "id": true}',
    b'{"scan": "a.bin", "id": 1.5}',
    b'{"op": 5}',
    b'{"op": ["query"]}',
    b'{"scan": "a.bin", "max_distance": "1"}',
    b'{"scan": "a.bin", "max_distance": NaN}',
    b'{"scan": "a\\u0000.bin"}',
    b'{"scan": "a.bin", "token": "x"}',
    b'{"scan": "a.bin", "name": "b"}',
    b"1" * 5000,  # an integer past Python's digit limit
]


def test_every_malformed_line_gets_exactly_one_error_line(strict: Path) -> None:
    s = connect(strict)
    payload = b"".join(m + b"\n" for m in MALFORMED) + b'{"id": "end", "op": "ping"}\n'
    s.sendall(payload)
    s.shutdown(socket.SHUT_WR)  # on a Unix socket this is not leaving: all are answered
    replies = read_all(s)
    s.close()
    assert len(replies) == len(MALFORMED) + 1
    for line, reply in zip(MALFORMED, replies):
        assert reply["ok"] is False, (line[:40], reply)
        assert reply["id"] is None
        assert reply["error"] and "\n" not in reply["error"]
        assert "internal error" not in reply["error"], (line[:40], reply)
    assert replies[-1] == {"id": "end", "ok": True, "op": "ping"}
    assert "nested too deeply" in replies[2]["error"]
    assert "empty request" in replies[0]["error"]


def test_a_slow_request_line_is_cut_off(strict: Path) -> None:
    s = connect(strict)
    t0 = time.monotonic()
    s.sendall(b'{"op": "pi')  # and nothing more
    replies = read_all(s)
    took = time.monotonic() - t0
    s.close()
    assert len(replies) == 1 and "took more than 4 s" in replies[0]["error"]
    assert 3.9 < took < 15


def test_an_idle_connection_is_closed_and_the_client_reconnects(strict: Path) -> None:
    s = connect(strict)
    t0 = time.monotonic()
    assert s.recv(10) == b""  # closed without a byte
    assert 1.9 < time.monotonic() - t0 < 15
    s.close()
    with Client(socket=strict) as c:
        assert c.ping()
        time.sleep(2.5)
        assert c.ping()  # on a new connection


def test_the_bytes_held_across_connections_are_bounded(strict: Path) -> None:
    # Four connections each start a 300 KiB line: 1.2 MiB > the 1 MiB budget.
    part = b'{"scan": "' + b"x" * (300 * 1024)
    conns = []
    t0 = time.monotonic()
    for _ in range(4):
        s = connect(strict)
        try:
            s.sendall(part)
        except BrokenPipeError:
            pass  # refused (and closed) before all of it was sent: its line is read below
        conns.append(s)
    # Until the 4 s a line may take are nearly up, what comes back is the budget's.
    refused = set()
    while time.monotonic() < t0 + 3.5 and len(refused) < len(conns):
        ready, _, _ = select.select([c for c in conns if c not in refused], [], [], 0.1)
        for s in ready:
            assert "request bytes" in json.loads(s.recv(65536))["error"]
            refused.add(s)
    assert 1 <= len(refused) <= 3  # the first ones fit
    for s in conns:
        s.close()
    time.sleep(0.5)
    with Client(socket=strict) as c:  # the budget came back
        assert c.ping()


def test_a_query_whose_client_left_stops(small_map: Path, monkeypatch) -> None:
    """In the server's own code path, with the client reported gone after the first
    check: of 20 matches' poses, at most one is estimated (beyond what the query
    stage itself estimates, measured on the same query without poses)."""
    from disco_cli.maps.facade import Map
    from disco_cli.query import relative_pose
    from disco_cli.service.serve import QueryService, ServeOptions

    calls = []
    real = relative_pose.estimate_relative_pose

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(relative_pose, "estimate_relative_pose", counted)
    checks = []

    def alive() -> bool:
        checks.append(1)
        return len(checks) <= 2  # the start, then the first match

    scan = next((small_map.parent / "scans").glob("*.bin"))
    line = json.dumps({"scan": str(scan), "topk": 20, "pose": True}).encode()
    with Map.open(small_map) as m:
        service = QueryService(m, ServeOptions(scan_root=small_map.parent))
        assert service.handle_line(json.dumps({"scan": str(scan), "topk": 20}).encode())["ok"]
        base = len(calls)  # the query stage's own, without poses
        calls.clear()
        assert service.handle_line(line, alive) is None
        assert (len(calls), service.cancelled, service.answered) == (base + 1, 1, 1)
        # Nobody leaving: all 20.
        reply = service.handle_line(line)
    assert reply["ok"] and len(reply["rows"]) == 20 and len(calls) == 2 * base + 21


def test_a_client_that_leaves_mid_query_is_not_worked_for(strict: Path, small_map) -> None:
    scan = next((small_map.parent / "scans").glob("*.bin"))
    with Client(socket=strict) as c:
        before = c.request({"op": "info"})
    s = connect(strict)
    s.sendall(json.dumps({"scan": str(scan), "topk": 10000, "pose": True}).encode() + b"\n")
    s.close()
    time.sleep(0.5)
    with Client(socket=strict) as c:
        after = c.request({"op": "info"})
    assert after["cancelled"] == before["cancelled"] + 1
    assert after["answered"] == before["answered"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_ends_the_server_as_ctrl_c_does(small_map: Path, tmp_path: Path, sig) -> None:
    sock = tmp_path / "s.sock"
    proc = start_server(small_map, sock, "--scan-root", str(small_map.parent))
    with Client(socket=sock) as c:
        c.query(next((small_map.parent / "scans").glob("*.bin")), topk=1)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert err.strip().splitlines()[-1] == "stopped after 1 queries"
    assert "Traceback" not in err
    assert not sock.exists()


def test_the_maps_warnings_reach_the_client(small_map: Path, tmp_path: Path) -> None:
    folder = tmp_path / "m"
    shutil.copytree(small_map.parent / "scans", folder / "scans")
    cli("build-db", folder / "scans", "-o", folder / "map.db")
    # Damage row 3 behind disco's back (its checksum no longer holds), and take away
    # the file of scan 5 (a match without a pose).
    with sqlite3.connect(folder / "map.db") as conn:
        conn.execute("UPDATE scans SET x = coalesce(x, 0) + 0.5 WHERE id = 3")
    conn.close()
    scans = sorted((folder / "scans").glob("*.bin"))
    gone = scans[4]
    query = tmp_path / "q.bin"
    shutil.copy(gone, query)
    gone.unlink()
    sock = tmp_path / "w.sock"
    proc = start_server(folder / "map.db", sock, "--scan-root", str(tmp_path))
    try:
        with Client(socket=sock) as c:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                rows = c.query(query, topk=5, pose=True)
            first = list(c.warnings)
            assert [str(w.message) for w in caught] == [f"disco serve: {w}" for w in first]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c.query(query, topk=1)
            second = list(c.warnings)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert any("scan 3" in w and "damaged" in w for w in first), first
    assert any(gone.name in w and "no relative pose" in w for w in first), first
    assert any("scan 3" in w for w in second)  # every later answer leaves it out too
    assert 3 not in [r["match_id"] for r in rows]


def test_a_reply_that_comes_too_late_is_a_client_error(strict: Path, small_map: Path) -> None:
    scan = next((small_map.parent / "scans").glob("*.bin"))
    with Client(socket=strict) as c:
        before = c.request({"op": "info"})["cancelled"]
    with Client(socket=strict, timeout=0.05) as c:
        with pytest.raises(ClientError, match="no reply") as info:
            c.query(scan, topk=20, pose=True)  # 20 ICPs: far longer than 50 ms
        assert isinstance(info.value.__cause__, OSError)
        c._timeout = 60.0
        assert c.ping()  # on a new connection: the late reply is not taken for this one
        assert c.request({"op": "info"})["cancelled"] == before + 1


def test_the_socket_file_appears_only_once_the_server_listens(tmp_path: Path, monkeypatch) -> None:
    """A client that sees the socket file must be able to connect: the server binds under
    a private name and moves the file into place after listen()."""
    from disco_cli.service import serve_net

    path = tmp_path / "s.sock"
    seen: dict[str, bool] = {}
    real_listen = socket.socket.listen

    def listen(sock, *args):
        seen["file before listen"] = path.exists()
        return real_listen(sock, *args)

    monkeypatch.setattr(socket.socket, "listen", listen)
    server = serve_net.make_server(object(), socket_path=path)
    try:
        assert seen == {"file before listen": False}
        assert path.is_socket() and str(server.server_address) == str(path)
        assert [p.name for p in tmp_path.iterdir()] == ["s.sock"]  # no private name left
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as client:
            client.connect(str(path))  # accepted by the backlog without a serving thread
    finally:
        server.server_close()
