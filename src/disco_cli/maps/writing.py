"""Writing to a map: adding scans (one transaction per batch, resumable) and
repairing damaged rows, as the `Map` methods `add`, `add_many`, `add_files` and
`repair` (a base class of `Map`, so that the facade stays one job: opening and
querying), with what they report.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.embedding import batches
from disco_cli.embedding.batches import embed_side_views
from disco_cli.embedding.load import array_points, scan_bev, side_view_bevs
from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.io.poses import pose_rows
from disco_cli.maps.database import ModelInfo, ScanBatch, stored_paths
from disco_cli.maps.milvus_address import parse_address
from disco_cli.maps.store import store_class

__all__ = ["MapWriting", "AddResult", "Interrupted", "RepairResult", "map_address", "store_class"]


def map_address(path: Any) -> Any:
    """A map's address: a `milvus:` one (`disco_cli.maps.milvus_store`), else a file path."""
    return parse_address(path) or Path(path)


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during `Map.add_files`. Every batch committed before it is stored (one
    transaction each): `added` scans were added by this call; `added` is None when no
    file was created."""

    def __init__(self, added: int | None):
        super().__init__()
        self.added = added

    def report(self, path: Any, given: int, held: int) -> str:
        """`disco build-db`'s line on what is safe: of `given` scans, the map at `path`
        held `held` before this call."""
        if self.added is None:
            return f"interrupted: nothing written; {path} was not created"
        return (
            f"interrupted: {path} holds {held + self.added} of the {given} scans given, "
            "safely stored; run the same command again to resume"
        )


@dataclass
class AddResult:
    """What `Map.add_files` did."""

    written: int = 0  # scans added
    already: int = 0  # scans skipped because the map holds them already
    bad: list[str] | None = None  # unreadable scans skipped (skip_bad=True)
    ids: list[int] = field(default_factory=list)  # the added scans' ids, in the order given

    def summary(self, seconds: float) -> str:
        """The line "wrote N scans in S s (R scans/s)" for a build that took `seconds`,
        and how many scans the map held already."""
        rate = self.written / max(seconds, 1e-9)
        scans = "scan" if self.written == 1 else "scans"
        text = f"wrote {self.written} {scans} in {seconds:.1f} s ({rate:.1f} scans/s)"
        return text + (f", {self.already} were in it already" if self.already else "")


@dataclass
class RepairResult:
    """What `Map.repair` did: the damaged scans rewritten, those it could not place
    among the scans given (`{id: stored path}`), and the file's other problems."""

    repaired: list[int]
    unplaced: dict[int, str]
    problems: list[str]


