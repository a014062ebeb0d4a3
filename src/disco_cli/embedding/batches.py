"""Loaded scans to signatures: the network run on them one batch at a time.

`embedded` joins `load.load_stream` and `embed_stream` into one stream of batches over
scan files, so the network works on one batch while the pool reads the next scans;
`embed_one` and `signature` embed a single scan's points (the library API).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from disco_cli.embedding.load import Loaded, array_points, load_stream, scan_bev
from disco_cli.runtime.threads import get_threads

__all__ = [
    "Embedded",
    "embed_stream",
    "embedded",
    "embed_side_views",
    "embed_one",
    "embed_paths",
    "signature",
]


@dataclass
class Embedded:
    """A batch of embedded scans (input order), and the scans that failed before it."""

    items: list[Loaded]
    signatures: np.ndarray  # [B, D] float32
    features: np.ndarray  # [B, ...] float32
    errors: list[Loaded] = field(default_factory=list)
    side_signatures: np.ndarray | None = None  # [B, V, D] float32 when side views were asked


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


def signature(model: Any, points: Any, name: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """`(signature [D], features [...])` of one scan (an N x 3 or N x 4 array) under a
    model from `load_model`, for those who keep signatures in their own storage:
    compare signatures by Euclidean distance, and `model.yaw(features_q, features_m[None])`
    gives the yaw between two scans."""
    return embed_one(array_points(points, name), model, name)
