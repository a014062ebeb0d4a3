"""Milvus writes that cannot collide (issue 42): a writer stalled past its lease, the
heartbeat that keeps a slow one's claim, counters that only move forward, a live
writer's claim kept when Milvus Lite is opened, appends cut off halfway found by
`info --check` and settled by `--repair`, and copies whole only at their end.

Skipped where pymilvus or milvus-lite is not installed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymilvus")
pytest.importorskip("milvus_lite")

from conftest import package_path  # noqa: E402
from test_milvus_server import server  # noqa: E402,F401  # the module's server fixture
from typer.testing import CliRunner  # noqa: E402

import disco_cli.maps.milvus_store as milvus_store  # noqa: E402
from disco_cli.cli import app  # noqa: E402
from disco_cli.maps.database import ScanBatch  # noqa: E402
from disco_cli.maps.milvus_lock import (  # noqa: E402
    LEASE_ENV,
    WriteLock,
    advance_counters,
    read_state,
)
from disco_cli.maps.milvus_store import MilvusDatabase  # noqa: E402


def _cli(*args: object) -> tuple[int, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, res.output


def _built(samples: Path, address: str) -> str:
    code, text = _cli("build-db", samples / "00", "-o", address)
    assert code == 0, text
    return address


def _batch(db: MilvusDatabase, tag: str, n: int) -> ScanBatch:
    rng = np.random.default_rng(sum(map(ord, tag)))
    sig = rng.standard_normal((n, db.signature_dim)).astype(np.float32)
    sig /= np.linalg.norm(sig, axis=1, keepdims=True)
    feats = np.zeros((n, *db.feature_shape), np.float32)
    return ScanBatch(paths=[f"/{tag}/{i}" for i in range(n)], signatures=sig, features=feats)


def _until(condition, what: str, deadline_s: float = 120.0) -> None:
    deadline = time.monotonic() + deadline_s
    while not condition():
        assert time.monotonic() < deadline, f"{what}: not within {deadline_s:g} s"
        time.sleep(0.05)


# A writer that stops itself (SIGSTOP) just before it inserts its scan rows, as a
# paused process or a swapping robot computer would: its fence was checked, its intent
# written, its heartbeat stops with it.
_STALLING_WRITER = """
import os, signal, sys
import numpy as np
from disco_cli.errors import DiscoError
from disco_cli.maps.database import ScanBatch
from disco_cli.maps.milvus_store import MilvusDatabase
db = MilvusDatabase.open(sys.argv[1], writable=True)
insert = db._client.insert
def stalling(collection, rows, *a, **k):
    if collection == db._scans:
        print("stalling", flush=True)
        os.kill(os.getpid(), signal.SIGSTOP)
    return insert(collection, rows, *a, **k)
db._client.insert = stalling
sig = np.ones((3, db.signature_dim), np.float32) / np.sqrt(db.signature_dim)
batch = ScanBatch(paths=[f"/stalled/{i}" for i in range(3)], signatures=sig,
                  features=np.zeros((3, *db.feature_shape), np.float32))
try:
    print(db.append(batch), flush=True)
except DiscoError as exc:
    print(f"error: {exc}", file=sys.stderr)
    sys.exit(1)
finally:
    db.close()
