"""The write protocol of a Milvus map (`milvus_store.py`): the writers' lock (a lease
renewed by a heartbeat, and a fencing epoch), counters that only move forward, and the
intents that let a write cut off halfway be found and settled.

Milvus has no transaction over two requests and no compare-and-swap. Everything here
is built from inserts of keys never stored before, deletes, and strongly consistent
reads; nothing relies on an insert of a stored key replacing the earlier row (Milvus
Lite replaces it; a Milvus server's behaviour is not verified here, docs/scaling.md).
The rows, in the map's meta collection beside its meta keys (which hold no ":"):

- `lock:TOKEN:BEAT`: a writer's claim. A writer inserts one, reads every claim, and
  holds the lock when no other writer's claim is there; else it deletes its own, waits
  a random moment and tries again. Of two claims the later one's writer reads after the
  earlier was stored, and steps back. While it holds the lock a heartbeat thread
  inserts the next BEAT and deletes the one before, every quarter of the lease.
  Another writer takes a claim as a dead writer's once it has watched the same BEAT
  for the lease (`DISCO_MILVUS_LEASE_S`, default 600 s; on its own clock: the machines'
  clocks need not agree) and deletes it.
- `fence:EPOCH`: a writer that takes the lock inserts the next epoch; the current
  epoch is the largest. Before each step of a write (`WriteLock.check`) the writer
  reads that its claim is there and that the epoch is still its own. A writer that
  stalled past its lease (a paused process, a swapping computer) finds a later epoch
  and stops with one line (`LostLock`).
- `counter:next:N`, `counter:gen:N`: `next_id` and `generation`, each the largest of
  its rows (and of the plain `next_id` and `generation` keys that older versions
  read); a commit inserts a larger row and deletes smaller ones, so neither moves back.
- `intent:EPOCH`: the ids `[start, end)` a write under EPOCH is giving and its rows'
  checksums, inserted before its first row and deleted when it commits. A writer
  starts after every intent's end (a stalled writer may still insert there). The
  writer inserts its intent and then checks the fence; the next holder inserts its
  fence and then reads the intents: one of the two sees the other's row, so either the
  stalled writer stops before writing a row or the next holder keeps clear of its ids.
  An intent whose writer lost the lock is an append cut off halfway: `check` reports
  it and `settle` finishes it (every row there, sound) or undoes it.
- `gap:START`: ids `[start, end)` an undone write held, never given (not reported
  as rows deleted).
"""

from __future__ import annotations

import json
import math
import os
import random
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

from disco_cli.errors import DatabaseError, DiscoError

__all__ = [
    "LEASE_ENV",
    "LEASE_S",
    "LostLock",
    "MapState",
    "WriteLock",
    "lease_seconds",
    "read_state",
    "advance_counters",
    "is_protocol_key",
]

# Seconds a claim may stay unchanged before another writer takes it as a dead one's.
LEASE_S = 600.0
LEASE_ENV = "DISCO_MILVUS_LEASE_S"
_CLAIM = "lock:"
_FENCE = "fence:"
_NEXT = "counter:next:"
_GEN = "counter:gen:"
_INTENT = "intent:"
_GAP = "gap:"
_ALL_ROWS = 16384  # Milvus's query window: far above the meta rows a map keeps


def lease_seconds(value: float | None = None) -> float:
    """The lease: `value`, else `DISCO_MILVUS_LEASE_S`, else `LEASE_S`."""
    if value is not None:
        return float(value)
    text = os.environ.get(LEASE_ENV)
    if text is None:
        return LEASE_S
    try:
        got = float(text)
    except ValueError:
        got = math.nan
    if not (math.isfinite(got) and got > 0):
        raise DiscoError(f"{LEASE_ENV}: a number of seconds above 0, not {text!r}")
    return got


def is_protocol_key(key: str) -> bool:
    """A row of the write protocol, not a meta key of the map."""
    return ":" in key


def _padded(n: int) -> str:
    return f"{int(n):020d}"


def _number(key: str) -> int:
    return int(key.rsplit(":", 1)[1])


