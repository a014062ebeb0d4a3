"""`disco serve`'s requests: one map and one model, loaded once, answering the queries
that arrive over a local socket (`disco_cli/service/serve_net.py` holds the socket side), so
that programs that ask many times pay the start-up once.

The protocol is JSON lines (docs/serve.md): each request is one JSON object on one
line, each reply one JSON object on one line, in order, over one connection for as
long as the client likes. A query names a scan file or carries the points inline:

    {"id": 7, "scan": "/data/scans/000123.bin", "topk": 3}
    {"id": 8, "points": {"shape": [N, 4], "data": "<base64 of float32 little-endian>"}}

and is answered with the rows `disco query --format jsonl` prints for it:

    {"id": 7, "ok": true, "query": "/data/scans/000123.bin", "rows": [{"query": ..., ...}]}

A request that cannot be answered (not JSON, an unknown field, a scan that cannot be
read) gets `{"id": ..., "ok": false, "error": "<one line>"}` and the server goes on.
Scan files are read only under the server's scan root (none without one). A
request asks for at most `max_poses` poses (ICP runs). Queries are answered one at a
time, on the thread that opened the map (SQLite connections and the model stay on one
thread; one query at a time is also what keeps latency flat on a shared CPU). A query
whose client has gone is dropped, or stopped between two matches' poses.

The map is opened read-only unless the server takes appends (`--allow-append`;
`disco_cli/service/appends.py`): those are answered on the same thread as the queries,
one request at a time, so that several writers never collide on ids. Before each query
the server looks at the map file's size and modification time (and its WAL's; a
Milvus map's generation) and takes a new snapshot when another process has written to
it.
"""

from __future__ import annotations

import base64
import json
import math
import os
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.embedding.load import array_points
from disco_cli.errors import DiscoError
from disco_cli.io.readers import is_bag, read_scan
from disco_cli.maps.facade import QueryResult
from disco_cli.query.localize import surest_first
from disco_cli.query.query_policy import policy_for
from disco_cli.query.verification import check_row
from disco_cli.runtime.columns import POSE_COLUMNS, RESULT_COLUMNS
from disco_cli.runtime.console import _plain
from disco_cli.service.appends import APPEND_FIELDS, Appender

__all__ = ["QueryService", "ServeOptions", "MAX_POSES", "MAX_REQUEST_BYTES"]

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
    "token",
}
_MAX_TOPK = 10000
# Each pose is an ICP run on the server's one worker (tens of milliseconds on a 2-core
# VM for the sample scans, more for dense ones): 100 keeps one request within seconds.
MAX_POSES = 100


class RequestError(DiscoError):
    """A request the server cannot answer: its reply is one error line."""


class Cancelled(Exception):
    """The client of the request being answered has gone: stop its work (not a
    DiscoError, so that nothing on the way mistakes it for a scan's problem)."""


@dataclass
class ServeOptions:
    """What every request gets unless it says otherwise, and where scans may be read:
    only under `scan_root` (None: no scan file is read at all; requests send their
    points inline). `max_poses`: the most matches one request may ask a pose of (each
    is an ICP run on the one worker), so `topk` is at most that with `pose` or
    `verify`. `policy`: the query stage's `QueryPolicy` for every request (None: the
    map's model's). `allow_append`: take `append` requests (the map must be open for
    writing)."""

    topk: int = 10
    max_request_bytes: int = MAX_REQUEST_BYTES
    scan_root: Path | None = None
    policy: Any = None
    allow_append: bool = False
    max_poses: int = MAX_POSES


def _always() -> bool:
    return True


def _unless(alive: Callable[[], bool], stop: threading.Event) -> Callable[[], bool]:
    """`alive`, and false once the server is stopping (SIGTERM stops a long query too)."""
    return lambda: alive() and not stop.is_set()