class MapWriting:
    """The writing half of `Map` (`facade.py`), which owns the state it uses: `path`,
    `_db`, `_model`, `_source`, `_overwrite`, `_writable`, `side_offsets`,
    `_snapshot`, `_skipped`, `names()` and `_check_open()`."""

    # -- adding ----------------------------------------------------------------

    def add(self, points: Any, *, name: str | None = None, pose: Any = None, time=None) -> int:
        """Add one scan (an N x 3 or N x 4 array); returns its id. `pose`: the sensor's
        4 x 4 pose in the world (stored as x, y, z, yaw); `time` in seconds."""
        return self.add_many([(points, name, pose, time)])[0]

    def add_many(self, items: Iterable[tuple], *, batch: int = 32) -> list[int]:
        """Add scans from `(points, name, pose)` or `(points, name, pose, time)` tuples,
        one transaction per `batch` scans (as `disco build-db`); returns their ids.
        An unnamed scan is called `scan-<id>`."""
        self._check_writable()
        ids: list[int] = []
        part: list[tuple] = []
        next_id = 1 if self._db is None else self._db.next_id()
        for item in items:
            points, name, pose, time = (*item, None, None)[:4] if len(item) < 4 else item
            label = name or f"scan-{next_id + len(ids) + len(part)}"
            pts = array_points(points, label)
            bev = scan_bev(pts, self._model.bev_config, label)
            sides = (
                side_view_bevs(pts, self._model.bev_config, self.side_offsets)
                if self.side_offsets
                else None
            )
            part.append((label, bev, pose, time, sides))
            if len(part) >= batch:
                ids += self._write_bevs(part)
                part = []
        if part:
            ids += self._write_bevs(part)
        return ids

    def add_files(
        self,
        paths: list[str],
        *,
        poses: np.ndarray | None = None,
        times: np.ndarray | None = None,
        batch: int = 32,
        threads: int | None = None,
        scan_format: str | None = None,
        skip_bad: bool = False,
        on_progress: Callable[[int, int], None] | None = None,
        on_skip: Callable[[DiscoError], None] | None = None,
    ) -> AddResult:
        """Embed scan files and add them, one transaction per batch, reading and
        voxelizing on `threads` threads (None: `disco_cli.get_threads()`) while the
        network runs. Scans are stored by
        absolute path; those the map holds already are skipped, so running it again
        resumes. `poses`: `[N, 4]`
        x, y, z, yaw (rad) rows, NaN where unknown. The first unreadable scan raises
        its `ScanReadError`, unless `skip_bad` (then `on_skip(error)` is told).
        `on_progress(done, written)` after each batch. Ctrl-C raises `Interrupted`."""
        self._check_writable()
        n = len(paths)
        poses = np.full((n, 4), np.nan) if poses is None else np.asarray(poses, np.float64)
        times = np.full(n, np.nan) if times is None else np.asarray(times, np.float64)
        # Stored absolute, with the path relative to the map beside it, so that the map
        # can be read from any directory and moved as a whole (docs/database.md). Two
        # spellings of one file count once; an older map's relative paths count from here.
        absolute, rel_paths = stored_paths(paths, self.path)
        stored = {os.path.abspath(p) for p in self.names()}
        first = {p: i for i, p in reversed(list(enumerate(absolute)))}
        todo = [i for i, p in enumerate(absolute) if p not in stored and first[p] == i]
        result = AddResult(already=sum(p in stored for p in absolute), bad=[])
        if not todo:
            return result

        def embed_and_write() -> None:  # reads and writes add_files' own state
            todo_paths = (paths[i] for i in todo)
            with batches.embedded(  # looked up at each call: tests replace it
                todo_paths, self._model, batch, threads, scan_format, side_offsets=self.side_offsets
            ) as chunks:
                for chunk in chunks:
                    for item in chunk.errors:
                        if not skip_bad:
                            raise item.error  # type: ignore[misc]
                        if on_skip is not None:
                            on_skip(item.error)  # type: ignore[arg-type]
                        result.bad.append(item.path)  # type: ignore[union-attr]
                    if chunk.items:
                        rows = [todo[it.index] for it in chunk.items]
                        result.ids += self._append(
                            ScanBatch(
                                paths=[absolute[r] for r in rows],
                                rel_paths=[rel_paths[r] for r in rows],
                                signatures=chunk.signatures,
                                features=chunk.features,
                                poses=poses[rows],
                                times=times[rows],
                                side_offsets=self.side_offsets,
                                side_signatures=chunk.side_signatures,
                            )
                        )
                        result.written += len(rows)
                    if on_progress is not None:
                        on_progress(result.written + len(result.bad), result.written)  # type: ignore[arg-type]

        before = self._count()
        try:
            embed_and_write()
        except KeyboardInterrupt:
            now = self._count()
            raise Interrupted(None if now is None else now - (before or 0)) from None
        return result

    def repair(
        self,
        paths: list[str],
        *,
        poses: np.ndarray | None = None,
        times: np.ndarray | None = None,
        batch: int = 32,
        threads: int | None = None,
        scan_format: str | None = None,
        on_progress: Callable[[int, int], None] | None = None,
    ) -> RepairResult:
        """Re-embed the map's damaged scans (`Database.check`) from the scan files
        `paths`, with their `poses` and `times` as `add_files` takes them, and rewrite
        their rows. A damaged row is matched to a given file by its stored path, else its
        path relative to the map (a damaged path still leaves the other); the file must
        not be stored in a sound row. What cannot be placed is reported, not guessed."""
        self._check_writable()
        db = self._db
        if db is None:
            return RepairResult([], {}, [])
        problems = db.check()
        damaged = dict(db.damaged)
        others = [p for p in problems if not any(p.startswith(f"scan {i} (") for i in damaged)]
        if not damaged:
            return RepairResult([], {}, others)
        n = len(paths)
        poses = np.full((n, 4), np.nan) if poses is None else np.asarray(poses, np.float64)
        times = np.full(n, np.nan) if times is None else np.asarray(times, np.float64)
        absolute, rel_paths = stored_paths(paths, self.path)
        given: dict[str, int] = {}
        for i, p in enumerate(absolute):
            given.setdefault(p, i)
        raw = db.stored_names(damaged)
        sound = {os.path.abspath(p) for i, p in zip(db.ids(), db.paths()) if i not in damaged}
        folder = Path(os.path.abspath(self.path)).parent
        placed: dict[int, int] = {}  # damaged id -> index into paths
        unplaced: dict[int, str] = {}
        for rid in sorted(damaged):
            path, rel = raw.get(rid, ("", None))
            candidates = [os.path.abspath(path)] if isinstance(path, str) and path else []
            if isinstance(rel, str) and rel:
                candidates.append(os.path.normpath(folder / rel))
            pick = next(
                (
                    given[c]
                    for c in candidates
                    if c in given and c not in sound and given[c] not in placed.values()
                ),
                None,
            )
            if pick is None:
                unplaced[rid] = damaged[rid]
            else:
                placed[rid] = pick
        order = sorted(placed, key=placed.get)  # type: ignore[arg-type]
        repaired: list[int] = []
        with batches.embedded(  # looked up at each call: tests replace it
            (paths[placed[r]] for r in order),
            self._model,
            batch,
            threads,
            scan_format,
            side_offsets=self.side_offsets,
        ) as chunks:
            for chunk in chunks:
                for item in chunk.errors:
                    raise item.error  # type: ignore[misc]
                rids = [order[it.index] for it in chunk.items]
                rows = [placed[r] for r in rids]
                db.rewrite(
                    rids,
                    ScanBatch(
                        paths=[absolute[r] for r in rows],
                        rel_paths=[rel_paths[r] for r in rows],
                        signatures=chunk.signatures,
                        features=chunk.features,
                        poses=poses[rows],
                        times=times[rows],
                        side_offsets=self.side_offsets,
                        side_signatures=chunk.side_signatures,
                    ),
                )
                repaired += rids
                if on_progress is not None:
                    on_progress(len(repaired), len(repaired))
        self._snapshot = None
        self._skipped -= set(repaired)
        return RepairResult(repaired, unplaced, others)

    def _count(self) -> int | None:
        """Scans in the file now; None when there is no file (also when a new map's file
        appeared but was not opened yet, it is counted)."""
        if self._db is not None:
            return len(self._db)
        if not self.path.exists():
            return None
        try:
            with store_class(self.path).open(self.path, on_note=lambda _line: None) as fresh:
                return len(fresh)
        except DatabaseError:
            return 0

    def _check_writable(self) -> None:
        self._check_open()
        if not self._writable:
            raise DatabaseError(self.path, "opened read-only; use Map.open(path, writable=True)")

    def _write_bevs(self, part: list[tuple]) -> list[int]:
        sigs, feats = self._model.embed(np.stack([p[1] for p in part]))
        sides = embed_side_views([p[4] for p in part], self._model) if self.side_offsets else None
        rows = np.full((len(part), 4), np.nan)
        for k, (label, _, pose, _, _) in enumerate(part):
            if pose is not None:
                T = np.asarray(pose, dtype=np.float64)
                if T.shape != (4, 4) or not np.isfinite(T).all():
                    raise DiscoError(f"{label}: pose must be a finite 4 x 4 matrix, got {T.shape}")
                rows[k] = pose_rows(T[None])[0]
        times = [np.nan if p[3] is None else float(p[3]) for p in part]
        batch = ScanBatch(
            [p[0] for p in part],
            sigs,
            feats,
            rows,
            np.asarray(times),
            side_offsets=self.side_offsets,
            side_signatures=sides,
        )
        return self._append(batch)

    def _append(self, part: ScanBatch) -> list[int]:
        """Write `part` (creating the file with it for a new map); the ids it got."""
        # deferred: __version__ reads importlib.metadata (50-150 ms); only a new map needs it
        from disco_cli import __version__

        if self._db is None:
            self._db = store_class(self.path).create(
                self.path,
                ModelInfo.of(self._model),
                part,
                disco_version=__version__,
                extra_meta={"model_source": self._source},
                overwrite=self._overwrite,
            )
            ids = list(range(1, len(part.paths) + 1))
        else:
            ids = self._db.append(part)
        self._snapshot = None
        return ids
