"""A map in Milvus (issue 33): Milvus Lite round trips against the SQLite map of the same
scans, a damaged row, an unreachable server, and the extra missing.

Skipped where the `milvus` extra (pymilvus, milvus-lite) is not installed."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymilvus")
pytest.importorskip("milvus_lite")

from conftest import package_path, socket_listening  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from disco_cli.cli import app  # noqa: E402
from disco_cli.maps.database import Database, ScanBatch  # noqa: E402
from disco_cli.maps.facade import Map  # noqa: E402
from disco_cli.maps.milvus_address import INSTALL_HINT, parse_address  # noqa: E402
from disco_cli.maps.milvus_store import MilvusDatabase  # noqa: E402


def _cli(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, res.output


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


@pytest.fixture(scope="module")
def maps(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The bundled session 00 as an SQLite map (built) and a Milvus Lite map (built
    separately, from the same scans)."""
    out = tmp_path_factory.mktemp("milvus")
    sqlite_map = out / "map.db"
    milvus_map = f"milvus:{out / 'fleet.db'}"
    for target in (sqlite_map, milvus_map):
        code, text = _cli("build-db", samples / "00", "-o", target)
        assert code == 0, text
    return sqlite_map, milvus_map


def _answers(db: str | Path, queries: list[str], exclude=None, index="auto") -> list[tuple]:
    with Map.open(db, index=index) as m:
        out = []
        for res in m.query_files(queries, topk=3, exclude=exclude, threads=1):
            assert res.error is None, res.error
            out.append([(Path(x.name).name, x.distance, x.yaw_deg) for x in res.matches])
        return out


def _queries(samples: Path) -> list[str]:
    return sorted(str(p) for p in (samples / "01" / "velodyne").iterdir())


def test_addresses_parse() -> None:
    lite = parse_address("milvus:maps/fleet.db")
    assert lite.lite and lite.uri == "maps/fleet.db" and str(lite) == "milvus:maps/fleet.db"
    server = parse_address("milvus://db.example:19530/city_7")
    assert not server.lite and server.uri == "http://db.example:19530"
    assert server.name == "city_7"
    # A path option folds '//' into '/': still the same server.
    assert parse_address(Path("milvus://db.example:19530/city_7")) == server
    assert parse_address("map.db") is None and parse_address(Path("dir/map.db")) is None
    for bad in ("milvus://db.example/x", "milvus://h:1/", "milvus://h:1/9x", "milvus:"):
        with pytest.raises(Exception, match="milvus"):
            parse_address(bad)


def test_same_answers_as_sqlite(maps, samples: Path) -> None:
    """Both maps store the same float16 values: every query's matches, distances and
    yaw agree (top-1 on all 26, the top 3 to rounding)."""
    sqlite_map, milvus_map = maps
    queries = _queries(samples)
    want = _answers(sqlite_map, queries)
    assert len(want) == 26
    # A small map's signatures are searched here (auto); `ann` searches in Milvus.
    for index, kind in (("auto", "SignatureIndex"), ("ann", "MilvusIndex")):
        got = _answers(milvus_map, queries, index=index)
        for w, g in zip(want, got, strict=True):
            assert [m[0] for m in g] == [m[0] for m in w]
            np.testing.assert_allclose([m[1] for m in g], [m[1] for m in w], rtol=1e-5)
            np.testing.assert_allclose([m[2] for m in g], [m[2] for m in w], atol=1e-3)
        with Map.open(milvus_map, index=index) as m:
            assert type(m._index()[1]).__name__ == kind


def test_copy_round_trip(maps, tmp_path: Path) -> None:
    """SQLite -> Milvus -> SQLite keeps every row: paths, poses, times, signatures and
    features as the first map reads them."""
    sqlite_map, _ = maps
    there, back = f"milvus:{tmp_path / 'copy.db'}", tmp_path / "back.db"
    code, text = _cli("build-db", "--from", sqlite_map, "-o", there)
    assert code == 0 and "copied 26 scans" in text, text
    code, text = _cli("build-db", "--from", there, "-o", back)
    assert code == 0 and "copied 26 scans" in text, text
    with Database.open(sqlite_map) as a, Database.open(back) as b:
        assert a.paths() == b.paths()
        ids_a, sig_a = a.signatures()
        ids_b, sig_b = b.signatures()
        np.testing.assert_array_equal(sig_a, sig_b)
        pa, ta = a.poses()
        pb, tb = b.poses()
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(ta, tb)
        fa, fb = a.rows(ids_a).features, b.rows(ids_b).features
        # Features are re-encoded from their decoded values: float16 steps at most.
        np.testing.assert_allclose(fb, fa, rtol=2**-8, atol=2**-8 * np.abs(fa).max())
        assert a.model == b.model
    # A copy onto an existing map is refused.
    code, text = _cli("build-db", "--from", sqlite_map, "-o", there)
    assert code == 1 and "already exists" in text


