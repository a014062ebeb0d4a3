"""A store is a protocol with two implementations (issue 42): the same behaviour run on
the SQLite `Database` and on `MilvusDatabase` (Milvus Lite, skipped where pymilvus or
milvus-lite is not installed), every member of `store.MapStore` implemented by both with
its parameters, and the Milvus store sharing nothing with SQLite."""

from __future__ import annotations

import ast
import importlib.util
import inspect
import re
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from disco_cli.errors import DatabaseError
from disco_cli.maps import store as store_module
from disco_cli.maps.database import Database, ModelInfo, ScanBatch
from disco_cli.maps.database_rows import RowReader
from disco_cli.maps.milvus_store import MilvusDatabase
from disco_cli.maps.store import MapStore, open_store, store_class

INFO = ModelInfo("spectral", "abc123", {"dim": 16}, {"rings": 4, "sectors": 8})
HAS_MILVUS = all(importlib.util.find_spec(m) for m in ("pymilvus", "milvus_lite"))
STORES = [
    pytest.param("sqlite", id="sqlite"),
    pytest.param(
        "milvus",
        id="milvus",
        marks=pytest.mark.skipif(not HAS_MILVUS, reason="pymilvus and milvus-lite"),
    ),
]


def _batch(paths: list[str], seed: int, dim: int = 16) -> ScanBatch:
    rng = np.random.default_rng(seed)
    n = len(paths)
    poses = rng.normal(size=(n, 4))
    poses[0] = np.nan  # one scan without a pose
    return ScanBatch(
        paths=paths,
        signatures=rng.normal(size=(n, dim)).astype(np.float32),
        features=rng.normal(scale=300.0, size=(n, 4, 8)).astype(np.float32),
        poses=poses,
        times=seed + np.arange(n) * 0.1,
    )


