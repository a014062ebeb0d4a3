"""A client of `disco serve` (docs/serve.md), in the standard library alone, so that
it starts in a few tens of milliseconds:

    from disco_cli.service.client import Client
    with Client(socket="disco.sock") as c:
        for row in c.query("scans/000123.bin", topk=3):
            print(row["match"], row["distance"], row["yaw_deg"])

and from a shell, one reply line (JSON) per scan path read from the arguments or stdin:

    find scans -name '*.bin' | python -m disco_cli.service.client --socket disco.sock -

A server started with `--allow-append` also adds scans to its map: `c.append(scan)`
(`--append` from a shell).

Over TCP to a server started with `--tls-cert`, give the CA that signed its
certificate (`tls_ca=`, `--tls-ca`; or `tls=True` for the system's CAs).

Scan paths are sent absolute, resolved from this process's folder. Every failure is a
`ClientError` (the server's refusal of one request a `ServerError`, its subclass).
"""

from __future__ import annotations

import argparse
import base64
import errno
import json
import os
import select
import socket as _socket
import struct
import sys
import time
import warnings
from pathlib import Path
from typing import Any

__all__ = ["Client", "ClientError", "ServerError", "TOKEN_FILE_ENV"]

# Where the token of a TCP server is, when the client is not told (docs/serve.md).
TOKEN_FILE_ENV = "DISCO_TOKEN_FILE"


class ClientError(Exception):
    """The server could not be reached or answered nothing usable; the OS error, if
    any, is the cause."""


class ServerError(ClientError):
    """The server refused a request: its one-line reason."""


class _TryAgain(ClientError):
    """Connecting failed in a way that may pass: the server was busy (`cut` 0), or a
    TLS handshake was cut off (`cut` 1; it may also be a server without TLS)."""

    def __init__(self, line: str, cut: int = 0):
        super().__init__(line)
        self.cut = cut


