"""The query stage: a query's signature and features in, its ranked rows out.

One function, `match_queries`, under one `QueryPolicy` (query_policy.py):

1. The signature search (`signature_index.SignatureIndex`, or an index of
   `disco_cli.maps.index`): the query's nearest map scans; with views
   (`policy.view_offsets`), those of the query re-centred to either side too
   (`query_views.py`), each scan at its nearest.
2. Re-ranking (`policy.rerank_candidates`): each candidate's feature images against the
   query's and its views' (`model.rerank_distances_views`); where none of the first ones
   re-ranks better than `rerank_wider_above`, the next ones down to `rerank_wider`.
3. One score ranks the rows and is the `distance` they show (`ranking_score`):

       distance = r + signature_weight * (1 / floor - 1 / max(s, floor))

   r: the candidate's best re-rank distance over the query (r_own: its own) and its
   views (a view's plus `view_penalty`); s: its nearest signature distance over the
   same; floor: `policy.signature_floor`. A near signature outweighs re-rank distances
   that are all alike, far ones differ by little; the floor bounds the bonus, so a
   copy of the query in the map (s = 0) cannot push the other rows' distances apart:
   each row's distance is its own, whatever else the map holds. Without re-ranking the
   distance is the signature distance. `max_distance` applies to it before the top-k
   cut, so the rows are sorted by what they show.
4. The snap, a tie-break of that score (`snap_first`): among the candidates within
   `snap_radius` m of the best on the map whose own re-rank distance is within
   `snap_margin` of the best's, the one nearest the query's position (estimated from
   the best match) takes the best's score and comes first.
5. The yaw of the rows kept: parallax-free for the best `refine_yaw`, plain phase
   correlation for the others.
6. Each row's `confidence` from its cues (`confidence.place_confidence`): the
   probability that it is a true revisit, before any geometric check
   (`verification.py` adds the check's evidence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from disco_cli.io.poses.geometry import wrap_deg

# The index's names, where callers have long imported them from here.
from disco_cli.maps.signature_index import SignatureIndex, brute_force_topk  # noqa: F401
from disco_cli.model.interface import QueryModel
from disco_cli.query.confidence import PlaceCues, place_confidence, place_cues
from disco_cli.query.query_policy import QueryPolicy
from disco_cli.query.query_views import candidates_with_views, views_search

__all__ = [
    "Match",
    "match_queries",
    "effective_policy",
    "ranking_score",
    "snap_first",
    "query_on_map_conf",
]


@dataclass
class Match:
    """One match of a query in a database."""

    rank: int  # 1-based
    row: int  # row in the index (0-based, id order)
    match_id: int
    path: str
    # The score that ranks the rows (`ranking_score`): lower is better; bounded, and a
    # row's own (no other row changes it, but the snap's tie-break).
    distance: float
    yaw_deg: float
    pose: np.ndarray  # x, y, z, yaw (rad) of the match, NaN where unknown
    # In [0, 1]: 1 - (the best other heading's correlation peak) / (the yaw's own); low
    # where the place looks alike both ways (model/yaw_refine.py). NaN: the model has none.
    yaw_conf: float = float("nan")
    # The estimated probability that the row is a true revisit (`confidence.py`).
    confidence: float = float("nan")
    # The cues behind it (`confidence.PlaceCues`).
    cues: PlaceCues | None = None


def effective_policy(model: QueryModel, policy: QueryPolicy | None = None) -> QueryPolicy:
    """`policy` (default: the model's) less what the model cannot do."""
    p = model.query_policy if policy is None else policy
    can = model.abilities
    changes: dict[str, Any] = {}
    if not can.rerank and p.rerank_candidates:
        changes["rerank_candidates"] = 0
    if (not can.query_views or not can.rerank) and p.view_offsets:
        changes["view_offsets"] = ()
    if not can.locate and p.snap_radius:
        changes["snap_radius"] = 0.0
    if not can.refine_yaw and p.refine_yaw:
        changes["refine_yaw"] = 0
    return replace(p, **changes) if changes else p


def ranking_score(
    best: np.ndarray, signature_d: np.ndarray, weight: float, floor: float
) -> np.ndarray:
    """The distance of re-ranked candidates: `best + weight * (1/floor - 1/max(s, floor))`.

    The re-rank distance compares the query's feature images with each candidate
    scan's own. Where the query was taken 4-8 m to the side of every candidate, or the
    street looks alike all along, those distances differ by a few hundredths of noise;
    a near signature then tells the place apart. `-weight / s` grows fast as s shrinks
    and changes little among far signatures: under heavy change, where every signature
    is far, the re-ranking decides. The floor bounds it: at or below `floor` (a copy of
    the query, or nearly) the bonus is whole, and the distance never leaves
    [best, best + weight / floor]."""
    score = np.array(best, np.float64)  # a copy: the snap writes into it
    if weight:
        s = np.maximum(np.asarray(signature_d, np.float64), floor)
        score = score + weight * (1.0 / floor - 1.0 / s)
    return score


def query_on_map_conf(
    model: QueryModel,
    query_features: np.ndarray,
    match_features: np.ndarray,
    pose: np.ndarray,
    check_below: float = QueryPolicy.yaw_check_below,
) -> tuple[float, np.ndarray, float]:
    """(parallax-free yaw to the match, x, y [2] of the query sensor on the map, the
    yaw's confidence), from one match whose `pose` is its x, y, z, yaw (rad) on the map;
    `check_below` as the policy's `yaw_check_below`."""
    yaw, t, conf = model.query_position_conf(query_features, match_features, check_below)
    c, s = np.cos(pose[3]), np.sin(pose[3])
    xy = np.asarray(pose[:2], np.float64) + np.array([c * t[0] - s * t[1], s * t[0] + c * t[1]])
    return yaw, xy, float(conf)


def snap_first(
    model: QueryModel,
    query_features: np.ndarray,
    stored: Any,
    best: int,
    own: np.ndarray,
    radius: float,
    margin: float,
    check_below: float = QueryPolicy.yaw_check_below,
) -> tuple[int, float | None, float]:
    """The snap: (which candidate goes first, its parallax-free yaw, that yaw's
    confidence). `best` indexes the best-scored candidate in `stored` (poses, features)
    and `own` (the query's own re-rank distances).

    The query's position is estimated from the best match (its pose on the map plus
    `model.query_position_conf`); the candidates that may take its place lie within
    `radius` m of it on the map and re-rank, by the query's own distance, within
    `margin` of it (a view's match may stand far ahead of a nearer scan the query itself
    sees as well). Alike neighbours of one street re-rank within a few hundredths of each
    other, so the best is often the scan a metre or two past the query's; the pose says
    which is nearer. Without a pose on the best match, it stays first (yaw None).

    Where the snap moves the first, its yaw is the best match's carried over by the
    two map poses a few metres apart (the query's heading on the map is the best
    match's heading plus the yaw to it), not searched for again."""
    pose = np.asarray(stored.poses, dtype=np.float64)
    if not np.isfinite(pose[best, [0, 1, 3]]).all():
        return best, None, float("nan")
    yaw, estimate, conf = query_on_map_conf(
        model, query_features, stored.features_at(best), pose[best], check_below
    )
    with np.errstate(invalid="ignore"):  # NaN poses compare False: never candidates
        near = np.hypot(*(pose[:, :2] - pose[best, :2]).T) <= radius
    alike = own <= own[best] + margin
    cands = np.flatnonzero(near & alike)  # holds best itself
    nearest = int(cands[np.argmin(np.hypot(*(pose[cands, :2] - estimate).T))])
    if nearest == best:
        return best, float(yaw), conf
    if not np.isfinite(pose[nearest, 3]):
        return nearest, None, float("nan")
    turned = yaw + math.degrees(pose[best, 3] - pose[nearest, 3])
    return nearest, float(wrap_deg(turned)), conf


def _query_limit(limit: Any, exclude: Any, i: int) -> tuple[Any, Any]:
    """Query i's own row limit and exclusion mask, from the batch's."""
    lim = limit if np.ndim(limit) == 0 else int(np.asarray(limit)[i])  # None: ndim 0
    ex = None
    if exclude is not None:
        ex = np.asarray(exclude, dtype=bool)
        ex = ex[i] if ex.ndim == 2 else ex
    return lim, ex


class _Reranker:
    """One query's re-ranking: (own, best) re-rank distances of stored rows from `start`
    on, with its views' re-rank images where it has views."""

    def __init__(self, model: QueryModel, query_features: np.ndarray, images: Any, penalty: float):
        self.model, self.q, self.images, self.penalty = model, query_features, images, penalty

    def __call__(self, stored: Any, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
        if self.images is None:
            d = np.asarray(self.model.rerank_distances(self.q, stored.features[start:]), np.float64)
            return d, d
        # The rows' own arrays where the store keeps them apart: no stacked copy.
        rows = stored.feature_rows
        features = list(rows[start:]) if rows is not None else stored.features[start:]
        d = np.asarray(self.model.rerank_distances_views(self.q, features, self.images), np.float64)
        own = d[0]
        best = np.minimum(own, (d[1:] + self.penalty).min(axis=0)) if len(d) > 1 else own
        return own, best


def _reranked(
    model: QueryModel,
    policy: QueryPolicy,
    query_features: np.ndarray,
    db: Any,
    ids: np.ndarray,
    rows: np.ndarray,
    sig_d: np.ndarray,
    first: int,
    views: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, Any, np.ndarray, np.ndarray, np.ndarray]:
    """(rows re-ranked, their stored data, the query's own re-rank distances, the best
    over it and its views, signature distances), in one order.

    The candidates are `rows` (signature distances `sig_d`, nearest first) and, with
    `views` (what the views found, their signature distances, their re-rank images),
    the scans those find among the first nearest over the query and its views
    (`query_views.candidates_with_views`). The first pass re-ranks `first` of them;
    all of them where none re-ranks better than `policy.rerank_wider_above`."""
    images = None
    if views is not None:
        view_rows, view_d, images = views
        rows, sig_d, first = candidates_with_views(rows, sig_d, view_rows, view_d, first)
    rerank = _Reranker(model, query_features, images, policy.view_penalty)
    r = rows[:first]
    stored = db.rows(ids[r])
    own, best = rerank(stored)
    if len(rows) > len(r) and best.min() > policy.rerank_wider_above:
        # No candidate is a good match: re-rank the next ones too. All rows are read in
        # one answer (the first pass's come from the rows' cache), so that no joined
        # copy of the features is made.
        stored = db.rows(ids[rows])
        own_more, best_more = rerank(stored, len(r))
        r = rows
        own, best = np.concatenate([own, own_more]), np.concatenate([best, best_more])
    return r, stored, own, best, sig_d[: len(r)]


def match_queries(
    index: Any,
    ids: np.ndarray,
    db: Any,
    model: QueryModel,
    signatures: np.ndarray,
    features: np.ndarray,
    k: int,
    policy: QueryPolicy | None = None,
    limit: Any = None,
    exclude: np.ndarray | None = None,
    max_distance: float | None = None,
) -> list[list[Match]]:
    """Top-k matches of each query under `policy` (default: the model's own; what the
    model cannot do is left out: `effective_policy`), best first, sorted by their
    `distance` (see the module docstring). `index` searches the map's signatures (rows
    `ids`); `db` is a `Database` (anything with `rows(ids)`); `limit` (a row limit per
    query) and `exclude` (a mask over rows) narrow the search; `max_distance` drops rows
    above it before the cut to k."""
    policy = effective_policy(model, policy)
    rerank_n = policy.rerank_candidates
    first = max(k, rerank_n) if rerank_n > 0 else k
    depth = max(first, policy.wider)
    rows, dists = index.search(signatures, depth, limit=limit, exclude=exclude)
    approximate = len(index) >= policy.approximate_views_from
    out: list[list[Match]] = []
    for i in range(len(rows)):
        keep = rows[i] >= 0
        r, d = rows[i][keep], dists[i][keep]
        snapped: tuple[int, float | None, float] | None = None
        if len(r) and rerank_n > 0:
            views = None
            if policy.view_offsets:
                sigs, images = model.query_views(features[i], policy.view_offsets)
                lim, ex = _query_limit(limit, exclude, i)
                view_rows, view_d = views_search(
                    index, sigs, first, approximate, limit=lim, exclude=ex
                )
                views = (view_rows, view_d, images)
            r, stored, own, best, sig_d = _reranked(
                model, policy, features[i], db, ids, r, d, first, views
            )
            d = ranking_score(best, sig_d, policy.signature_weight, policy.signature_floor)
            order = np.lexsort((r, d))
            if policy.snaps:
                b = int(order[0])
                n, yaw, conf = snap_first(
                    model,
                    features[i],
                    stored,
                    b,
                    own,
                    policy.snap_radius,
                    policy.snap_margin,
                    policy.yaw_check_below,
                )
                d[n] = min(d[n], d[b])  # the tie-break: it takes the best's score
                snapped = (n, yaw, conf)
                ahead = np.arange(len(r)) != n
                order = np.lexsort((r, ahead, d))
            cue_args = (d, own, best, sig_d, stored.poses, r)
        else:
            stored = db.rows(ids[r]) if len(r) else None
            order = np.arange(len(r))
            cue_args = (d, d, d, d, stored.poses if stored else None, r)
        if max_distance is not None:
            order = order[d[order] <= max_distance]
        order = order[:k]
        if len(order) == 0:
            out.append([])
            continue
        cues = place_cues(*cue_args, only=order)
        feats = stored.features_at(order)
        yaw, conf = (np.asarray(a, np.float64) for a in model.yaw_conf(features[i], feats))
        todo = np.arange(min(policy.refine_yaw, len(order)))
        if len(todo) and snapped is not None and snapped[1] is not None and order[0] == snapped[0]:
            # The snap refined the first already (or carried the yaw to it).
            yaw[0], conf[0], todo = snapped[1], snapped[2], todo[1:]
        if len(todo):
            y, c = model.refine_yaw_conf(features[i], feats[todo], policy.yaw_check_below)
            yaw[todo], conf[todo] = y, c
        out.append(
            [
                Match(
                    rank=j + 1,
                    row=int(r[o]),
                    match_id=int(stored.ids[o]),
                    path=stored.paths[o],
                    distance=float(d[o]),
                    yaw_deg=float(yaw[j]),
                    pose=stored.poses[o],
                    yaw_conf=float(conf[j]),
                    confidence=place_confidence(model, cues[j], float(conf[j])),
                    cues=cues[j],
                )
                for j, o in enumerate(order)
            ]
        )
    return out
