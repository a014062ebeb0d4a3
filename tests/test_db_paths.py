"""Stored scan paths: absolute plus relative to the database, so that a map works from
any directory, moved as a whole, or mounted elsewhere (`--scan-root`); old databases
with relative paths keep working.

Every command runs from another directory than the one the database was built in
(monkeypatch.chdir). The truth for poses is the same query on the map where it was
built; for paths, os.path on the files the test made.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.maps.database import Database

Q = "01/velodyne/000005.bin"  # drives past 00/000004 (docs/cli.md)


def run(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, list(args))
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def rows(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.fixture()
def site(samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """site/maps/map.db built from site/data/00 by a relative path, run from site/."""
    site = tmp_path / "site"
    shutil.copytree(samples / "00", site / "data" / "00")
    shutil.copytree(samples / "01", site / "data" / "01")
    (site / "maps").mkdir()
    monkeypatch.chdir(site)
    code, _, err = run("build-db", "data/00", "-o", "maps/map.db", "-m", "spectral")
    assert code == 0, err
    return site


def _pose_rows(db: Path, query: Path, *extra: str) -> tuple[int, list[dict], str]:
    code, out, err = run(
        "query", str(query), "-d", str(db), "-k", "3", "--pose", "--format", "jsonl", *extra
    )
    return code, rows(out), err


def test_build_db_stores_absolute_and_db_relative_paths(site: Path) -> None:
    with sqlite3.connect(site / "maps" / "map.db") as conn:
        stored = conn.execute("SELECT path, rel_path FROM scans ORDER BY id").fetchall()
    files = sorted((site / "data" / "00" / "velodyne").glob("*.bin"))
    assert [p for p, _ in stored] == [str(f) for f in files]
    want = [os.path.join("..", "data", "00", "velodyne", f.name) for f in files]
    assert [r for _, r in stored] == want
    # Resuming with the same relative input from the same place skips them all ...
    code, _, err = run("build-db", "data/00", "-o", "maps/map.db", "-m", "spectral")
    assert code == 0 and f"all {len(files)} scans are in it already" in err
    # ... and so does the absolute spelling from anywhere.
    os.chdir(site / "maps")
    code, _, err = run("build-db", str(site / "data" / "00"), "-o", "map.db", "-m", "spectral")
    assert code == 0 and f"all {len(files)} scans are in it already" in err


def test_query_pose_from_another_directory(site: Path, tmp_path: Path) -> None:
    code, here, err = _pose_rows(site / "maps" / "map.db", site / "data" / Q)
    assert code == 0, err
    assert all(r["dx"] is not None for r in here)
    # Built from here: the matches print as they were typed, relative.
    assert here[0]["match"].startswith(os.path.join("data", "00", "velodyne", ""))
    os.chdir(tmp_path)
    code, there, err = _pose_rows(Path("site/maps/map.db"), Path("site/data") / Q)
    assert code == 0 and "warning" not in err, err
    assert [(r["match_id"], r["dx"], r["dy"]) for r in there] == [
        (r["match_id"], r["dx"], r["dy"]) for r in here
    ]
    # A printed match path opens from where the command ran.
    assert [r["match"] for r in there] == [os.path.join("site", r["match"]) for r in here]
    os.chdir(site / "maps")  # the scans are not under this folder: absolute paths
    code, up, _ = _pose_rows(Path("map.db"), site / "data" / Q)
    assert [r["match"] for r in up] == [str(site / r["match"]) for r in here]


def test_a_moved_map_folder_still_finds_its_scans(site: Path, tmp_path: Path) -> None:
    code, before, err = _pose_rows(site / "maps" / "map.db", site / "data" / Q)
    assert code == 0, err
    moved = tmp_path / "elsewhere" / "site"
    shutil.move(str(site), str(moved))
    os.chdir(tmp_path)
    # The stored absolute paths are gone; the paths relative to the database find them.
    code, after, err = _pose_rows(moved / "maps" / "map.db", moved / "data" / Q)
    assert code == 0 and "warning" not in err, err
    assert [(r["match_id"], r["dx"], r["dy"], r["dz"]) for r in after] == [
        (r["match_id"], r["dx"], r["dy"], r["dz"]) for r in before
    ]
    assert all(Path(r["match"]).is_file() for r in after)  # where they are now


def test_scan_root_remaps_and_a_missing_scan_keeps_its_row(site: Path, tmp_path: Path) -> None:
    db = site / "maps" / "map.db"
    code, before, err = _pose_rows(db, site / "data" / Q)
    assert code == 0, err
    # The scans move away from the database (another disk, mounted elsewhere).
    mount = tmp_path / "mnt" / "disk"
    mount.mkdir(parents=True)
    shutil.move(str(site / "data"), str(mount / "data"))
    query = mount / "data" / Q
    os.chdir(tmp_path)
    code, lost, err = _pose_rows(db, query)
    # Place recognition does not need the stored scans: the same rows, poses empty.
    assert code == 0, err
    assert [(r["match_id"], r["distance"]) for r in lost] == [
        (r["match_id"], r["distance"]) for r in before
    ]
    assert all(r["dx"] is None and r["accepted"] is None for r in lost)
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning")]
    assert len(warnings) == len(before) and all("--scan-root" in w for w in warnings)
    assert "Traceback" not in err and "error" not in err
    # --scan-root finds them under the new root.
    code, found, err = _pose_rows(db, query, "--scan-root", str(mount))
    assert code == 0 and "warning" not in err, err
    assert [(r["match_id"], r["dx"], r["dy"]) for r in found] == [
        (r["match_id"], r["dx"], r["dy"]) for r in before
    ]
    # --verify keeps only accepted poses: a match without one is not printed.
    verify = ["-k", "3", "--verify", "--format", "jsonl"]
    code, out, err = run("query", str(query), "-d", str(db), *verify)
    assert code == 0 and rows(out) == []


def test_loops_db_from_another_directory_reuses_the_signatures(
    site: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = ["-m", "spectral", "--exclude-frames", "5", "--format", "jsonl"]
    code, want, err = run("loops", "data/00", *args)
    assert code == 0, err

    def no_embedding(*a, **k):  # noqa: ANN002, ANN003
        raise AssertionError("loops re-embedded scans that the database holds")

    monkeypatch.setattr("disco_cli.embedding.batches.load_stream", no_embedding)
    os.chdir(tmp_path)
    code, got, err = run("loops", "site/data/00", "-d", "site/maps/map.db", *args)
    assert code == 0, err
    strip = _loops(want)
    assert _same_loops(_loops(got), strip)
    # The scans mounted elsewhere: --scan-root tells loops which stored scans they are.
    mount = tmp_path / "mnt"
    mount.mkdir()
    shutil.move(str(site / "data"), str(mount / "data"))
    moved = str(mount / "data" / "00")
    code, got, err = run("loops", moved, "-d", "site/maps/map.db", *args, "--scan-root", str(mount))
    assert code == 0, err
    assert _same_loops(_loops(got), strip)


def _loops(out: str) -> list[tuple]:
    return [(r["query_index"], r["match_index"], r["distance"]) for r in rows(out)]


def _same_loops(a: list[tuple], b: list[tuple]) -> bool:
    """The same pairs; distances within the rounding of the map's float16 signatures."""
    return [r[:2] for r in a] == [r[:2] for r in b] and all(
        abs(x[2] - y[2]) < 1e-4 for x, y in zip(a, b)
    )