class QueryService:
    """Answers requests against one open map. `handle_line` answers on the calling
    thread; connection threads `submit` lines instead, and the thread that opened the
    map answers them in `work`.

    The map's warnings (damaged rows left out, a match's scan that cannot be read)
    still go where they went and also into the reply of the query that met them;
    damaged rows, once found, are named in every later reply too, since every answer
    leaves them out."""

    def __init__(self, map_: Any, options: ServeOptions | None = None):
        self.map = map_
        self.options = options or ServeOptions()
        self._root = (
            None if self.options.scan_root is None else os.path.realpath(self.options.scan_root)
        )
        self._lock = threading.Lock()
        self._stamp = self._map_stamp()
        self._queue: queue.Queue = queue.Queue()
        self._alive: Callable[[], bool] = _always
        self._notes: list[str] | None = None  # this query's warnings
        self._damaged: list[str] = []  # every damaged-rows line so far
        self.answered = 0
        self.cancelled = 0
        self.appender = (
            Appender(map_, self._scan_path, _decode_points, RequestError)
            if self.options.allow_append
            else None
        )
        told_damaged, told_missing = map_.on_damaged, map_.on_missing_scan

        def damaged(msg: str) -> None:
            self._damaged.append(_one_line(msg))
            told_damaged(msg)

        def missing(msg: str) -> None:
            if self._notes is not None:
                self._notes.append(_one_line(msg))
            told_missing(msg)

        map_.on_damaged, map_.on_missing_scan = damaged, missing

    def submit(self, line: bytes, alive: Callable[[], bool] = _always) -> dict[str, Any] | None:
        """The reply to `line`, answered by the thread running `work` (blocks); None
        when `alive()` turned false (the client left) before it was answered."""
        done: Future = Future()
        self._queue.put((line, alive, done))
        return done.result()

    def work(self, stop: threading.Event) -> None:
        """Answer submitted lines until `stop` is set."""
        while not stop.is_set():
            try:
                line, alive, done = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                done.set_result(self.handle_line(line, _unless(alive, stop)))
            except BaseException as exc:  # never leave a connection waiting
                done.set_result({"id": None, "ok": False, "error": "internal error"})
                if not isinstance(exc, Exception):
                    raise
        while True:  # those still waiting get no answer: their connections close
            try:
                self._queue.get_nowait()[2].set_result(None)
            except queue.Empty:
                break

    # -- the map changed ----------------------------------------------------------

    def _map_stamp(self) -> int | None:
        """The store's `generation` (`store.MapStore`: every write raises it, another
        process's too); None for a new map before its first scan."""
        db = self.map.database
        return None if db is None else db.generation

    def _refresh_if_changed(self) -> None:
        stamp = self._map_stamp()
        if stamp != self._stamp:
            self.map.refresh()
            self._stamp = stamp

    # -- requests -------------------------------------------------------------------

    def handle_line(
        self, line: bytes, alive: Callable[[], bool] = _always
    ) -> dict[str, Any] | None:
        """The reply to one request line (never raises for a bad request); None when
        `alive()` turned false before the answer was ready."""
        rid = None
        try:
            if not alive():
                raise Cancelled
            if not line.strip():
                raise RequestError("empty request: one JSON object per line")
            try:
                request = json.loads(line)
            except (ValueError, UnicodeDecodeError) as exc:
                raise RequestError(f"the request is not JSON ({exc})") from None
            except RecursionError:
                raise RequestError("the request is nested too deeply") from None
            if not isinstance(request, dict):
                raise RequestError("the request must be a JSON object")
            rid = request.get("id")
            if rid is not None and (not isinstance(rid, (int, str)) or isinstance(rid, bool)):
                rid = None
                raise RequestError("'id' must be a number or a string")
            self._alive = alive
            return {"id": rid, "ok": True, **self.handle(request)}
        except Cancelled:
            self.cancelled += 1
            return None
        except DiscoError as exc:
            return {"id": rid, "ok": False, "error": _one_line(str(exc))}
        except MemoryError:
            return {"id": rid, "ok": False, "error": "the request needs more memory than is free"}
        finally:
            self._alive = _always

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """The reply's fields for a decoded request; raises `DiscoError` for bad ones."""
        op = request.get("op", "query")
        fields = APPEND_FIELDS if op == "append" else _QUERY_FIELDS
        unknown = sorted(set(request) - fields)
        if unknown:
            raise RequestError(f"unknown field {unknown[0]!r} (docs/serve.md lists the fields)")
        if op == "ping":
            return {"op": "ping"}
        if op == "auth":  # the connection is past its check already (serve_net)
            return {"op": "auth"}
        if "token" in request:
            raise RequestError("'token' goes in an 'auth' request only")
        if op == "info":
            with self._lock:
                self._refresh_if_changed()
                return {
                    "op": "info",
                    "map": str(self.map.path),
                    "scans": len(self.map),
                    "scan_root": self._root,
                    "answered": self.answered,
                    "cancelled": self.cancelled,
                    "appends": self.appender is not None,
                    "appended": self.appended,
                }
        if op == "append":
            if self.appender is None:
                raise RequestError(
                    "this server takes no appends: its map is read-only unless it is "
                    "started with disco serve --allow-append"
                )
            with self._lock:
                return self.appender.append(request)
        if op != "query":
            raise RequestError(f"unknown op {op!r}: query, append, info or ping")
        return self._query(request)

    @property
    def appended(self) -> int:
        """Scans this server has added to its map."""
        return 0 if self.appender is None else self.appender.added

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
        if has_scan and "name" in request:
            raise RequestError("'name' names inline points; a scan is named by its path")
        name = request.get("name", "points")
        if not isinstance(name, str):
            raise RequestError("'name' must be a string")
        with_pose = pose or verify
        if with_pose and topk > self.options.max_poses:
            raise RequestError(
                f"'topk' is at most {self.options.max_poses} with 'pose' or 'verify': each "
                "match's pose is an ICP run on the server's one worker "
                "(disco serve --max-poses)"
            )
        keys = RESULT_COLUMNS + (POSE_COLUMNS + ["T"] if with_pose else [])
        with self._lock:
            self._refresh_if_changed()
            self._notes = []
            try:
                if has_scan:
                    name = self._scan_path(request["scan"])
                    result = self._query_file(name, topk, with_pose, max_distance, scan_format)
                else:
                    result = self._query_points(
                        request["points"], name, topk, with_pose, verify, max_distance
                    )
                rows, errors = result.rows(self.map.shown, keys, verify=verify)
                notes = self._notes
            finally:
                self._notes = None
            self.answered += 1
        reply: dict[str, Any] = {
            "query": name,
            "rows": [{k: _plain(v) for k, v in row.items()} for row in rows],
        }
        warnings = list(dict.fromkeys(_one_line(e) for e in errors + notes + self._damaged))
        if warnings:
            reply["warnings"] = warnings
        return reply

    def _scan_path(self, scan: Any) -> str:
        """The file a request's `scan` names, when the server may read it: under the
        scan root (relative paths from it; links followed before the check). The
        refusal is the same whether the file exists or not."""
        if not isinstance(scan, str) or not scan or "\0" in scan:
            raise RequestError("'scan' must be a file path")
        if self._root is None:
            raise RequestError(
                "this server reads no scan files (it has no scan root: disco serve "
                "--scan-root, ServeOptions.scan_root); send the points inline"
            )
        path = os.path.join(self._root, scan)  # an absolute scan replaces the root
        # A bag message is BAG#TOPIC@STAMP: its bag must lie under the root too.
        parts = [path, path.rpartition("@")[0].rpartition("#")[0]]
        if not all(_inside(self._root, p) for p in parts if p):
            raise RequestError(
                f"{scan}: outside the folder this server reads scans from (disco serve --scan-root)"
            )
        if os.path.isdir(path) and not is_bag(path):
            raise RequestError(f"{scan}: a folder, not a scan file: send one scan per request")
        return path

    def _query_file(self, path, topk, pose, max_distance, scan_format) -> Any:
        result = next(
            iter(
                self.map.query_files(
                    [path],
                    topk=topk,
                    max_distance=max_distance,
                    scan_format=scan_format,
                    policy=self._policy(pose),
                )
            )
        )
        if result.error is not None:
            raise result.error
        if pose:
            # Read again rather than kept by query_files: the poses are refined here,
            # one match at a time, so that a client who leaves stops them.
            points = read_scan(path, scan_format)
            result.matches = self._refine(result.matches, points, verify=False)
        return result

    def _query_points(self, field, name, topk, pose, verify, max_distance) -> Any:
        points = array_points(_decode_points(field), name)
        matches = self.map.query(
            points, topk=topk, max_distance=max_distance, name=name, policy=self._policy(pose)
        )
        if pose:
            matches = self._refine(matches, points, verify=verify)
        return QueryResult(0, name, matches)

    def _policy(self, pose: bool) -> Any:
        """The query stage's policy; with a pose the rows come unchecked, as `_refine`
        checks each of them with its pose (what `Map.query(..., pose=True)` does)."""
        policy = policy_for(self.map.model, self.options.policy)
        return replace(policy, check_candidates=0) if pose else policy

    def _refine(self, matches: list, points: np.ndarray, verify: bool) -> list:
        """`Map.query(..., pose=True)`'s rows from `matches` (unchecked): each checked
        with its pose in turn, the client asked between two whether it is still there
        (a `topk` of 100 with poses is 100 ICPs), then the surest first."""
        read_match = self.map._points.get  # the map's own cache of its scans' points
        out = []
        for m in matches:
            if not self._alive():
                raise Cancelled
            row = check_row(self.map.model, m, points, lambda r: read_match(r.name), True)
            if not verify or row.accepted:
                out.append(row)
        return surest_first(out, self._policy(True).check_promotes_below)


def _inside(root: str, path: str) -> bool:
    real = os.path.realpath(path)
    return real == root or real.startswith(root.rstrip(os.sep) + os.sep)


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
