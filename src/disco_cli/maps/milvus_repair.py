"""A Milvus map's check and the settling of appends cut off halfway (`milvus_store.py`).

An append is three requests (side views, scans, counters) under an intent row
(`milvus_lock.py`). One cut off between them (a killed process, a writer that lost its
lease) leaves its intent: `check_map` reports it in one line, and `settle` (`disco
build-db --repair`) finishes it when every scan row is the intent's own (by its
checksum) and sound with all its side views, or else undoes it: it deletes the intent's
own rows only (another writer's rows at those ids are never touched) and records its
ids as never given.
"""

from __future__ import annotations

from typing import Any

from disco_cli.maps.milvus_lock import (
    WriteLock,
    advance_counters,
    drop_intent,
    read_state,
)

__all__ = ["check_map", "cut_off_line", "settle", "undo"]

# A `copy_map` into Milvus holds this meta key until its last batch is in.
COPY_MARK = "copy_incomplete"


def _span(ids: list[int]) -> str:
    return f"ids {ids[0]}-{ids[-1]}" if ids else "no ids"


def cut_off_rows(db: Any, intent: dict) -> tuple[list[int], set[int], dict[int, int]]:
    """The ids of `intent`, those whose scan row is the intent's own (its checksum),
    and how many side views each of its ids has."""
    ids = list(range(int(intent.get("start", 0)), int(intent.get("end", 0))))
    if not ids:
        return ids, set(), {}
    crcs = set(intent.get("crcs") or ())
    within = f"id >= {ids[0]} and id <= {ids[-1]}"
    own = {int(r["id"]) for r in db._query(within, ["id", "crc"]) if r.get("crc") in crcs}
    views: dict[int, int] = {}
    if db.side_offsets:
        views_within = f"scan_id >= {ids[0]} and scan_id <= {ids[-1]}"
        for v in db._query(views_within, ["scan_id"], db._views_c):
            views[int(v["scan_id"])] = views.get(int(v["scan_id"]), 0) + 1
    return ids, own, views


def cut_off_line(db: Any, intent: dict) -> str:
    ids, own, views = cut_off_rows(db, intent)
    text = f"an append cut off halfway: {_span(ids)}, {len(own)} of {len(ids)} scan rows"
    if db.side_offsets:
        text += f" and {sum(views.values())} of {len(ids) * len(db.side_offsets)} side views"
    return text + " written; disco build-db --repair finishes or undoes it"


def undo(db: Any, epoch: int, intent: dict) -> None:
    """Delete what the append of `intent` stored (its own rows, and side views with no
    scan row) and its intent, recording its ids as never given. Best effort: whatever
    stays is reported by `check_map`."""
    try:
        ids, own, _ = cut_off_rows(db, intent)
        if ids and db.side_offsets:
            held = {int(r["id"]) for r in db._query(f"id >= {ids[0]} and id <= {ids[-1]}", ["id"])}
            loose = [i for i in ids if i in own or i not in held]
            if loose:
                db._client.delete(db._views_c, filter=f"scan_id in {loose}")
        if own:
            db._client.delete(db._scans, filter=f"id in {sorted(own)}")
        drop_intent(db._client, db._meta_c, epoch, (ids[0], ids[-1] + 1) if ids else None)
    except Exception:
        pass


def settle(db: Any) -> list[str]:
    """Finish or undo every append cut off halfway, holding the writers' lock; one line
    for each."""
    done: list[str] = []
    with WriteLock(db._client, db._meta_c, db.path) as lock:
        state = lock.check()
        for epoch, intent in sorted(state.cut_off().items()):
            lock.check()
            ids, own, views = cut_off_rows(db, intent)
            whole = (
                bool(ids)
                and own == set(ids)
                and all(views.get(i, 0) == len(db.side_offsets) for i in ids)
                and all(
                    db._scan_problem_m(r) is None
                    for r in db._query(f"id >= {ids[0]} and id <= {ids[-1]}", db._SCAN_FIELDS)
                )
            )
            if whole:
                now = read_state(db._client, db._meta_c)
                advance_counters(db._client, db._meta_c, now, ids[-1] + 1, now.generation + 1)
                drop_intent(db._client, db._meta_c, epoch, None)
                done.append(f"finished an append cut off halfway ({_span(ids)})")
            else:
                undo(db, epoch, intent)
                done.append(
                    f"undid an append cut off halfway ({_span(ids)}, {len(own)} rows written)"
                )
        db._read_counters()
    return done


def check_map(db: Any) -> list[str]:
    """Every problem of the map: every row through the checks a read makes, the side
    views, appends cut off halfway, an unfinished copy, and ids missing below `next_id`
    (ids are never skipped but by an undone append)."""
    db.damaged = {}
    problems: list[str] = []
    state = db._read_counters()
    if COPY_MARK in db.meta:
        problems.append(
            f"an unfinished copy from {db.meta[COPY_MARK]}: it lacks scans; "
            "copy it again (disco build-db --from ... replaces it)"
        )
    # Ids an append still writes or that one cut off left: reported as such, not by row.
    pending: set[int] = set()
    for intent in state.intents.values():
        pending.update(range(int(intent.get("start", 0)), int(intent.get("end", 0))))
    for intent in state.cut_off().values():
        problems.append(cut_off_line(db, intent))
    never = {i for a, b in state.gaps for i in range(a, b)}
    fields = [*db._SCAN_FIELDS, "features", "feature_scale", "feature_crc"]
    rows = sorted(
        (r for r in db._query("", fields) if int(r["id"]) not in pending),
        key=lambda r: int(r["id"]),
    )
    names = {int(r["id"]): r.get("path") for r in rows}
    _, _, bad = db._sound_rows(rows)
    for r in rows:
        rid = int(r["id"])
        if rid not in bad:
            problem = db._features_of(rid, r)[1]
            if problem:
                bad[rid] = problem
    if db.side_offsets:
        views = [v for v in db._view_rows() if int(v["scan_id"]) not in pending]
        for rid, problem in db._view_problems(views)[1].items():
            bad.setdefault(rid, problem)
        counts: dict[int, int] = {}
        for v in views:
            counts[int(v["scan_id"])] = counts.get(int(v["scan_id"]), 0) + 1
        for rid in names:
            if counts.get(rid, 0) != len(db.side_offsets):
                bad.setdefault(rid, "lacks some of its side views")
    gone = sorted(set(range(1, state.next_id)) - set(names) - pending - never)
    if gone:
        shown = ", ".join(map(str, gone[:20])) + (" ..." if len(gone) > 20 else "")
        problems.append(f"{len(gone)} scans missing (ids {shown}): rows deleted")
    for rid in sorted(bad):
        problems.append(f"scan {rid} ({names.get(rid, '?')}): {bad[rid]}")
    db._note_damaged(bad, names)
    return problems
