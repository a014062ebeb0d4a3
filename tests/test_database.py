"""The SQLite map database: round trips, compact features, refusals, transactions."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from disco_cli.errors import DatabaseError
from disco_cli.maps.database import FORMAT_VERSION, Database, MatchRows, ModelInfo, ScanBatch

INFO = ModelInfo("spectral", "abc123", {"dim": 16}, {"rings": 4, "sectors": 8})


def _batch(start: int, n: int, rng: np.random.Generator, dim: int = 16) -> ScanBatch:
    poses = rng.normal(size=(n, 4))
    poses[0] = np.nan  # one scan without a pose
    return ScanBatch(
        paths=[f"scans/{i:06d}.bin" for i in range(start, start + n)],
        signatures=rng.normal(size=(n, dim)).astype(np.float32),
        features=rng.normal(scale=300.0, size=(n, 4, 8)).astype(np.float32),
        poses=poses,
        times=np.arange(start, start + n) * 0.1,
    )


def test_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    a, b = _batch(0, 5, rng), _batch(5, 3, rng)
    db = Database.create(tmp_path / "map.db", INFO, a)
    db.append(b)
    db.close()
    db = Database.open(tmp_path / "map.db")
    assert len(db) == 8
    assert db.model == INFO
    assert db.format_version == FORMAT_VERSION
    assert db.paths() == a.paths + b.paths
    ids, sigs = db.signatures()
    np.testing.assert_array_equal(ids, np.arange(1, 9))
    # float16 signatures: each value within 2^-11 of its row's largest magnitude.
    want_sigs = np.concatenate([a.signatures, b.signatures])
    row_max = np.abs(want_sigs).max(1, keepdims=True)
    assert np.all(np.abs(sigs - want_sigs) <= row_max * 2.0**-11)
    poses, times = db.poses()
    np.testing.assert_array_equal(poses, np.concatenate([a.poses, b.poses]))
    np.testing.assert_allclose(times, np.concatenate([a.times, b.times]))
    rows = db.rows([7, 2])
    assert rows.paths == [b.paths[1], a.paths[1]]
    want = np.stack([b.features[1], a.features[1]])
    # float16 (11 significant bits), then rounded to 9: relative error <= 2^-9 + 2^-11
    # of each value, or half the spacing of float16's subnormals at 9 bits (2^-23 of the
    # largest magnitude) for the smallest values.
    scale = np.abs(want).reshape(2, -1).max(1)[:, None, None]
    bound = np.abs(want) * (2.0**-9 + 2.0**-11) + scale * 2.0**-22
    assert np.all(np.abs(rows.features - want) <= bound)
    assert db.has_poses()
    assert db.check() == []
    assert db.existing(["scans/000003.bin", "nope.bin"]) == {"scans/000003.bin"}


def test_features_are_deflated_float16_of_9_significant_bits_on_disk(tmp_path: Path) -> None:
    import zlib

    batch = _batch(0, 2, np.random.default_rng(1))
    db = Database.create(tmp_path / "m.db", INFO, batch)
    blob, scale = db._conn.execute("SELECT data, scale FROM features WHERE id = 1").fetchone()
    raw = np.frombuffer(zlib.decompress(blob, -15), "<u2")
    assert raw.size == 4 * 8
    assert not (raw & 3).any()  # the two lowest mantissa bits are dropped
    # Each value within 2^-9 (+ float16's own 2^-11) of features / their largest magnitude
    # (float64 truth), or of the subnormals' spacing at 9 bits for the smallest.
    want = batch.features[0].astype(np.float64).reshape(-1) / np.abs(batch.features[0]).max()
    got = raw.view("<f2").astype(np.float64)
    assert np.all(np.abs(got - want) <= np.abs(want) * (2.0**-9 + 2.0**-11) + 2.0**-22)
    assert scale == pytest.approx(np.abs(batch.features[0]).max(), rel=1e-7)


def test_create_refuses_existing(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    path.write_bytes(b"x")
    with pytest.raises(DatabaseError, match="already exists"):
        Database.create(path, INFO, _batch(0, 1, np.random.default_rng(0)))
    assert path.read_bytes() == b"x"


def test_failed_first_batch_leaves_no_file(tmp_path: Path) -> None:
    bad = _batch(0, 2, np.random.default_rng(0))
    bad.paths[1] = bad.paths[0]  # UNIQUE violation inside the first transaction
    with pytest.raises(DatabaseError):
        Database.create(tmp_path / "m.db", INFO, bad)
    assert list(tmp_path.iterdir()) == []


def test_failed_batch_is_rolled_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    db = Database.create(tmp_path / "m.db", INFO, _batch(0, 3, rng))
    with pytest.raises(DatabaseError):
        db.append(_batch(2, 3, rng))  # 000002 is stored already
    assert len(db) == 3
    with pytest.raises(DatabaseError, match="16-dim"):
        db.append(_batch(10, 2, rng, dim=8))
    assert len(db) == 3


def test_reader_sees_only_committed_batches(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    writer = Database.create(tmp_path / "m.db", INFO, _batch(0, 2, rng))
    reader = Database.open(tmp_path / "m.db")
    writer._conn.execute("BEGIN")
    writer._conn.execute(
        "INSERT INTO scans (path, signature, signature_scale, crc) VALUES ('x', x'00', 1, 0)"
    )
    assert len(reader) == 2  # the open transaction is invisible
    writer._conn.rollback()
    writer.append(_batch(2, 1, rng))
    assert len(reader) == 3


def test_check_model(tmp_path: Path) -> None:
    db = Database.create(tmp_path / "m.db", INFO, _batch(0, 1, np.random.default_rng(0)))
    db.check_model(INFO)
    # The same weights under another name (a checkpoint path for `default`) are accepted.
    db.check_model(ModelInfo("default", "abc123", {}, INFO.bev_config))
    with pytest.raises(DatabaseError, match="model 'spectral'.*not 'default'"):
        db.check_model(ModelInfo("default", "def456", {}, INFO.bev_config))
    with pytest.raises(DatabaseError, match="fingerprint"):
        db.check_model(ModelInfo("spectral", "zzz", {}, INFO.bev_config))
    with pytest.raises(DatabaseError, match="BEV configuration.*rings"):
        db.check_model(ModelInfo("spectral", "abc123", {}, {"rings": 5, "sectors": 8}))


def test_open_bad_files(tmp_path: Path) -> None:
    with pytest.raises(DatabaseError, match="no such database"):
        Database.open(tmp_path / "missing.db")
    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    with pytest.raises(DatabaseError, match="empty file"):
        Database.open(empty)
    text = tmp_path / "text.db"
    text.write_text("hello world, not a database at all\n")
    with pytest.raises(DatabaseError, match="not an SQLite file"):
        Database.open(text)
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE t (a)")
    with pytest.raises(DatabaseError, match="not a disco database"):
        Database.open(other)
    corrupt = tmp_path / "corrupt.db"
    Database.create(corrupt, INFO, _batch(0, 50, np.random.default_rng(0))).close()
    data = bytearray(corrupt.read_bytes())
    data[100:4096] = b"\xff" * (4096 - 100)  # wreck the schema page
    corrupt.write_bytes(bytes(data))
    with pytest.raises(DatabaseError, match="corrupt|not a disco"):
        Database.open(corrupt)


def test_newer_format_refused(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    Database.create(path, INFO, _batch(0, 1, np.random.default_rng(0))).close()
    with sqlite3.connect(path) as conn:
        conn.execute(
            "UPDATE meta SET value=? WHERE key='format_version'", (str(FORMAT_VERSION + 1),)
        )
    with pytest.raises(DatabaseError, match=f"version {FORMAT_VERSION + 1} is newer"):
        Database.open(path)


def test_empty_database_refused_for_search(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    Database.create(path, INFO, _batch(0, 2, np.random.default_rng(0))).close()
    with sqlite3.connect(path) as conn:
        conn.execute("DELETE FROM scans")
    with pytest.raises(DatabaseError, match="empty"):
        Database.open(path).signatures()


def _set_scan(path: Path, rid: int, **values: object) -> None:
    """Change columns of one scan row and give it the checksum of its new values: a row
    that passes its checksum, so that only the value checks can find it."""
    from disco_cli.maps.database import _SCAN_ROW, _scan_crc

    with sqlite3.connect(path) as conn:
        for col, v in values.items():
            conn.execute(f"UPDATE scans SET {col} = ? WHERE id = ?", (v, rid))
        row = conn.execute(f"SELECT {_SCAN_ROW} FROM scans WHERE id = ?", (rid,)).fetchone()
        conn.execute("UPDATE scans SET crc = ? WHERE id = ?", (_scan_crc(*row[:10]), rid))


def test_check_finds_bad_blobs(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    Database.create(path, INFO, _batch(0, 4, np.random.default_rng(0))).close()
    nan = np.full(16, np.nan, "<f2").tobytes()
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE scans SET signature = x'0000' WHERE id = 2")
        blob = bytearray(conn.execute("SELECT data FROM features WHERE id = 4").fetchone()[0])
        blob[len(blob) // 2] ^= 0x01  # one flipped bit inside the deflated features
        conn.execute("UPDATE features SET data = ? WHERE id = 4", (bytes(blob),))
    _set_scan(path, 3, signature=nan)
    db = Database.open(path)
    problems = db.check()
    assert len(problems) == 3
    assert "scan 2" in problems[0] and "bytes" in problems[0]
    assert "scan 3" in problems[1] and "finite" in problems[1]
    assert "scan 4" in problems[2] and "checksum" in problems[2]
    assert sorted(db.damaged) == [2, 3, 4]


def test_meta_holds_configs_as_json(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    Database.create(path, INFO, _batch(0, 1, np.random.default_rng(0))).close()
    with sqlite3.connect(path) as conn:
        meta = dict(conn.execute("SELECT key, value FROM meta"))
        mode = conn.execute("PRAGMA journal_mode").fetchone()[0]
    assert json.loads(meta["bev_config"]) == INFO.bev_config
    assert json.loads(meta["model_config"]) == INFO.model_config
    assert meta["model_name"] == "spectral" and meta["fingerprint"] == "abc123"
    assert mode == "wal"


# -- damaged files: one DatabaseError naming the file, the file left as it was ---------


def _made(tmp_path: Path, n: int = 40) -> Path:
    path = tmp_path / "m.db"
    db = Database.create(path, INFO, _batch(0, n, np.random.default_rng(0), dim=512))
    db.close()
    return path


def test_a_cut_file_is_named_as_cut(tmp_path: Path) -> None:
    path = _made(tmp_path)
    data = path.read_bytes()
    page = int.from_bytes(data[16:18], "big")
    page = 65536 if page == 1 else page  # SQLite writes 65536 as 1
    assert len(data) % page == 0 and len(data) > 4 * page
    cuts = {
        len(data) - 100: "not a whole number of",  # the issue's `head -c -100`
        len(data) - page: f"header says {len(data) // page} pages",
        page: f"header says {len(data) // page} pages",
        60: "shorter than the SQLite header",
        10: "shorter than the SQLite header",
    }
    for cut, words in cuts.items():
        path.write_bytes(data[:cut])
        for writable in (False, True):
            with pytest.raises(DatabaseError, match=words) as err:
                Database.open(path, writable=writable)
            assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)
            assert path.read_bytes() == data[:cut]
            assert sorted(p.name for p in tmp_path.iterdir()) == ["m.db"]


def test_damage_is_found_by_the_check_by_writers_and_by_the_read_that_meets_it(
    tmp_path: Path,
) -> None:
    path = _made(tmp_path)
    data = bytearray(path.read_bytes())
    page = int.from_bytes(data[16:18], "big")
    page = 65536 if page == 1 else page  # SQLite writes 65536 as 1
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as conn:
        root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name='scans'").fetchone()[0]
    data[(root - 1) * page] = 0xFF  # no b-tree page has this type
    path.write_bytes(bytes(data))
    # The full check (asked for, and always before writing) refuses the file untouched.
    for kwargs in ({"verify": True}, {"writable": True}):
        with pytest.raises(DatabaseError, match="corrupt database") as err:
            Database.open(path, **kwargs)
        assert "\n" not in str(err.value)
        assert path.read_bytes() == bytes(data)
    # A plain open reads only the header, meta and schema (a cheap open): the damage
    # surfaces on the first read of the scans, and in check(), as a DatabaseError.
    db = Database.open(path)
    with pytest.raises(DatabaseError, match="corrupt or unreadable"):
        db.paths()
    with pytest.raises(DatabaseError, match="corrupt or unreadable"):
        db.check()
    db.close()
    assert path.read_bytes() == bytes(data)


def test_a_stray_sqlite_error_is_one_line() -> None:
    import typer

    from disco_cli.runtime.console import handle_errors

    @handle_errors
    def command() -> None:
        raise sqlite3.DatabaseError("database disk image is malformed")

    with pytest.raises(typer.Exit) as exit_:
        command()
    assert exit_.value.exit_code == 1


@pytest.mark.parametrize("scale", [0.0, np.inf, 1e30])
def test_a_signature_out_of_range_is_skipped_by_search_and_listed_by_check(
    tmp_path: Path, scale: float
) -> None:
    # A row whose checksum holds but whose signature would derail the search (1e30 is
    # finite, but its square overflows float32): the search's check and check() agree.
    path = _made(tmp_path, n=5)
    _set_scan(path, 4, signature_scale=scale)
    with Database.open(path) as db:
        ids, _ = db.signatures()
        assert list(ids) == [1, 2, 3, 5]
        assert list(db.damaged) == [4]
        problems = db.check()
    assert len(problems) == 1 and problems[0].startswith("scan 4 ")


def test_a_pose_changed_to_text_is_a_damaged_row_not_an_error(tmp_path: Path) -> None:
    path = _made(tmp_path, n=5)
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE scans SET x = 'abc' WHERE id = 2")
    with Database.open(path) as db:
        poses, _ = db.poses()
        assert np.isnan(poses[1]).all() and np.isfinite(poses[2, :3]).all()
        assert list(db.signatures()[0]) == [1, 3, 4, 5]
        assert list(db.damaged) == [2]
        with pytest.raises(DatabaseError, match="1 damaged row skipped: scan 2"):
            db.rows([1, 2])


def test_rows_read_again_after_a_rewrite_give_the_new_row(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    db = Database.create(tmp_path / "m.db", INFO, _batch(0, 4, rng))
    first = db.rows([2, 3]).features
    np.testing.assert_array_equal(db.rows([3, 2]).features, first[::-1])  # kept decoded
    new = _batch(1, 1, rng)
    db.rewrite([2], new)
    got = db.rows([2]).features[0]
    want = new.features[0]
    assert np.all(np.abs(got - want) <= np.abs(want) * 2.0**-8 + np.abs(want).max() * 2.0**-22)
    assert db.rows([2]).paths == new.paths


def test_rows_hand_out_the_cached_arrays_read_only_and_stack_on_demand(tmp_path: Path) -> None:
    """`rows` gives each row's cached array (no stacked copy until `features` is asked
    for); nobody can write into the cache through it, and the stack is a copy."""
    rng = np.random.default_rng(4)
    batch = _batch(0, 5, rng)
    db = Database.create(tmp_path / "m.db", INFO, batch)
    got = db.rows([4, 1, 4])
    assert got.feature_rows is not None and len(got.feature_rows) == 3
    assert got.feature_rows[0] is got.feature_rows[2]  # one cached array for scan 4
    with pytest.raises(ValueError, match="read-only"):
        got.feature_rows[1][...] = 0.0
    stacked = got.features
    np.testing.assert_array_equal(stacked, np.stack(got.feature_rows))
    stacked[...] = 0.0  # a copy: the cache keeps its values
    again = db.rows([1]).features[0]
    assert np.abs(again).max() > 0
    np.testing.assert_array_equal(db.rows([4, 1]).features_at(1), again)
    np.testing.assert_array_equal(db.rows([4, 1, 4]).features_at([2, 1]), db.rows([4, 1]).features)
    assert db.rows([1]).features_at(np.zeros(0, np.int64)).shape == (0, *again.shape)
    assert db.rows([]).features.shape == (0, *again.shape)
    with pytest.raises(ValueError, match="either features or feature_rows"):
        MatchRows(got.ids, got.paths, got.poses)


def test_rows_all_damaged_raise_damaged_rows(tmp_path: Path) -> None:
    from disco_cli.maps.database import DamagedRows

    path = _made(tmp_path, n=3)
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE features SET crc = crc + 1")
    with Database.open(path) as db, pytest.raises(DamagedRows) as err:
        db.rows([1, 2])
    assert err.value.ids == [1, 2]
