"""Copying a map between stores without embedding again (`disco build-db --from`):
SQLite to Milvus, Milvus to SQLite, or either to another of its kind."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.io.output_paths import check_output_file
from disco_cli.maps.database import (
    DamagedRows,
    ModelInfo,
    ScanBatch,
    damaged_line,
    stored_paths,
)
from disco_cli.maps.milvus_address import parse_address
from disco_cli.maps.milvus_repair import COPY_MARK
from disco_cli.maps.milvus_store import MilvusDatabase
from disco_cli.maps.store import MapStore, open_store, store_class

__all__ = ["copy_map", "copy_command"]


def copy_map(
    source: Any,
    target: Any,
    *,
    batch: int = 1000,
    on_progress: Callable[[int, int], None] | None = None,
    on_damaged: Callable[[str], None] | None = None,
) -> int:
    """Copy the map at `source` into a new map at `target` (either may be a `milvus:`
    address or an SQLite file) without embedding again: signatures, features, poses,
    times, paths and meta; ids are renumbered 1, 2, ... in order. Every scan left out
    (a damaged row, or side views missing) is named in one line to `on_damaged`. The
    scans copied.

    The copy is whole only at its end: an SQLite copy is written under a temporary name
    and renamed into place; a Milvus copy carries the meta key `copy_incomplete` until
    its last batch is in (`info --check` reports it, and a copy again replaces it)."""
    replace = _unfinished_copy(target)
    if _exists(target) and not replace:
        raise DatabaseError(target, "already exists; copy into a new map")
    with open_store(source, on_note=lambda _line: None) as src:
        ids, sigs = src.signatures()
        side_ids, side_sigs = src.side_signatures()
        all_ids = src.ids()
        poses, times = src.poses()
        at = {int(i): k for k, i in enumerate(all_ids)}
        sig_at = {int(i): k for k, i in enumerate(ids)}
        views: dict[int, list] = {}
        for i, s in zip(side_ids, side_sigs):
            views.setdefault(int(i), []).append(s)
        skipped = dict(src.damaged)
        keep = []
        for k, i in enumerate(ids):
            if not src.side_offsets or len(views.get(int(i), ())) == len(src.side_offsets):
                keep.append(k)
            else:
                skipped[int(i)] = "lacks some of its side views"
        meta = {k: v for k, v in src.meta.items() if k in ("model_source",)}
        milvus = parse_address(target) is not None
        if milvus:
            meta[COPY_MARK] = str(source)
        # An SQLite copy is built under another name, renamed into place at the end.
        into = target if milvus else _partial_name(Path(target))
        dst: MapStore | None = None
        written = 0
        try:
            for s in range(0, len(keep), batch):
                part = [int(ids[k]) for k in keep[s : s + batch]]
                while True:
                    try:
                        rows = src.rows(part)
                        break
                    except DamagedRows as exc:
                        skipped.update({i: src.damaged.get(i, "?") for i in exc.ids})
                        part = [i for i in part if i not in exc.ids]
                if not part:
                    continue
                rows_at = [at[i] for i in part]
                scan_batch = ScanBatch(
                    paths=rows.paths,
                    # Relative to the new map's folder, as a build there would store them.
                    rel_paths=stored_paths(rows.paths, parse_address(target) or target)[1],
                    signatures=sigs[[sig_at[i] for i in part]],
                    features=rows.features,
                    poses=poses[rows_at],
                    times=times[rows_at],
                    side_offsets=src.side_offsets,
                    side_signatures=(
                        np.stack([np.stack(views[i]) for i in part]) if src.side_offsets else None
                    ),
                )
                if dst is None:
                    dst = _create_database(
                        into,
                        src.model,
                        scan_batch,
                        src.meta.get("disco_version", ""),
                        meta,
                        replace,
                    )
                else:
                    dst.append(scan_batch)
                written += len(part)
                if on_progress is not None:
                    on_progress(written, len(keep))
            if isinstance(dst, MilvusDatabase):
                dst._client.delete(dst._meta_c, filter=f'key in ["{COPY_MARK}"]')
        except BaseException:
            if not milvus:
                Path(into).unlink(missing_ok=True)
            raise
        finally:
            if dst is not None:
                dst.close()
        if dst is None:
            raise DatabaseError(source, "no sound scan to copy")
        if not milvus:
            _move_into_place(Path(into), Path(target))
        skipped.update(src.damaged)
        if skipped and on_damaged is not None:
            on_damaged(f"{source}: {damaged_line(skipped, source)}")
    return written


def _exists(path: Any) -> bool:
    address = parse_address(path)
    return address.exists() if address is not None else Path(path).exists()


def _unfinished_copy(path: Any) -> bool:
    """Whether `path` is a Milvus map that a copy began and never finished."""
    address = parse_address(path)
    if address is None or not address.exists():
        return False
    try:
        with MilvusDatabase.open(address, on_note=lambda _line: None) as db:
            return COPY_MARK in db.meta
    except DatabaseError:
        return False


def _partial_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.copy-{os.getpid()}")


def _move_into_place(partial: Path, target: Path) -> None:
    """Rename the finished copy to `target`, never over a map that appeared meanwhile."""
    try:
        os.link(partial, target)
    except FileExistsError:
        partial.unlink(missing_ok=True)
        raise DatabaseError(target, "already exists; copy into a new map") from None
    except OSError:
        if target.exists():
            partial.unlink(missing_ok=True)
            raise DatabaseError(target, "already exists; copy into a new map") from None
        os.replace(partial, target)
    partial.unlink(missing_ok=True)


def _create_database(
    path: Any, model: ModelInfo, first: ScanBatch, version: str, meta: dict, replace: bool
) -> MapStore:
    # An SQLite copy's partial file is this process's own: one there is an earlier
    # run's (of the same pid), replaced.
    overwrite = replace or parse_address(path) is None
    return store_class(path).create(path, model, first, version, meta, overwrite=overwrite)


def copy_command(source: str, target: Any, inputs: Any, warn: Callable[[str], None]) -> str:
    """`disco build-db --from SOURCE -o TARGET`: the copy, and the line that says so."""
    if inputs:
        raise DiscoError("--from copies a map: give no scans with it")
    if str(source) == str(target) or parse_address(source) == parse_address(target) is not None:
        raise DiscoError(f"{source}: --from and --output name the same map")
    if parse_address(source) is None and not Path(source).is_file():
        raise DatabaseError(source, "no such database")
    if parse_address(target) is None:
        check_output_file(target, what="the database")
    start = time.perf_counter()
    n = copy_map(source, target, on_damaged=warn)
    seconds = time.perf_counter() - start
    return f"{parse_address(target) or target}: copied {n} scans from {source} in {seconds:.1f} s"
