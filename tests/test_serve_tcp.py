"""`disco serve` over TCP facing connections it should not trust (issue 42): idle
connections that never show the token cannot keep out a client that has it; a full
server says it is full; TLS with a self-signed certificate, and a client that does
not trust it is refused in one line; a non-loopback host needs TLS or an explicit
risk; one request asks for a bounded number of poses; a library server without a scan
root reads no file."""

from __future__ import annotations

import base64
import json
import select
import shutil
import socket
import ssl
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_serve import QUERIES, cli, start_server
from test_serve_fleet import free_port, together
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DiscoError
from disco_cli.io.readers import read_scan
from disco_cli.maps.facade import Map
from disco_cli.query import relative_pose
from disco_cli.service.client import Client, ClientError, ServerError
from disco_cli.service.serve import MAX_POSES, QueryService, ServeOptions
from disco_cli.service.serve_net import NetOptions, make_server

# The target: with this many idle unauthenticated connections open, a client
# with the token is answered within ANSWERED_WITHIN seconds.
N_IDLE = 64
ANSWERED_WITHIN = 3.0
PENDING = 16  # --max-pending of the starving test's server


@pytest.fixture(scope="module")
def tcp_map(samples: Path, tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("tcp")
    paths = sorted(str(p) for p in (samples / "00" / "velodyne").glob("*.bin"))
    cli("build-db", *paths[:20], "-o", tmp / "map.db")
    return tmp / "map.db"


@pytest.fixture(scope="module")
def expected(tcp_map: Path, samples: Path) -> list[dict]:
    """The truth: `disco query --format jsonl` of the first query scan, top 3."""
    out = cli("query", samples / QUERIES[0], "--db", tcp_map, "-k", "3", "--format", "jsonl")
    return [json.loads(x) for x in out.splitlines()]


def tcp_server(db: Path, folder: Path, *extra: str):
    """A TCP server of `db`: (port, token file, process)."""
    port = free_port()
    token = folder / f"{port}.token"
    proc = start_server(
        db, folder / "unused.sock", "--port", str(port), "--token-file", str(token), *extra,
        wait_for=token,
    )  # fmt: skip
    return port, token, proc


def stop(proc: subprocess.Popen) -> str:
    proc.terminate()
    _, err = proc.communicate(timeout=60)
    return err


def idle_connections(port: int, n: int) -> list[socket.socket]:
    """`n` connections that send nothing, each established (in the server's accept
    queue, in this order) before the next is opened."""
    return [socket.create_connection(("127.0.0.1", port), timeout=60) for _ in range(n)]


def lines_until_closed(s: socket.socket) -> list[dict]:
    data = b""
    while True:
        try:
            chunk = s.recv(65536)
        except ConnectionResetError:
            break
        if not chunk:
            break
        data += chunk
    return [json.loads(x) for x in data.splitlines()]


def test_idle_unauthenticated_connections_do_not_starve_a_client(
    tcp_map: Path, tmp_path: Path, samples: Path, expected: list[dict]
) -> None:
    # A deadline far past the test: no idle connection leaves by expiring, so what
    # lets the client in is the quota of its own, not a timeout racing the test.
    port, token, proc = tcp_server(
        tcp_map, tmp_path, "--auth-timeout", "600", "--max-pending", str(PENDING),
        "--max-clients", "5",
    )  # fmt: skip
    idle = []
    try:
        idle = idle_connections(port, N_IDLE)
        t0 = time.monotonic()
        with Client(port=port, token_file=token) as first:
            rows = first.query(samples / QUERIES[0], topk=3)
            took = time.monotonic() - t0
            assert rows == expected
            assert took < ANSWERED_WITHIN, took
            # Accepted in order, each past the quota closes the one waiting longest:
            # the first N_IDLE - PENDING made room for later ones, and one more for the
            # client. Each was told why, in one line.
            evicted = N_IDLE - PENDING + 1
            for s in idle[:evicted]:
                replies = lines_until_closed(s)
                assert len(replies) == 1 and replies[0]["ok"] is False, replies
                assert "busy" in replies[0]["error"] and "--max-pending" in replies[0]["error"]
            # The rest still wait, answered nothing: never refused, never timed out.
            readable, _, _ = select.select(idle[evicted:], [], [], 0)
            assert readable == []
            # And they take none of the clients' slots: all 5 are there for clients.
            more = [Client(port=port, token_file=token) for _ in range(4)]
            try:
                assert all(c.ping() for c in more) and first.ping()
            finally:
                for c in more:
                    c.close()
    finally:
        for s in idle:
            s.close()
        stop(proc)


def test_a_connection_without_the_token_is_closed_at_its_deadline(
    tcp_map: Path, tmp_path: Path
) -> None:
    port, token, proc = tcp_server(tcp_map, tmp_path, "--auth-timeout", "1")
    try:
        for first in (b"", b'{"op": "auth", "tok'):  # nothing; half a line, never ended
            t0 = time.monotonic()  # before the server can have accepted it
            s = socket.create_connection(("127.0.0.1", port), timeout=60)
            s.sendall(first)
            assert lines_until_closed(s) == []  # no byte of answer
            took = time.monotonic() - t0
            s.close()
            assert 1.0 <= took < 30, (first, took)  # its deadline, not --read-timeout's 30 s
        with Client(port=port, token_file=token) as c:  # a client with it still gets in
            assert c.ping()
    finally:
        stop(proc)


def test_a_full_tcp_server_says_it_is_full(tcp_map: Path, tmp_path: Path) -> None:
    port, token, proc = tcp_server(tcp_map, tmp_path, "--max-clients", "1")
    try:
        with Client(port=port, token_file=token) as first:
            assert first.ping()
            with pytest.raises(ClientError) as info:
                Client(port=port, token_file=token)
            msg = str(info.value)
            assert "the server is full: 1 clients are connected" in msg
            assert "--max-clients" in msg and "token" not in msg
            assert first.ping()  # the client in is not disturbed
        # Its slot comes back once the server has seen it close.
        deadline = time.monotonic() + 60
        while True:
            try:
                with Client(port=port, token_file=token) as c:
                    assert c.ping()
                break
            except ClientError as exc:
                assert "full" in str(exc) and time.monotonic() < deadline
                time.sleep(0.1)
    finally:
        stop(proc)


def test_the_command_line_client_says_full_in_one_line(tcp_map: Path, tmp_path: Path) -> None:
    port, token, proc = tcp_server(tcp_map, tmp_path, "--max-clients", "1")
    try:
        with Client(port=port, token_file=token) as first:
            assert first.ping()
            res = client_cli("--port", str(port), "--token-file", str(token), "x.bin")
        assert res.returncode == 1
        assert res.stderr.count("\n") == 1 and "the server is full" in res.stderr
    finally:
        stop(proc)


def client_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "disco_cli.service.client", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


# -- TLS -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def certificate(tmp_path_factory) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key (PEM), by the openssl CLI."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("no openssl command to make a certificate with")
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    res = subprocess.run(
        [openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
         "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost",
         "-keyout", str(key), "-out", str(cert)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    if res.returncode != 0:
        pytest.skip(f"openssl could not make a certificate: {res.stderr.strip()[-200:]}")
    return cert, key


@pytest.fixture(scope="module")
def tls_server(tcp_map: Path, certificate, tmp_path_factory):
    cert, key = certificate
    folder = tmp_path_factory.mktemp("tls-server")
    port, token, proc = tcp_server(tcp_map, folder, "--tls-cert", str(cert), "--tls-key", str(key))
    yield port, token, cert
    err = stop(proc)
    assert "Traceback" not in err


def test_a_round_trip_over_tls(tls_server, samples: Path, expected: list[dict]) -> None:
    port, token, cert = tls_server
    with Client(port=port, token_file=token, tls_ca=cert) as c:
        assert c.query(samples / QUERIES[0], topk=3) == expected
        assert c._sock.version() in ("TLSv1.2", "TLSv1.3")  # encrypted, not plain
    res = client_cli(
        "--port", str(port), "--token-file", str(token), "--tls-ca", str(cert), "-k", "3",
        str(samples / QUERIES[0]),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["rows"] == expected


def test_a_client_without_the_ca_is_refused_in_one_line(tls_server, samples: Path) -> None:
    port, token, _ = tls_server
    with pytest.raises(ClientError, match="TLS certificate is not trusted") as info:
        Client(port=port, token_file=token, tls=True)  # the system's CAs only
    assert "\n" not in str(info.value) and "--tls-ca" in str(info.value)
    res = client_cli("--port", str(port), "--token-file", str(token), "--tls", "x.bin")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert res.stderr.count("\n") == 1 and "not trusted" in res.stderr
    # Plain text to a TLS server: the token is never taken, and the message says TLS.
    with pytest.raises(ClientError, match="TLS"):
        Client(port=port, token_file=token)
    with Client(port=port, token_file=token, tls_ca=tls_server[2]) as c:
        assert c.ping()  # the server went on


def test_a_tls_connection_must_show_the_token_too(tls_server) -> None:
    port, token, cert = tls_server
    ctx = ssl.create_default_context(cafile=str(cert))
    raw = socket.create_connection(("127.0.0.1", port), timeout=60)
    with ctx.wrap_socket(raw, server_hostname="127.0.0.1") as s:
        s.sendall(b'{"op": "auth", "token": "not-it"}\n{"op": "ping"}\n')
        try:
            got = s.recv(100)
        except ConnectionResetError:  # closed with bytes unread: no answer either
            got = b""
        assert got == b""


# -- the command line: TLS and hosts ---------------------------------------------------


def serve_fails(*args: str) -> str:
    res = CliRunner().invoke(app, ["serve", *args])
    assert res.exit_code != 0, res.output
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert len(res.output.strip().splitlines()) == 1, res.output  # one line
    return " ".join(res.output.split())


def test_a_non_loopback_host_needs_tls_or_an_explicit_risk(tcp_map: Path) -> None:
    port = str(free_port())
    out = serve_fails("--db", str(tcp_map), "--port", port, "--host", "0.0.0.0")
    assert "--tls-cert" in out and "--insecure-plaintext" in out and "in clear" in out


def test_tls_options_are_checked(tcp_map: Path, tmp_path: Path, certificate) -> None:
    cert, key = certificate
    port = str(free_port())
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate\n")
    out = serve_fails("--db", str(tcp_map), "--port", port, "--tls-cert", str(junk))
    assert f"{junk}: cannot load the TLS certificate" in out
    out = serve_fails("--db", str(tcp_map), "--port", port, "--tls-cert", str(cert),
                      "--tls-key", str(junk))  # fmt: skip
    assert "cannot load the TLS certificate and its key" in out
    out = serve_fails("--db", str(tcp_map), "--socket", str(tmp_path / "s.sock"),
                      "--tls-cert", str(cert))  # fmt: skip
    assert "--port only" in out
    out = serve_fails("--db", str(tcp_map), "--port", port, "--tls-key", str(key))
    assert "--tls-cert" in out


def test_the_library_refuses_a_plaintext_network_host_too() -> None:
    with pytest.raises(DiscoError, match="--insecure-plaintext"):
        make_server(object(), host="0.0.0.0", port=free_port(), net=NetOptions(token="t"))


# -- the work of one request and the files it may read ---------------------------------


@pytest.fixture()
def icp_calls(monkeypatch) -> list:
    """Every relative pose (ICP run) estimated from here on."""
    calls: list = []
    real = relative_pose.estimate_relative_pose

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(relative_pose, "estimate_relative_pose", counted)
    return calls


def test_one_request_asks_for_a_bounded_number_of_poses(
    tcp_map: Path, samples: Path, icp_calls: list
) -> None:
    scan = str(samples / QUERIES[0])

    def work(service: QueryService, **fields) -> tuple[dict, int]:
        """The reply to a request for `scan`, and the ICP runs it took."""
        before = len(icp_calls)
        reply = service.handle_line(json.dumps({"scan": scan, **fields}).encode())
        return reply, len(icp_calls) - before

    with Map.open(tcp_map) as m:
        default = QueryService(m, ServeOptions(scan_root=samples))
        for field in ("pose", "verify"):
            reply, runs = work(default, topk=MAX_POSES + 1, **{field: True})
            assert reply["ok"] is False and f"at most {MAX_POSES}" in reply["error"]
            assert "--max-poses" in reply["error"] and runs == 0  # refused before any work
        # Without poses a large topk is only a search (the map has 20 scans), and costs
        # what a top 1 costs (the best match's yaw).
        plain, base = work(default, topk=1)
        reply, runs = work(default, topk=5000)
        assert plain["ok"] and reply["ok"] and len(reply["rows"]) == 20 and runs == base
        three = QueryService(m, ServeOptions(scan_root=samples, max_poses=3))
        reply, runs = work(three, topk=3, pose=True)
        assert reply["ok"] and len(reply["rows"]) == 3 and runs == base + 3
        reply, runs = work(three, topk=4, pose=True)
        assert reply["ok"] is False and "at most 3" in reply["error"] and runs == 0


def test_the_command_line_bounds_poses_per_request(tcp_map: Path, samples: Path) -> None:
    sock = tcp_map.parent / "poses.sock"
    proc = start_server(tcp_map, sock, "--max-poses", "2")
    try:
        with Client(socket=sock) as c:
            assert len(c.query(samples / QUERIES[0], topk=2, pose=True)) == 2
            reply = c.request({"scan": str(samples / QUERIES[0]), "topk": 3, "pose": True})
        assert reply["ok"] is False and "at most 2" in reply["error"]
    finally:
        stop(proc)


def test_a_library_server_without_a_scan_root_reads_no_file(
    tcp_map: Path, samples: Path, monkeypatch
) -> None:
    """`ServeOptions()` has no scan root: a request's scan file is never opened (no
    `open` audit event for it), and inline points are still answered."""
    scan = samples / QUERIES[0]
    points = read_scan(str(scan))
    opened: list[str] = []
    watching = [False]

    def audit(event: str, args: tuple) -> None:
        if watching[0] and event == "open" and args and str(args[0]).endswith(scan.name):
            opened.append(str(args[0]))

    sys.addaudithook(audit)
    with Map.open(tcp_map) as m:
        service = QueryService(m, ServeOptions())
        watching[0] = True
        try:
            for path in (str(scan), scan.name, "/etc/hostname"):
                reply = service.handle_line(json.dumps({"scan": path}).encode())
                assert reply["ok"] is False and "reads no scan files" in reply["error"]
        finally:
            watching[0] = False
        assert opened == []
        field = {"shape": list(points.shape), "data": base64.b64encode(points.tobytes()).decode()}
        reply = service.handle_line(json.dumps({"points": field, "topk": 1}).encode())
        assert reply["ok"] and reply["rows"]
        # The audit hook does see a read where one is allowed: the check is live.
        rooted = QueryService(m, ServeOptions(scan_root=samples))
        watching[0] = True
        try:
            assert rooted.handle_line(json.dumps({"scan": str(scan)}).encode())["ok"]
        finally:
            watching[0] = False
        assert opened, "the audit hook saw no read of an allowed scan"


# -- the client against a scripted server ----------------------------------------------


def scripted_server(replies: list[bytes]) -> tuple[int, list[bytes], threading.Thread]:
    """A one-thread TCP server: connection i gets its first line answered with
    `replies[i]` (then closed, unless the reply is ok: then a ping is answered too).
    Returns (port, the first lines received, its thread)."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    got: list[bytes] = []

    def run() -> None:
        with listener:
            for reply in replies:
                conn, _ = listener.accept()
                with conn, conn.makefile("rb") as f:
                    got.append(f.readline())
                    conn.sendall(reply)
                    if b'"ok": true' in reply:
                        f.readline()
                        conn.sendall(b'{"id": 2, "ok": true, "op": "ping"}\n')

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return port, got, thread


BUSY = (
    b'{"id": null, "ok": false, "busy": true, "error": "the server is busy: 16 newer '
    b'connections are waiting to show the token (disco serve --max-pending); try again"}\n'
)


def test_a_client_closed_to_make_room_connects_again() -> None:
    port, got, thread = scripted_server([BUSY, BUSY, b'{"id": 1, "ok": true, "op": "auth"}\n'])
    with Client(port=port, token="t", connect_timeout=60) as c:
        assert c.ping()
    thread.join(timeout=60)
    assert [json.loads(line)["op"] for line in got] == ["auth"] * 3  # it asked three times


def test_a_client_kept_busy_gives_up_at_its_connect_timeout() -> None:
    port, got, thread = scripted_server([BUSY] * 1000)
    t0 = time.monotonic()
    with pytest.raises(ClientError, match="the server is busy") as info:
        Client(port=port, token="t", connect_timeout=0.5)
    # It kept asking until its timeout was nearly spent (it stops when the next wait,
    # at most 0.2 s, would pass it), not at the first busy line.
    assert 0.3 < time.monotonic() - t0 < 30 and len(got) >= 1
    assert not isinstance(info.value, ServerError) and "\n" not in str(info.value)


@pytest.mark.parametrize("tls", [False, True], ids=["plain", "tls"])
def test_more_clients_at_once_than_the_waiting_quota_are_all_answered(
    tcp_map: Path, tmp_path: Path, request, tls: bool
) -> None:
    """40 clients with the token connecting together, past --max-pending 1: those
    closed to make room for newer ones are told so (over TLS too, where one displaced
    in its handshake finishes it first) and connect again, and every one is answered."""
    extra, ca = [], None
    if tls:
        cert, key = request.getfixturevalue("certificate")
        extra, ca = ["--tls-cert", str(cert), "--tls-key", str(key)], cert
    port, token, proc = tcp_server(tcp_map, tmp_path, "--max-pending", "1", *extra)
    try:

        def ask(i: int) -> bool:
            with Client(port=port, token_file=token, tls_ca=ca, connect_timeout=120) as c:
                return c.request({"op": "ping", "id": i})["id"] == i

        got = together(40, ask)
    finally:
        err = stop(proc)
    assert got == [True] * 40, [g for g in got if g is not True][:3]
    assert "Traceback" not in err
