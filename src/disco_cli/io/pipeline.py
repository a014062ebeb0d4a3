"""Scans in, signatures out: reading and voxelizing overlapped with the network.

A feeder thread takes scan paths as they come (a list, or stdin line by line) and
hands each to a small pool of worker threads that read it and build its polar BEV
(both release the GIL in their heavy parts). The consumer gets the loaded scans in
input order, as soon as each is ready, and runs the network on them in the calling
thread, one batch at a time, while the pool already loads the next scans.
"""

from __future__ import annotations

import queue
import sys
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, PoseFileError, ScanReadError
from disco_cli.io.poses import ScanPoser, find_pose_file, read_times, xy_yaw
from disco_cli.io.readers import is_bag, list_scans, read_scan
from disco_cli.maps.map_side_views import side_view_bevs
from disco_cli.model.bev import polar_bev
from disco_cli.runtime.threads import get_threads

__all__ = [
    "Loaded",
    "Embedded",
    "load_stream",
    "embed_stream",
    "embedded",
    "embed_side_views",
    "load_bev",
    "scan_bev",
    "array_points",
    "embed_one",
    "embed_paths",
    "signature",
    "ScanList",
    "scan_paths",
    "file_beside",
    "sequence_times",
    "QueryPoses",
    "query_paths",
    "collect_scans",
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


@dataclass
class Embedded:
    """A batch of embedded scans (input order), and the scans that failed before it."""

    items: list[Loaded]
    signatures: np.ndarray  # [B, D] float32
    features: np.ndarray  # [B, ...] float32
    errors: list[Loaded] = field(default_factory=list)
    side_signatures: np.ndarray | None = None  # [B, V, D] float32 when side views were asked


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


def embed_one(points: np.ndarray, model: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """`(signature [D], features [...])` of one scan's points."""
    bev = scan_bev(points, model.bev_config, name)
    out = _embed([Loaded(0, name, bev=bev)], model)
    return out.signatures[0], out.features[0]


def embed_paths(
    paths: list[str],
    model: Any,
    scan_format: str | None = None,
    batch: int = 32,
    workers: int | None = None,
    on_progress: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`(signatures [N, D], features [N, ...])` of scan files, in order; the first
    unreadable one raises its `ScanReadError`. `on_progress(k)` after each batch of k."""
    sigs, feats = [], []
    with embedded(map(str, paths), model, batch, workers, scan_format, prefetch=8) as chunks:
        for out in chunks:
            if out.errors:
                raise out.errors[0].error  # type: ignore[misc]
            sigs.append(out.signatures)
            feats.append(out.features)
            if on_progress is not None:
                on_progress(len(out.items))
    return np.concatenate(sigs), np.concatenate(feats)


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


@contextmanager
def embedded(
    paths: Iterable[str],
    model: Any,
    batch: int,
    workers: int | None = None,
    scan_format: str | None = None,
    *,
    prefetch: int | None = None,
    keep_points: bool = False,
    side_offsets: tuple[float, ...] = (),
) -> Iterator[Iterator[Embedded]]:
    """`load_stream` then `embed_stream` over scan files, as one stream of batches; the
    readers stop when the block ends. By default `2 * batch` scans (at least 4 per
    worker) are read ahead, so the next batch is ready when the network is. `workers`:
    the threads that read and voxelize, one scan each (None: `disco_cli.get_threads()`)."""
    workers = get_threads() if workers is None else workers
    loaded = load_stream(
        paths,
        model.bev_config,
        workers=workers,
        prefetch=max(2 * batch, 4 * workers) if prefetch is None else prefetch,
        scan_format=scan_format,
        keep_points=keep_points,
        side_offsets=side_offsets,
    )
    try:
        yield embed_stream(loaded, model, batch)
    finally:
        loaded.close()  # type: ignore[attr-defined]


def embed_stream(loaded: Iterable[Loaded], model: Any, batch: int) -> Iterator[Embedded]:
    """Group loaded scans into batches of up to `batch` and run the model on each.

    Failed scans travel in `errors` of the next batch yielded (a batch may be empty
    of items when only errors are pending), so the caller sees each failure before any
    scan that came after it is embedded.
    """
    batch = max(1, int(batch))
    items: list[Loaded] = []
    for item in loaded:
        if item.error is not None:
            if items:
                yield _embed(items, model)
                items = []
            yield Embedded([], np.empty((0, 0), np.float32), np.empty((0, 0), np.float32), [item])
            continue
        items.append(item)
        if len(items) >= batch:
            yield _embed(items, model)
            items = []
    if items:
        yield _embed(items, model)


def embed_side_views(side_bevs: list[np.ndarray], model: Any) -> np.ndarray:
    """`[B, V, D]` signatures of B scans' side views (`[V, ...]` BEVs each), in one
    network batch."""
    views = np.concatenate(side_bevs).astype(np.float32, copy=False)
    sigs = np.asarray(model.embed(views)[0], dtype=np.float32)
    return sigs.reshape(len(side_bevs), len(side_bevs[0]), -1)


def _embed(items: list[Loaded], model: Any) -> Embedded:
    bevs = np.stack([it.bev for it in items]).astype(np.float32, copy=False)
    sigs, feats = model.embed(bevs)
    sigs = np.ascontiguousarray(np.asarray(sigs, dtype=np.float32))
    feats = np.ascontiguousarray(np.asarray(feats, dtype=np.float32))
    sides = None
    if items[0].side_bevs is not None:
        sides = embed_side_views([it.side_bevs for it in items], model)  # type: ignore[misc]
    for it in items:
        it.bev = it.side_bevs = None  # let the BEVs go now that they are embedded
    return Embedded(items, sigs, feats, side_signatures=sides)


# -- inputs: folders, files and stdin ------------------------------------------


def stdin_paths() -> Iterator[str]:
    """Scan paths from stdin, one per line, read lazily (blank lines skipped)."""
    for line in sys.stdin:
        line = line.strip()
        if line:
            yield line


def query_paths(
    inputs: list[str], scan_format: str | None = None, topic: str | None = None
) -> tuple[Iterator[str], list[str] | None]:
    """`disco query`'s scans: folders and bags expanded as for build-db, `-` read from
    stdin line by line as they come; and their list when it is known up front (None with
    stdin or a bag, whose scans go one by one, by the frame number or time in the name)."""

    def expand(a: str) -> list[str]:
        listed = a != "-" and (is_bag(a) or Path(a).is_dir())
        return [str(f) for f in list_scans(a, scan_format, topic)] if listed else [a]

    given = [f for a in inputs for f in expand(a)]
    paths = (p for s in given for p in (stdin_paths() if s == "-" else [s]))
    return paths, None if "-" in given or any(map(is_bag, inputs)) else given


def frame_rows(paths: list[str], n_rows: int, source: str) -> np.ndarray:
    """Which row of a per-frame file (poses, times) belongs to each scan.

    Row i for the i-th scan when the counts agree; otherwise the frame number in each
    scan's name (KITTI `000123.bin` is row 123). `PoseFileError` when neither fits.
    """
    if len(paths) == n_rows:
        return np.arange(n_rows)
    rows = []
    for p in paths:
        stem = Path(p).stem
        if not stem.isdigit() or int(stem) >= n_rows:
            raise PoseFileError(
                f"{source}: {n_rows} rows for {len(paths)} scans, and {p} has no frame "
                "number within it"
            )
        rows.append(int(stem))
    return np.asarray(rows, dtype=np.int64)


def scan_paths(
    inputs: list[Any], scan_format: str | None = None, topic: str | None = None
) -> list[Path]:
    """The scan files of every input (files, folders or bags), in order; `ScanReadError`
    when there are none."""
    paths: list[Path] = []
    for item in inputs:
        paths += list_scans(item, format=scan_format, topic=topic)
    if not paths:
        raise ScanReadError(", ".join(map(str, inputs)), "no scans found")
    return paths


def file_beside(inputs: list[Path], given: Path | None, name: str | None = None) -> Path | None:
    """`given`, else NAME (default: the pose file, `disco_cli.io.poses.find_pose_file`) beside
    the scans when a single folder was given."""
    if given is not None:
        return given
    if len(inputs) != 1 or not inputs[0].is_dir():
        return None
    if name is None:
        return find_pose_file(inputs[0])
    return inputs[0] / name if (inputs[0] / name).is_file() else None


def sequence_times(folder: Any, paths: list[str], times_file: Any = None) -> np.ndarray | None:
    """The time (s) of each scan of a sequence: from `times_file`, else the header stamps
    of scans in a bag, else `times.txt` in `folder`, by row or frame number
    (`frame_rows`); None when there is none of these."""
    # deferred: io.readers.bags stays off the query path, which imports this module
    from disco_cli.io.readers.bags import scan_stamps

    stamps = scan_stamps(paths) if times_file is None else None
    if stamps is not None and np.isfinite(stamps).all():
        return stamps
    folder = Path(folder)
    times_file = times_file or (folder / "times.txt" if folder.is_dir() else None)
    if times_file is None or not Path(times_file).is_file():
        return None
    t = read_times(times_file)
    return t[frame_rows(paths, len(t), str(times_file))]


def window_times(
    folder: Any, paths: list[str], times_file: Any, exclude_seconds: float | None, warn: Any
) -> np.ndarray | None:
    """`sequence_times` for a window of `exclude_seconds` (a `DiscoError` where there
    are none; `warn` hears of times that go backwards)."""
    stamps = sequence_times(folder, paths, times_file)
    if exclude_seconds is None:
        return stamps
    if stamps is None:
        raise DiscoError(f"{folder}: --exclude-seconds needs times.txt beside the scans or --times")
    if np.any(np.diff(stamps) < 0):
        warn(f"{folder}: timestamps are not increasing; frames are taken in file order")
    return stamps


class QueryPoses:
    """The pose rows (x, y, z, yaw; NaN when unknown) of query scans from a pose file
    (`disco_cli.io.poses.ScanPoser`): for scans known up front (`paths`) KITTI's "row i for
    scan i" applies when their count is the file's; scans streamed (stdin) go one by one,
    by frame number or time. `missing` counts the queries without a pose; `warn` hears of
    them (once when streamed)."""

    def __init__(self, poses_file: Any, pose_opts: dict, paths: list[str] | None, warn: Any):
        self.poser = ScanPoser(poses_file, **pose_opts)
        self.warn = warn
        self.missing = 0
        self.rows = None
        if paths is not None:
            T, report = self.poser.poses(list(paths))
            self.rows = pose_rows(T)
            if report.warning():
                warn(report.warning())

    def __call__(self, index: int, path: str) -> np.ndarray:
        if self.rows is not None:
            row = self.rows[index]
        else:
            T, report = self.poser.poses([path])
            row = pose_rows(T)[0]
            if report.missing and not self.missing:
                self.warn(report.warning())
        if not np.isfinite(row[:2]).all():
            self.missing += 1
        return row

    def exclusion(self, m: Any, radius: float) -> Callable[[int, str], np.ndarray]:
        """`Map.query_files`'s `exclude` for map `m`: the query's own scan, and the
        scans within `radius` m (x, y) of its pose."""
        return lambda i, p: m.near(self(i, p)[:2], radius, p)


def pose_rows(T: np.ndarray) -> np.ndarray:
    """`[N, 4, 4]` poses as `[N, 4]` rows of x, y, z, yaw (radians)."""
    x, y, yaw = xy_yaw(np.asarray(T))
    return np.stack([x, y, np.asarray(T)[:, 2, 3], yaw], axis=1)


def check_device(device: str) -> None:
    """`DiscoError` unless `device` is cpu, or cuda with a CUDA device that torch sees."""
    if device not in ("cpu", "cuda"):
        raise DiscoError(f"--device must be cpu or cuda, not {device!r}")
    if device == "cuda":
        import torch  # deferred: torch costs ~1.5 s; only --device cuda asks it

        if not torch.cuda.is_available():
            raise DiscoError("--device cuda: torch sees no CUDA device here; use --device cpu")


def signature(model: Any, points: Any, name: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """`(signature [D], features [...])` of one scan (an N x 3 or N x 4 array) under a
    model from `load_model`, for those who keep signatures in their own storage:
    compare signatures by Euclidean distance, and `model.yaw(features_q, features_m[None])`
    gives the yaw between two scans."""
    return embed_one(array_points(points, name), model, name)


@dataclass
class ScanList:
    """The scans of a build in input order, with pose rows and times (NaN = unknown)."""

    paths: list[str]
    poses: np.ndarray  # [N, 4] x, y, z, yaw
    times: np.ndarray  # [N]
    no_pose: int = 0  # scans a pose file was given for that got no pose


def collect_scans(
    inputs: list[str],
    poses_file: Path | None,
    times_file: Path | None,
    calib: str | None,
    scan_format: str | None = None,
    pose_opts: dict | None = None,
    warn: Any = None,
    topic: str | None = None,
    pose_topic: str | None = None,
) -> ScanList:
    """Expand folders, files and `-` (stdin) into one list of scans.

    A folder with a pose file (`disco_cli.io.poses.find_pose_file`) and `times.txt` beside
    its scans brings them along unless `--poses` / `--times` are given; those cover all
    scans. Poses come from `disco_cli.io.poses.ScanPoser`; scans left without one are
    named in one `warn` per pose file and counted in `ScanList.no_pose`.
    Scans in a bag are timed by their header stamps, and posed from the bag's
    `pose_topic` when given (by time, like a pose file).
    """
    # deferred: io.readers.bags stays off the query path, which imports this module
    from disco_cli.io.readers.bags import scan_stamps

    opts = dict(pose_opts or {})
    opts.setdefault("calib", "auto" if calib is None else calib)
    paths: list[str] = []
    poses: list[np.ndarray] = []
    times: list[np.ndarray] = []
    seen: set[str] = set()
    no_pose = 0
    used: list[Path] = []  # the pose and times files read

    def lidar_rows(group: list[str], pose_file: Path) -> np.ndarray:
        nonlocal no_pose
        used.append(Path(pose_file))
        T, report = ScanPoser(pose_file, **opts).poses(group)
        if report.warning():
            (warn or warnings.warn)(report.warning())
        no_pose += report.missing
        return pose_rows(T)

    for item in inputs:
        if item == "-":
            group = list(stdin_paths())
        else:
            group = [str(p) for p in list_scans(item, scan_format, topic)]
        group = [p for p in dict.fromkeys(group) if p not in seen]
        seen.update(group)
        n = len(group)
        p_rows, t_rows = np.full((n, 4), np.nan), scan_stamps(group)
        folder = Path(item)
        if item != "-" and folder.is_dir() and group:
            beside = find_pose_file(folder) if poses_file is None else None
            if beside is not None:
                p_rows = lidar_rows(group, beside)
            if times_file is None and (folder / "times.txt").is_file():
                used.append(folder / "times.txt")
                t = read_times(folder / "times.txt")
                t_rows = t[frame_rows(group, len(t), str(folder / "times.txt"))]
        paths += group
        poses.append(p_rows)
        times.append(t_rows)
    all_poses = np.concatenate(poses) if poses else np.empty((0, 4))
    all_times = np.concatenate(times) if times else np.empty(0)
    if poses_file is not None:
        all_poses = lidar_rows(paths, poses_file)
    if times_file is not None:
        t = read_times(times_file)
        all_times = t[frame_rows(paths, len(t), str(times_file))]
    if pose_topic is not None:
        from disco_cli.io.readers.bags import bag_poses  # deferred: as scan_stamps above

        T, missing = bag_poses(paths, pose_topic, opts.get("max_time_gap"), opts.get("extrinsic"))
        if missing:
            (warn or warnings.warn)(
                f"{pose_topic}: {len(missing)} of {len(paths)} scans have no pose near their "
                f"stamp (e.g. {missing[0]}); they are left without one"
            )
        no_pose += len(missing)
        all_poses = pose_rows(T)
    from disco_cli.io.missed_poses import missed_hint  # deferred: it loads io.readers.bags

    # Poses or times left unused (a folder's poses.txt beside scans given one by one, a
    # bag's odometry topic): one line that says how to supply them.
    hint = missed_hint(
        paths,
        all_poses if poses_file is None and pose_topic is None else None,
        all_times if times_file is None else None,
        used=used,
    )
    if hint:
        (warn or warnings.warn)(hint)
    return ScanList(paths, all_poses, all_times, no_pose)
