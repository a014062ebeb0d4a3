"""Scans to polar BEVs: read (a file or an array), voxelize, and overlap the two.

A feeder thread takes scan paths as they come (a list, or stdin line by line) and
hands each to a small pool of worker threads that read it and build its polar BEV
(both release the GIL in their heavy parts). The consumer gets the loaded scans in
input order, as soon as each is ready (`load_stream`); `batches.py` runs the network
on them while the pool already loads the next scans.

A map's side views (`maps/map_side_views.py` says why a map stores them) are the same
scan's points seen from a sensor moved sideways: `side_view_bevs` voxelizes them here,
with the scan.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.io.readers import read_scan
from disco_cli.model.bev import polar_bev
from disco_cli.runtime.threads import get_threads

__all__ = [
    "Loaded",
    "load_stream",
    "load_bev",
    "scan_bev",
    "array_points",
    "seen_from",
    "side_view_bevs",
]

_END = object()


@dataclass
class Loaded:
    """One scan after reading and voxelizing: `bev` or `error` is set."""

    index: int  # position in the input
    path: str  # as given
    bev: np.ndarray | None = None
    error: DiscoError | None = None
    points: np.ndarray | None = None  # kept only when asked for (relative pose)
    side_bevs: np.ndarray | None = None  # [V, ...] for a map with side views


def load_bev(path: str, bev_config: Any, scan_format: str | None = None) -> np.ndarray:
    """Read one scan and voxelize it; `ScanReadError` when it is unreadable or holds
    no point inside the BEV's range."""
    return _load_points_bev(path, bev_config, scan_format)[1]


def _load_points_bev(
    path: str, bev_config: Any, scan_format: str | None
) -> tuple[np.ndarray, np.ndarray]:
    points = read_scan(path, scan_format)
    return points, scan_bev(points, bev_config, path)


def scan_bev(points: np.ndarray, bev_config: Any, name: str) -> np.ndarray:
    """The polar BEV of a scan's points; `ScanReadError` naming `name` when it holds no
    point inside the BEV's range."""
    try:
        bev = polar_bev(points, bev_config)
    except DiscoError:
        raise
    except (ValueError, TypeError) as exc:
        raise ScanReadError(name, f"cannot voxelize ({exc})") from None
    if not np.any(bev):
        raise ScanReadError(name, f"no points in range ({len(points)} points, none in the BEV)")
    return bev


def array_points(points: Any, name: str) -> np.ndarray:
    """Points handed over as an array (the library API), checked as an .npy scan file
    would be: float32 `N x 4`, rows without finite x, y, z dropped; `ScanReadError`
    naming `name` with the same reason an .npy file of that array gets."""
    from disco_cli.io.readers.npy import from_array  # deferred: arrays only; files never need it

    if not isinstance(points, np.ndarray):
        try:
            points = np.asarray(points)
        except (TypeError, ValueError) as exc:
            raise ScanReadError(name, f"not a numeric array ({exc})") from None
    return from_array(points, name)


def seen_from(points: np.ndarray, offset: float) -> np.ndarray:
    """A copy of `points` as a sensor moved `offset` m along the scan's y axis sees them."""
    moved = np.array(points, dtype=np.float32, copy=True)
    moved[:, 1] -= np.float32(offset)
    return moved


def side_view_bevs(points: np.ndarray, bev_config: Any, offsets: Sequence[float]) -> np.ndarray:
    """`[V, H, R, S]` BEVs of `points` seen from a sensor moved by each offset along y
    (at least one offset). A view with no point left in range is an all-zero BEV (it
    then matches nothing)."""
    if not offsets:
        raise ValueError("side views: no offsets")
    out = [polar_bev(seen_from(points, offset), bev_config) for offset in offsets]
    return np.stack(out).astype(np.float32, copy=False)


def _load_one(
    index: int,
    path: str,
    bev_config: Any,
    scan_format: str | None,
    keep_points: bool,
    side_offsets: tuple[float, ...] = (),
) -> Loaded:
    try:
        points, bev = _load_points_bev(path, bev_config, scan_format)
        sides = side_view_bevs(points, bev_config, side_offsets) if side_offsets else None
        return Loaded(index, path, bev=bev, points=points if keep_points else None, side_bevs=sides)
    except DiscoError as exc:
        return Loaded(index, path, error=exc)
    except (OSError, MemoryError) as exc:
        return Loaded(index, path, error=ScanReadError(path, f"cannot read ({exc})"))


def load_stream(
    paths: Iterable[str],
    bev_config: Any,
    workers: int | None = None,
    prefetch: int = 8,
    scan_format: str | None = None,
    keep_points: bool = False,
    side_offsets: tuple[float, ...] = (),
) -> Iterator[Loaded]:
    """Loaded scans in input order, each as soon as it (and those before it) are ready.
    With `side_offsets`, each also carries the BEVs of its side views.

    `paths` is consumed on a feeder thread, so a slow producer (stdin) never holds back
    results that are ready already. At most `prefetch` scans are in flight. `workers`
    threads read them (None: `disco_cli.get_threads()`).
    """
    workers = max(1, int(get_threads() if workers is None else workers))
    pending: queue.Queue = queue.Queue(maxsize=max(1, prefetch))
    stop = threading.Event()
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="disco-load")

    def put(item: Any) -> bool:
        while not stop.is_set():
            try:
                pending.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def feed() -> None:
        try:
            for i, p in enumerate(paths):
                if stop.is_set():
                    return
                fut = pool.submit(
                    _load_one, i, str(p), bev_config, scan_format, keep_points, side_offsets
                )
                if not put(fut):
                    return
        except BaseException as exc:  # e.g. stdin went away: the consumer re-raises it
            put(exc)
            return
        put(_END)

    # A daemon thread: a feeder blocked on stdin must never keep the process alive.
    feeder = threading.Thread(target=feed, name="disco-feed", daemon=True)
    feeder.start()
    try:
        while True:
            item = pending.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            fut: Future = item
            yield fut.result()
    finally:
        stop.set()
        pool.shutdown(wait=False, cancel_futures=True)
