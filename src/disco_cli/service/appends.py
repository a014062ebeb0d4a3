"""`disco serve --allow-append`'s appends: scans that writers send to the server,
embedded with its loaded model and added to its map by the map's own writer
(`Map.add_files` for scan files, as `disco build-db --append` adds them; `Map.add_many`
for inline points), on the server's one worker thread, so that writers never collide
on ids and no row is lost.

One scan per request, or several under `scans`:

    {"op": "append", "scan": "/data/01/velodyne/000007.bin", "pose": [[...], ...], "time": 0.7}
    {"op": "append", "points": {"shape": [N, 4], "data": "..."}, "name": "robot-3/000007"}
    {"op": "append", "scans": [{"scan": ...}, {"scan": ...}]}

A request is all or nothing: every scan in it is read and checked before anything is
written, and written as one batch: one SQLite transaction, or on a Milvus map one
append of three requests (side views, scans, counters) whose ids stay reserved by its
intent until the last, so that one cut off halfway is found by `disco info --check`
and finished or undone by `disco build-db --repair` (`maps/milvus_repair.py`). A scan
the map holds already (a file by its absolute path, inline points by their name) is not
added again: its id is replied,
so that a writer may resend a request whose reply it never got.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from disco_cli.embedding.load import scan_bev
from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.io.poses import pose_rows
from disco_cli.io.readers import read_scan
from disco_cli.runtime.threads import get_threads

__all__ = ["APPEND_FIELDS", "MAX_APPEND_SCANS", "Appender"]

# The fields of an append request; each scan of `scans` takes those of one scan.
APPEND_FIELDS = {"id", "op", "scan", "points", "name", "pose", "time", "scan_format", "scans"}
_SCAN_FIELDS = {"scan", "points", "name", "pose", "time"}
# A request holds the one worker for as long as it embeds: bound what one may ask.
MAX_APPEND_SCANS = 1000


@dataclass
class _Scan:
    """One scan of a request: a file (`path`) or inline points named `name`."""

    path: str | None
    points: np.ndarray | None
    name: str
    pose: np.ndarray | None  # 4 x 4, the sensor in the map's frame
    time: float | None


class Appender:
    """Appends requests' scans to `map_` (opened writable). `scan_path(field)` is the
    service's check of a `scan` field (under its scan root), `decode(field)` its
    decoding of a `points` field; both raise `DiscoError` for a bad one."""

    def __init__(
        self,
        map_: Any,
        scan_path: Callable[[Any], str],
        decode: Callable[[Any], np.ndarray],
        refuse: Callable[[str], DiscoError],
    ):
        self.map = map_
        self._scan_path = scan_path
        self._decode = decode
        self._refuse = refuse
        self.added = 0  # scans added since the server started

    def append(self, request: dict[str, Any]) -> dict[str, Any]:
        """The reply's fields for an append request: the scans' ids in the order given
        (new or held already), how many were added, and the map's size after."""
        scan_format = request.get("scan_format")
        if scan_format is not None and not isinstance(scan_format, str):
            raise self._refuse("'scan_format' must be a string")
        scans = self._parse(request)
        files = scans[0].path is not None
        if any((s.path is not None) != files for s in scans):
            raise self._refuse("the scans of one request must be all files or all inline points")
        keys = [os.path.abspath(s.path) if s.path is not None else s.name for s in scans]
        if len(set(keys)) < len(keys):
            twice = next(k for k in keys if keys.count(k) > 1)
            raise self._refuse(f"{twice}: given twice in one request")
        if files:
            ids, added = self._add_files(scans, keys, scan_format)
        else:
            ids, added = self._add_points(scans)
        self.added += added
        return {"op": "append", "scan_ids": ids, "added": added, "scans": len(self.map)}

    # -- reading the request -----------------------------------------------------

    def _parse(self, request: dict[str, Any]) -> list[_Scan]:
        if "scans" not in request:
            return [self._scan(request)]
        own = sorted(set(request) & _SCAN_FIELDS)
        if own:
            raise self._refuse(f"'{own[0]}' goes inside each of 'scans', not beside it")
        items = request["scans"]
        if not isinstance(items, list) or not items:
            raise self._refuse("'scans' must be a non-empty list of scans")
        if len(items) > MAX_APPEND_SCANS:
            raise self._refuse(
                f"'scans' holds {len(items)} scans; at most {MAX_APPEND_SCANS} per request"
            )
        out = []
        for k, item in enumerate(items):
            if not isinstance(item, dict):
                raise self._refuse(f"scans[{k}] must be a JSON object")
            unknown = sorted(set(item) - _SCAN_FIELDS)
            if unknown:
                raise self._refuse(f"scans[{k}]: unknown field {unknown[0]!r}")
            try:
                out.append(self._scan(item))
            except DiscoError as exc:
                raise self._refuse(f"scans[{k}]: {exc}") from None
        return out

    def _scan(self, fields: dict[str, Any]) -> _Scan:
        has_scan, has_points = "scan" in fields, "points" in fields
        if has_scan == has_points:
            raise self._refuse("give exactly one of 'scan' (a file path) or 'points'")
        pose, time = _pose(fields.get("pose"), self._refuse), fields.get("time")
        if time is not None and (
            isinstance(time, bool) or not isinstance(time, (int, float)) or not math.isfinite(time)
        ):
            raise self._refuse("'time' must be a finite number (seconds)")
        time = None if time is None else float(time)
        if has_scan:
            if "name" in fields:
                raise self._refuse("a scan file is stored by its path; 'name' names inline points")
            path = self._scan_path(fields["scan"])
            return _Scan(path, None, path, pose, time)
        name = fields.get("name")
        if not isinstance(name, str) or not name.strip() or "\0" in name:
            raise self._refuse(
                "inline points need a 'name': the scan's path in the map, unique in it"
            )
        return _Scan(None, self._decode(fields["points"]), name, pose, time)

    # -- writing -----------------------------------------------------------------

    def _add_files(
        self, scans: list[_Scan], keys: list[str], scan_format: str | None
    ) -> tuple[list, int]:
        paths = [s.path for s in scans]
        if len(paths) > 1:
            # Map.add_files stores every scan before the first bad one: check them all
            # first, so that a request with a bad scan writes nothing.
            for p in paths:
                _check_file(p, scan_format, self.map.model.bev_config)  # type: ignore[arg-type]
        poses = np.full((len(scans), 4), np.nan)
        for k, s in enumerate(scans):
            if s.pose is not None:
                poses[k] = pose_rows(s.pose[None])[0]
        times = np.array([np.nan if s.time is None else s.time for s in scans])
        result = self.map.add_files(
            paths,
            poses=poses,
            times=times,
            batch=len(paths),  # one batch: all or nothing
            threads=min(len(paths), get_threads()),
            scan_format=scan_format,
        )
        if not result.already:
            return list(result.ids), result.written
        return self._ids_of(keys, os.path.abspath), result.written

    def _add_points(self, scans: list[_Scan]) -> tuple[list, int]:
        names = [s.name for s in scans]
        held = self.map.database.existing(names)
        # add_many embeds every scan before it writes the batch (all or nothing), so
        # a bad one (no finite point, none in range, a bad pose) writes nothing.
        items = [(s.points, s.name, s.pose, s.time) for s in scans if s.name not in held]
        added = self.map.add_many(items, batch=len(items) + 1) if items else []
        if not held:
            return list(added), len(added)
        return self._ids_of(names, str), len(added)

    def _ids_of(self, keys: list[str], key_of: Callable[[str], str]) -> list:
        """The stored ids of `keys` (a resend names scans held already)."""
        db = self.map.database
        where = {key_of(p): int(i) for p, i in zip(db.paths(), db.ids())}
        return [where.get(k) for k in keys]


def _pose(value: Any, refuse: Callable[[str], DiscoError]) -> np.ndarray | None:
    """A request's `pose`: the sensor's 4 x 4 pose in the map's frame, or None."""
    if value is None:
        return None
    msg = (
        "'pose' must be the sensor's 4 x 4 pose in the map's frame "
        "(4 rows of 4 finite numbers, the last 0, 0, 0, 1)"
    )
    if not (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(r, list) and len(r) == 4 for r in value)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in value for v in r)
    ):
        raise refuse(msg)
    T = np.asarray(value, dtype=np.float64)
    if not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
        raise refuse(msg)
    return T


def _check_file(path: str, scan_format: str | None, bev_config: Any) -> None:
    """What `Map.add_files` checks of a scan file before embedding it: that it reads,
    and has points in the BEV's range (`ScanReadError` naming it)."""
    try:
        scan_bev(read_scan(path, scan_format), bev_config, path)
    except (OSError, MemoryError) as exc:
        raise ScanReadError(path, f"cannot read ({exc})") from None
