"""Terminal tables at 60, 80 and 120 columns: every column is shown and no number or
path is cut. The truth is the same command's `--format tsv` output (which a terminal's
width does not touch); the table's cells are read back from what it drew."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.runtime.table_layout import PATH_COLUMNS, print_table, short_path

WIDTHS = (60, 80, 120)


def _run(*args: str, columns: int = 200) -> str:
    res = CliRunner().invoke(app, list(args), env={"COLUMNS": str(columns)})
    assert res.exit_code == 0, res.output
    return res.stdout


def _tsv(*args: str) -> list[dict[str, str]]:
    lines = _run(*args, "--format", "tsv").splitlines()
    header = lines[0].split("\t")
    return [dict(zip(header, ln.split("\t"))) for ln in lines[1:]]


def _read_tables(text: str) -> list[dict[str, str]]:
    """The records a drawn output holds: boxed tables (stacked ones joined on their first
    column, wrapped cells joined with a space) or `name value` blocks."""
    lines = text.splitlines()
    if not any(ln.startswith("┃") for ln in lines):
        return _read_records(lines)
    records: list[dict[str, str]] = []
    header: list[str] = []
    row = 0
    current: dict[str, str] | None = None
    for ln in lines:
        if ln.startswith("┃"):
            header = [c.strip() for c in ln.strip("┃").split("┃")]
            row, current = 0, None
        elif ln.startswith("│"):
            cells = [c.strip() for c in ln.strip("│").split("│")]
            if cells[0]:  # a new row; else the wrapped rest of the one above
                if row == len(records):
                    records.append({})
                current = records[row]
                row += 1
                for name, cell in zip(header, cells):
                    assert current.get(name, cell) == cell, "key columns disagree"
                    current[name] = cell
            else:
                assert current is not None
                for name, cell in zip(header, cells):
                    if cell:
                        current[name] += " " + cell
    return records


def _read_records(lines: list[str]) -> list[dict[str, str]]:
    records, current = [], {}
    for ln in lines[1:]:  # the title first
        if not ln.strip():
            records.append(current)
            current = {}
            continue
        name, _, value = ln.partition(" ")
        current[name] = value.strip()
    if current:
        records.append(current)
    return records


def _same(name: str, shown: str, truth: str) -> bool:
    if name in PATH_COLUMNS and shown.startswith("…/"):
        # shortened from the left only: the file name and what follows the cut are whole
        return truth.endswith(shown[1:]) and Path(shown).name == Path(truth).name
    # wrapped text is the same characters, line breaks aside
    return shown.split() == truth.split()


def _check(drawn: str, truth: list[dict[str, str]], columns: int, omit: tuple = ()) -> None:
    assert max(len(ln) for ln in drawn.splitlines()) <= columns
    shown = _read_tables(drawn)
    assert len(shown) == len(truth)
    for got, want in zip(shown, truth):
        assert set(got) == set(want) - set(omit), f"columns missing at {columns}: {drawn}"
        for name, value in got.items():
            assert _same(name, value, want[name]), (name, value, want[name], columns)


@pytest.fixture(scope="module")
def map_db(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("tables") / "map.db"
    _run("build-db", str(samples / "00"), "-o", str(db))
    return db


@pytest.mark.parametrize("pose", [False, True])
@pytest.mark.parametrize("columns", WIDTHS)
def test_query_table_keeps_every_column_whole(
    map_db: Path, samples: Path, columns: int, pose: bool
) -> None:
    args = ["query", str(samples / "01/velodyne/000005.bin"), "--db", str(map_db), "--topk", "3"]
    args += ["--pose"] if pose else []
    truth = _tsv(*args)
    drawn = _run(*args, "--format", "table", columns=columns)
    assert drawn.splitlines()[0] == str(samples / "01/velodyne/000005.bin")  # the title, whole
    _check(drawn, truth, columns, omit=("query",))


@pytest.mark.parametrize("columns", WIDTHS)
def test_loops_verify_table_keeps_every_column_whole(samples: Path, columns: int) -> None:
    args = ["loops", str(samples / "00"), "--exclude-frames", "5"]
    args += ["--verify"]
    truth = _tsv(*args)
    assert truth, "the samples have loops"
    _check(_run(*args, "--format", "table", columns=columns), truth, columns)


@pytest.mark.parametrize("columns", WIDTHS)
def test_info_table_keeps_field_names_and_values_whole(map_db: Path, columns: int) -> None:
    truth = _tsv("info", str(map_db))
    _check(_run("info", str(map_db), "--format", "table", columns=columns), truth, columns)


def test_a_very_narrow_terminal_gets_one_block_per_record(map_db: Path, samples: Path) -> None:
    args = ["query", str(samples / "01/velodyne/000005.bin"), "--db", str(map_db), "--topk", "2"]
    args += ["--pose"]
    drawn = _run(*args, "--format", "table", columns=30)
    assert "┃" not in drawn
    _read = _read_records(drawn.splitlines())
    truth = _tsv(*args)
    assert len(_read) == 2
    for got, want in zip(_read, truth):
        assert got == {k: v for k, v in want.items() if k != "query"}  # paths whole too


def test_tsv_and_jsonl_do_not_depend_on_the_terminal_width(map_db: Path, samples: Path) -> None:
    args = ["query", str(samples / "01/velodyne/000005.bin"), "--db", str(map_db), "--pose"]
    for fmt in ("tsv", "jsonl"):
        outs = {_run(*args, "--format", fmt, columns=c) for c in (40, 200)}
        assert len(outs) == 1


def _draw(names: list[str], rows: list[list[str]], width: int) -> str:
    out = io.StringIO()
    print_table(Console(file=out, width=width, soft_wrap=True), names, rows)
    return out.getvalue()


def test_shortened_paths_stay_distinct() -> None:
    # Two sequences with the same file names: the file name alone would not tell them apart.
    paths = [f"/data/runs/2024/seq{s}/velodyne/{i:06d}.bin" for s in "AB" for i in range(3)]
    rows = [[str(i + 1), p, f"{0.1 * i:.4f}"] for i, p in enumerate(paths)]
    drawn = _draw(["rank", "match", "distance"], rows, width=44)
    shown = [r["match"] for r in _read_tables(drawn)]
    assert all(s.startswith("…/") and p.endswith(s[1:]) for s, p in zip(shown, paths))
    assert len(set(shown)) == len(paths)
    assert all(len(ln) <= 44 for ln in drawn.splitlines())


def test_short_path_cuts_at_a_slash_and_keeps_the_file_name() -> None:
    p = "data/samples/00/velodyne/000004.bin"
    assert short_path(p, 100) == p
    assert short_path(p, 21) == "…/velodyne/000004.bin"
    assert short_path(p, 20) == "…/000004.bin"
    assert short_path(p, 3) == "…/000004.bin"  # never less than the file name


def test_a_column_wider_than_the_terminal_is_shown_as_records() -> None:
    drawn = _draw(["fingerprint"], [["f" * 50], ["g" * 50]], width=30)
    assert "┃" not in drawn
    assert drawn.split() == ["fingerprint", "f" * 50, "fingerprint", "g" * 50]