def test_append_keeps_earlier_answers(maps, samples: Path, tmp_path: Path) -> None:
    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    queries = _queries(samples)
    before = _answers(fleet, queries)
    code, text = _cli("build-db", samples / "00", "-o", fleet)  # resumed: nothing to add
    assert code == 0 and "all 26 scans are in it already" in text, text
    code, text = _cli("build-db", samples / "01", "-o", fleet)
    assert code == 1 and "--append" in text
    code, text = _cli("build-db", samples / "01", "-o", fleet, "--append")
    assert code == 0 and "wrote 26 scans" in text, text
    with Map.open(fleet) as m:
        assert len(m) == 52
        names = m.names()
    assert [Path(n).parent.parent.name for n in names] == ["00"] * 26 + ["01"] * 26
    # The session's own scans left out, every earlier answer is unchanged.
    after = _answers(fleet, queries, exclude=lambda i, p: np.arange(27, 53))
    assert after == before
    # With them, each query finds itself first.
    found = _answers(fleet, queries)
    assert [g[0][0] for g in found] == [Path(q).name for q in queries]
    assert all(g[0][1] < 1e-3 for g in found)


def _damage(address: str, rid: int) -> None:
    """Change scan `rid`'s stored x without its checksum, through Milvus itself."""
    from disco_cli.maps.milvus_address import connect, disconnect
    from disco_cli.maps.milvus_schema import load_collections

    where = parse_address(address)
    client = connect(where)
    try:
        load_collections(where, client)
        row = client.query(
            "disco_scans", filter=f"id == {rid}", output_fields=["*"], consistency_level="Strong"
        )[0]
        row = dict(row)
        row["x"] = (row["x"] or 0.0) + 5.0
        client.upsert("disco_scans", [row])
    finally:
        disconnect(where, client)


def test_damaged_row_reported_and_skipped(maps, samples: Path, tmp_path: Path) -> None:
    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    code, text = _cli("info", fleet, "--check")
    assert code == 0 and "damaged_scans" in text
    # Scan 5 (000004.bin) is the best match of session 01's scan 5.
    _damage(fleet, 5)
    code, text = _cli("info", fleet, "--check")
    assert code == 1
    assert "scan 5 (" in text and "checksum mismatch" in text
    assert "damaged scans: 5" in text
    query = str(samples / "01" / "velodyne" / "000005.bin")
    for index in ("auto", "ann"):  # found when the signatures are read / the row is
        with Map.open(fleet, index=index) as m:
            heard: list[str] = []
            m.on_damaged = heard.append
            found = m.query(np.fromfile(query, np.float32).reshape(-1, 4), topk=3)
        assert len(heard) == 1 and "1 damaged row skipped: scan 5" in heard[0], index
        assert 5 not in [x.match_id for x in found] and len(found) == 3
    # Copying leaves the damaged row out and says so.
    code, text = _cli("build-db", "--from", fleet, "-o", tmp_path / "rest.db")
    assert code == 0 and "copied 25 scans" in text and "scan 5" in text
    # --repair rewrites the row from the scans the map was built from.
    code, text = _cli("build-db", samples / "00", "-o", fleet, "--repair")
    assert code == 0 and "repaired 1 damaged scans" in text, text
    assert _cli("info", fleet, "--check")[0] == 0


def test_milvus_lite_held_by_another_process(maps, samples: Path) -> None:
    """Milvus Lite takes one process per folder: a second one gets one line, exit 1."""
    _, milvus_map = maps
    with Map.open(milvus_map):
        res = _run("query", samples / "01" / "velodyne" / "000005.bin", "--db", milvus_map)
    assert res.returncode == 1
    assert _lines(res.stderr) == [
        f"error: {milvus_map}: cannot open Milvus Lite (Open local milvus failed); another "
        "process may hold it: Milvus Lite takes one process per map (several need a server)"
    ]


def _run(*args, env=None) -> subprocess.CompletedProcess:
    full = {**os.environ, "PYTHONPATH": package_path(), "COLUMNS": "200", **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "disco_cli.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        env=full,
    )


