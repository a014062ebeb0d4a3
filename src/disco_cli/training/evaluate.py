"""Quick retrieval and yaw figures for any model of the protocol (used during training).

Queries are randomly rotated (their BEVs rolled by a random number of sectors), so the
figures measure rotation invariance and the yaw estimate over the whole circle. With
poses, a query searches the scans of the other sessions of its world and counts as found
when the top-1 lies within `radius`; self-supervised, a copy searches the originals and
must find its source. Yaw error is taken over the correctly found queries.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from disco_cli.model.yaw import wrap_deg
from disco_cli.training.data import TrainData


def _embed(
    model: Any, data: TrainData, rows: np.ndarray, rolls: np.ndarray | None = None, batch: int = 64
) -> tuple[np.ndarray, np.ndarray]:
    sigs, feats = [], []
    for s in range(0, len(rows), batch):
        b = data.float_bevs(rows[s : s + batch])
        if rolls is not None:
            r = rolls[s : s + batch]
            b = np.stack([np.roll(x, int(k), axis=-1) for x, k in zip(b, r)])
        sg, ft = model.embed(b)
        sigs.append(sg)
        feats.append(ft)
    return np.concatenate(sigs), np.concatenate(feats)


def query_plan(
    data: TrainData,
    radius: float,
    self_supervised: bool,
    max_queries: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """(query rows, database rows)."""
    anchors = data.anchors
    if self_supervised:
        queries = np.flatnonzero(data.source != np.arange(len(data)))
        db = anchors
    else:
        # Queries from every session but each group's first; the database is that first one.
        first = {}
        for a in anchors:
            first.setdefault(int(data.group[a]), int(data.session[a]))
        in_first = np.array([data.session[a] == first[int(data.group[a])] for a in anchors])
        db = anchors[in_first]
        queries = anchors[~in_first]
        if len(queries) == 0:  # one session per world: loop closure within it instead
            db, queries = anchors, anchors
    if len(queries) > max_queries:
        queries = np.sort(rng.choice(queries, size=max_queries, replace=False))
    return queries, db


def retrieval_metrics(
    model: Any,
    data: TrainData,
    radius: float,
    self_supervised: bool = False,
    max_queries: int = 300,
    seed: int = 0,
    time_gap: int = 50,
) -> dict[str, float]:
    """Recall@1 and yaw error (mean, median, degrees) of `model` on `data`."""
    rng = np.random.default_rng(seed)
    queries, db = query_plan(data, radius, self_supervised, max_queries, rng)
    rolls = rng.integers(0, data.sectors, size=len(queries))
    q_sig, q_feat = _embed(model, data, queries, rolls)
    d_sig, d_feat = _embed(model, data, db)
    dist = ((q_sig[:, None, :] - d_sig[None]) ** 2).sum(-1)
    same_seq_loop = bool(np.intersect1d(queries, db).size)
    if self_supervised:
        truth = data.source[queries][:, None] == db[None]
    else:
        gap = np.linalg.norm(data.xy[queries][:, None] - data.xy[db][None], axis=-1)
        truth = (gap < radius) & (data.group[queries][:, None] == data.group[db][None])
        if same_seq_loop:
            near_t = (data.session[queries][:, None] == data.session[db][None]) & (
                np.abs(data.frame[queries][:, None] - data.frame[db][None]) < time_gap
            )
            dist[near_t] = np.inf
            truth &= ~near_t
    has = truth.any(axis=1)
    top = np.argmin(dist, axis=1)
    found = truth[np.arange(len(queries)), top] & has
    errors = []
    for qi in np.flatnonzero(found):
        m = db[top[qi]]
        est = float(model.yaw(q_feat[qi], d_feat[top[qi]][None])[0])
        true = wrap_deg(
            data.heading_deg[queries[qi]] - rolls[qi] * 360.0 / data.sectors - data.heading_deg[m]
        )
        errors.append(abs(float(wrap_deg(est - true))))
    n = int(has.sum())
    errs = np.asarray(errors)
    return {
        "queries": n,
        "recall_at_1": float(found.sum() / n) if n else float("nan"),
        "yaw_err_mean": float(errs.mean()) if len(errs) else float("nan"),
        "yaw_err_median": float(np.median(errs)) if len(errs) else float("nan"),
    }
