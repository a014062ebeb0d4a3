"""`disco serve`'s socket side: connections in, request lines to the `QueryService`
(disco_cli/service/serve.py), reply lines out.

What one client can take is bounded: the clients connected at once (`max_clients`;
one more is told the server is full), the bytes of requests held in memory across all
connections (`max_buffer_bytes`), the time a request line may take to arrive
(`read_timeout`) and a connection may sit idle (`idle_timeout`).

Over TCP a connection's first line must be `{"op": "auth", "token": "<the token
file's contents>"}` (after the TLS handshake, with `tls`): a wrong token or any other
line closes it without a byte of answer. Until it has shown the token a connection
is only waiting: it holds none of the `max_clients` slots, but one of `max_pending`
of its own, for at most `auth_timeout` seconds from its arrival. When they are all
taken, the one waiting longest is closed to make room (with a "busy" line), so
connections that never show a token cannot keep out a client that has it.
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import json
import os
import secrets
import select
import signal
import socket
import socketserver
import ssl
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from disco_cli.errors import DiscoError

__all__ = [
    "NetOptions",
    "is_loopback",
    "make_server",
    "serve_forever",
    "tls_context",
    "write_token",
]

_CHUNK = 64 * 1024
_AUTH_LINE_BYTES = 4096  # what an unauthenticated client may make the server hold
# A TLS handshake is looked at this often for a displacement, and given this much more
# time once displaced (to say so in a line its client can read).
_HANDSHAKE_SLICE = 0.2
_HANDSHAKE_GRACE = 1.0


@dataclass
class NetOptions:
    """Limits on the connections (seconds, bytes; None: no limit)."""

    max_clients: int = 64  # clients connected at once (over TCP: past the token)
    max_buffer_bytes: int = 256 * 1024 * 1024
    read_timeout: float = 30.0
    idle_timeout: float | None = 600.0
    auth_timeout: float = 5.0  # TCP: from arrival to the token, the TLS handshake included
    max_pending: int = 16  # TCP: connections that have not shown the token yet
    token: str | None = None  # TCP: the credential of the first line
    tls: ssl.SSLContext | None = None  # TCP: a server-side context (`tls_context`)
    insecure_plaintext: bool = False  # TCP: a non-loopback host without `tls` is allowed


class _Refused(Exception):
    """The connection cannot go on: its one error line (then it is closed)."""


class _Closed(Exception):
    """The connection ended, or went quiet for good."""


class _Budget:
    """The request bytes held across all connections, bounded."""

    def __init__(self, limit: int):
        self.limit = limit
        self.used = 0
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        with self._lock:
            if self.used + n > self.limit:
                return False
            self.used += n
            return True

    def give(self, n: int) -> None:
        with self._lock:
            self.used -= n


class _LineReader:
    """Request lines from one socket. Every byte it holds (the line being read, lines
    read ahead, the line being answered until `release`) is taken from the budget."""

    def __init__(self, sock: socket.socket, budget: _Budget):
        self.sock = sock
        self.budget = budget
        self.buf = bytearray()
        self.held = 0

    def line(
        self, limit: int, idle: float | None, read: float, deadline: float | None = None
    ) -> bytes:
        """The next line (`limit` bytes at most), waiting `idle` s for its first byte
        and `read` s from there for the rest; by the monotonic time `deadline` at the
        latest, if given (then `_Closed`)."""
        scanned = 0
        started = None if not self.buf else time.monotonic()
        while True:
            end = self.buf.find(b"\n", scanned)
            if end > limit or (end < 0 and len(self.buf) > limit):
                raise _Refused(f"the request is longer than {limit} bytes; closing")
            if end >= 0:
                line = bytes(self.buf[: end + 1])
                del self.buf[: end + 1]
                return line  # still held: `release` it once answered
            scanned = len(self.buf)
            if started is None:
                wait = idle
            else:
                wait = started + read - time.monotonic()
                if wait <= 0:
                    raise _Refused(f"the request line took more than {read:g} s; closing")
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise _Closed
                wait = left if wait is None else min(wait, left)
            if not self.budget.take(_CHUNK):
                raise _Refused(
                    "the server holds as many request bytes as it may "
                    "(disco serve --max-buffer-mb); try again later"
                )
            try:
                self.sock.settimeout(wait)
                data = self.sock.recv(_CHUNK)
            except socket.timeout:
                data = None
            except OSError:
                data = b""
            self.budget.give(_CHUNK - len(data or b""))  # what came is held from here on
            if data is None:
                if started is None:
                    raise _Closed  # idle too long: the client reconnects when it needs to
                continue  # the line's deadline is checked above
            if not data:
                raise _Closed
            self.held += len(data)
            self.buf += data
            if started is None:
                started = time.monotonic()

    def release(self, n: int) -> None:
        self.held -= n
        self.budget.give(n)

    def close(self) -> None:
        self.budget.give(self.held)
        self.held = 0
        self.buf.clear()


def _gone(sock: socket.socket, tcp: bool) -> bool:
    """Whether the client has closed its connection. On a Unix socket a half-closed
    one (the client only stopped sending) is told apart; over TCP it looks the same."""
    poller = select.poll()
    poller.register(sock, select.POLLIN | select.POLLRDHUP)
    events = poller.poll(0)
    flags = events[0][1] if events else 0
    if flags & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
        return True
    return tcp and bool(flags & select.POLLRDHUP)


class _Handler(socketserver.BaseRequestHandler):
    """One connection: request lines in, reply lines out, until the client closes."""

    def handle(self) -> None:
        server = self.server
        net: NetOptions = server.net  # type: ignore[attr-defined]
        service = server.service  # type: ignore[attr-defined]
        sock: socket.socket = self.request
        tcp = sock.family != socket.AF_UNIX
        reader = _LineReader(sock, server.budget)  # type: ignore[attr-defined]

        def alive() -> bool:
            return not _gone(sock, tcp)

        try:
            if net.token is not None and not self._admitted(reader, net):
                return
            limit = service.options.max_request_bytes
            while True:
                try:
                    line = reader.line(limit, net.idle_timeout, net.read_timeout)
                except _Closed:
                    return
                except _Refused as exc:
                    self._send({"id": None, "ok": False, "error": str(exc)}, net)
                    return  # the rest of the line cannot be told from the next request
                try:
                    reply = service.submit(line, alive)
                finally:
                    reader.release(len(line))
                if reply is None or not self._send(reply, net):
                    return
        finally:
            reader.close()

    def _admitted(self, reader: _LineReader, net: NetOptions) -> bool:
        """Whether this TCP connection becomes a client: its TLS handshake (with `tls`)
        and an `auth` line with the token, by its deadline, and a free client slot.
        A wrong token gets no byte back; a full server, or a connection closed to make
        room for a newer one while it waited, gets one line saying so."""
        slots: _Slots = self.server.slots  # type: ignore[attr-defined]
        sock = self.request
        deadline = slots.arrived(sock) + net.auth_timeout
        try:
            if isinstance(sock, ssl.SSLSocket) and not self._handshake(sock, slots, deadline):
                return False
            verdict, rid = self._token(reader, net, deadline)
        except OSError:  # the handshake failed, or was cut off
            return False
        if not verdict and verdict is not None:
            return False
        admitted = slots.admit(sock) if verdict else None
        if admitted is None:  # no token by the deadline, or closed to make room
            if slots.was_evicted(sock):
                self._send(_busy_reply(net, rid), net)
            return False
        if not admitted:
            self._send({"id": rid, "ok": False, "error": _full(net)}, net)
            return False
        return self._send({"id": rid, "ok": True, "op": "auth"}, net)

    def _handshake(self, sock: ssl.SSLSocket, slots: _Slots, deadline: float) -> bool:
        """Whether the TLS handshake completed by `deadline`, and the connection still
        waits for its token. One closed to make room meanwhile is not cut off in its
        handshake (a client could not tell that from a wrong token): it gets a second
        more to finish it, and then the "busy" line."""
        until = deadline
        while True:
            now = time.monotonic()
            if until == deadline and slots.was_evicted(sock):
                until = min(deadline, now + _HANDSHAKE_GRACE)
            if now >= until:
                return False
            sock.settimeout(min(until - now, _HANDSHAKE_SLICE))
            try:
                sock.do_handshake()
                break
            except TimeoutError:  # not done yet: look again whether it was displaced
                continue
        if slots.handshaken(sock):
            return True
        self._send(_busy_reply(self.server.net, None), self.server.net)  # type: ignore[attr-defined]
        return False

    def _token(
        self, reader: _LineReader, net: NetOptions, deadline: float
    ) -> tuple[bool | None, Any]:
        """(True, its id) for an `auth` line with the token; (False, None) for any
        other line; (None, None) when none came by `deadline`."""
        try:
            line = reader.line(_AUTH_LINE_BYTES, None, net.auth_timeout, deadline)
        except _Closed:
            return None, None
        except _Refused:  # longer than an auth line may be
            return False, None
        reader.release(len(line))
        try:
            request = json.loads(line)
        except Exception:  # not JSON, nested too deeply: no answer either way
            return False, None
        if not isinstance(request, dict) or request.get("op") != "auth":
            return False, None
        token = request.get("token")
        if not isinstance(token, str) or not hmac.compare_digest(
            token.encode(), str(net.token).encode()
        ):
            return False, None
        rid = request.get("id")
        rid = rid if isinstance(rid, (int, str)) and not isinstance(rid, bool) else None
        return True, rid

    def _send(self, reply: dict[str, Any], net: NetOptions) -> bool:
        try:
            self.request.settimeout(net.read_timeout)  # a client that never reads
            self.request.sendall(json.dumps(reply).encode() + b"\n")
            return True
        except OSError:  # the client went away
            return False


def _full(net: NetOptions) -> str:
    return (
        f"the server is full: {net.max_clients} clients are connected "
        "(disco serve --max-clients); try again later"
    )


def _busy_reply(net: NetOptions, rid: Any) -> dict[str, Any]:
    """The line to a connection closed to make room ("busy": it may try again at once)."""
    error = (
        f"the server is busy: {net.max_pending} newer connections are waiting to show "
        "the token (disco serve --max-pending); try again"
    )
    return {"id": rid, "ok": False, "error": error, "busy": True}


class _Slots:
    """Who holds the server's connections: at most `max_clients` clients, and over
    TCP at most `max_pending` connections that have not shown the token yet (kept
    apart, so that they never take a client's slot). A waiting connection past the
    quota makes room by closing the one waiting longest."""

    def __init__(self, max_clients: int, max_pending: int):
        self.max_clients = max_clients
        self.max_pending = max_pending
        self.clients: set[Any] = set()
        self.waiting: dict[Any, float] = {}  # in order of arrival: the oldest first
        self.evicted: set[Any] = set()
        self.shaking: set[Any] = set()  # TLS connections still in their handshake
        self.arrival: dict[Any, float] = {}
        self._lock = threading.Lock()

    def join(self, sock: Any) -> bool:
        """A connection that needs no token: a client now, unless the server is full."""
        with self._lock:
            if len(self.clients) >= self.max_clients:
                return False
            self.clients.add(sock)
            return True

    def wait(self, sock: Any, tls: bool) -> Any:
        """A connection that must show the token first; the one it displaces, if that
        must be woken (a TLS handshake is not: its thread looks for itself)."""
        with self._lock:
            victim = None
            if len(self.waiting) >= self.max_pending:
                victim = next(iter(self.waiting))
                del self.waiting[victim]
                self.evicted.add(victim)
                if victim in self.shaking:
                    victim = None
            now = time.monotonic()
            self.waiting[sock] = now
            self.arrival[sock] = now
            if tls:
                self.shaking.add(sock)
            return victim

    def handshaken(self, sock: Any) -> bool:
        """A TLS connection's handshake is done: whether it still waits (not displaced)."""
        with self._lock:
            self.shaking.discard(sock)
            return sock not in self.evicted

    def arrived(self, sock: Any) -> float:
        with self._lock:
            return self.arrival.get(sock, time.monotonic())

    def was_evicted(self, sock: Any) -> bool:
        with self._lock:
            return sock in self.evicted

    def admit(self, sock: Any) -> bool | None:
        """A connection that showed the token: a client now (True), unless the server
        is full (False) or it was closed to make room before (None: its reading side
        is shut down, so it cannot go on; the client connects again)."""
        with self._lock:
            if sock in self.evicted:
                return None
            self.waiting.pop(sock, None)
            if len(self.clients) >= self.max_clients:
                return False
            self.clients.add(sock)
            return True

    def leave(self, sock: Any) -> None:
        with self._lock:
            self.clients.discard(sock)
            self.waiting.pop(sock, None)
            self.evicted.discard(sock)
            self.shaking.discard(sock)
            self.arrival.pop(sock, None)


class _Limited(socketserver.ThreadingMixIn):
    """A thread per connection: `net.max_clients` clients, and over TCP
    `net.max_pending` connections waiting to show the token besides (`_Slots`)."""

    daemon_threads = True
    request_queue_size = 256  # the listen backlog: a fleet connecting at once waits there

    def setup_limits(self, service: Any, net: NetOptions) -> None:
        self.service = service
        self.net = net
        self.budget = _Budget(net.max_buffer_bytes)
        self.slots = _Slots(net.max_clients, net.max_pending)

    def get_request(self) -> tuple[Any, Any]:
        conn, addr = super().get_request()  # type: ignore[misc]
        if self.net.tls is not None:  # the handshake is the connection's thread's work
            conn = self.net.tls.wrap_socket(conn, server_side=True, do_handshake_on_connect=False)
        return conn, addr

    def verify_request(self, request: Any, client_address: Any) -> bool:
        if self.net.token is not None:
            victim = self.slots.wait(request, self.net.tls is not None)
            if victim is not None:
                try:  # its thread wakes at end of stream, says why, and closes it
                    socket.socket.shutdown(victim, socket.SHUT_RD)
                except OSError:
                    pass
            return True
        if self.slots.join(request):
            return True
        # The Unix socket's clients are this user's: tell them why.
        full = {"id": None, "ok": False, "error": _full(self.net)}
        try:
            request.settimeout(1.0)
            request.sendall(json.dumps(full).encode() + b"\n")
        except OSError:
            pass
        return False

    def process_request(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request(request, client_address)  # type: ignore[misc]
        except BaseException:
            self.slots.leave(request)
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)  # type: ignore[misc]
        finally:
            self.slots.leave(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        print(f"disco serve: a connection failed ({exc!r})", file=sys.stderr)


class _UnixServer(_Limited, socketserver.UnixStreamServer):
    """Bound under a private name and moved into place once it listens: a client that
    sees the socket file is never refused by a server still between bind and listen."""

    def server_bind(self) -> None:
        self._final_path = str(self.server_address)
        self.server_address = f"{self._final_path}.{os.getpid()}.binding"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.server_address)
        super().server_bind()

    def server_activate(self) -> None:
        super().server_activate()
        os.replace(self.server_address, self._final_path)
        self.server_address = self._final_path


class _TCPServer(_Limited, socketserver.TCPServer):
    allow_reuse_address = True


def make_server(
    service: Any,
    *,
    socket_path: str | Path | None = None,
    host: str = "127.0.0.1",
    port: int | None = None,
    net: NetOptions | None = None,
) -> socketserver.BaseServer:
    """A threading server for `service` on a Unix socket (created with mode 0600; a
    stale socket file left by a dead server is replaced) or a TCP port (`net.token`
    required of every connection; a host other than a loopback address needs
    `net.tls`, or `net.insecure_plaintext` to take the risk)."""
    if (socket_path is None) == (port is None):
        raise DiscoError("serve: give a socket path or a port, not both")
    net = net or NetOptions()
    if net.max_clients < 1 or net.max_pending < 1 or not net.auth_timeout > 0:
        raise DiscoError("serve: max_clients and max_pending must be >= 1, auth_timeout > 0")
    if socket_path is not None and net.tls is not None:
        raise DiscoError("serve: TLS is for a TCP port; a Unix socket is guarded by its mode")
    if port is not None and net.tls is None and not net.insecure_plaintext:
        if not is_loopback(host):
            raise DiscoError(
                f"{host}: not a loopback address, and without TLS the token and the scans "
                "would cross the network in clear: give --tls-cert and --tls-key (or "
                "--insecure-plaintext to accept the risk)"
            )
    server: _Limited
    if socket_path is not None:
        path = Path(socket_path)
        if path.exists() or path.is_symlink():
            if not path.is_socket():
                raise DiscoError(f"{path}: exists and is not a socket; choose another --socket")
            if _socket_alive(path):
                raise DiscoError(f"{path}: another server is listening there")
            path.unlink()
        if not path.parent.is_dir():
            raise DiscoError(f"{path}: folder {path.parent} does not exist")
        old = os.umask(0o177)  # only this user may connect
        try:
            server = _UnixServer(str(path), _Handler)
        except OSError as exc:
            raise DiscoError(f"{path}: cannot listen there ({exc.strerror})") from None
        finally:
            os.umask(old)
        net = NetOptions(**{**net.__dict__, "token": None})  # the file's mode is the check
    else:
        if not net.token:
            raise DiscoError("serve: a TCP port needs a token")
        try:
            server = _TCPServer((host, port), _Handler)
        except OSError as exc:
            raise DiscoError(f"{host}:{port}: cannot listen there ({exc.strerror})") from None
    server.setup_limits(service, net)
    return server  # type: ignore[return-value]


def is_loopback(host: str) -> bool:
    """Whether `host` is `localhost` or a loopback address (nothing else is resolved)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def tls_context(cert: str | Path, key: str | Path | None = None) -> ssl.SSLContext:
    """A server-side TLS context (TLS 1.2 or later) with the certificate chain of `cert`
    (PEM) and its private key (`key`, or in `cert` itself)."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    # A waiting connection closed to make room is woken by shutting down its reading
    # side; taken as the end of the stream rather than an error, the connection can
    # still send its one "busy" line. (A request is acted on only once its whole line
    # is in, so a stream cut short is never mistaken for a request.)
    ctx.options |= getattr(ssl, "OP_IGNORE_UNEXPECTED_EOF", 0)
    try:
        ctx.load_cert_chain(str(cert), None if key is None else str(key))
    except OSError as exc:  # ssl.SSLError among them
        why = getattr(exc, "reason", None) or exc.strerror or str(exc)  # "PEM lib", say
        where = str(cert) if key is None else f"{cert}, {key}"
        raise DiscoError(
            f"{where}: cannot load the TLS certificate and its key ({why}); "
            "both must be PEM files, the key matching the certificate"
        ) from None
    return ctx


def _socket_alive(path: Path) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(0.5)
        s.connect(str(path))
        return True
    except OSError:
        return False
    finally:
        s.close()


def write_token(path: str | Path) -> str:
    """A new random token, written to `path` with mode 0600 (replacing what was there,
    never through a link)."""
    token = secrets.token_urlsafe(32)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise DiscoError(f"{path}: cannot write the token file ({exc.strerror})") from None
    return token


def _remove_token(path: Path, token: str) -> None:
    try:
        if path.read_text().strip() == token:  # not one a newer server wrote since
            path.unlink()
    except OSError:
        pass


def serve_forever(
    server: socketserver.BaseServer,
    on_ready: Callable[[], None],
    token_file: Path | None = None,
) -> None:
    """Serve until Ctrl-C or SIGTERM (either returns, after the query in hand): connections on
    background threads, queries on this one. The socket file and the token file are
    removed on the way out."""
    service = server.service  # type: ignore[attr-defined]
    stop = threading.Event()
    listener = threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True
    )
    listener.start()
    old = None
    if threading.current_thread() is threading.main_thread():
        # A service manager stops servers with SIGTERM: leave as cleanly as on Ctrl-C.
        # Ctrl-C is taken the same way, whatever disposition the server inherited (a
        # shell's background job starts with SIGINT ignored, and Python keeps that).
        old = {
            sig: signal.signal(sig, lambda *_: stop.set())
            for sig in (signal.SIGTERM, signal.SIGINT)
        }
    try:
        on_ready()
        service.work(stop)
    finally:
        stop.set()
        server.shutdown()
        server.server_close()
        for sig, handler in (old or {}).items():
            signal.signal(sig, handler)
        if isinstance(server, _UnixServer):
            try:
                os.unlink(server.server_address)  # type: ignore[arg-type]
            except OSError:
                pass
        if token_file is not None:
            _remove_token(token_file, server.net.token)  # type: ignore[attr-defined]
