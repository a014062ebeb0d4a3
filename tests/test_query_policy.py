"""The query stage's settings as one value (query_policy.py): bad values are refused by
name, options make a changed copy checked against what the model can do, and the stage
leaves out what a model cannot do."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import FrozenInstanceError, fields, replace
from pathlib import Path

import numpy as np
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


# For every field, values out of its range (or of no number at all) and the words its
# one-line refusal starts with: "<field> must be ...".
BAD = {
    "rerank_candidates": [-1, 2.5, True, float("inf"), float("nan"), "10", None],
    "rerank_wider": [-40, 0.5, False, float("inf")],
    "rerank_wider_above": [-0.1, 2.5, -float("inf"), float("nan"), "0.7", None],
    "signature_weight": [-0.3, float("inf"), float("nan"), "0.3", True],
    "signature_floor": [0.0, -0.05, 2.5, float("inf"), float("nan"), None],
    "view_offsets": [(4.0, -6.0), (float("inf"),), (0.0,), "4,6", 4.0, (4.0, "x"), None],
    "view_penalty": [-0.03, float("inf"), float("nan"), "0.03"],
    "approximate_views_from": [-1, 4096.5, float("inf")],
    "snap_radius": [-1.0, float("inf"), float("nan"), "5"],
    "snap_margin": [-0.1, -1e-9, -float("inf"), float("nan"), "0.1", None],
    "refine_yaw": [-2, 1.5, float("nan")],
    "yaw_check_below": [-0.1, 1.5, float("inf"), float("nan"), "0.6"],
    "check_candidates": [-1, 2.5, True, float("inf")],
    "check_promotes_below": [-0.1, 1.5, float("inf"), float("nan"), "0.3", None],
}


def test_every_field_has_a_range_and_is_refused_out_of_it_in_one_line() -> None:
    names = [f.name for f in fields(QueryPolicy)]
    assert not [n for n in names if n not in BAD], "a field without a range: check it"
    for name in names:
        for value in BAD[name]:
            with pytest.raises(DiscoError) as info:
                replace(QueryPolicy(), **{name: value})
            message = str(info.value)
            assert message.startswith(f"{name} must be ") and "\n" not in message, message
            assert message.endswith(f", not {value!r}"), message


def test_the_ends_of_each_range_are_accepted() -> None:
    p = QueryPolicy()
    for name, value in (
        ("rerank_wider_above", 0.0), ("rerank_wider_above", 2.0),
        ("rerank_wider_above", float("inf")),  # never wider
        ("signature_weight", 0.0), ("signature_floor", 2.0), ("view_penalty", 0.0),
        ("snap_radius", 0.0), ("snap_margin", 0.0), ("snap_margin", float("inf")),  # any
        ("yaw_check_below", 0.0), ("yaw_check_below", 1.0), ("view_offsets", ()),
        ("rerank_candidates", 0), ("check_candidates", 0), ("signature_weight", np.float32(1)),
        ("check_promotes_below", 0.0), ("check_promotes_below", 1.0),
    ):  # fmt: skip
        assert getattr(replace(p, **{name: value}), name) == value, name
    # Whole numbers given as floats (a JSON file, numpy) become ints: a slice takes them.
    q = replace(p, rerank_candidates=4.0, rerank_wider=np.int64(12), refine_yaw=np.float64(2))
    assert (q.rerank_candidates, q.rerank_wider, q.refine_yaw) == (4, 12, 2)
    assert all(type(v) is int for v in (q.rerank_candidates, q.rerank_wider, q.refine_yaw))


def test_a_negative_snap_margin_is_one_line_not_a_crash(tmp_path) -> None:
    """It crashed the snap ("attempt to get argmin of an empty sequence"): refused when
    the policy is made, by `Map.query`'s caller and by an ablation's `--policy`."""
    with pytest.raises(DiscoError, match=r"^snap_margin must be a re-rank distance >= 0"):
        replace(load_model("default").query_policy, snap_margin=-0.1)
    script = Path(__file__).resolve().parent.parent / "benchmarks" / "ood_eval.py"
    res = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "no-world"), "--models", "spectral",
         "--policy", "snap_margin=-0.1"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 1 and res.stdout == "", res.stdout
    assert res.stderr.strip().splitlines() == [
        "--policy snap_margin=-0.1: snap_margin must be a re-rank distance >= 0, or inf: any, "
        "not -0.1"
    ], res.stderr


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