def _scans(folder: Path, tag: str, n: int) -> list[str]:
    """`n` scan files that exist (so that `locate` finds them), absolute."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        p = folder / f"{tag}{i:03d}.bin"
        p.write_bytes(b"")
        out.append(str(p))
    return out


def _assert_float16_close(got: np.ndarray, want: np.ndarray) -> None:
    """Signatures are stored as float16 of each row divided by its largest magnitude:
    each value within 2^-11 of that magnitude."""
    row_max = np.abs(want).max(1, keepdims=True)
    assert np.all(np.abs(got - want) <= row_max * 2.0**-11)


def _assert_features_close(got: np.ndarray, want: np.ndarray) -> None:
    """Features are float16 rounded to 9 significant bits (test_database.py's bound)."""
    scale = np.abs(want).reshape(len(want), -1).max(1)[:, None, None]
    bound = np.abs(want) * (2.0**-9 + 2.0**-11) + scale * 2.0**-22
    assert np.all(np.abs(got - want) <= bound)


@pytest.fixture(params=STORES)
def address(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return str(tmp_path / "map.db")
    return f"milvus:{tmp_path / 'fleet.db'}"


def test_each_store_keeps_the_contract(address: str, tmp_path: Path) -> None:
    milvus = address.startswith("milvus:")
    store = store_class(address)
    assert store is (MilvusDatabase if milvus else Database)
    a = _batch(_scans(tmp_path / "scans", "a", 5), seed=1)
    b = _batch(_scans(tmp_path / "scans", "b", 3), seed=2)
    db = store.create(address, INFO, a, disco_version="test")
    try:
        assert isinstance(db, MapStore)
        for name in _data_members():  # instance attributes: only an open store has them
            assert hasattr(db, name), name
        if milvus:
            assert not any(isinstance(v, sqlite3.Connection) for v in vars(db).values())
        assert db.model == INFO and db.checksummed and db.damaged == {}
        assert len(db) == 5 and db.next_id() == 6

        before = db.generation
        assert db.append(b) == [6, 7, 8]
        assert db.generation > before
        assert len(db) == 8 and db.next_id() == 9
        np.testing.assert_array_equal(db.ids(), np.arange(1, 9))
        assert db.paths() == a.paths + b.paths
        assert db.locations() == a.paths + b.paths
        assert db.locate(b.paths[1]) == Path(b.paths[1])
        assert db.locate(str(tmp_path / "never.bin")) is None
        assert db.stored_names([2, 99]) == {2: (a.paths[1], None)}
        assert db.existing([a.paths[0], "/nowhere.bin"]) == {a.paths[0]}
        assert db.has_poses()

        ids, sigs = db.signatures()
        np.testing.assert_array_equal(ids, np.arange(1, 9))
        _assert_float16_close(sigs, np.concatenate([a.signatures, b.signatures]))
        poses, times = db.poses()
        np.testing.assert_array_equal(poses, np.concatenate([a.poses, b.poses]))
        np.testing.assert_array_equal(times, np.concatenate([a.times, b.times]))
        rows = db.rows([7, 2])
        assert rows.paths == [b.paths[1], a.paths[1]]
        np.testing.assert_array_equal(rows.poses, [b.poses[1], a.poses[1]])
        _assert_features_close(rows.features, np.stack([b.features[1], a.features[1]]))
        side_ids, side_sigs = db.side_signatures()
        assert side_ids.shape == (0,) and side_sigs.shape == (0, 16)

        # The exact index answers each stored signature with its own scan.
        index_ids, index = db.index_for("exact")
        np.testing.assert_array_equal(index_ids, ids)
        found, _ = index.search(sigs[[2, 6]], 1)
        np.testing.assert_array_equal(index_ids[found[:, 0]], [3, 7])

        # A rewrite replaces the rows it names, and only those; the generation moves on.
        c = _batch(_scans(tmp_path / "scans", "c", 2), seed=3)
        before = db.generation
        db.rewrite([2, 5], c)
        assert db.generation > before
        assert len(db) == 8
        assert db.paths() == [a.paths[0], c.paths[0], *a.paths[2:4], c.paths[1], *b.paths]
        ids, sigs = db.signatures()
        _assert_float16_close(sigs[[1, 4]], c.signatures)
        _assert_float16_close(sigs[[0, 2, 3]], a.signatures[[0, 2, 3]])
        _assert_features_close(db.rows([5]).features, c.features[1:])
        assert db.check() == [] and db.damaged == {}

        # Refusals: one DatabaseError line naming the map; nothing written.
        other = ModelInfo("spectral", "ffff00", INFO.model_config, INFO.bev_config)
        with pytest.raises(DatabaseError) as refused:
            db.check_model(other)
        line = str(refused.value)
        assert "\n" not in line and line.startswith(f"{address}: built with model 'spectral'")
        assert "fingerprint abc123" in line and "fingerprint ffff00" in line
        db.check_model(INFO)  # its own model passes
        before = db.generation
        wide = _batch(["/elsewhere/0.bin", "/elsewhere/1.bin"], seed=4, dim=8)
        with pytest.raises(DatabaseError, match="holds 16-dim signatures, got 8"):
            db.append(wide)
        assert len(db) == 8 and db.generation == before and db.next_id() == 9
        with pytest.raises(DatabaseError, match="already exists"):
            store.create(address, INFO, a)
    finally:
        db.close()
    db.close()  # closing twice is harmless

    with open_store(address) as again:
        assert type(again) is store and again.model == INFO and len(again) == 8
        assert again.migrated_line() == "" and again.read_only is None
        np.testing.assert_array_equal(again.signatures()[1], sigs)
    # `overwrite` replaces the map with the new first batch.
    store.create(address, INFO, b, overwrite=True).close()
    with open_store(address) as fresh:
        assert fresh.paths() == b.paths and fresh.next_id() == 4


def test_open_store_refuses_what_is_not_a_map(tmp_path: Path) -> None:
    with pytest.raises(DatabaseError, match="no such database"):
        open_store(tmp_path / "none.db")
    assert not (tmp_path / "none.db").exists()


def _members() -> dict[str, object]:
    """`MapStore`'s members, found by inspecting the class: its annotations (data) and
    what its body defines (methods, properties, classmethods)."""
    own = {
        n: v
        for n, v in vars(MapStore).items()
        if isinstance(v, (property, classmethod)) or inspect.isfunction(v)
    }
    own.pop("__init__", None)  # Protocol's own
    own.pop("__subclasshook__", None)
    return {**{n: None for n in MapStore.__annotations__}, **own}


def _data_members() -> list[str]:
    return [n for n, v in _members().items() if v is None]


def test_the_protocols_members_are_those_its_source_declares() -> None:
    """The inspection above against store.py's text: every name declared in the class."""
    tree = ast.parse(Path(store_module.__file__).read_text())
    (cls,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "MapStore"]
    declared = {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}
    declared |= {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign)}
    assert set(_members()) == declared
    assert {"append", "rewrite", "check", "generation", "__len__", "path"} <= declared


@pytest.mark.parametrize("cls", [Database, MilvusDatabase])
def test_every_member_is_implemented_with_its_parameters(cls: type) -> None:
    assert MapStore not in cls.__mro__  # structural: each implements, none inherits stubs
    for name, member in _members().items():
        if member is None:
            continue  # data: checked on open stores above
        impl = inspect.getattr_static(cls, name, None)
        assert impl is not None, f"{cls.__name__} lacks {name}"
        assert type(impl) is type(member), f"{cls.__name__}.{name} is a {type(impl).__name__}"
        if isinstance(member, property):
            continue
        want = inspect.signature(getattr(MapStore, name)).parameters
        got = inspect.signature(getattr(cls, name)).parameters
        for p, w in want.items():
            assert p in got, f"{cls.__name__}.{name} lacks parameter {p}"
            assert (got[p].kind, got[p].default) == (w.kind, w.default), (
                f"{cls.__name__}.{name}({p})"
            )
        for p in set(got) - set(want):  # a store's own extras must be optional
            assert got[p].default is not inspect.Parameter.empty, f"{cls.__name__}.{name}({p})"


def test_milvus_shares_nothing_with_sqlite() -> None:
    assert not issubclass(MilvusDatabase, Database)
    assert not issubclass(MilvusDatabase, RowReader)
    assert not hasattr(MilvusDatabase, "_conn")
    for klass in MilvusDatabase.__mro__[:-1]:  # but object
        source = inspect.getsource(klass)
        assert not re.search(r"\b_conn\b|\bsqlite3\b", source), klass
    # The SQLite store does hold its connection there (what the check above looks for).
    assert "self._conn" in inspect.getsource(Database)
