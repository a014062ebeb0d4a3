"""A damaged map database, cut or with flipped bytes, from every command that opens one.

The database is a real one (data/samples/00, spectral model), built once per session.
Each damaged copy goes through query, eval, loops, info, info --check and build-db
(--append and resume) with CliRunner. The truth for "damaged" comes from outside
disco: the copy's size against the original's, and SQLite's own integrity check run
on a second copy by the test. What must hold: never a traceback; a cut file, and a damaged one
met by a writer or `info --check`, gives exit status 1 and one line naming the file (or
the check's list); a reader refuses damage it reads in one line; the file is left byte
for byte as it was.
"""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app


def _page_size(data: bytes) -> int:
    """The page size in an SQLite header (65536 is written as 1)."""
    size = int.from_bytes(data[16:18], "big")
    return 65536 if size == 1 else size


def _commands(db: Path, samples: Path) -> dict[str, list[str]]:
    """Every command that opens a database, reading or writing (writers last)."""
    q = str(samples / "01" / "velodyne" / "000005.bin")
    return {
        "query": ["query", q, "-d", str(db), "-k", "2", "--format", "tsv"],
        "eval": ["eval", str(samples / "01"), "-d", str(db), "-k", "2", "--format", "tsv"],
        "loops": ["loops", str(samples / "00"), "-m", "spectral", "-d", str(db)]
        + ["--exclude-frames", "5", "--format", "tsv"],
        "info": ["info", str(db), "--format", "tsv"],
        "info --check": ["info", str(db), "--check", "--format", "tsv"],
        "resume": ["build-db", str(samples / "00"), "-o", str(db), "-m", "spectral"],
        "append": ["build-db", str(samples / "01"), "-o", str(db), "-m", "spectral", "--append"],
    }


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _sqlite_says_damaged(data: bytes, where: Path) -> bool:
    """SQLite's own verdict on these bytes, on a copy that disco never opens."""
    where.write_bytes(data)
    try:
        conn = sqlite3.connect(f"file:{where}?mode=ro", uri=True)
        try:
            rows = conn.execute("PRAGMA integrity_check").fetchall()
        finally:
            conn.close()
    except sqlite3.DatabaseError:
        return True
    finally:
        for suffix in ("", "-wal", "-shm"):
            Path(f"{where}{suffix}").unlink(missing_ok=True)
    return rows != [("ok",)]


def _run(args: list[str]) -> tuple[int, str]:
    res = CliRunner().invoke(app, args)
    # A traceback would be an exception other than the exit the command line raises.
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        import traceback

        where = "".join(traceback.format_exception(*res.exc_info)[-6:])
        raise AssertionError(f"{args}: {type(res.exception).__name__}: {res.exception}\n{where}")
    assert "Traceback" not in res.output, res.output
    return res.exit_code, res.stderr


def _check_refused(name: str, code: int, err: str, db: Path) -> None:
    assert code == 1, f"{name}: exit {code}, {err!r}"
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"{name}: {err!r}"
    assert lines[0].startswith(f"error: {db}: "), f"{name}: {err!r}"


@pytest.fixture(scope="module", autouse=True)
def built_once():
    """Typer builds the click command on every CliRunner.invoke (0.1-0.2 s, most of a
    refused command's time): build it once for the hundreds of runs here."""
    import typer.testing

    command = typer.main.get_command(app)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(typer.testing, "_get_command", lambda _app: command)
        yield


@pytest.fixture(scope="module")
def original(samples_spectral_db: Path) -> bytes:
    data = samples_spectral_db.read_bytes()
    page = _page_size(data)
    assert len(data) % page == 0 and len(data) // page > 4
    return data


