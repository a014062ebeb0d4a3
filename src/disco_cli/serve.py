"""`disco serve`'s server: one map and one model, loaded once, answering queries over a
local socket so that programs that ask many times pay the start-up once.

The protocol is JSON lines (docs/serve.md): each request is one JSON object on one
line, each reply one JSON object on one line, in order, over one connection for as
long as the client likes. A query names a scan file or carries the points inline:

    {"id": 7, "scan": "scans/000123.bin", "topk": 3}
    {"id": 8, "points": {"shape": [N, 4], "data": "<base64 of float32 little-endian>"}}

and is answered with the rows `disco query --format jsonl` prints for it:

    {"id": 7, "ok": true, "query": "scans/000123.bin", "rows": [{"query": ..., "rank": 1, ...}]}

A request that cannot be answered (not JSON, too long, an unknown field, a scan that
cannot be read) gets `{"id": ..., "ok": false, "error": "<one line>"}` and the server
goes on. Queries are answered one at a time, on the thread that opened the map (SQLite
connections and the model stay on one thread; one query at a time is also what
keeps latency flat on a shared CPU); connections are read and written concurrently,
so a slow client holds no one up between its requests.

The map is opened read-only; before each query the server looks at the map file's
size and modification time (and its WAL's) and takes a new snapshot when another
process has appended to it.
"""

from __future__ import annotations

import base64
import json
import math
import os
import queue
import signal
import socket
import socketserver
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.columns import POSE_COLUMNS, RESULT_COLUMNS
from disco_cli.errors import DiscoError

__all__ = ["QueryService", "ServeOptions", "make_server", "MAX_REQUEST_BYTES"]

# A 130k-point scan inline is 2.8 MB of base64: 64 MiB leaves room for the largest
# sensors and still bounds what one hostile line can make the server hold.
MAX_REQUEST_BYTES = 64 * 1024 * 1024
_QUERY_FIELDS = {
    "id",
    "op",
    "scan",
    "points",
    "name",
    "topk",
    "pose",
    "verify",
    "max_distance",
    "scan_format",
}
_MAX_TOPK = 10000


class RequestError(DiscoError):
    """A request the server cannot answer: its reply is one error line."""


@dataclass
class ServeOptions:
    """What every request gets unless it says otherwise."""

    topk: int = 10
    max_request_bytes: int = MAX_REQUEST_BYTES


def _plain(value: Any) -> Any:
    """JSON-ready values, as `disco query --format jsonl` writes them."""
    from disco_cli.console import _plain as plain

    return plain(value)