@dataclass
class MapState:
    """What the write protocol's rows say, read at one instant."""

    next_id: int = 1
    generation: int = 0
    fence: int = 0
    claims: dict[str, list[str]] = field(default_factory=dict)  # token -> its claim keys
    claim_values: dict[str, str] = field(default_factory=dict)  # token -> latest value
    intents: dict[int, dict] = field(default_factory=dict)  # epoch -> intent
    gaps: list[tuple[int, int]] = field(default_factory=list)
    keys: set[str] = field(default_factory=set)

    def free_from(self) -> int:
        """The first id no one has given or may still be giving."""
        ends = [int(i["end"]) for i in self.intents.values()] + [e for _, e in self.gaps]
        return max([self.next_id, *ends])

    def cut_off(self) -> dict[int, dict]:
        """Intents whose writer no longer holds the lock."""
        return {
            e: i
            for e, i in self.intents.items()
            if e != self.fence or i.get("token") not in self.claims
        }


def fold_state(rows: dict[str, str]) -> MapState:
    """A `MapState` from the meta collection's rows (`{key: value}`)."""
    s = MapState(keys=set(rows))
    nexts, gens, fences = [], [], [0]
    for key, value in rows.items():
        if key.startswith(_CLAIM):
            token = key.split(":")[1]
            s.claims.setdefault(token, []).append(key)
            if key == max(s.claims[token]):
                s.claim_values[token] = value
        elif key.startswith(_FENCE):
            fences.append(_number(key))
        elif key.startswith(_NEXT):
            nexts.append(_number(key))
        elif key.startswith(_GEN):
            gens.append(_number(key))
        elif key.startswith(_INTENT):
            try:
                s.intents[_number(key)] = json.loads(value)
            except ValueError:
                s.intents[_number(key)] = {"start": 0, "end": 0, "token": "?", "crcs": []}
        elif key.startswith(_GAP):
            try:
                got = json.loads(value)
                s.gaps.append((int(got["start"]), int(got["end"])))
            except (ValueError, KeyError, TypeError):
                pass
    for legacy, into in (("next_id", nexts), ("generation", gens)):
        try:
            into.append(int(rows[legacy]))
        except (KeyError, ValueError):
            pass
    s.next_id = max(nexts, default=1)
    s.generation = max(gens, default=0)
    s.fence = max(fences)
    return s


def _rows(client: Any, collection: str, filt: str = 'key != ""') -> dict[str, str]:
    got = client.query(
        collection,
        filter=filt,
        output_fields=["key", "value"],
        limit=_ALL_ROWS,
        consistency_level="Strong",
    )
    return {r["key"]: r["value"] for r in got}


def read_state(client: Any, collection: str) -> MapState:
    # The protocol's rows, and the plain counters an older disco wrote alone.
    filt = 'key like "%:%" or key in ["next_id", "generation"]'
    return fold_state(_rows(client, collection, filt))


def insert_keys(client: Any, collection: str, values: dict[str, str]) -> None:
    if values:
        rows = [{"key": k, "value": v, "v": [0.0, 0.0]} for k, v in values.items()]
        client.insert(collection, rows)


def delete_keys(client: Any, collection: str, keys: Any) -> None:
    keys = sorted(keys)
    if keys:
        client.delete(collection, filter=f"key in {json.dumps(keys)}")


def advance_counters(
    client: Any, collection: str, state: MapState, next_id: int, generation: int
) -> None:
    """Raise `next_id` and `generation` to at least these values: new rows, then the
    smaller rows deleted (the plain keys, for older readers, follow)."""
    next_id, generation = max(next_id, state.next_id), max(generation, state.generation)
    insert_keys(client, collection, {_NEXT + _padded(next_id): "", _GEN + _padded(generation): ""})
    client.upsert(
        collection,
        [
            {"key": "next_id", "value": str(next_id), "v": [0.0, 0.0]},
            {"key": "generation", "value": str(generation), "v": [0.0, 0.0]},
        ],
    )
    old = [
        k
        for k in state.keys
        if (k.startswith(_NEXT) and _number(k) < next_id)
        or (k.startswith(_GEN) and _number(k) < generation)
    ]
    delete_keys(client, collection, old)


def write_intent(client: Any, collection: str, epoch: int, value: dict) -> None:
    insert_keys(client, collection, {_INTENT + _padded(epoch): json.dumps(value)})


def drop_intent(client: Any, collection: str, epoch: int, gap: tuple[int, int] | None) -> None:
    """Delete the intent of `epoch`, recording `gap` (ids never given) first."""
    if gap is not None and gap[1] > gap[0]:
        value = json.dumps({"start": gap[0], "end": gap[1]})
        insert_keys(client, collection, {_GAP + _padded(gap[0]): value})
    delete_keys(client, collection, [_INTENT + _padded(epoch)])


