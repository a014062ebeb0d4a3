"""`disco serve` for many clients and over TCP: 20 clients connecting at the same moment
are all answered (Unix socket and TCP), each with the rows `disco query` prints; the
client sends absolute paths; every client failure is one `ClientError`; TCP answers
no one without the token; scan files are read only under the scan root."""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import threading
import time
from pathlib import Path

import pytest
from test_serve import QUERIES, cli, start_server

from disco_cli.service.client import Client, ClientError, ServerError

N_CLIENTS = 20


@pytest.fixture(scope="module")
def fleet_map(samples: Path, tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fleet")
    db = tmp / "map.db"
    paths = sorted(str(p) for p in (samples / "00" / "velodyne").glob("*.bin"))
    cli("build-db", *paths[:20], "-o", db)
    return db


@pytest.fixture(scope="module")
def expected(fleet_map: Path, samples: Path) -> dict[str, list[dict]]:
    """The truth: `disco query --format jsonl` of each query scan, in its own process."""
    scans = [str(samples / q) for q in QUERIES]
    out = cli("query", *scans, "--db", fleet_map, "-k", "3", "--format", "jsonl")
    rows = [json.loads(x) for x in out.splitlines()]
    return {s: [r for r in rows if r["query"] == s] for s in scans}


@pytest.fixture(scope="module")
def unix_server(fleet_map: Path):
    sock = fleet_map.parent / "fleet.sock"
    proc = start_server(fleet_map, sock)
    yield sock
    proc.terminate()
    proc.wait(timeout=30)


def free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture(scope="module")
def tcp_server(fleet_map: Path):
    """A TCP server of the map: (port, token file, its process)."""
    port = free_port()
    token = fleet_map.parent / "tcp.token"
    ready = fleet_map.parent / "unused.sock"  # start_server waits for a path: the token
    proc = start_server(
        fleet_map, ready, "--port", str(port), "--token-file", str(token), wait_for=token
    )
    yield port, token, proc
    proc.terminate()
    proc.wait(timeout=30)


def together(n: int, ask) -> list:
    """`ask(i)` on n threads released at the same moment: each result or exception."""
    gate = threading.Barrier(n)
    out: list = [None] * n

    def run(i: int) -> None:
        gate.wait()
        try:
            out[i] = ask(i)
        except BaseException as exc:  # recorded, then asserted on
            out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    return out


def test_twenty_clients_at_once_are_all_answered_on_the_unix_socket(
    unix_server: Path, expected: dict
) -> None:
    scans = list(expected)

    def ask(i: int) -> list:
        with Client(socket=unix_server) as c:
            return c.query(scans[i % len(scans)], topk=3)

    got = together(N_CLIENTS, ask)
    errors = [g for g in got if isinstance(g, BaseException)]
    assert not errors, errors[:3]
    for i, rows in enumerate(got):
        assert rows == expected[scans[i % len(scans)]]


def test_twenty_clients_at_once_are_all_answered_over_tcp(tcp_server, expected: dict) -> None:
    port, token, _ = tcp_server
    scans = list(expected)

    def ask(i: int) -> list:
        with Client(port=port, token_file=token) as c:
            return c.query(scans[i % len(scans)], topk=3)

    got = together(N_CLIENTS, ask)
    errors = [g for g in got if isinstance(g, BaseException)]
    assert not errors, errors[:3]
    for i, rows in enumerate(got):
        assert rows == expected[scans[i % len(scans)]]


def test_relative_paths_are_the_clients(
    unix_server: Path, expected: dict, samples: Path, monkeypatch
) -> None:
    scan = str(samples / QUERIES[0])
    monkeypatch.chdir(Path(scan).parent)  # the server runs elsewhere
    with Client(socket=unix_server.absolute()) as c:
        rows = c.query(Path(scan).name, topk=3)
    assert rows == expected[scan]


def test_every_client_failure_is_a_client_error(tmp_path: Path, unix_server: Path) -> None:
    with pytest.raises(ClientError, match="cannot reach") as info:
        Client(socket=tmp_path / "nobody.sock")
    assert isinstance(info.value.__cause__, OSError)
    with pytest.raises(ClientError, match="cannot reach"):
        Client(port=free_port(), token="x")
    with pytest.raises(ClientError, match="token"):
        Client(port=free_port(), token_file=tmp_path / "absent.token")
    with pytest.raises(ClientError):
        Client()
    with Client(socket=unix_server) as c:
        with pytest.raises(ServerError) as refused:
            c.query(tmp_path / "x.bin")
        assert isinstance(refused.value, ClientError)
        assert c.ping()  # still usable


def _raw(port: int, payload: bytes, wait: float = 5.0) -> bytes:
    """Everything a TCP connection gets back for `payload` until the server closes it."""
    s = socket.create_connection(("127.0.0.1", port), timeout=wait)
    try:
        s.sendall(payload)
        got = b""
        while True:
            chunk = s.recv(65536)
            if not chunk:
                return got
            got += chunk
    finally:
        s.close()


def test_tcp_without_the_token_gets_no_answer(tcp_server, samples: Path) -> None:
    port, token_file, _ = tcp_server
    token = token_file.read_text().strip()
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    query = json.dumps({"scan": str(samples / QUERIES[0])}).encode() + b"\n"
    for first in (
        query,  # no auth at all
        b'{"op": "ping"}\n',
        json.dumps({"op": "auth", "token": token[:-1] + "x"}).encode() + b"\n",
        json.dumps({"op": "auth", "token": ""}).encode() + b"\n",
        b"[" * 3000 + b"\n",
        b"\n",
        b"x" * 10000,  # longer than an auth line may be, no newline
    ):
        assert _raw(port, first + query) == b"", first[:40]
    # With it, the same query is answered.
    auth = json.dumps({"id": 1, "op": "auth", "token": token}).encode() + b"\n"
    replies = [json.loads(x) for x in _raw_lines(port, auth + query, 2)]
    assert replies[0] == {"id": 1, "ok": True, "op": "auth"}
    assert replies[1]["ok"] is True and replies[1]["rows"]
    with pytest.raises(ClientError, match="wrong token"):
        Client(port=port, token="not-it")


def _raw_lines(port: int, payload: bytes, n: int) -> list[bytes]:
    s = socket.create_connection(("127.0.0.1", port), timeout=60)
    f = s.makefile("rb")
    s.sendall(payload)
    out = [f.readline() for _ in range(n)]
    s.close()
    return out


def test_the_token_file_is_found_by_env_and_removed_at_exit(
    fleet_map: Path, tmp_path: Path, monkeypatch
) -> None:
    port = free_port()
    token = tmp_path / "t.token"
    proc = start_server(fleet_map, tmp_path / "x.sock", "--port", str(port),
                        "--token-file", str(token), wait_for=token)  # fmt: skip
    try:
        monkeypatch.setenv("DISCO_TOKEN_FILE", str(token))
        with Client(port=port) as c:
            assert c.ping()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert str(token) in err  # stated at start
    assert not token.exists()


def test_scans_are_read_only_under_the_scan_root(
    unix_server: Path, samples: Path, tmp_path: Path
) -> None:
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"\0" * 1600)
    link_dir = samples.parent / "samples"  # the root is data/samples (start_server)
    with Client(socket=unix_server) as c:
        root = c.request({"op": "info"})["scan_root"]
        assert Path(root) == link_dir.resolve()
        errors = {}
        for path in (secret, tmp_path / "absent.bin", Path("/etc/hostname")):
            reply = c.request({"scan": str(path)})
            assert reply["ok"] is False
            errors[path] = reply["error"].replace(str(path), "PATH")
        # The same line whether the file exists or not: nothing about it leaks.
        assert len(set(errors.values())) == 1, errors
        assert "outside" in next(iter(errors.values()))
        for sneaky in (f"{root}/../../{secret}", f"{root}/00/../../{tmp_path}/secret.bin"):
            assert not c.request({"scan": sneaky})["ok"]
        # A relative path is taken from the root.
        rows = c.request({"scan": QUERIES[0], "topk": 1})
        assert rows["ok"] and rows["query"] == str(Path(root) / QUERIES[0])