def test_unreachable_server_one_line(samples: Path) -> None:
    start = time.monotonic()
    res = _run(
        "query",
        samples / "01" / "velodyne" / "000005.bin",
        "--db",
        "milvus://127.0.0.1:1/x",
        env={"DISCO_MILVUS_TIMEOUT": "2"},
    )
    took = time.monotonic() - start
    assert res.returncode == 1
    lines = _lines(res.stderr)
    assert len(lines) == 1 and lines[0].startswith(
        "error: milvus://127.0.0.1:1/x: cannot reach the Milvus server within 2 s"
    ), res.stderr
    assert took < 30  # bounded: a hang would run into the subprocess timeout


def test_extra_missing_one_line(maps, monkeypatch: pytest.MonkeyPatch, samples: Path) -> None:
    _, milvus_map = maps
    monkeypatch.setitem(sys.modules, "pymilvus", None)  # import pymilvus -> ImportError
    query = samples / "01" / "velodyne" / "000005.bin"
    for args in (("query", query, "--db", milvus_map), ("info", milvus_map)):
        code, text = _cli(*args)
        assert code == 1
        assert _lines(text) == [f"error: {INSTALL_HINT}"]
    assert "pip install 'disco-cli[milvus]'" in INSTALL_HINT


def test_orphan_rows_counted_in(maps, tmp_path: Path) -> None:
    """Rows an older disco's interrupted append inserted before it raised next_id (no
    intent row) are kept, and the next append does not reuse their ids."""
    from disco_cli.maps.milvus_lock import read_state

    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    db = MilvusDatabase.open(fleet, writable=True)
    try:
        counters = [k for k in read_state(db._client, db._meta_c).keys if k.startswith("counter:")]
        db._client.delete(db._meta_c, filter=f"key in {counters!r}".replace("'", '"'))
        db._write_meta({"next_id": "20"})  # as if ids 20-26 were written, not counted
        assert read_state(db._client, db._meta_c).next_id == 20
    finally:
        db.close()
    db = MilvusDatabase.open(fleet, writable=True)
    try:
        assert db.next_id() == 27
        assert db.check() == []
    finally:
        db.close()


def test_writers_taking_turns_lose_no_rows(maps, tmp_path: Path) -> None:
    """Two writers holding one map append in turn: each reads the counters again, so no
    id is given twice and no row is overwritten."""
    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    with Database.open(sqlite_map) as src:
        ids, sigs = src.signatures()
        rows = src.rows(ids[:3])

    def batch(tag: str) -> ScanBatch:
        return ScanBatch(
            paths=[f"/robot-{tag}/{p}" for p in rows.paths],
            signatures=sigs[:3],
            features=rows.features,
            poses=rows.poses,
        )

    a = MilvusDatabase.open(fleet, writable=True)
    b = MilvusDatabase.open(fleet, writable=True)
    try:
        got = [a.append(batch("a1")), b.append(batch("b1")), a.append(batch("a2"))]
    finally:
        a.close()
        b.close()
    assert got == [[27, 28, 29], [30, 31, 32], [33, 34, 35]]
    with MilvusDatabase.open(fleet) as db:
        assert len(db) == 35 and db.check() == []
        assert sum("/robot-" in p for p in db.paths()) == 9


def test_serve_answers_from_a_milvus_map(maps, samples: Path, tmp_path: Path) -> None:
    """`disco serve --db milvus:...` replies what `disco query` prints for the SQLite map."""
    import json

    from disco_cli.service.client import Client

    sqlite_map, milvus_map = maps
    scans = [str(samples / "01" / "velodyne" / f"{i:06d}.bin") for i in (5, 12, 18)]
    code, out = _cli("query", *scans, "--db", sqlite_map, "-k", "3", "--format", "jsonl")
    assert code == 0, out
    want = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
    sock = tmp_path / "disco.sock"
    env = {**os.environ, "PYTHONPATH": package_path()}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "disco_cli.cli",
            "serve",
            "--db",
            milvus_map,
            "--socket",
            str(sock),
            "--topk",
            "3",
            "--scan-root",
            str(samples),
        ],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 120
        while not sock.exists() or not socket_listening(sock):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.1)
        with Client(sock) as c:
            got = [row for scan in scans for row in c.query(scan)]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert [r["match"] for r in got] == [r["match"] for r in want]
    np.testing.assert_allclose([r["yaw_deg"] for r in got], [r["yaw_deg"] for r in want])


