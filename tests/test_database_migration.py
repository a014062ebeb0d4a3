"""Migrating a format-1 map keeps the original: tested on files written the way format 1
wrote them (commit b1b53ee's schema and encoding: float32 signatures, float16 features
divided by their largest magnitude, no checksums), here with sqlite3 and NumPy alone,
never converted from a format-2 map, so that the float32 -> float16 loss is real.

The truth: the float32 values this test wrote. The backup must be the original byte for
byte; the migrated map must hold those values within float16's rounding (and not
exactly: the loss must show), and answer a search with its own scan at the distance
that rounding makes."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DatabaseError
from disco_cli.maps.database import Database, backup_path

D = 64  # signature dimension of the synthetic maps
FEATURES = (2, 5, 12)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_format1(
    path: Path,
    paths: list[str],
    signatures: np.ndarray,
    features: np.ndarray,
    poses: np.ndarray,
    times: np.ndarray,
    meta: dict[str, str],
) -> None:
    """A format-1 map at `path`, as b1b53ee's `Database.create`/`append` wrote one."""
    conn = sqlite3.connect(path)
    with conn:
        conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        conn.execute(
            "CREATE TABLE scans (id INTEGER PRIMARY KEY, path TEXT NOT NULL UNIQUE, "
            "time REAL, x REAL, y REAL, z REAL, yaw REAL, signature BLOB NOT NULL, "
            "features BLOB NOT NULL, feature_scale REAL NOT NULL, rel_path TEXT)"
        )
        conn.executemany("INSERT INTO meta VALUES (?, ?)", sorted(meta.items()))
        for i, p in enumerate(paths):
            f = features[i].astype(np.float32)
            scale = float(np.max(np.abs(f))) or 1.0
            x, y, z, yaw = (None if not np.isfinite(v) else float(v) for v in poses[i])
            t = None if not np.isfinite(times[i]) else float(times[i])
            conn.execute(
                "INSERT INTO scans (path, time, x, y, z, yaw, signature, features, "
                "feature_scale, rel_path) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    p, t, x, y, z, yaw,
                    signatures[i].astype("<f4").tobytes(),
                    (f / scale).astype("<f2").tobytes(),
                    scale,
                    None,
                ),
            )  # fmt: skip
    conn.execute("PRAGMA journal_mode=WAL")  # format 1 switched to WAL when it wrote
    conn.close()


def _meta(dim: int, shape: tuple[int, ...], **model: str) -> dict[str, str]:
    return {
        "format_version": "1",
        "disco_version": "0.1.0",
        "model_name": model.get("name", "synthetic"),
        "fingerprint": model.get("fingerprint", "f" * 64),
        "model_config": model.get("model_config", json.dumps({"dim": dim})),
        "bev_config": model.get("bev_config", json.dumps({"rings": 5})),
        "signature_dim": str(dim),
        "feature_shape": json.dumps(list(shape)),
        "feature_dtype": "float16",
        **({"model_source": model["source"]} if "source" in model else {}),
    }


@pytest.fixture()
def old_map(tmp_path: Path) -> tuple[Path, dict]:
    rng = np.random.default_rng(7)
    n = 40
    sigs = rng.normal(size=(n, D)).astype(np.float32)
    sigs /= np.linalg.norm(sigs, axis=1, keepdims=True)  # unit vectors, as the models give
    feats = rng.normal(scale=30.0, size=(n, *FEATURES)).astype(np.float32)
    poses = rng.normal(scale=50.0, size=(n, 4))
    poses[3] = np.nan  # one scan without a pose
    times = np.arange(n) * 0.1
    paths = [f"/data/00/velodyne/{i:06d}.bin" for i in range(n)]
    db = tmp_path / "map.db"
    write_format1(db, paths, sigs, feats, poses, times, _meta(D, FEATURES))
    truth = {"paths": paths, "sigs": sigs, "feats": feats, "poses": poses, "times": times}
    return db, truth


