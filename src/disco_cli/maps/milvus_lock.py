"""The writers' lock of a Milvus map (`milvus_store.py`): one append at a time.

Milvus has no transaction and no compare-and-swap, and an insert whose id is already
stored replaces that row without a word (Milvus Lite's server and Milvus alike). Two
appends that read the same `next_id` would give their scans the same ids, and the
later one's rows would silently replace the earlier one's. So an append first takes
the lock, from nothing but inserts and strongly consistent reads:

1. insert a claim row `lock:TOKEN` (TOKEN unique to this append) into the meta
   collection;
2. read every claim; if another writer's is there, delete its own, wait a random
   moment and start again; else it holds the lock until it deletes its claim.

Two writers cannot both hold it: of two claims, the one inserted later was inserted
before its writer read the claims, and that read (strong consistency) sees the earlier
claim. Both may see each other and both step back; the random waits part them.

A writer killed while holding the lock leaves its claim. A claim another writer has
watched unchanged for `LEASE_S` seconds is taken as such a leftover and deleted (it
measures the time on its own clock: the machines' clocks need not agree); an append
that holds the lock longer than that (far beyond any append of a batch, or building the
HNSW index) is taken as dead. Milvus Lite takes one process per map folder, so there
every claim found when the map is opened for writing is a leftover (`clear`).
"""

from __future__ import annotations

import json
import os
import random
import socket
import time
import uuid
from typing import Any

__all__ = ["LEASE_S", "WriteLock"]

# Seconds a claim may stay unchanged before another writer takes it as a dead one's.
LEASE_S = 600.0
_PREFIX = "lock:"
_FILTER = f'key like "{_PREFIX}%"'


class WriteLock:
    """`with WriteLock(client, meta_collection):` holds the map's writers' lock."""

    def __init__(self, client: Any, collection: str):
        self._client = client
        self._collection = collection
        self._key = ""

    def claims(self) -> dict[str, str]:
        got = self._client.query(
            self._collection,
            filter=_FILTER,
            output_fields=["key", "value"],
            consistency_level="Strong",
        )
        return {r["key"]: r["value"] for r in got}

    def clear(self) -> None:
        """Delete every claim (Milvus Lite's leftovers, when opened for writing)."""
        keys = list(self.claims())
        if keys:
            self._client.delete(self._collection, filter=f"key in {json.dumps(keys)}")

    def __enter__(self) -> WriteLock:
        seen: dict[tuple[str, str], float] = {}  # (claim, value) -> first seen here
        wait = 0.02
        while True:
            self._key = _PREFIX + uuid.uuid4().hex
            value = json.dumps({"host": socket.gethostname(), "pid": os.getpid()})
            self._client.insert(
                self._collection, [{"key": self._key, "value": value, "v": [0.0, 0.0]}]
            )
            now = time.monotonic()
            others = {k: v for k, v in self.claims().items() if k != self._key}
            dead = [k for k, v in others.items() if now - seen.setdefault((k, v), now) >= LEASE_S]
            if dead:
                self._client.delete(self._collection, filter=f"key in {json.dumps(dead)}")
            if not set(others) - set(dead):
                return self
            self._release()
            time.sleep(random.uniform(wait / 2, wait))
            wait = min(wait * 2, 0.5)

    def __exit__(self, kind: Any, *exc: Any) -> None:
        try:
            self._release()
        except Exception:
            if kind is None:
                raise
            # The append's own error says more; the claim is left for the lease to clear.

    def _release(self) -> None:
        if self._key:
            key, self._key = self._key, ""
            self._client.delete(self._collection, filter=f"key in {json.dumps([key])}")