"""


def _state_letter(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_stalled_writer_past_its_lease(
    server: str,  # noqa: F811
    samples: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One writer SIGSTOPped past its lease while a second writes, then SIGCONTed: no
    id is given twice, no row is lost, and the stalled writer fails with one line."""
    lease = 2.0
    monkeypatch.setenv(LEASE_ENV, str(lease))
    address = _built(samples, f"{server}/stall")
    with MilvusDatabase.open(address) as db:
        before = dict(zip(db.ids().tolist(), db.paths()))
    assert sorted(before) == list(range(1, 27))
    env = {**os.environ, "PYTHONPATH": package_path(), LEASE_ENV: str(lease)}
    stalled = subprocess.Popen(
        [sys.executable, "-c", _STALLING_WRITER, address],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert stalled.stdout.readline().strip() == "stalling", stalled.stderr.read()
        _until(lambda: _state_letter(stalled.pid) == "T", "the writer stopped")
        start = time.monotonic()
        with MilvusDatabase.open(address, writable=True) as db:
            # It waits out the stalled writer's lease, then writes past its intent.
            got = db.append(_batch(db, "second", 3))
        assert time.monotonic() - start >= lease
        os.kill(stalled.pid, signal.SIGCONT)
        out, err = stalled.communicate(timeout=120)
    finally:
        stalled.kill()
    assert stalled.returncode == 1, (out, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "lost the map's writers' lock" in lines[0], err
    assert "Traceback" not in err
    assert got == [30, 31, 32]  # ids 27-29 were the stalled writer's intent: kept clear
    with MilvusDatabase.open(address) as db:
        assert db.check() == []
        stored = dict(zip(db.ids().tolist(), db.paths()))
        assert db.next_id() == 33
        assert WriteLock(db._client, db._meta_c).claims() == {}
    assert stored == {**before, 30: "/second/0", 31: "/second/1", 32: "/second/2"}


def test_heartbeat_keeps_a_slow_writers_claim(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A write that holds the lock for longer than the lease keeps it (its heartbeat
    renews the claim): the other writer waits for it, and their ids stay apart."""
    lease = 2.0
    monkeypatch.setenv(LEASE_ENV, str(lease))
    address = _built(samples, f"milvus:{tmp_path / 'slow.db'}")
    a = MilvusDatabase.open(address, writable=True)
    b = MilvusDatabase.open(address, writable=True)  # one process: both may write
    try:
        insert = a._client.insert
        inside = threading.Event()

        def slow(collection, rows, *args, **kw):
            if collection == a._scans:
                inside.set()
                time.sleep(3 * lease)
            return insert(collection, rows, *args, **kw)

        monkeypatch.setattr(a._client, "insert", slow)
        got: dict[str, list] = {}
        first = threading.Thread(target=lambda: got.update(a=a.append(_batch(a, "a", 2))))
        first.start()
        assert inside.wait(60)
        got["b"] = b.append(_batch(b, "b", 2))
        first.join(60)
        assert not first.is_alive()
    finally:
        a.close()
        b.close()
    assert got == {"a": [27, 28], "b": [29, 30]}
    with MilvusDatabase.open(address) as db:
        assert db.check() == [] and len(db) == 30
        names = db.stored_names([27, 28, 29, 30])
    assert [names[i][0] for i in (27, 28, 29, 30)] == ["/a/0", "/a/1", "/b/0", "/b/1"]


def test_counters_only_move_forward(samples: Path, tmp_path: Path) -> None:
    """A late, smaller `next_id` (a stalled writer's commit, or an older disco's plain
    key) never moves the counters back."""
    address = _built(samples, f"milvus:{tmp_path / 'counters.db'}")
    with MilvusDatabase.open(address, writable=True) as db:
        stale = read_state(db._client, db._meta_c)
        assert (stale.next_id, stale.generation) == (27, 1)
        db.append(_batch(db, "x", 4))
        # The stale writer commits what it read before that append.
        advance_counters(db._client, db._meta_c, stale, 20, 1)
        db._write_meta({"next_id": "5"})  # an older disco's unconditional upsert
        assert read_state(db._client, db._meta_c).next_id == 31
        assert db.append(_batch(db, "y", 1)) == [31]
    with MilvusDatabase.open(address) as db:
        assert db.next_id() == 32 and db.generation == 3 and db.check() == []


def test_opening_lite_keeps_a_live_writers_claim(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Opening a Milvus Lite map for writing deletes the claims other processes left
    (one process per folder: theirs are dead) but not this process's live one; it waits
    for that writer instead."""
    monkeypatch.setenv(LEASE_ENV, "3600")  # no claim is taken as dead by waiting
    address = _built(samples, f"milvus:{tmp_path / 'live.db'}")
    with MilvusDatabase.open(address, writable=True) as a:
        lock = WriteLock(a._client, a._meta_c, a.path).__enter__()
        # Another process's claim, left when it was killed (this one holds the lock).
        dead = {"key": "lock:dead:00000000", "value": json.dumps({"host": "x", "pid": 1})}
        a._client.insert(a._meta_c, [{**dead, "v": [0.0, 0.0]}])
        opened: list = []
        other = threading.Thread(
            target=lambda: opened.append(MilvusDatabase.open(address, writable=True))
        )
        other.start()
        try:
            _until(lambda: "lock:dead:00000000" not in lock.claims(), "the dead claim deleted")
            time.sleep(1.0)
            assert not opened and other.is_alive()  # waits for the live writer
            lock.check()  # still holds the lock: its claim and its epoch
        finally:
            lock.__exit__(None)
        other.join(60)
        assert len(opened) == 1
        b = opened[0]
        try:
            assert b.append(_batch(b, "b", 1)) == [27]
        finally:
            b.close()


def _cut_off(address: str, tag: str, n: int, monkeypatch: pytest.MonkeyPatch, at: str) -> None:
    """An append killed `at` "scans" (before its scan rows) or "counters" (after them)."""

    class Killed(BaseException):
        pass

    db = MilvusDatabase.open(address, writable=True)
    try:
        if at == "scans":
            insert = db._client.insert

            def dies(collection, rows, *args, **kw):
                if collection == db._scans:
                    raise Killed
                return insert(collection, rows, *args, **kw)

            monkeypatch.setattr(db._client, "insert", dies)
        else:

            def dies_too(*args, **kw):
                raise Killed

            monkeypatch.setattr(milvus_store, "advance_counters", dies_too)
        with pytest.raises(Killed):
            db.append(_batch(db, tag, n))
    finally:
        monkeypatch.undo()
        db.close()


@pytest.mark.parametrize("at", ["counters", "scans"])
def test_append_cut_off_found_and_settled(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, at: str
) -> None:
    """An append cut off after its scan rows is finished by --repair (every row its own
    and sound); one cut off before them is undone. `info --check` names it first."""
    address = _built(samples, f"milvus:{tmp_path / 'cut.db'}")
    _cut_off(address, "cut", 3, monkeypatch, at)
    code, text = _cli("info", address, "--check")
    written = 3 if at == "counters" else 0
    assert code == 1 and f"an append cut off halfway: ids 27-29, {written} of 3 scan rows" in text
    assert "Traceback" not in text
    code, text = _cli("build-db", samples / "00", "-o", address, "--repair")
    assert code == 0, text
    code, text = _cli("info", address, "--check")
    assert code == 0 and "\ncheck\tok" in text, text
    with MilvusDatabase.open(address, writable=True) as db:
        if at == "counters":  # finished: the rows are the map's
            assert len(db) == 29 and db.stored_names([29])[29][0] == "/cut/2"
        else:  # undone: its ids are never given
            assert len(db) == 26
        assert db.append(_batch(db, "next", 1)) == [30]
        assert db.check() == []


def test_interrupted_copy_is_marked_and_redone(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A copy cut off after its first batch: into Milvus it is reported by `info
    --check` and replaced by the next copy; into SQLite nothing is left at the target."""
    import disco_cli.maps.milvus_copy as milvus_copy

    source = _built(samples, f"milvus:{tmp_path / 'src.db'}")
    appended = {"n": 0}
    real = MilvusDatabase.append

    def append_once(self, batch, _meta_first=None):
        if _meta_first is None:
            raise KeyboardInterrupt
        appended["n"] += 1
        return real(self, batch, _meta_first)

    monkeypatch.setattr(MilvusDatabase, "append", append_once)
    target = f"milvus:{tmp_path / 'copy.db'}"
    with pytest.raises(KeyboardInterrupt):
        milvus_copy.copy_map(source, target, batch=10)
    monkeypatch.undo()
    assert appended["n"] == 1
    code, text = _cli("info", target, "--check")
    assert code == 1 and f"an unfinished copy from {source}" in text, text
    assert milvus_copy.copy_map(source, target, batch=10) == 26
    code, text = _cli("info", target, "--check")
    assert code == 0 and "\nscans\t26" in text, text

    from disco_cli.maps.database import Database

    real_sqlite = Database.append
    monkeypatch.setattr(
        Database, "append", lambda self, b: (_ for _ in ()).throw(KeyboardInterrupt)
    )
    file_target = tmp_path / "copy-file.db"
    with pytest.raises(KeyboardInterrupt):
        milvus_copy.copy_map(source, file_target, batch=10)
    monkeypatch.setattr(Database, "append", real_sqlite)
    assert sorted(p.name for p in tmp_path.iterdir() if "copy-file" in p.name) == []
    assert milvus_copy.copy_map(source, file_target, batch=10) == 26


def test_copy_names_scans_without_their_side_views(samples: Path, tmp_path: Path) -> None:
    """A scan whose side views are not all there is left out of a copy and named."""
    address = f"milvus:{tmp_path / 'views.db'}"
    code, text = _cli("build-db", samples / "00", "-o", address, "--side-views", "4")
    assert code == 0, text
    with MilvusDatabase.open(address, writable=True) as db:
        views = len(db.side_offsets)
        db._client.delete(db._views_c, filter=f"key in [{7 * 64}]")
    code, text = _cli("build-db", "--from", address, "-o", tmp_path / "copy.db")
    assert code == 0 and "copied 25 scans" in text, text
    assert "scan 7" in text and "side views" in text, text
    assert views >= 1