def test_migration_keeps_the_original_and_rounds_as_documented(old_map) -> None:
    db, truth = old_map
    original, sha = db.read_bytes(), _sha(db)
    with Database.open(db) as old:  # a reader leaves it as it is
        assert old.format_version == 1
    assert _sha(db) == sha
    with Database.open(db, writable=True) as new:
        line = new.migrated_line()
        assert new.format_version == 2
        assert new.migration_backup == backup_path(db) == db.with_name("map.db.v1")
        ids, sigs = new.signatures()
        rows = new.rows(ids)
        poses, times = new.poses()
    assert line.startswith(f"{db}: migrated from format 1 to format 2")
    assert line.endswith(f"the format-1 file is kept as {db}.v1") and "\n" not in line
    # The backup is the original file, byte for byte, and reads as the float32 map.
    assert backup_path(db).read_bytes() == original
    with Database.open(backup_path(db)) as kept:
        assert kept.format_version == 1
        assert np.array_equal(kept.signatures()[1], truth["sigs"])
    # Same ids, paths, poses and times; signatures within float16's half step (values
    # divided by their largest magnitude, <= 1: a step of at most 2^-11 there), and not
    # equal: the loss is real.
    assert ids.tolist() == list(range(1, 41)) and rows.paths == truth["paths"]
    np.testing.assert_array_equal(poses, truth["poses"])
    np.testing.assert_array_equal(times, truth["times"])
    scale = np.max(np.abs(truth["sigs"]), axis=1, keepdims=True)
    err = np.abs(sigs - truth["sigs"])
    assert np.all(err <= scale * 2.0**-12 * (1 + 1e-6))
    assert err.max() > 0
    # Features: format 1 held float16 of f / scale; format 2 keeps 9 of its 11
    # significant bits (a relative error of at most 2^-9 more).
    f16 = truth["feats"] / np.max(np.abs(truth["feats"]), axis=(1, 2, 3), keepdims=True)
    f16 = f16.astype(np.float16).astype(np.float32)
    stored = f16 * np.max(np.abs(truth["feats"]), axis=(1, 2, 3), keepdims=True)
    fscale = np.max(np.abs(stored), axis=(1, 2, 3), keepdims=True)
    ferr = np.abs(rows.features - stored)
    assert np.all(ferr <= np.abs(stored) * 2.0**-9 + fscale * 2.0**-24)
    assert ferr.max() > 0


def test_the_migrated_map_finds_each_scan_at_its_rounding_distance(old_map) -> None:
    from disco_cli.query.search import SignatureIndex

    db, truth = old_map
    with Database.open(db, writable=True) as new:
        ids, sigs = new.signatures()
    index = SignatureIndex(sigs)
    rows, dist = index.search(truth["sigs"], k=2)
    assert np.array_equal(ids[rows[:, 0]], ids)  # each original finds its own scan
    rounding = np.linalg.norm(sigs - truth["sigs"], axis=1)
    np.testing.assert_allclose(dist[:, 0], rounding, atol=1e-6)
    assert np.all(rounding <= np.sqrt(D) * 2.0**-12) and np.all(dist[:, 1] > 0.5)


def test_a_taken_backup_name_refuses_the_migration_and_leaves_the_map(old_map) -> None:
    db, _ = old_map
    backup_path(db).write_text("someone's file\n")
    sha = _sha(db)
    with pytest.raises(DatabaseError, match=r"cannot migrate from format 1: .*map\.db\.v1 exists"):
        Database.open(db, writable=True)
    assert _sha(db) == sha and backup_path(db).read_text() == "someone's file\n"
    assert sorted(p.name for p in db.parent.iterdir()) == ["map.db", "map.db.v1"]
    with Database.open(db) as still:
        assert still.format_version == 1


def test_build_db_migrates_a_real_format1_map_and_says_where_the_original_is(
    samples: Path, tmp_path: Path
) -> None:
    from disco_cli import load_model, read_scan, signature
    from disco_cli.maps.database import ModelInfo

    model = load_model("spectral")
    info = ModelInfo.of(model)
    scans = sorted(str(p) for p in (samples / "00" / "velodyne").glob("*.bin"))
    embedded = [signature(model, read_scan(p)) for p in scans]
    sigs = np.stack([s for s, _ in embedded]).astype(np.float32)
    feats = np.stack([f for _, f in embedded]).astype(np.float32)
    n = len(scans)
    db = tmp_path / "old.db"
    meta = _meta(
        sigs.shape[1],
        feats.shape[1:],
        name=info.name,
        fingerprint=info.fingerprint,
        model_config=json.dumps(info.model_config, sort_keys=True),
        bev_config=json.dumps(info.bev_config, sort_keys=True),
        source="spectral",
    )
    write_format1(db, scans, sigs, feats, np.full((n, 4), np.nan), np.full(n, np.nan), meta)
    original = db.read_bytes()
    query = ["query", str(samples / "01"), "-d", str(db), "-k", "3", "--format", "jsonl"]

    def answers() -> list[dict]:
        res = CliRunner().invoke(app, query)
        assert res.exit_code == 0, res.output
        return [json.loads(line) for line in res.stdout.splitlines()]

    before = answers()
    res = CliRunner().invoke(
        app, ["build-db", str(samples / "00"), "-o", str(db), "-m", "spectral"]
    )
    assert res.exit_code == 0, res.output
    said = [ln for ln in res.stderr.splitlines() if "migrated" in ln]
    assert len(said) == 1 and said[0].endswith(f"the format-1 file is kept as {db}.v1")
    assert backup_path(db).read_bytes() == original
    after = answers()
    assert [r["match_id"] for r in after] == [r["match_id"] for r in before]
    # Signatures are unit vectors: float16 moves a distance by well under 1e-3.
    assert max(abs(a["distance"] - b["distance"]) for a, b in zip(after, before)) < 1e-3
    shutil.copy(backup_path(db), tmp_path / "again.db")  # the backup still is a whole map
    with Database.open(tmp_path / "again.db") as kept:
        assert kept.format_version == 1 and len(kept) == n