def _make_old(db: Path, base: Path, to_format1) -> None:  # noqa: ANN001
    """Turn a database into what older disco wrote: format 1, paths relative to where
    build-db ran (`base`), no rel_path column."""
    to_format1(db, rel_paths=False)
    with sqlite3.connect(db) as conn:
        for rid, path in conn.execute("SELECT id, path FROM scans").fetchall():
            rel = os.path.relpath(path, base)
            conn.execute("UPDATE scans SET path = ? WHERE id = ?", (rel, rid))


def test_an_old_database_with_relative_paths_keeps_working(
    site: Path, tmp_path: Path, to_format1
) -> None:  # noqa: ANN001
    db = site / "maps" / "map.db"
    code, before, err = _pose_rows(db, site / "data" / Q)
    assert code == 0, err
    _make_old(db, site, to_format1)
    with Database.open(db) as old:
        assert old.paths()[0] == os.path.join("data", "00", "velodyne", "000000.bin")
    # From where it was built: as before.
    code, same, err = _pose_rows(db, site / "data" / Q)
    assert code == 0 and "warning" not in err, err
    assert [(r["match"], r["dx"]) for r in same] == [(r["match"], r["dx"]) for r in before]
    code, _, err = run("build-db", "data/00", "-o", "maps/map.db", "-m", "spectral")
    assert code == 0 and "scans are in it already" in err
    # From elsewhere, --scan-root names the folder it was built in.
    os.chdir(tmp_path)
    code, there, err = _pose_rows(db, site / "data" / Q, "--scan-root", str(site))
    assert code == 0 and "warning" not in err, err
    assert [r["dx"] for r in there] == [r["dx"] for r in same]
    # Appending to it works too; the new rows carry absolute paths.
    os.chdir(site)
    code, _, err = run("build-db", "data/01", "-o", "maps/map.db", "-m", "spectral", "--append")
    assert code == 0, err
    with Database.open(db) as old:
        paths = old.paths()
    n = len(list((site / "data" / "00" / "velodyne").glob("*.bin")))
    assert paths[n:] == sorted(str(f) for f in (site / "data" / "01" / "velodyne").glob("*.bin"))