class Client:
    """One connection to a `disco serve` server, on a Unix socket or a TCP port.
    Requests are answered in order; a refused one raises `ServerError` and the
    connection stays usable. A connection the server closed while idle is opened
    again on the next request.

    `connect_timeout`: how long connecting may wait (a server busy with a fleet of
    connects); `timeout`: how long a reply may take (None: forever). Over TCP the
    token is `token`, else the contents of `token_file`, else of the file named by
    $DISCO_TOKEN_FILE, else of `disco-PORT.token` in the current folder (where
    `disco serve --port PORT` writes it by default).

    TLS (a server started with `--tls-cert`): `tls_ca`, the CA file (PEM) that signed
    the server's certificate, which must name `host`; or `tls=True` to trust the
    system's CAs. The handshake is bounded by `connect_timeout`."""

    def __init__(
        self,
        socket: str | Path | None = None,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        timeout: float | None = 60.0,
        connect_timeout: float = 10.0,
        token: str | None = None,
        token_file: str | Path | None = None,
        tls: bool = False,
        tls_ca: str | Path | None = None,
    ):
        if (socket is None) == (port is None):
            raise ClientError("give a socket path or a port")
        if socket is not None and (tls or tls_ca is not None):
            raise ClientError("TLS is for a TCP port; a Unix socket is guarded by its mode")
        self._where: Any = str(socket) if socket is not None else (host, port)
        self._timeout = timeout
        self._connect_timeout = connect_timeout
        self._token = None if port is None else (token or _read_token(port, token_file))
        self._tls = _tls_context(tls_ca) if tls or tls_ca is not None else None
        self._sock: _socket.socket | None = None
        self._reader: Any = None
        self._next_id = 0
        self.warnings: list[str] = []  # those of the last reply
        self._open()

    @property
    def where(self) -> str:
        return self._where if isinstance(self._where, str) else "%s:%s" % self._where

    def _open(self) -> None:
        """Connect (and show the token). A server busy with connections waiting to
        show theirs closed this one to make room: try again, as for a full listen
        queue, until `connect_timeout` is spent; so too, up to 10 times, when a TLS
        handshake is cut off (what such a close looks like before the handshake ends)."""
        deadline = time.monotonic() + self._connect_timeout
        delay, cut = 0.01, 0
        while True:
            try:
                return self._open_once(deadline)
            except _TryAgain as exc:
                cut += exc.cut
                if cut > 10 or time.monotonic() + delay > deadline:
                    raise ClientError(str(exc)) from exc.__cause__
            time.sleep(delay)
            delay = min(delay * 2, 0.2)

    def _open_once(self, deadline: float) -> None:
        sock = _connect(self._where, max(deadline - time.monotonic(), 0.001))
        if self._tls is not None:
            sock = self._handshake(sock, deadline)
        self._sock = sock
        self._sock.settimeout(self._timeout)
        self._reader = self._sock.makefile("rb")
        if self._token is not None:
            reply = self._exchange({"op": "auth", "token": self._token})
            if reply is None:
                self.close()
                hint = "" if self._tls is not None else ", or a server that speaks TLS (tls_ca=)"
                raise ClientError(
                    f"{self.where}: the server closed the connection at the token: a wrong "
                    f"token (a server restarted since writes a new one){hint}?"
                )
            if not reply.get("ok"):  # full, or busy with connections waiting to show one
                self.close()
                line = f"{self.where}: {reply.get('error', 'refused')}"
                if reply.get("busy") is True:
                    raise _TryAgain(line)
                raise ClientError(line)

    def _handshake(self, sock: _socket.socket, deadline: float) -> _socket.socket:
        """`sock` wrapped in TLS, the server's certificate checked against the CA."""
        import ssl  # deferred: only TLS clients pay for ssl (tens of ms)

        host = self._where[0]
        try:
            sock.settimeout(max(deadline - time.monotonic(), 0.001))
            return self._tls.wrap_socket(sock, server_hostname=host)  # type: ignore[union-attr]
        except ssl.SSLCertVerificationError as exc:
            sock.close()
            raise ClientError(
                f"{self.where}: the server's TLS certificate is not trusted "
                f"({exc.verify_message}): give the CA that signed it (tls_ca=, --tls-ca)"
            ) from exc
        except OSError as exc:  # ssl.SSLError and timeouts among them
            sock.close()
            why = getattr(exc, "reason", None) or exc.strerror or type(exc).__name__
            line = (
                f"{self.where}: the TLS handshake failed ({why}): is the server started "
                "with --tls-cert?"
            )
            if isinstance(exc, (ssl.SSLEOFError, ConnectionResetError)):
                raise _TryAgain(line, cut=1) from exc
            raise ClientError(line) from exc

    def close(self) -> None:
        if self._sock is not None:
            self._reader.close()
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _exchange(self, fields: dict[str, Any]) -> dict[str, Any] | None:
        """Send one request; its reply, or None when the connection closed first."""
        assert self._sock is not None
        self._next_id += 1
        line = json.dumps({"id": self._next_id, **fields}).encode() + b"\n"
        try:
            try:
                self._sock.sendall(line)
            except OSError as exc:
                if not (isinstance(exc, (BrokenPipeError, ConnectionResetError)) or _tls_eof(exc)):
                    raise
                # Closed by the server: a line it sent first (full, busy) may still be there.
            reply = self._reader.readline()
        except ConnectionResetError:
            return None
        except OSError as exc:  # a timeout among them
            self.close()  # a late reply must not pass for the next request's
            raise ClientError(f"{self.where}: no reply ({exc})") from exc
        if not reply:
            return None
        try:
            return json.loads(reply)
        except ValueError as exc:
            raise ClientError(f"{self.where}: the reply is not JSON ({exc})") from exc

    def request(self, fields: dict[str, Any]) -> dict[str, Any]:
        """Send one request and return the whole reply (ok or not)."""
        if self._sock is None or _closed_by_peer(self._sock):
            self.close()
            self._open()
        reply = self._exchange(fields)
        if reply is None:
            # Closed while this was sent: the server timed out an idle connection,
            # or was restarted. Queries change nothing and an append of a scan the
            # map holds already adds nothing, so asking again is safe.
            self.close()
            self._open()
            reply = self._exchange(fields)
        if reply is None:
            self.close()
            raise ClientError(f"{self.where}: the server closed the connection")
        self.warnings = list(reply.get("warnings", []))
        for line in self.warnings:
            warnings.warn(f"disco serve: {line}", stacklevel=3)
        return reply

    def query(self, scan: Any, *, topk: int | None = None, pose: bool = False, **fields) -> list:
        """The rows of `disco query --format jsonl` for one scan: a file path (sent
        absolute, read by the server) or an N x 3 / N x 4 array of points (sent
        inline). The reply's warnings are in `self.warnings` and raised as Python
        warnings."""
        req: dict[str, Any] = {**fields, **_scan_fields(scan)}
        if topk is not None:
            req["topk"] = topk
        if pose:
            req["pose"] = True
        reply = self.request(req)
        if not reply.get("ok"):
            raise ServerError(reply.get("error", "refused"))
        return reply["rows"]

    def append(
        self,
        scan: Any,
        *,
        name: str | None = None,
        pose: Any = None,
        time: float | None = None,
        scan_format: str | None = None,
    ) -> dict[str, Any]:
        """Add one scan to the map of a server started with `--allow-append`: a file
        path (sent absolute, read by the server) or an N x 3 / N x 4 array of points
        with its `name` (its path in the map, unique there). `pose`: the sensor's 4 x 4
        pose in the map's frame; `time` in seconds. Returns the reply: `scan_ids` (the
        scan's id, in a list), `added` (0 when the map held it already: a resend adds
        nothing) and `scans` (the map's size now)."""
        item = _append_item({"scan": scan, "name": name, "pose": pose, "time": time})
        return self._append({**item, "scan_format": scan_format})

    def append_many(self, scans: Any, *, scan_format: str | None = None) -> dict[str, Any]:
        """Add several scans in one request, all or none: each a file path, or a dict of
        `append`'s arguments (`scan`, `name`, `pose`, `time`). `scan_ids` are in the
        order given."""
        items = [_append_item(s if isinstance(s, dict) else {"scan": s}) for s in scans]
        return self._append({"scans": items, "scan_format": scan_format})

    def _append(self, fields: dict[str, Any]) -> dict[str, Any]:
        req = {"op": "append", **{k: v for k, v in fields.items() if v is not None}}
        reply = self.request(req)
        if not reply.get("ok"):
            raise ServerError(reply.get("error", "refused"))
        return {k: reply[k] for k in ("scan_ids", "added", "scans")}

    def ping(self) -> bool:
        return bool(self.request({"op": "ping"}).get("ok"))