class QueryService:
    """Answers requests against one open map. `handle_line` answers on the calling
    thread; connection threads `submit` lines instead, and the thread that opened the
    map answers them in `work`."""

    def __init__(self, map_: Any, options: ServeOptions | None = None):
        self.map = map_
        self.options = options or ServeOptions()
        self._lock = threading.Lock()
        self._stamp = self._file_stamp()
        self._queue: queue.Queue = queue.Queue()
        self.answered = 0

    def submit(self, line: bytes) -> dict[str, Any]:
        """The reply to `line`, answered by the thread running `work` (blocks)."""
        done: Future = Future()
        self._queue.put((line, done))
        return done.result()

    def work(self, stop: threading.Event) -> None:
        """Answer submitted lines until `stop` is set."""
        while not stop.is_set():
            try:
                line, done = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                done.set_result(self.handle_line(line))
            except BaseException as exc:  # never leave a connection waiting
                done.set_result({"id": None, "ok": False, "error": "internal error"})
                if not isinstance(exc, Exception):
                    raise

    # -- the map on disk ----------------------------------------------------------

    def _file_stamp(self) -> tuple:
        """Size and mtime of the map file and its WAL: they change when another
        process appends."""
        stamp = []
        for suffix in ("", "-wal"):
            try:
                st = os.stat(f"{self.map.path}{suffix}")
                stamp.append((st.st_size, st.st_mtime_ns))
            except OSError:
                stamp.append(None)
        return tuple(stamp)

    def _refresh_if_changed(self) -> None:
        stamp = self._file_stamp()
        if stamp != self._stamp:
            self.map.refresh()
            self._stamp = stamp

    # -- requests -------------------------------------------------------------------

    def handle_line(self, line: bytes) -> dict[str, Any]:
        """The reply to one request line (never raises for a bad request)."""
        rid = None
        try:
            try:
                request = json.loads(line)
            except (ValueError, UnicodeDecodeError) as exc:
                raise RequestError(f"the request is not JSON ({exc})") from None
            if not isinstance(request, dict):
                raise RequestError("the request must be a JSON object")
            rid = request.get("id")
            if rid is not None and not isinstance(rid, (int, str)):
                rid = None
                raise RequestError("'id' must be a number or a string")
            return {"id": rid, "ok": True, **self.handle(request)}
        except DiscoError as exc:
            return {"id": rid, "ok": False, "error": _one_line(str(exc))}
        except MemoryError:
            return {"id": rid, "ok": False, "error": "the request needs more memory than is free"}

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """The reply's fields for a decoded request; raises `DiscoError` for bad ones."""
        unknown = sorted(set(request) - _QUERY_FIELDS)
        if unknown:
            raise RequestError(f"unknown field {unknown[0]!r} (docs/serve.md lists the fields)")
        op = request.get("op", "query")
        if op == "ping":
            return {"op": "ping"}
        if op == "info":
            with self._lock:
                self._refresh_if_changed()
                return {"op": "info", "map": str(self.map.path), "scans": len(self.map)}
        if op != "query":
            raise RequestError(f"unknown op {op!r}: query, info or ping")
        return self._query(request)

    def _query(self, request: dict[str, Any]) -> dict[str, Any]:
        topk = _int_field(request, "topk", self.options.topk, 1, _MAX_TOPK)
        pose = _bool_field(request, "pose")
        verify = _bool_field(request, "verify")
        max_distance = request.get("max_distance")
        if max_distance is not None and (
            not isinstance(max_distance, (int, float))
            or isinstance(max_distance, bool)
            or not math.isfinite(max_distance)
            or max_distance < 0
        ):
            raise RequestError("'max_distance' must be a finite number >= 0")
        scan_format = request.get("scan_format")
        if scan_format is not None and not isinstance(scan_format, str):
            raise RequestError("'scan_format' must be a string")
        has_scan, has_points = "scan" in request, "points" in request
        if has_scan == has_points:
            raise RequestError("give exactly one of 'scan' (a file path) or 'points'")
        with_pose = pose or verify
        keys = RESULT_COLUMNS + (POSE_COLUMNS + ["T"] if with_pose else [])
        with self._lock:
            self._refresh_if_changed()
            if has_scan:
                scan = request["scan"]
                if not isinstance(scan, str) or not scan:
                    raise RequestError("'scan' must be a file path")
                name = scan
                result = self._query_file(scan, topk, with_pose, max_distance, scan_format)
                if result.error is not None:
                    raise result.error
                rows, errors = result.rows(self.map.shown, keys, verify=verify)
            else:
                name = request.get("name", "points")
                if not isinstance(name, str):
                    raise RequestError("'name' must be a string")
                points = _decode_points(request["points"])
                matches = self.map.query(
                    points,
                    topk=topk,
                    pose=with_pose,
                    verify=verify,
                    max_distance=max_distance,
                    name=name,
                )
                from disco_cli.map import QueryResult

                rows, errors = QueryResult(0, name, matches).rows(
                    self.map.shown, keys, verify=verify
                )
            self.answered += 1
        reply: dict[str, Any] = {
            "query": name,
            "rows": [{k: _plain(v) for k, v in row.items()} for row in rows],
        }
        if errors:
            reply["warnings"] = [_one_line(e) for e in errors]
        return reply

    def _query_file(self, path, topk, pose, max_distance, scan_format) -> Any:
        results = list(
            self.map.query_files(
                [path],
                topk=topk,
                pose=pose,
                max_distance=max_distance,
                scan_format=scan_format,
            )
        )
        return results[0]


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _int_field(request: dict, key: str, default: int, lo: int, hi: int) -> int:
    value = request.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise RequestError(f"'{key}' must be an integer from {lo} to {hi}")
    return value