class LostLock(DatabaseError):
    """A writer that stalled past its lease: another writer holds the map now."""


class WriteLock:
    """`with WriteLock(client, meta_collection) as lock:` holds the map's writers' lock;
    `lock.check()` before each step of a write, `lock.epoch` its fencing epoch."""

    def __init__(
        self, client: Any, collection: str, where: Any = "map", lease: float | None = None
    ):
        self._client = client
        self._collection = collection
        self._where = where
        self.lease = lease_seconds(lease)
        self.epoch = 0
        self.token = ""
        self._beat = 0
        self._value = json.dumps({"host": socket.gethostname(), "pid": os.getpid()})
        self._lost = False
        self._renewed = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def claims(self) -> dict[str, str]:
        return _rows(self._client, self._collection, f'key like "{_CLAIM}%"')

    def clear_other_processes(self) -> None:
        """Delete the claims of other processes (a Milvus Lite folder takes one process
        at a time: theirs are leftovers). This process's own claims are kept."""
        dead = [k for k, v in self.claims().items() if v != self._value]
        delete_keys(self._client, self._collection, dead)

    def _claim_key(self) -> str:
        return f"{_CLAIM}{self.token}:{self._beat:08d}"

    def __enter__(self) -> WriteLock:
        seen: dict[tuple[str, str], float] = {}  # (token, latest beat) -> first seen here
        wait = 0.02
        while True:
            self.token, self._beat = uuid.uuid4().hex, 0
            insert_keys(self._client, self._collection, {self._claim_key(): self._value})
            now = time.monotonic()
            state = read_state(self._client, self._collection)
            others = {t: k for t, k in state.claims.items() if t != self.token}
            dead = [
                t
                for t, k in others.items()
                if now - seen.setdefault((t, max(k)), now) >= self.lease
            ]
            delete_keys(self._client, self._collection, [k for t in dead for k in others[t]])
            if not set(others) - set(dead):
                self.epoch = state.fence + 1
                insert_keys(
                    self._client, self._collection, {_FENCE + _padded(self.epoch): self.token}
                )
                after = read_state(self._client, self._collection)
                if self.token in after.claims and after.fence == self.epoch:
                    old = [
                        k for k in after.keys if k.startswith(_FENCE) and _number(k) < self.epoch
                    ]
                    delete_keys(self._client, self._collection, old)
                    self._start_heartbeat()
                    return self
                # Another writer fenced meanwhile, or took this claim as dead: again.
            self._release()
            time.sleep(random.uniform(wait / 2, wait))
            wait = min(wait * 2, 0.5)

    def check(self) -> MapState:
        """The map's state, when this writer still holds the lock; else `LostLock`."""
        state = read_state(self._client, self._collection)
        if self._lost or self.token not in state.claims or state.fence != self.epoch:
            self._lost = True
            stalled = time.monotonic() - self._renewed
            raise LostLock(
                self._where,
                f"this write lost the map's writers' lock: its claim went {stalled:.0f} s "
                f"without renewal (the lease is {self.lease:g} s; the process was paused, or "
                "could not reach Milvus) and another writer has taken the map; nothing of "
                "this write is kept; run it again",
            )
        return state

    def _start_heartbeat(self) -> None:
        self._lost = False
        self._renewed = time.monotonic()
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._heartbeat, name="disco-milvus-lease", daemon=True
        )
        self._thread.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.lease / 4):
            try:
                state = read_state(self._client, self._collection)
                mine = state.claims.get(self.token)
                if not mine or state.fence != self.epoch:
                    self._lost = True  # taken over: never put the claim back
                    return
                self._beat += 1
                insert_keys(self._client, self._collection, {self._claim_key(): self._value})
                delete_keys(self._client, self._collection, mine)
                self._renewed = time.monotonic()
            except Exception:
                continue  # renewed at the next beat; `check` decides whether it still holds

    def __exit__(self, kind: Any, *exc: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        try:
            self._release()
        except Exception:
            if kind is None:
                raise
            # The write's own error says more; the claim is left for the lease to clear.

    def _release(self) -> None:
        if self.token:
            token, self.token = self.token, ""
            mine = self.claims()
            delete_keys(
                self._client, self._collection, [k for k in mine if k.split(":")[1] == token]
            )
