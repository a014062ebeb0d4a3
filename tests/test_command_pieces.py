"""Library pieces the thin commands call: printing in blocks, query rows, loop columns."""

from __future__ import annotations

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.maps.facade import QueryResult
from disco_cli.maps.writing import AddResult
from disco_cli.query.localize import Match
from disco_cli.query.loop_detector import loop_columns
from disco_cli.runtime.console import in_blocks


def test_in_blocks_joins_groups_at_the_boundaries_and_skips_empty_blocks() -> None:
    groups = [[1], [], [2, 3], [], [], [], [4], []]
    # Written out by hand: groups 1-3, 4-6 (all empty: skipped), 7-8.
    assert list(in_blocks(groups, 3)) == [[1, 2, 3], [4]]
    assert list(in_blocks(groups, 1)) == [[1], [2, 3], [4]]
    assert list(in_blocks([[], []], 64)) == []
    assert list(in_blocks(([k] for k in range(5)), 2)) == [[0, 1], [2, 3], [4]]


def _match(rank: int, accepted: bool | None, T: np.ndarray | None, reason: str = "") -> Match:
    return Match(
        rank, rank, f"scan{rank}.bin", 0.1 * rank, 5.0, T=T, accepted=accepted, reason=reason
    )


def test_query_rows_filter_and_report() -> None:
    eye = np.eye(4)
    res = QueryResult(
        0,
        "q.bin",
        [
            _match(1, True, eye),
            _match(2, False, eye, "fitness 0.1 < 0.3"),  # rejected: a row unless --verify
            _match(3, False, None, "cannot read"),  # no pose: an error, never a row
            _match(4, None, None),  # the match's scan is missing: a row, pose columns empty
        ],
    )
    shown = lambda name: "maps/" + name  # noqa: E731
    keys = ["query", "rank", "match", "accepted", "dx"]
    rows, errors = res.rows(shown, keys)
    assert [r["rank"] for r in rows] == [1, 2, 4]
    assert errors == ["maps/scan3.bin: cannot read"]
    assert rows[0] == {
        "query": "q.bin",
        "rank": 1,
        "match": "maps/scan1.bin",
        "accepted": True,
        "dx": 0.0,
    }
    assert rows[2]["accepted"] is None and rows[2]["dx"] is None
    rows, errors = res.rows(shown, keys, verify=True)
    assert [r["rank"] for r in rows] == [1] and len(errors) == 1
    failed = QueryResult(1, "bad.bin", [], error=DiscoError("bad.bin: no points"))
    assert failed.rows(shown, keys) == ([], ["bad.bin: no points"])


def test_loop_columns_and_build_summary() -> None:
    columns, keys = loop_columns(pose=False)
    assert (
        columns
        == keys
        == ["query_index", "query", "match_index", "match"]
        + [
            "distance",
            "confidence",
            "yaw_deg",
            "yaw_conf",
        ]
    )
    columns, keys = loop_columns(pose=True, verbose=True)
    assert columns[8:] == ["roll_deg", "pitch_deg", "dx", "dy", "dz", "fitness", "rmse"] + [
        "accepted",
        "reason",
    ]
    assert keys == columns + ["T"]
    assert AddResult(written=20, already=3).summary(4.0) == (
        "wrote 20 scans in 4.0 s (5.0 scans/s), 3 were in it already"
    )
    assert AddResult(written=0).summary(0.0) == "wrote 0 scans in 0.0 s (0.0 scans/s)"
