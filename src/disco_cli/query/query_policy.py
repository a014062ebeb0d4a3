"""Every setting of the query stage, in one frozen value passed to it (`search.match_queries`).

A query goes: the signature search (the query's own, and its views' beside it), the
re-ranking of the nearest candidates by their feature images, one score that orders the
rows and is the `distance` they show, the snap (a tie-break of that score), and the yaw.
Each number that steers those steps is a field here, with why it has its value and
where that was measured; each rule can be switched off through its field (0 or ()), so
that an ablation is `dataclasses.replace(policy, field=0)`.

A model carries the policy it was tuned with (`model.query_policy`: DiSCO's is the
defaults below, Scan Context's and the spectral floor's switch off what they cannot
do). Command-line options and `Map.query`'s keywords make a new one with `policy_for`;
nothing changes a model.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, replace
from typing import Any

from disco_cli.errors import DiscoError

__all__ = ["QueryPolicy", "NO_RERANKING", "policy_for"]


@dataclass(frozen=True)
class QueryPolicy:
    # Nearest signatures re-ranked by the aligned correlation of their feature images
    # (model/verify.py); 0: rows in signature order, nothing below applies but the yaw.
    rerank_candidates: int = 10
    # Where even the best of those re-ranks worse than `rerank_wider_above`, the place may
    # have changed more than the signature tolerates: re-rank down to `rerank_wider`
    # (0: never). The fewest misses on the selection worlds 5001-5008 of the thresholds
    # 0.3-0.9 (docs/research/model-history.md, "Re-ranking wider when unsure").
    rerank_wider: int = 40
    rerank_wider_above: float = 0.7
    # The score subtracts this over the candidate's signature distance (its nearest, the
    # query's views included): a near signature outweighs re-rank distances that are all
    # alike; far ones differ by little. The largest of 0.1-0.4 with which no selection
    # world (5001-5008, 5101-5103) fell below re-ranking alone (model-history.md,
    # "Re-ranking with the signature"). Checked again on the calibrated selection worlds
    # 8621-8623: without it 2 / 4 / 4 fewer queries right (NCLT- / MulRan- / Oxford-like)
    # and Oxford-like R@100%P 0.518 -> 0.453 (docs/results.md). 0: the re-rank distance
    # alone.
    signature_weight: float = 0.3
    # The signature distance the bonus above stops growing at: a copy of the query in
    # the map (s = 0) gets weight / floor, no more, so the distance stays bounded and
    # no row's distance depends on another's. Below every true match's signature
    # distance on the selection worlds 8621-8623 (docs/confidence.md), so the rows'
    # order is today's wherever the map holds no copy.
    signature_floor: float = 0.05
    # The query's views: its feature images re-centred this many metres to either side
    # along its own y axis (a revisit 4-8 m beside the map's route), searched beside the
    # query and re-ranked at their best. +-4/6 m gave what +-4..6 m did on every
    # selection world, one view a side lost queries on 5102/5103 (model-history.md,
    # "Query-side views, built"). On the calibrated selection worlds 8621-8623 they gain
    # 4 of 3,723 queries (0 / 1 / 3) for about 3 ms of a query (bench_query.py): the
    # weakest rule that still gains, so it stays (docs/results.md). (): no views.
    view_offsets: tuple[float, ...] = (4.0, 6.0)
    # Added to a view's re-rank distance: a view sees less than the scan, so where both
    # re-rank alike the scan's own wins (chosen with the offsets, same worlds).
    view_penalty: float = 0.03
    # From this many map scans the views search the map's projected signatures (96 axes,
    # 4x widened, re-measured exactly; query_views.ProjectedSignatures): four more exact
    # passes over 10,000 scans cost 0.37 ms each; 0.94 of the views' nearest rows are the
    # exact ones ("Query-side views, built"). The query's own search stays exact.
    approximate_views_from: int = 4096
    # The snap, a tie-break of the score: among candidates within `snap_radius` m of the
    # best on the map whose own re-rank distance is within `snap_margin` of the best's,
    # the one nearest the query's position (estimated from the best match) takes the
    # best's score and goes first. 5 m is as far as the position estimate reaches
    # (3 + 1.5 + 0.5 m); it found all 27 "a metre past the true scan" misses of the
    # suite's 47 and lost none (model-history.md, "Snapping to the nearest map scan").
    # On the calibrated selection worlds 8621-8623 it gains 107 of 3,723 queries (44 / 63
    # / 0), the wider pass above 36 (11 / 25 / 0) (docs/results.md). 0: no snap.
    snap_radius: float = 5.0
    snap_margin: float = 0.1
    # How many best matches get the parallax-free yaw (model/yaw_refine.py): about 1.5 ms
    # each, so only the best by default; 0: plain phase correlation.
    refine_yaw: int = 1
    # Below this yaw confidence (1 - the best other heading's peak / the yaw's own) the
    # parallax-free yaw searches the other heading too and keeps the one the images'
    # plain correlation prefers: alike streets give 0.1-0.55, asymmetric ones 0.8-0.95.
    # On test_yaw_flip's street alike both ways the search before it turned 5 of 24
    # queries around, the check none; on selection world 5103, 3 of 111 yaws over 10
    # degrees before, none with it (model-history.md, "The yaw check"). The calibrated
    # selection worlds 8621-8623 have no such street: it moved 2 of 3,723 queries' yaws
    # by over 1 degree (10.6 -> 6.0; one wrong either way), and it stays for the streets
    # alike both ways that issue 24 asked never to flip (docs/results.md). 0: no check.
    # (The search's grid, 3 m steps reaching 6 m to the query's sides, is the model's:
    # model/yaw_refine.py.)
    yaw_check_below: float = 0.6
    # The geometric check (query/verification.py): the best this many rows get the
    # layout check (their height images phase-correlated with the query's, a few ms
    # each) and a confidence with its evidence. It needs the map's scans (their files);
    # where they cannot be read the rows stay unchecked. The best 3 hold the true place
    # for 0.3-1.0 % more queries than the first alone on the selection worlds 8621-8623
    # (docs/confidence.md). 0: no check, the cheaper path (`--no-check`).
    check_candidates: int = 3
    # A checked row goes first only where the first's confidence is below this and its
    # own is higher: of 8 promotion rules tried on the selection worlds' rows (always,
    # by margins of 0.1-0.5, below 0.3 or 0.5), the one that lost no NCLT-like query
    # (0.960) and gained MulRan- and Oxford-like ones (0.930 -> 0.935, 0.741 -> 0.749);
    # always promoting lost 2 % on NCLT-like, whose neighbours 1 m apart all look right
    # (docs/confidence.md). 0: never.
    check_promotes_below: float = 0.3

    def __post_init__(self) -> None:
        """Every field against its range, refused in one `DiscoError` line naming it
        (a value out of range crashed the stage, or quietly turned a rule around: a
        negative `snap_margin` left the snap no candidate to choose; a negative weight or
        penalty favours what it should hold back). Integral floats become ints; an
        infinite margin or threshold is one that never binds. (tests/test_query_policy.py
        holds every field to having a range here.)"""
        counts = ("rerank_candidates", "rerank_wider", "approximate_views_from", "refine_yaw",
                  "check_candidates")  # fmt: skip
        # Each number's range, as (in range?, what it must be). Re-rank distances are
        # 1 - a correlation (0..2), signature distances those of unit vectors (0..2), a
        # yaw confidence 0..1; inf is allowed only where it means "never binds".
        ranges = {
            "rerank_wider_above": (
                lambda v: 0 <= v <= 2 or v == math.inf,
                "a re-rank distance in 0..2 (1 - a correlation), or inf: never wider",
            ),
            "signature_weight": (lambda v: 0 <= v < math.inf, "a finite weight >= 0"),
            "signature_floor": (lambda v: 0 < v <= 2, "a signature distance in (0, 2]"),
            "view_penalty": (lambda v: 0 <= v < math.inf, "a finite re-rank distance >= 0"),
            "snap_radius": (lambda v: 0 <= v < math.inf, "a finite snap radius >= 0 m (0: none)"),
            "snap_margin": (lambda v: v >= 0, "a re-rank distance >= 0, or inf: any"),
            "yaw_check_below": (lambda v: 0 <= v <= 1, "a yaw confidence in 0..1 (0: no check)"),
            "check_promotes_below": (lambda v: 0 <= v <= 1, "a confidence in 0..1 (0: never)"),
        }
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            real = isinstance(value, numbers.Real) and not isinstance(value, bool)
            if name in counts:
                if not real or not math.isfinite(value) or int(value) != value or value < 0:
                    raise DiscoError(f"{name} must be an integer >= 0, not {value!r}")
                object.__setattr__(self, name, int(value))
            elif name in ranges:
                in_range, what = ranges[name]
                if not real or math.isnan(value) or not in_range(float(value)):
                    raise DiscoError(f"{name} must be {what}, not {value!r}")
        try:
            if isinstance(self.view_offsets, str):
                raise TypeError
            offsets = tuple(float(o) for o in self.view_offsets)
        except (TypeError, ValueError):
            offsets = None
        if offsets is None or any(not math.isfinite(o) or o <= 0 for o in offsets):
            raise DiscoError(
                f"view_offsets must be distances > 0 m (none: no views), not {self.view_offsets!r}"
            )
        object.__setattr__(self, "view_offsets", offsets)

    @property
    def wider(self) -> int:
        """The second pass's depth, 0 where there is none (no re-ranking, or a first
        pass as deep)."""
        if self.rerank_candidates == 0 or self.rerank_wider <= self.rerank_candidates:
            return 0
        return self.rerank_wider

    @property
    def snaps(self) -> bool:
        """Whether the snap runs: it moves among re-ranked candidates only."""
        return self.rerank_candidates > 0 and self.snap_radius > 0

    def report(self) -> dict[str, Any]:
        """The policy as an evaluation report's "policy" entry (every field)."""
        out = asdict(self)
        out["view_offsets"] = list(self.view_offsets)
        return out