def _bool_field(request: dict, key: str) -> bool:
    value = request.get(key, False)
    if not isinstance(value, bool):
        raise RequestError(f"'{key}' must be true or false")
    return value


def _decode_points(field: Any) -> np.ndarray:
    """`{"shape": [N, C], "data": base64 float32 LE}` (C = 3 or 4) as an array."""
    if not isinstance(field, dict) or set(field) - {"shape", "data", "dtype"}:
        raise RequestError('\'points\' must be {"shape": [N, 3|4], "data": "<base64>"}')
    if field.get("dtype", "float32") != "float32":
        raise RequestError("'points' must be float32 (dtype 'float32')")
    shape, data = field.get("shape"), field.get("data")
    if (
        not isinstance(shape, list)
        or len(shape) != 2
        or not all(isinstance(s, int) and not isinstance(s, bool) for s in shape)
        or shape[0] < 1
        or shape[1] not in (3, 4)
    ):
        raise RequestError("'points.shape' must be [N, 3] or [N, 4] with N >= 1")
    if not isinstance(data, str):
        raise RequestError("'points.data' must be a base64 string")
    try:
        raw = base64.b64decode(data, validate=True)
    except ValueError:
        raise RequestError("'points.data' is not valid base64") from None
    if len(raw) != shape[0] * shape[1] * 4:
        raise RequestError(
            f"'points.data' holds {len(raw)} bytes, not {shape[0]} x {shape[1]} float32"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(shape).astype(np.float32)


# -- the socket side ------------------------------------------------------------------


class _Handler(socketserver.StreamRequestHandler):
    """One connection: request lines in, reply lines out, until the client closes."""

    def handle(self) -> None:
        service: QueryService = self.server.service  # type: ignore[attr-defined]
        limit = service.options.max_request_bytes
        while True:
            try:
                line = self.rfile.readline(limit + 1)
            except (OSError, ValueError):
                return
            if not line:
                return
            if len(line) > limit and not line.endswith(b"\n"):
                reply = {
                    "id": None,
                    "ok": False,
                    "error": f"the request is longer than {limit} bytes; closing",
                }
                self._send(reply)
                return  # the rest of the line cannot be told from the next request
            if not line.strip():
                continue
            if not self._send(service.submit(line)):
                return

    def _send(self, reply: dict[str, Any]) -> bool:
        try:
            self.wfile.write(json.dumps(reply).encode() + b"\n")
            self.wfile.flush()
            return True
        except OSError:  # the client went away
            return False


class _UnixServer(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True


class _TCPServer(socketserver.ThreadingMixIn, socketserver.TCPServer):
    daemon_threads = True
    allow_reuse_address = True


def make_server(
    service: QueryService,
    *,
    socket_path: str | Path | None = None,
    host: str = "127.0.0.1",
    port: int | None = None,
) -> socketserver.BaseServer:
    """A threading server for `service` on a Unix socket (created with mode 0600; a
    stale socket file left by a dead server is replaced) or a TCP port."""
    if (socket_path is None) == (port is None):
        raise DiscoError("serve: give a socket path or a port, not both")
    server: socketserver.BaseServer
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
    else:
        try:
            server = _TCPServer((host, port), _Handler)
        except OSError as exc:
            raise DiscoError(f"{host}:{port}: cannot listen there ({exc.strerror})") from None
    server.service = service  # type: ignore[attr-defined]
    return server


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


def serve_forever(server: socketserver.BaseServer, on_ready: Callable[[], None]) -> None:
    """Serve until interrupted: connections on a background thread, queries on this
    one. The socket file is removed on the way out."""
    service: QueryService = server.service  # type: ignore[attr-defined]
    stop = threading.Event()
    listener = threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True
    )
    listener.start()
    if threading.current_thread() is threading.main_thread():
        # A service manager stops servers with SIGTERM: leave as cleanly as on Ctrl-C.
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    on_ready()
    try:
        service.work(stop)
    finally:
        stop.set()
        server.shutdown()
        server.server_close()
        if isinstance(server, _UnixServer):
            try:
                os.unlink(server.server_address)  # type: ignore[arg-type]
            except OSError:
                pass