def _scan_fields(scan: Any) -> dict[str, Any]:
    """A scan as a request sends it: a file path made absolute, or points inline."""
    if isinstance(scan, (str, Path)):
        return {"scan": os.path.abspath(scan)}
    import numpy as np  # deferred: only callers with arrays have numpy to pay for

    pts = np.ascontiguousarray(scan, dtype="<f4")
    return {"points": {"shape": list(pts.shape), "data": base64.b64encode(pts.tobytes()).decode()}}


def _append_item(item: dict[str, Any]) -> dict[str, Any]:
    """One scan of an append request from `Client.append`'s arguments."""
    unknown = sorted(set(item) - {"scan", "name", "pose", "time"})
    if unknown:
        raise ClientError(f"append: unknown field {unknown[0]!r}")
    if item.get("scan") is None:
        raise ClientError("append: give a scan file path or an array of points")
    out = _scan_fields(item["scan"])
    for key in ("name", "time"):
        if item.get(key) is not None:
            out[key] = item[key]
    pose = item.get("pose")
    if pose is not None:
        # A NumPy array or nested sequences, as JSON rows of plain numbers.
        try:
            out["pose"] = [[float(v) for v in row] for row in pose]
        except (TypeError, ValueError) as exc:
            raise ClientError(f"append: 'pose' must be 4 rows of 4 numbers ({exc})") from None
    return out


def _tls_context(ca: str | Path | None) -> Any:
    """A client-side TLS context trusting `ca` (a PEM file), or the system's CAs."""
    import ssl  # deferred: only TLS clients pay for ssl (tens of ms)

    try:
        return ssl.create_default_context(cafile=None if ca is None else str(ca))
    except OSError as exc:  # ssl.SSLError among them
        why = getattr(exc, "reason", None) or exc.strerror or str(exc)  # "PEM lib", say
        raise ClientError(f"{ca}: cannot load the CA file ({why}); it must be PEM") from exc


def _tls_eof(exc: OSError) -> bool:
    """Whether `exc` is a TLS connection found closed by its peer."""
    ssl = sys.modules.get("ssl")
    return ssl is not None and isinstance(exc, (ssl.SSLEOFError, ssl.SSLZeroReturnError))


def _read_token(port: int, token_file: str | Path | None) -> str:
    path = token_file or os.environ.get(TOKEN_FILE_ENV) or f"disco-{port}.token"
    try:
        token = Path(path).read_text().strip()
    except OSError as exc:
        raise ClientError(
            f"{path}: cannot read the server's token ({exc.strerror}); pass "
            f"token_file= (--token-file) or set {TOKEN_FILE_ENV}"
        ) from exc
    if not token:
        raise ClientError(f"{path}: the token file is empty")
    return token


# Connects refused for a moment when a fleet connects at once: wait and try again.
_BUSY = {errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR, errno.ETIMEDOUT}


