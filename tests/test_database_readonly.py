"""A map this process may not write: a read-only folder (0555), a read-only file (0444),
a map of another user. Each opens read-only, says so in one line, and answers `query`,
`info`, `eval` and `serve` exactly as a writable copy of the same map does.

The tests run as root, which may write anything, so every read-only case runs its
command in a subprocess as uid/gid 65534 (`nobody`) through `setpriv`; they are skipped
where that is not possible. The truth is the same command on a writable copy, run here.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import package_path, socket_listening
from typer.testing import CliRunner

from disco_cli.cli import app

NOBODY = 65534
SETPRIV = shutil.which("setpriv")
QUERY = "01/velodyne/000005.bin"


def _nobody_cmd() -> list[str]:
    return [SETPRIV, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", sys.executable]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": package_path(), "HOME": "/tmp", "COLUMNS": "200"}


def as_nobody(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`disco ARGS` run as uid 65534, from this process's folder unless `cwd` (results
    name scans relative to it)."""
    cmd = _nobody_cmd() + ["-m", "disco_cli.cli", *args]
    return subprocess.run(
        cmd, cwd=cwd or os.getcwd(), env=_env(), capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def can_drop_root() -> None:
    if os.geteuid() != 0 or SETPRIV is None:
        pytest.skip("needs root and setpriv to run a command as another user")
    probe = subprocess.run(
        _nobody_cmd() + ["-c", "import os, disco_cli; print(os.getuid())"],
        cwd="/",
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    if probe.returncode != 0 or probe.stdout.strip() != str(NOBODY):
        pytest.skip(f"cannot run disco as uid {NOBODY}: {probe.stderr.strip()[-200:]}")


@pytest.fixture()
def site(samples_spectral_db: Path, can_drop_root: None) -> Iterator[Path]:
    """A folder every user may enter (pytest's own tmp folders are 0700), holding a
    writable copy of the map (`writable/map.db`, the truth) and a folder `work` where
    uid 65534 may write (its socket, its -shm files)."""
    top = Path(tempfile.mkdtemp(prefix="disco-ro-"))
    os.chmod(top, 0o755)
    (top / "writable").mkdir()
    shutil.copy(samples_spectral_db, top / "writable" / "map.db")
    (top / "work").mkdir()
    os.chown(top / "work", NOBODY, NOBODY)
    yield top
    for folder, _, files in os.walk(top):
        os.chmod(folder, 0o755)
        for f in files:
            os.chmod(Path(folder, f), 0o644)
    shutil.rmtree(top)


def _read_only_map(top: Path, layout: str) -> Path:
    """The map placed as `layout` says: `folder` (0555 folder, 0444 file), `file` (0444
    file in a folder uid 65534 may write), `owner` (root's 0644 file in root's 0755
    folder)."""
    folder = top / layout
    folder.mkdir()
    db = folder / "map.db"
    shutil.copy(top / "writable" / "map.db", db)
    if layout == "folder":
        os.chmod(db, 0o444)
        os.chmod(folder, 0o555)
    elif layout == "file":
        os.chmod(db, 0o444)
        os.chown(folder, NOBODY, NOBODY)
    else:
        os.chmod(db, 0o644)
        os.chmod(folder, 0o755)
    return db


def _cli(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, list(args))
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def _library_error(db: Path, writable: bool) -> subprocess.CompletedProcess:
    """`Database.open(db, writable)` as uid 65534; its DatabaseError printed on stdout."""
    script = (
        "import sys\n"
        "from disco_cli.maps.database import Database\n"
        "from disco_cli.errors import DatabaseError\n"
        "try:\n"
        f"    Database.open(sys.argv[1], writable={writable})\n"
        "except DatabaseError as exc:\n"
        "    print(exc)\n"
    )
    cmd = _nobody_cmd() + ["-c", script, str(db)]
    return subprocess.run(cmd, cwd="/", env=_env(), capture_output=True, text=True, timeout=120)


def _one_note(err: str, db: Path) -> None:
    """Exactly one line about the read-only open, and no word of damage."""
    notes = [ln for ln in err.splitlines() if "opened read-only" in ln]
    assert notes == [notes[0]] and notes[0].startswith(f"note: {db}: opened read-only"), err
    assert "corrupt" not in err and "Traceback" not in err, err


@pytest.mark.parametrize("layout", ["folder", "file", "owner"])
def test_a_read_only_map_answers_query_and_info_like_a_writable_one(
    site: Path, samples: Path, layout: str
) -> None:
    db = _read_only_map(site, layout)
    writable = site / "writable" / "map.db"
    before = db.read_bytes()
    q = str(samples / QUERY)
    for args in (
        ["query", q, "--db", "{db}", "-k", "5", "--pose", "--format", "jsonl"],
        ["info", "{db}", "--format", "jsonl"],
        ["info", "{db}", "--check", "--format", "jsonl"],
    ):
        code, want, err = _cli(*[a.format(db=writable) for a in args])
        assert code == 0, err
        got = as_nobody(*[a.format(db=db) for a in args])
        assert got.returncode == 0, got.stderr
        if args[0] == "info":  # the size counts the -wal/-shm files beside the map
            want = {k: v for k, v in json.loads(want).items() if k != "size"}
            assert {k: v for k, v in json.loads(got.stdout).items() if k != "size"} == want
        else:
            assert got.stdout == want and want.count("\n") == 5
        _one_note(got.stderr, db)
    assert db.read_bytes() == before
    # Nothing left beside it: a 0444 file (`folder`, `file`) is read as immutable, and
    # so is a map in a folder that cannot take the WAL's -shm (`owner`).
    assert sorted(p.name for p in db.parent.iterdir()) == ["map.db"]


def test_eval_on_a_read_only_map(site: Path, samples: Path) -> None:
    db = _read_only_map(site, "folder")
    args = ["eval", str(samples / "01"), "-d", "{db}", "-k", "2", "--format", "jsonl"]
    code, want, err = _cli(*[a.format(db=site / "writable" / "map.db") for a in args])
    assert code == 0, err
    got = as_nobody(*[a.format(db=db) for a in args])
    assert got.returncode == 0 and got.stdout == want, got.stderr
    _one_note(got.stderr, db)


def test_serve_on_a_read_only_map(site: Path, samples: Path) -> None:
    from disco_cli.service.client import Client

    db = _read_only_map(site, "folder")
    sock = site / "work" / "disco.sock"
    cmd = _nobody_cmd() + ["-m", "disco_cli.cli", "serve", "--db", str(db)]
    cmd += ["--socket", str(sock), "--topk", "3", "--scan-root", str(samples)]
    proc = subprocess.Popen(cmd, cwd=site / "work", env=_env(), stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not sock.exists() or not socket_listening(sock):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.1)
        with Client(socket=sock) as c:
            reply = c.query(str(samples / QUERY))
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    _, want, _ = _cli(
        "query", str(samples / QUERY), "--db", str(site / "writable" / "map.db"), "-k", "3",
        "--format", "jsonl",
    )  # fmt: skip
    want_rows = [json.loads(line) for line in want.splitlines()]
    got = reply
    assert [r["match_id"] for r in got] == [r["match_id"] for r in want_rows]
    assert [r["distance"] for r in got] == [r["distance"] for r in want_rows]
    _one_note(err, db)


def test_writing_a_read_only_map_is_refused_as_a_permission_problem(site: Path) -> None:
    db = _read_only_map(site, "folder")
    got = _library_error(db, writable=True)
    assert got.stdout.strip() == (
        f"{db}: cannot write: neither the file nor its folder is writable here (permission denied)"
    ), got.stderr


def test_a_pending_wal_in_a_read_only_folder_is_named_not_called_corrupt(site: Path) -> None:
    # A writer still holds the map: its WAL has writes not yet in the file. A copy of
    # both files in a read-only folder cannot get the -shm SQLite needs to read the WAL,
    # and reading the file alone would miss those writes.
    src = site / "writable" / "map.db"
    writer = sqlite3.connect(src)
    try:
        writer.execute("PRAGMA wal_autocheckpoint=0")
        writer.execute(
            "UPDATE meta SET value = CAST(value AS INTEGER) + 1 WHERE key = 'generation'"
        )
        writer.commit()
        assert os.path.getsize(f"{src}-wal") > 0
        folder = site / "pending"
        folder.mkdir()
        shutil.copy(src, folder / "map.db")
        shutil.copy(f"{src}-wal", folder / "map.db-wal")
    finally:
        writer.close()
    for f in folder.iterdir():
        os.chmod(f, stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
    os.chmod(folder, 0o555)
    got = as_nobody("info", str(folder / "map.db"), cwd=site / "work")
    assert got.returncode == 1, got.stdout
    lines = got.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {folder / 'map.db'}: cannot open"), (
        got.stderr
    )
    assert "map.db-wal" in lines[0] and "corrupt" not in lines[0]


@pytest.mark.parametrize("hidden", ["file", "folder"])
def test_a_map_this_user_may_not_read_is_named_so(site: Path, samples: Path, hidden: str) -> None:
    db = _read_only_map(site, "owner")
    os.chmod(db if hidden == "file" else db.parent, 0o600 if hidden == "file" else 0o700)
    for command in (["info", str(db)], ["query", str(samples / QUERY), "--db", str(db)]):
        got = as_nobody(*command)
        lines = got.stderr.strip().splitlines()
        assert got.returncode in (1, 2) and len(lines) == 1, got.stderr
        assert lines[0].startswith("error: ") and str(db) in lines[0], got.stderr
        assert "not readable" in lines[0] or "Permission denied" in lines[0], got.stderr
        assert "corrupt" not in lines[0]
    # The library says the same (the command line may refuse it before).
    got = _library_error(db, writable=False)
    assert got.stdout.strip() == f"{db}: cannot read (Permission denied)", got.stderr


# -- a read-only open leaves nothing that stops a later writer (issue 42) ----------------


def _own_map(top: Path, name: str) -> Path:
    """A copy of the map owned by uid 65534, at 0444, in a folder of its own: its owner
    made it read-only, and may make it writable again."""
    folder = top / name
    folder.mkdir()
    os.chown(folder, NOBODY, NOBODY)
    db = folder / "map.db"
    shutil.copy(top / "writable" / "map.db", db)
    os.chown(db, NOBODY, NOBODY)
    os.chmod(db, 0o444)
    return db


def _scans_in(db: Path) -> list[str]:
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [r[0] for r in conn.execute("SELECT path FROM scans ORDER BY id")]
    finally:
        conn.close()


def _append_as_owner(db: Path, samples: Path) -> tuple[subprocess.CompletedProcess, Path]:
    extra = db.parent / "extra.bin"
    shutil.copy(samples / "01" / "velodyne" / "000007.bin", extra)
    os.chmod(db, 0o644)  # the owner makes the map writable again
    got = as_nobody("build-db", str(extra), "-o", str(db), "--append", "-q", cwd=db.parent)
    return got, extra


def test_a_query_of_a_0444_map_leaves_nothing_that_stops_a_later_append(
    site: Path, samples: Path
) -> None:
    # Before: the query left map.db-wal and map.db-shm at 0444 beside the map, and the
    # append failed with "attempt to write a readonly database".
    db = _own_map(site, "own")
    before = _scans_in(site / "writable" / "map.db")
    got = as_nobody("query", str(samples / QUERY), "--db", str(db), "-k", "1", "--format", "jsonl")
    assert got.returncode == 0 and json.loads(got.stdout)["match_id"] == 5, got.stderr
    _one_note(got.stderr, db)
    assert sorted(p.name for p in db.parent.iterdir()) == ["map.db"]
    got, extra = _append_as_owner(db, samples)
    assert got.returncode == 0, got.stderr
    assert _scans_in(db) == before + [str(extra)]


def test_side_files_a_read_only_open_left_are_made_writable_by_their_owner(
    site: Path, samples: Path
) -> None:
    # What an older disco, or the sqlite3 shell, leaves: a read-only (mode=ro) open of
    # the 0444 map by its owner creates map.db-wal and map.db-shm at 0444.
    db = _own_map(site, "left")
    script = "import sqlite3, sys\nc = sqlite3.connect(f'file:{sys.argv[1]}?mode=ro', uri=True)\n"
    script += "c.execute('SELECT count(*) FROM scans').fetchall()\nc.close()\n"
    left = subprocess.run(_nobody_cmd() + ["-c", script, str(db)], cwd="/", env=_env(),
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert left.returncode == 0, left.stderr
    for side in ("map.db-wal", "map.db-shm"):
        assert stat.S_IMODE((db.parent / side).stat().st_mode) == 0o444
    before = _scans_in(site / "writable" / "map.db")
    got, extra = _append_as_owner(db, samples)
    assert got.returncode == 0, got.stderr
    assert _scans_in(db) == before + [str(extra)]


def test_side_files_of_another_user_are_named_for_removal(site: Path, samples: Path) -> None:
    db = _own_map(site, "theirs")
    for side in ("map.db-wal", "map.db-shm"):  # root's, 0444: uid 65534 may not change them
        (db.parent / side).write_bytes(b"")
        os.chmod(db.parent / side, 0o444)
    got, _ = _append_as_owner(db, samples)
    lines = got.stderr.strip().splitlines()
    assert got.returncode == 1 and len(lines) == 1, got.stderr
    assert lines[0].startswith(f"error: {db}: cannot write: map.db-wal"), got.stderr
    assert "remove map.db-wal and map.db-shm" in lines[0] and "corrupt" not in lines[0]
    assert _scans_in(db) == _scans_in(site / "writable" / "map.db")