def _offsets(size: int, PAGE: int) -> list[int]:  # noqa: N803
    """Every page boundary, a point inside every page, and the first bytes of the header."""
    rng = np.random.default_rng(0)
    inside = [k * PAGE + int(rng.integers(1, PAGE)) for k in range(size // PAGE)]
    return sorted(set(range(0, size, PAGE)) | set(inside) | {1, 15, 16, 17, 50, 99, 100, 101})


def test_every_cut_is_refused_by_every_command(
    original: bytes, samples: Path, tmp_path: Path
) -> None:
    db = tmp_path / "cut.db"
    PAGE = _page_size(original)  # noqa: N806
    offsets = _offsets(len(original), PAGE)
    assert len(offsets) > 2 * (len(original) // PAGE)
    for n, cut in enumerate(offsets):
        data = original[:cut]
        db.write_bytes(data)
        commands = _commands(db, samples)
        # Every command in the header and the first and last pages; elsewhere three
        # commands in turn, so that each meets a cut at about every other page.
        if 101 < cut < len(original) - PAGE and cut >= PAGE:
            names = list(commands)
            commands = {k: commands[k] for k in {names[(n + j) % 7] for j in (0, 2, 4)}}
        for name, args in commands.items():
            code, err = _run(args)
            _check_refused(name, code, err, db)
            assert db.read_bytes() == data, f"{name} changed the file cut at {cut}"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.db"]


def _flip_cases(size: int, PAGE: int, seed: int = 0) -> list[list[tuple[int, int]]]:  # noqa: N803
    """(position, xor mask) lists: single bytes anywhere (mostly inside stored blobs,
    which SQLite cannot check), bytes of page headers (b-tree page type, cell count,
    content start, overflow page links) and of the file header, and a few at once."""
    rng = np.random.default_rng(seed)
    pages = size // PAGE

    def mask() -> int:
        return int(rng.integers(1, 256))

    cases = [[(int(rng.integers(0, size)), mask())] for _ in range(12)]
    cases += [
        [(int(rng.integers(0, pages)) * PAGE + int(rng.integers(0, 12)), mask())] for _ in range(12)
    ]
    cases += [[(int(rng.integers(16, 100)), mask())] for _ in range(4)]
    cases += [[(int(rng.integers(0, size)), mask()) for _ in range(4)] for _ in range(4)]
    return cases


def test_flipped_bytes_never_give_a_traceback(
    original: bytes, samples: Path, tmp_path: Path
) -> None:
    verdicts = []
    for k, flips in enumerate(_flip_cases(len(original), _page_size(original))):
        data = bytearray(original)
        for pos, m in flips:
            data[pos] ^= m
        data = bytes(data)
        folder = tmp_path / f"flip{k}"
        folder.mkdir()
        db = folder / "map.db"
        damaged = _sqlite_says_damaged(data, folder / "oracle.db")
        verdicts.append(damaged)
        for name, args in _commands(db, samples).items():
            db.write_bytes(data)
            code, err = _run(args)
            where = f"{name} with flips {flips}"
            if damaged and name in ("resume", "append"):
                # SQLite itself finds the file damaged: a writer checks the whole file
                # first and refuses it, untouched.
                _check_refused(where, code, err, db)
            elif damaged and name == "info --check":
                # The full check finds it: one error line, or the problems listed.
                assert code == 1, f"{where}: exit {code}: {err!r}"
                lines = err.strip().splitlines()
                assert len(lines) == 1 or lines[0].startswith("problem: "), f"{where}: {err!r}"
            else:
                # A reader opens cheaply (header, meta, schema) and meets SQLite's damage
                # only where it reads; on a file sound to SQLite, disco may still refuse
                # what the bytes now say (a model name, a config, a blob's size) or read
                # values that changed: one line either way, or an answer.
                assert code in (0, 1), f"{where}: exit {code}: {err!r}"
                if code == 1 and name not in ("query", "loops"):  # those go on per scan
                    lines = err.strip().splitlines()
                    if name == "info --check":  # lists every problem, then the way out
                        assert lines[0].startswith("problem: "), f"{where}: {err!r}"
                    else:
                        assert len(lines) == 1, f"{where}: {err!r}"
            if code != 0 or name != "append":
                assert db.read_bytes() == data, f"{where} changed a file it did not write"
        shutil.rmtree(folder)
    # The cases reach both kinds of damage: what SQLite sees and what it cannot.
    assert 5 <= sum(verdicts) <= len(verdicts) - 5, verdicts


def test_a_damaged_file_is_refused_before_writing(original: bytes, samples: Path, tmp_path):
    # Damage in the scans table's root page, which opening (meta, schema) never reads:
    # only a check of the whole file finds it.
    copy = tmp_path / "copy.db"
    copy.write_bytes(original)
    conn = sqlite3.connect(f"file:{copy}?mode=ro", uri=True)
    root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'scans'").fetchone()
    conn.close()
    data = bytearray(original)
    data[(root[0] - 1) * _page_size(original)] = 0xFF  # the b-tree page type: no such type
    db = tmp_path / "map.db"
    db.write_bytes(bytes(data))
    assert _sqlite_says_damaged(bytes(data), tmp_path / "oracle.db")
    before = _sha(db)
    for name in ("append", "resume"):
        code, err = _run(_commands(db, samples)[name])
        _check_refused(name, code, err, db)
        assert "corrupt" in err
        assert _sha(db) == before