# A model that cannot re-rank: rows in signature order with the plain yaw.
NO_RERANKING = QueryPolicy(
    rerank_candidates=0,
    rerank_wider=0,
    signature_weight=0.0,
    view_offsets=(),
    snap_radius=0.0,
    refine_yaw=0,
)


def policy_for(
    model: Any,
    base: QueryPolicy | None = None,
    *,
    rerank: int | None = None,
    rerank_wider: int | None = None,
    snap_radius: float | None = None,
    refine_yaw: int | None = None,
    check: bool = True,
) -> QueryPolicy:
    """`base` (default: the model's own `query_policy`) with the settings given (None:
    unchanged), checked against what the model can do: one `DiscoError` naming the
    option otherwise. `check=False`: no geometric check of the candidates
    (`check_candidates` 0, the cheaper path)."""
    policy = model.query_policy if base is None else base
    can = model.abilities
    changes: dict[str, Any] = {}
    if rerank is not None:
        if rerank > 0 and not can.rerank:
            raise DiscoError(f"model {model.name} cannot re-rank; use --rerank 0")
        changes["rerank_candidates"] = rerank
    if rerank_wider is not None:
        if rerank_wider > 0 and not model.query_policy.rerank_wider:
            raise DiscoError(
                f"model {model.name} has no wider re-ranking pass; leave out --rerank-wider"
            )
        changes["rerank_wider"] = rerank_wider
    if snap_radius is not None:
        if snap_radius > 0 and not can.locate:
            raise DiscoError(
                f"model {model.name} cannot estimate the query's position; use --snap-radius 0"
            )
        changes["snap_radius"] = snap_radius
    if refine_yaw is not None:
        # A model without the parallax-free yaw gives every row its plain one.
        changes["refine_yaw"] = refine_yaw if can.refine_yaw else 0
        if refine_yaw < 0:
            changes["refine_yaw"] = refine_yaw  # refused by the check below
    if not check:
        changes["check_candidates"] = 0
    return replace(policy, **changes) if changes else policy
