"""Copying a map between stores without embedding again (`disco build-db --from`):
SQLite to Milvus, Milvus to SQLite, or either to another of its kind."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.io.output_paths import check_output_file
from disco_cli.maps.database import (
    DamagedRows,
    Database,
    ModelInfo,
    ScanBatch,
    damaged_line,
    stored_paths,
)
from disco_cli.maps.milvus_address import parse_address
from disco_cli.maps.milvus_store import MilvusDatabase

__all__ = ["copy_map", "copy_command", "open_database"]


def open_database(path: Any, **kwargs: Any) -> Database:
    """`Database.open` for a plain path, `MilvusDatabase.open` for a `milvus:` address."""
    if parse_address(path) is not None:
        return MilvusDatabase.open(path, **kwargs)
    return Database.open(path, **kwargs)


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
    times, paths and meta; ids are renumbered 1, 2, ... in order. Damaged rows are
    left out and `on_damaged` hears one line naming them. The scans copied."""
    if _exists(target):
        raise DatabaseError(target, "already exists; copy into a new map")
    with open_database(source, on_note=lambda _line: None) as src:
        ids, sigs = src.signatures()
        side_ids, side_sigs = src.side_signatures()
        all_ids = src.ids()
        poses, times = src.poses()
        at = {int(i): k for k, i in enumerate(all_ids)}
        sig_at = {int(i): k for k, i in enumerate(ids)}
        views: dict[int, list] = {}
        for i, s in zip(side_ids, side_sigs):
            views.setdefault(int(i), []).append(s)
        keep = [
            k
            for k, i in enumerate(ids)
            if not src.side_offsets or len(views.get(int(i), ())) == len(src.side_offsets)
        ]
        skipped = dict(src.damaged)
        meta = {k: v for k, v in src.meta.items() if k in ("model_source",)}
        dst: Database | None = None
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
                        target, src.model, scan_batch, src.meta.get("disco_version", ""), meta
                    )
                else:
                    dst.append(scan_batch)
                written += len(part)
                if on_progress is not None:
                    on_progress(written, len(keep))
        finally:
            if dst is not None:
                dst.close()
        if dst is None:
            raise DatabaseError(source, "no sound scan to copy")
        skipped.update(src.damaged)
        if skipped and on_damaged is not None:
            on_damaged(f"{source}: {damaged_line(skipped, source)}")
    return written


def _exists(path: Any) -> bool:
    address = parse_address(path)
    return address.exists() if address is not None else Path(path).exists()


def _create_database(
    path: Any, model: ModelInfo, first: ScanBatch, version: str, meta: dict
) -> Database:
    if parse_address(path) is not None:
        return MilvusDatabase.create(path, model, first, version, meta)
    return Database.create(path, model, first, version, meta)


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
