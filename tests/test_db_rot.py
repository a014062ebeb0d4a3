"""Rot inside a map's rows: values changed through SQLite, so that every page stays valid
and only the rows' checksums can tell.

A map of data/samples/00 (the learned `default` model, which re-ranks with the stored
features) is damaged in five ways, each in its own rows: (a) one signature value scaled
by 1.5, (b) the low bit of one float16 feature, (c) a side view's signature (a map
built with side views), (d) the pose, (e) the stored path. The truth is the set of rows
the test changed: `info --check` must name exactly that set, `query` must never return
one of them and must warn naming them, and `build-db --repair` must restore the map to
what the undamaged one answers. A format-1 map (written here by hand, as disco wrote
it before checksums) opens read-only as it is and is migrated when written to.
"""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import zlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app

PER_KIND = 3  # damaged rows of each kind


def run(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, list(args))
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def jsonl(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def clean(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rot") / "clean.db"
    code, _, err = run("build-db", str(samples / "00"), "-o", str(out))
    assert code == 0, err
    return out


def _query(db: Path, samples: Path) -> tuple[int, list[dict], list[str]]:
    args = ["query", str(samples / "01"), "-d", str(db), "-k", "5", "--format", "jsonl"]
    code, out, err = run(*args)
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning")]
    return code, jsonl(out), warnings


def _check(db: Path) -> tuple[int, set[int]]:
    """`info --check`'s exit status and the scans it lists as damaged."""
    code, _, err = run("info", str(db), "--check")
    listed = re.search(r"^damaged scans: ([\d ]+)$", err, re.M)
    return code, set() if listed is None else {int(v) for v in listed.group(1).split()}


def _rewrite_blob(conn: sqlite3.Connection, table: str, column: str, where: str, fn) -> None:  # noqa: ANN001
    (blob,) = conn.execute(f"SELECT {column} FROM {table} WHERE {where}").fetchone()
    conn.execute(f"UPDATE {table} SET {column} = ? WHERE {where}", (fn(bytes(blob)),))


def _scale_one_value(blob: bytes) -> bytes:
    v = np.frombuffer(blob, "<f2").copy()
    k = int(np.argmax(np.abs(v)))  # a value that matters
    v[k] = v[k] * np.float16(1.5)
    return v.tobytes()


def _flip_low_bit_of_a_feature(blob: bytes) -> bytes:
    # The stored features are deflated float16: the rot changes one float16 value's
    # lowest bit, and the blob is what deflating the changed values gives.
    v = np.frombuffer(zlib.decompress(blob, -15), "<u2").copy()
    v[len(v) // 3] ^= 1
    packer = zlib.compressobj(6, zlib.DEFLATED, -15)
    return packer.compress(v.tobytes()) + packer.flush()


def _damage(db: Path, n_scans: int) -> dict[str, set[int]]:
    """Damage PER_KIND rows of each kind (disjoint, chosen at random); the ids per kind."""
    rng = np.random.default_rng(7)
    ids = [int(i) for i in rng.permutation(np.arange(1, n_scans + 1))]
    kinds = {
        k: set(ids[j * PER_KIND : (j + 1) * PER_KIND])
        for j, k in enumerate(["signature", "features", "pose", "path"])
    }
    with sqlite3.connect(db) as conn:
        for rid in kinds["signature"]:
            _rewrite_blob(conn, "scans", "signature", f"id = {rid}", _scale_one_value)
        for rid in kinds["features"]:
            _rewrite_blob(conn, "features", "data", f"id = {rid}", _flip_low_bit_of_a_feature)
        for rid in kinds["pose"]:
            conn.execute("UPDATE scans SET x = x + 0.5 WHERE id = ?", (rid,))
        for rid in kinds["path"]:
            # One character of the file name: 000004.bin -> 000014.bin (absolute path).
            conn.execute(
                "UPDATE scans SET path = replace(path, '/0000', '/0001') WHERE id = ?", (rid,)
            )
    conn.close()
    return kinds


def test_rot_in_any_row_is_found_skipped_and_repaired(
    clean: Path, samples: Path, tmp_path: Path
) -> None:
    n = len(list((samples / "00" / "velodyne").glob("*.bin")))
    code, want, warnings = _query(clean, samples)
    assert code == 0 and want and not warnings
    assert _check(clean) == (0, set())

    db = tmp_path / "map.db"
    shutil.copy(clean, db)
    kinds = _damage(db, n)
    damaged = set().union(*kinds.values())
    assert len(damaged) == 4 * PER_KIND
    # SQLite sees nothing wrong: only the checksums can.
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        assert conn.execute("PRAGMA integrity_check").fetchall() == [("ok",)]

    # info --check names exactly the damaged rows (100 %), and exits 1.
    code, listed = _check(db)
    assert code == 1 and listed == damaged

    # query: exit 0, never a damaged scan, and warnings that name what was skipped.
    code, got, warnings = _query(db, samples)
    assert code == 0 and got
    assert not {r["match_id"] for r in got} & damaged
    named = {int(i) for w in warnings for i in re.findall(r"scan (\d+) \(", w)}
    assert warnings and named <= damaged
    # Every damaged scan the clean map answered with was met, skipped and named, and the
    # rows that the signature, pose or path damage touched were all left out at loading.
    used = {r["match_id"] for r in want} & damaged
    assert used - kinds["features"] <= named and used & kinds["features"] <= named
    assert len(warnings) <= 1 + len(kinds["features"])
    skipped = sum(int(re.search(r"(\d+) damaged rows? skipped", w).group(1)) for w in warnings)
    assert skipped >= 3 * PER_KIND

    # build-db --repair with the inputs the map was built from restores it.
    code, _, err = run("build-db", str(samples / "00"), "-o", str(db), "--repair")
    assert code == 0, err
    assert f"repaired {len(damaged)} damaged scans" in err
    assert _check(db) == (0, set())
    code, again, warnings = _query(db, samples)
    assert code == 0 and not warnings
    # The same answers as the undamaged map: re-embedding gives the same signatures up
    # to float rounding of another batch size, below what float16 keeps.
    assert [(r["query"], r["match_id"], r["match"]) for r in again] == [
        (r["query"], r["match_id"], r["match"]) for r in want
    ]
    for a, b in zip(again, want):
        assert a["distance"] == pytest.approx(b["distance"], abs=1e-3)
        assert a["yaw_deg"] == pytest.approx(b["yaw_deg"], abs=0.05)


def test_a_damaged_side_view_is_found_and_repaired(samples: Path, tmp_path: Path) -> None:
    db = tmp_path / "views.db"
    scans = sorted((samples / "00" / "velodyne").glob("*.bin"))[:8]
    build = ["build-db", *map(str, scans), "-o", str(db), "-m", "spectral", "--side-views", "2"]
    assert run(*build)[0] == 0
    with sqlite3.connect(db) as conn:
        for rid in (2, 5):
            _rewrite_blob(
                conn,
                "side_views",
                "signature",
                f"scan_id = {rid} AND offset_m > 0",
                _scale_one_value,
            )
    conn.close()
    assert _check(db) == (1, {2, 5})
    code, got, warnings = _query(db, samples)
    assert code == 0 and len(warnings) == 1 and "scan 2 (a side view)" in warnings[0]
    code, _, err = run("build-db", *map(str, scans), "-o", str(db), "--repair")
    assert code == 0 and "repaired 2 damaged scans" in err, err
    assert _check(db) == (0, set())


def test_repair_says_what_it_cannot_place(clean: Path, samples: Path, tmp_path: Path) -> None:
    db = tmp_path / "map.db"
    shutil.copy(clean, db)
    _damage(db, 26)
    # Only 01's scans given: none of them is a damaged scan of 00.
    code, _, err = run("build-db", str(samples / "01"), "-o", str(db), "--repair")
    assert code == 1 and "none of the given scans is it" in err
    assert "Traceback" not in err


def test_a_format1_map_opens_as_it_is_and_is_migrated_when_written(
    clean: Path, samples: Path, tmp_path: Path, to_format1
) -> None:  # noqa: ANN001
    db = tmp_path / "old.db"
    shutil.copy(clean, db)
    to_format1(db)
    # Read-only: opens as format 1 (no checksums), and answers as the same map.
    code, out, err = run("info", str(db), "--check", "--format", "jsonl")
    assert code == 0 and json.loads(out)["format_version"] == 1
    assert "format 1: its rows carry no checksums" in err
    code, old_rows, warnings = _query(db, samples)
    _, want, _ = _query(clean, samples)
    assert code == 0 and not warnings
    assert [r["match_id"] for r in old_rows] == [r["match_id"] for r in want]
    # Writing to it (a resumed build) migrates it to format 2 first, in place.
    code, _, err = run("build-db", str(samples / "00"), "-o", str(db))
    assert code == 0 and "migrated from format 1 to format 2" in err, err
    code, out, _ = run("info", str(db), "--check", "--format", "jsonl")
    assert code == 0 and json.loads(out)["format_version"] == 2
    code, migrated, _ = _query(db, samples)
    assert [r["match_id"] for r in migrated] == [r["match_id"] for r in want]
    # Now rot is found in it like in any format-2 map.
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE scans SET y = y - 1 WHERE id = 4")
    conn.close()
    assert _check(db) == (1, {4})