def test_resumed_build_adds_the_rest(samples: Path, tmp_path: Path) -> None:
    """A build stopped after some scans is resumed by the same command, as for SQLite."""
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    scans = sorted(str(p) for p in (samples / "00" / "velodyne").iterdir())
    assert _cli("build-db", *scans[:10], "-o", fleet)[0] == 0
    code, text = _cli("build-db", samples / "00", "-o", fleet)
    assert code == 0 and "wrote 16 scans" in text and "10 were in it already" in text, text
    with Map.open(fleet) as m:
        assert [Path(n).name for n in m.names()] == [Path(p).name for p in scans]


def test_hnsw_from_a_size(maps, samples: Path, tmp_path: Path, monkeypatch) -> None:
    """Past HNSW_MIN_ROWS scans the map's vector index becomes HNSW (here lowered to 20),
    and Milvus's search through it gives the SQLite map's answers on the samples."""
    pytest.importorskip("faiss")
    import disco_cli.maps.milvus_store as store
    from disco_cli.maps.milvus_address import connect, disconnect

    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    monkeypatch.setattr(store, "HNSW_MIN_ROWS", 20)
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    where = parse_address(fleet)
    client = connect(where)
    try:
        assert client.describe_index("disco_scans", "sig")["index_type"] == "HNSW"
    finally:
        disconnect(where, client)
    queries = _queries(samples)
    want = _answers(sqlite_map, queries)
    got = _answers(fleet, queries, index="ann")
    assert [g[0][0] for g in got] == [w[0][0] for w in want]


def test_hnsw_switch_when_a_resent_call_finds_it_made(maps, tmp_path: Path, monkeypatch) -> None:
    """pymilvus resends a create_index the server cut off (Milvus Lite's gRPC server
    does, past minutes behind its compaction); the resent call finds the index the first
    made and fails: the switch to HNSW is then complete all the same."""
    pytest.importorskip("faiss")
    import disco_cli.maps.milvus_store as store

    sqlite_map, _ = maps
    fleet = f"milvus:{tmp_path / 'fleet.db'}"
    assert _cli("build-db", "--from", sqlite_map, "-o", fleet)[0] == 0
    monkeypatch.setattr(store, "HNSW_MIN_ROWS", 20)
    with MilvusDatabase.open(fleet, writable=True) as db:
        made = db._client.create_index

        def resent(*args, **kwargs):
            made(*args, **kwargs)
            made(*args, **kwargs)  # the resent call: "index already exists"

        monkeypatch.setattr(db._client, "create_index", resent)
        db._choose_index()
        assert db._client.describe_index("disco_scans", "sig")["index_type"] == "HNSW"
    with MilvusDatabase.open(fleet) as db:
        assert db.meta["index_type"] == "HNSW"


def test_reads_paged_as_whole(maps, monkeypatch) -> None:
    """Reads come in pages of ids (wide rows in smaller ones); with pages of 5 and 3
    rows the 26 scans read back as the SQLite map holds them, in id order."""
    import disco_cli.maps.milvus_store as store

    sqlite_map, milvus_map = maps
    with Database.open(sqlite_map) as db:
        want_ids, want_sigs = db.signatures()
        want_paths = db.paths()
    monkeypatch.setattr(store, "_PAGE_NARROW", 5)
    monkeypatch.setattr(store, "_PAGE", 3)
    with MilvusDatabase.open(milvus_map) as db:
        assert db.ids().tolist() == want_ids.tolist()
        assert db.paths() == want_paths
        ids, sigs = db.signatures()
    assert ids.tolist() == want_ids.tolist()
    np.testing.assert_array_equal(sigs, want_sigs)


def test_bad_addresses_one_line(maps, samples: Path, tmp_path: Path) -> None:
    sqlite_map, _ = maps
    query = samples / "01" / "velodyne" / "000005.bin"
    cases = [
        (
            ("build-db", samples / "00", "-o", f"milvus:{tmp_path}/no/x.db"),
            f"folder {tmp_path}/no does not exist; create it first",
        ),
        (("info", f"milvus:{tmp_path}/none.db"), "no such database"),
        (
            ("query", query, "--db", "milvus://h/x"),
            "no such database (a server is milvus://HOST:PORT/NAME)",
        ),
        (("info", f"milvus:{sqlite_map}"), "is a file, not a Milvus Lite folder"),
        (
            ("build-db", "--from", sqlite_map, "-o", sqlite_map),
            "--from and --output name the same map",
        ),
    ]
    for args, said in cases:
        code, text = _cli(*args)
        assert code == 1, text
        assert len(_lines(text)) == 1 and _lines(text)[0].endswith(said), text
