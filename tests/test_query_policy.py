"""The query stage's settings as one value (query_policy.py): bad values are refused by
name, options make a changed copy checked against what the model can do, and the stage
leaves out what a model cannot do."""

from __future__ import annotations

from dataclasses import FrozenInstanceError, replace

import pytest

from disco_cli.errors import DiscoError
from disco_cli.model import load_model
from disco_cli.query.query_policy import QueryPolicy, policy_for
from disco_cli.query.search import effective_policy


@pytest.mark.parametrize(
    "field, value",
    [
        ("rerank_candidates", -1),
        ("rerank_candidates", 2.5),
        ("rerank_wider", True),
        ("refine_yaw", -2),
        ("approximate_views_from", -1),
        ("signature_weight", float("nan")),
        ("snap_margin", float("nan")),
        ("yaw_check_below", float("nan")),
        ("view_offsets", (4.0, -6.0)),
        ("view_offsets", (float("inf"),)),
    ],
)
def test_a_bad_setting_is_refused_by_name(field, value) -> None:
    with pytest.raises(DiscoError, match=field.split("_")[0]):
        replace(QueryPolicy(), **{field: value})


def test_a_policy_is_a_value() -> None:
    p = QueryPolicy()
    with pytest.raises(FrozenInstanceError):
        p.rerank_candidates = 3  # type: ignore[misc]
    assert replace(p, view_offsets=[5, 7]).view_offsets == (5.0, 7.0)  # a tuple of floats
    assert replace(p, snap_margin=float("inf")).snap_margin == float("inf")  # never binds
    # The second pass exists only deeper than the first, and only with re-ranking.
    assert p.wider == p.rerank_wider > p.rerank_candidates
    assert replace(p, rerank_wider=p.rerank_candidates).wider == 0
    assert replace(p, rerank_candidates=0).wider == 0 and not replace(p, rerank_candidates=0).snaps
    assert p.report()["view_offsets"] == list(p.view_offsets)


def test_options_make_a_copy_checked_against_the_model() -> None:
    default, spectral, sc = load_model("default"), load_model("spectral"), load_model("scancontext")
    shipped = default.query_policy
    p = policy_for(default, rerank=4, rerank_wider=0, snap_radius=2.5, refine_yaw=3)
    assert (p.rerank_candidates, p.rerank_wider, p.snap_radius, p.refine_yaw) == (4, 0, 2.5, 3)
    assert default.query_policy == shipped  # the model's own is untouched
    assert policy_for(default) is shipped  # nothing given: the model's
    for model, option, message in (
        (spectral, {"rerank": 5}, "spectral cannot re-rank; use --rerank 0"),
        (spectral, {"rerank_wider": 5}, "spectral has no wider re-ranking pass"),
        (sc, {"rerank_wider": 50}, "scancontext has no wider re-ranking pass"),
        (sc, {"snap_radius": 5.0}, "scancontext cannot estimate the query's position"),
    ):
        with pytest.raises(DiscoError, match=message):
            policy_for(model, **option)
    # Asking for none of a rule is always fine; a yaw a model cannot refine stays plain.
    assert policy_for(spectral, rerank=0, rerank_wider=0, snap_radius=0).rerank_candidates == 0
    assert policy_for(sc, refine_yaw=2).refine_yaw == 0


def test_the_stage_leaves_out_what_a_model_cannot_do() -> None:
    full = QueryPolicy()
    spectral = effective_policy(load_model("spectral"), full)
    assert spectral.rerank_candidates == 0 and spectral.view_offsets == ()
    assert spectral.snap_radius == 0 and spectral.refine_yaw == full.refine_yaw
    sc = effective_policy(load_model("scancontext"), full)
    assert sc.rerank_candidates == full.rerank_candidates and sc.view_offsets == ()
    assert sc.snap_radius == 0 and sc.refine_yaw == 0
    assert effective_policy(load_model("default"), full) == full