def test_a_link_out_of_the_root_is_refused(fleet_map: Path, tmp_path: Path, samples: Path) -> None:
    root = tmp_path / "root"
    root.mkdir()
    outside = tmp_path / "outside.bin"
    outside.write_bytes((samples / QUERIES[0]).read_bytes())
    (root / "in.bin").write_bytes(outside.read_bytes())
    (root / "link.bin").symlink_to(outside)
    sock = tmp_path / "r.sock"
    proc = start_server(fleet_map, sock, "--scan-root", str(root))
    try:
        with Client(socket=sock) as c:
            assert c.query(root / "in.bin", topk=1)
            with pytest.raises(ServerError, match="outside"):
                c.query(root / "link.bin", topk=1)
            with pytest.raises(ServerError, match="a folder, not a scan file"):
                c.query(root, topk=1)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert f"scans read under {root.resolve()}" in " ".join(err.split())


def test_a_full_server_turns_one_more_away_with_one_line(fleet_map: Path, tmp_path: Path) -> None:
    sock = tmp_path / "b.sock"
    proc = start_server(fleet_map, sock, "--max-clients", "2")
    try:
        with Client(socket=sock) as a, Client(socket=sock) as b:
            assert a.ping() and b.ping()
            with Client(socket=sock) as third:
                reply = third.request({"op": "ping"})
            assert reply["ok"] is False
            assert reply["error"].startswith("the server is full: 2 clients are connected")
        time.sleep(0.3)  # the two slots come back as their connections close
        with Client(socket=sock) as c:
            assert c.ping()
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_the_command_line_client_sends_absolute_paths(
    unix_server: Path, expected: dict, samples: Path
) -> None:
    scan = samples / QUERIES[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(__import__("sys").path)}
    res = subprocess.run(
        [__import__("sys").executable, "-m", "disco_cli.service.client", "--socket",
         str(unix_server), "-k", "3", scan.name],
        cwd=scan.parent, capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["rows"] == expected[str(scan)]
    res = subprocess.run(
        [__import__("sys").executable, "-m", "disco_cli.service.client", "--socket",
         str(unix_server.parent / "none.sock"), "x.bin"],
        capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert res.returncode == 1 and res.stderr.startswith("error: ")
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr
