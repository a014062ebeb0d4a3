"""`disco serve`'s socket side: connections in, request lines to the `QueryService`
(disco_cli/service/serve.py), reply lines out.

What one client can take is bounded: the connections open at once (`max_clients`;
one more gets one "busy" line on the Unix socket, nothing over TCP), the bytes of
requests held in memory across all connections (`max_buffer_bytes`), the time a
request line may take to arrive (`read_timeout`) and a connection may sit idle
(`idle_timeout`). Over TCP a connection's first line must be
`{"op": "auth", "token": "<the token file's contents>"}`: anything else, or nothing
within `auth_timeout`, closes it without a byte of answer.
"""

from __future__ import annotations

import hmac
import json
import os
import secrets
import select
import signal
import socket
import socketserver
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from disco_cli.errors import DiscoError

__all__ = ["NetOptions", "make_server", "serve_forever", "write_token"]

_CHUNK = 64 * 1024
_AUTH_LINE_BYTES = 4096  # what an unauthenticated client may make the server hold


@dataclass
class NetOptions:
    """Limits on the connections (seconds, bytes; None: no limit)."""

    max_clients: int = 64
    max_buffer_bytes: int = 256 * 1024 * 1024
    read_timeout: float = 30.0
    idle_timeout: float | None = 600.0
    auth_timeout: float = 10.0
    token: str | None = None  # TCP: the credential of the first line


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

    def line(self, limit: int, idle: float | None, read: float) -> bytes:
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
            if net.token is not None and not self._authorized(reader, net):
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

    def _authorized(self, reader: _LineReader, net: NetOptions) -> bool:
        """Whether the first line is an `auth` request with the token (answered then);
        a connection without it gets no byte back."""
        try:
            line = reader.line(_AUTH_LINE_BYTES, net.auth_timeout, net.auth_timeout)
        except (_Closed, _Refused):
            return False
        reader.release(len(line))
        try:
            request = json.loads(line)
        except Exception:  # not JSON, nested too deeply: no answer either way
            return False
        if not isinstance(request, dict) or request.get("op") != "auth":
            return False
        token = request.get("token")
        if not isinstance(token, str) or not hmac.compare_digest(
            token.encode(), str(net.token).encode()
        ):
            return False
        rid = request.get("id")
        rid = rid if isinstance(rid, (int, str)) and not isinstance(rid, bool) else None
        return self._send({"id": rid, "ok": True, "op": "auth"}, net)

    def _send(self, reply: dict[str, Any], net: NetOptions) -> bool:
        try:
            self.request.settimeout(net.read_timeout)  # a client that never reads
            self.request.sendall(json.dumps(reply).encode() + b"\n")
            return True
        except OSError:  # the client went away
            return False


class _Limited(socketserver.ThreadingMixIn):
    """A thread per connection, up to `net.max_clients` of them."""

    daemon_threads = True
    request_queue_size = 256  # the listen backlog: a fleet connecting at once waits there

    def setup_limits(self, service: Any, net: NetOptions) -> None:
        self.service = service
        self.net = net
        self.budget = _Budget(net.max_buffer_bytes)
        self.active = 0
        self._count = threading.Lock()

    def verify_request(self, request: Any, client_address: Any) -> bool:
        with self._count:
            full = self.active >= self.net.max_clients
            if not full:
                self.active += 1
        if full and self.net.token is None:  # the Unix socket's clients are this user's
            busy = {
                "id": None,
                "ok": False,
                "error": f"the server is busy: {self.net.max_clients} connections are open "
                "(disco serve --max-clients); try again later",
            }
            try:
                request.settimeout(1.0)
                request.sendall(json.dumps(busy).encode() + b"\n")
            except OSError:
                pass
        return not full

    def process_request(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request(request, client_address)  # type: ignore[misc]
        except BaseException:
            self._done()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)  # type: ignore[misc]
        finally:
            self._done()

    def _done(self) -> None:
        with self._count:
            self.active -= 1

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        print(f"disco serve: a connection failed ({exc!r})", file=sys.stderr)


class _UnixServer(_Limited, socketserver.UnixStreamServer):
    pass


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
    required of every connection)."""
    if (socket_path is None) == (port is None):
        raise DiscoError("serve: give a socket path or a port, not both")
    net = net or NetOptions()
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