def _connect(address: Any, timeout: float) -> _socket.socket:
    """A connected socket, after waiting up to `timeout` s for a server whose
    listening queue is full. A Unix socket connects blocking, bounded by SO_SNDTIMEO:
    with a Python timeout it would be non-blocking, and a full queue answers EAGAIN
    at once instead of waiting."""
    unix = isinstance(address, str)
    deadline = time.monotonic() + timeout
    delay = 0.005
    while True:
        left = max(deadline - time.monotonic(), 0.001)
        s = _socket.socket(_socket.AF_UNIX if unix else _socket.AF_INET, _socket.SOCK_STREAM)
        try:
            if unix:
                sec = int(left)
                s.setsockopt(
                    _socket.SOL_SOCKET,
                    _socket.SO_SNDTIMEO,
                    struct.pack("ll", sec, int((left - sec) * 1e6)),
                )
                s.connect(address)
                s.setsockopt(_socket.SOL_SOCKET, _socket.SO_SNDTIMEO, struct.pack("ll", 0, 0))
            else:
                s.settimeout(left)
                s.connect(address)
            return s
        except OSError as exc:
            s.close()
            busy = exc.errno in _BUSY or isinstance(exc, TimeoutError)
            if not busy or time.monotonic() + delay > deadline:
                where = address if unix else "%s:%s" % address
                why = exc.strerror or type(exc).__name__
                if busy:
                    why = f"still busy after {timeout:g} s ({why})"
                raise ClientError(f"{where}: cannot reach the server ({why})") from exc
            time.sleep(delay)
            delay = min(delay * 2, 0.2)


def _closed_by_peer(sock: _socket.socket) -> bool:
    """Whether the server closed this (idle) connection: readable at end of stream
    (under TLS, the raw stream: bytes there, a session ticket say, read as open)."""
    try:
        if getattr(sock, "pending", lambda: 0)():  # TLS bytes read and not yet taken
            return False
        ready, _, _ = select.select([sock], [], [], 0)
        if not ready:
            return False
        peek = _socket.MSG_PEEK | _socket.MSG_DONTWAIT
        return _socket.socket.recv(sock, 1, peek) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


def main(argv: list[str] | None = None) -> int:
    """`python -m disco_cli.service.client`: one JSON reply line per scan path (sent absolute,
    resolved from this process's folder)."""
    ap = argparse.ArgumentParser(
        prog="python -m disco_cli.service.client",
        description="Ask a running `disco serve` about scans (or add them to its map, "
        "--append): one JSON reply line per scan.",
    )
    ap.add_argument("scans", nargs="+", help="scan files, or - to read paths from stdin")
    ap.add_argument("--socket", help="the server's Unix socket (default: disco.sock)")
    ap.add_argument("--port", type=int, help="the server's TCP port instead")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument(
        "--token-file",
        help=f"TCP: the server's token file (default: ${TOKEN_FILE_ENV}, else disco-PORT.token)",
    )
    ap.add_argument(
        "--tls-ca",
        metavar="PEM",
        help="TCP: speak TLS, trusting the server's certificate if this CA signed it",
    )
    ap.add_argument("--tls", action="store_true", help="TCP: speak TLS, trusting the system's CAs")
    ap.add_argument("--topk", "-k", type=int, help="matches per query (server's default)")
    ap.add_argument("--pose", action="store_true", help="add the verified relative pose")
    ap.add_argument(
        "--append",
        action="store_true",
        help="add the scans to the map instead (a server started with --allow-append)",
    )
    args = ap.parse_args(argv)
    if args.append and (args.topk is not None or args.pose):
        ap.error("--topk and --pose are for queries, not --append")
    sock = None if args.port is not None else (args.socket or "disco.sock")
    paths = (
        (line.strip() for line in sys.stdin if line.strip())
        if args.scans == ["-"]
        else iter(args.scans)
    )
    failed = 0
    try:
        with Client(
            sock,
            host=args.host,
            port=args.port,
            token_file=args.token_file,
            tls=args.tls,
            tls_ca=args.tls_ca,
        ) as c:
            for path in paths:
                req: dict[str, Any] = {"scan": os.path.abspath(path)}
                if args.append:
                    req["op"] = "append"
                if args.topk is not None:
                    req["topk"] = args.topk
                if args.pose:
                    req["pose"] = True
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # they are in the reply printed
                    reply = c.request(req)
                failed += not reply.get("ok")
                sys.stdout.write(json.dumps(reply) + "\n")
                sys.stdout.flush()
    except ClientError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        return 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
