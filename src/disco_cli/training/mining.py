"""Pair mining: positives, negatives and hard negatives for quadruplets.

With poses: positives lie within d_pos in the same world (other sessions preferred, so the
network learns revisits rather than consecutive frames); negatives are beyond d_neg or in
another world. Self-supervised: positives are the augmented copies of a scan; negatives
are scans of the same sequence at least `time_gap` frames away.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from disco_cli.errors import DiscoError
from disco_cli.training.data import TrainData

# Share of positives taken from another session when the anchor has any there.
_CROSS_SESSION = 0.75


class PairMiner:
    def __init__(
        self,
        data: TrainData,
        d_pos: float,
        d_neg: float,
        self_supervised: bool = False,
        time_gap: int = 50,
    ):
        if d_neg < d_pos:
            raise DiscoError(f"--d-neg ({d_neg} m) must not be smaller than --d-pos ({d_pos} m)")
        self.data = data
        self.d_pos = d_pos
        self.d_neg = d_neg
        self.self_supervised = self_supervised
        self.time_gap = time_gap
        self.pool = data.anchors  # negatives are drawn from original scans only
        self.hard: dict[int, np.ndarray] = {}
        pos: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # Per world: a k-d tree of its scans' positions (positives here, verify_set later).
        self._trees: dict[int, tuple[cKDTree, np.ndarray]] = {}
        if self_supervised:
            for i in data.anchors:
                copies = np.flatnonzero((data.source == i) & (np.arange(len(data)) != i))
                if len(copies):
                    pos[int(i)] = (copies, copies[:0])
        else:
            for g in np.unique(data.group[data.anchors]):
                members = data.anchors[data.group[data.anchors] == g]
                tree = cKDTree(data.xy[members])
                self._trees[int(g)] = (tree, members)
                for k, near in enumerate(tree.query_ball_point(data.xy[members], d_pos)):
                    i = int(members[k])
                    js = members[np.asarray(near, dtype=np.int64)]
                    js = js[js != i]
                    if len(js):
                        cross = js[data.session[js] != data.session[i]]
                        pos[i] = (js, cross)
        self.positives = pos
        self.queries = np.asarray(sorted(pos), dtype=np.int64)
        if len(self.queries) == 0:
            raise DiscoError(
                f"no positive pairs within {d_pos} m: check --d-pos against the scan spacing"
            )

    def negative_mask(self, i: int, js: np.ndarray) -> np.ndarray:
        d = self.data
        if self.self_supervised:
            same = d.session[js] == d.session[i]
            return same & (np.abs(d.frame[js] - d.frame[i]) >= self.time_gap)
        far = np.linalg.norm(d.xy[js] - d.xy[i], axis=1) > self.d_neg
        return far | (d.group[js] != d.group[i])

    def positive(self, i: int, rng: np.random.Generator) -> int:
        js, cross = self.positives[i]
        if len(cross) and rng.random() < _CROSS_SESSION:
            return int(rng.choice(cross))
        return int(rng.choice(js))

    def _random_negatives(self, i: int, k: int, rng: np.random.Generator) -> np.ndarray:
        found: list[np.ndarray] = []
        n = 0
        for _ in range(20):
            cand = rng.choice(self.pool, size=max(8 * k, 32))
            good = cand[self.negative_mask(i, cand)]
            found.append(good)
            n += len(good)
            if n >= k:
                break
        good = np.concatenate(found)
        if len(good) == 0:
            raise DiscoError(
                f"scan {i} has no negatives beyond {self.d_neg} m: "
                "the data covers too small an area"
            )
        return good[:k] if len(good) >= k else rng.choice(good, size=k)

    def negatives(self, i: int, k: int, rng: np.random.Generator) -> np.ndarray:
        """k negatives of anchor i: half from its hard list once mining has run."""
        hard = self.hard.get(i)
        if hard is not None and len(hard):
            nh = k // 2
            picked = rng.choice(hard, size=nh, replace=len(hard) < nh)
            return np.concatenate([picked, self._random_negatives(i, k - nh, rng)])
        return self._random_negatives(i, k, rng)

    def other_negative(self, i: int, negs: np.ndarray, rng: np.random.Generator) -> int:
        """A negative of i that is also a negative of every one of negs (the quadruplet's 4th)."""
        for _ in range(20):
            cand = self._random_negatives(i, 16, rng)
            for c in cand:
                if np.all(self.negative_mask(int(c), negs)):
                    return int(c)
        return int(self._random_negatives(i, 1, rng)[0])

    def verify_set(
        self, i: int, n: int, radius: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """n scans of other sessions within `radius` of anchor i: the nearest and n - 1
        others at random, with their distances (m); None when the nearest is beyond d_pos
        or fewer than n lie that close."""
        d = self.data
        tree, members = self._trees[int(d.group[i])]
        js = members[np.asarray(tree.query_ball_point(d.xy[i], radius), dtype=np.int64)]
        js = js[d.session[js] != d.session[i]]
        if len(js) < n:
            return None
        dist = np.linalg.norm(d.xy[js] - d.xy[i], axis=1)
        first = int(np.argmin(dist))
        if dist[first] > self.d_pos:
            return None
        rest = np.delete(np.arange(len(js)), first)
        pick = np.concatenate([[first], rng.choice(rest, size=n - 1, replace=False)])
        return js[pick], dist[pick]

    def update_hard(self, signatures: np.ndarray, per_anchor: int = 10, search: int = 64) -> None:
        """Hard negatives: the anchors' nearest signatures that are true negatives.

        `signatures` are of `self.pool` (the original scans), in that order.
        """
        nn = _nearest_rows(np.asarray(signatures, dtype=np.float32), min(search, len(self.pool)))
        index = {int(a): r for r, a in enumerate(self.pool)}
        hard: dict[int, np.ndarray] = {}
        for i in self.queries:
            r = index[int(i)]
            cand = self.pool[np.atleast_1d(nn[r])]
            cand = cand[self.negative_mask(int(i), cand)][:per_anchor]
            hard[int(i)] = cand
        self.hard = hard


def _nearest_rows(x: np.ndarray, k: int, block: int = 1024) -> np.ndarray:
    """Indices [N, k] of each row's k nearest rows (itself included), by squared distance.

    Blocked matrix products: in 1024 dimensions a k-d tree degenerates to a slow brute
    force, and tens of thousands of training scans made it the slowest part of an epoch.
    """
    sq = (x * x).sum(axis=1)
    out = np.empty((len(x), k), dtype=np.int64)
    for s in range(0, len(x), block):
        d = sq[s : s + block, None] - 2.0 * (x[s : s + block] @ x.T) + sq[None, :]
        part = np.argpartition(d, k - 1, axis=1)[:, :k]
        order = np.argsort(np.take_along_axis(d, part, axis=1), axis=1, kind="stable")
        out[s : s + block] = np.take_along_axis(part, order, axis=1)
    return out
