"""Terminal plumbing shared by every command: errors, progress bars and result output.

Results go to stdout: a rich table when stdout is a terminal, TSV or JSON lines
when it is piped, flushed as soon as they are ready so that pipelines stream.
Everything meant for a person (progress, warnings, errors) goes to stderr.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sqlite3
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from enum import Enum
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from disco_cli.errors import DiscoError
from disco_cli.runtime.table_layout import print_table

stderr = Console(stderr=True, highlight=False)
# In a pipe or a log file, a message is one line however long: rich would wrap it at 80.
stderr.soft_wrap = not stderr.is_terminal

F = TypeVar("F", bound=Callable[..., Any])


class OutputFormat(str, Enum):
    table = "table"
    tsv = "tsv"
    jsonl = "jsonl"


def resolve_format(fmt: OutputFormat | None) -> OutputFormat:
    """The format asked for, else a table on a terminal and TSV in a pipe."""
    if fmt is not None:
        return fmt
    return OutputFormat.table if sys.stdout.isatty() else OutputFormat.tsv


def error(message: str) -> None:
    """Print one error line on stderr (the message as is: brackets in a path or an
    SQLite message are not markup)."""
    stderr.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)


def warn(message: str) -> None:
    stderr.print(f"[yellow]warning:[/] {escape(message)}", soft_wrap=True)


def note(message: str) -> None:
    """One line of information on stderr (e.g. an index being built)."""
    stderr.print(f"note: {escape(message)}", soft_wrap=True, highlight=False)


def say(message: str) -> None:
    """One line on stderr that only informs (a summary, a count): `-q` silences it, as it
    does progress; results, warnings and errors print all the same."""
    if not _quiet:
        stderr.print(message, soft_wrap=True, markup=False, highlight=False)


def plural(n: int, word: str) -> str:
    """`1 scan`, `2 scans`."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print one error line and return the Exit to raise: `raise fail("...")`."""
    error(message)
    return typer.Exit(code)


def stdout_closed() -> typer.Exit:
    """The reader of our stdout went away (`disco query ... | head`): a normal end, exit 0.

    stdout is pointed at /dev/null first, so that the interpreter's last flush of
    what is still buffered neither fails nor prints "Broken pipe" at exit.
    """
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass  # no real file descriptor (a test runner's stdout): nothing to protect
    return typer.Exit(0)


def handle_errors(func: F) -> F:
    """Turn a DiscoError (bad input) into one error line and exit status 1; a closed
    stdout into a quiet exit 0; an SQLite error that escaped the database layer into
    one line too (the last resort: `disco_cli.maps.database` names the file itself)."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except DiscoError as exc:
            raise fail(str(exc)) from None
        except BrokenPipeError:
            raise stdout_closed() from None
        except sqlite3.DatabaseError as exc:
            raise fail(f"database error: {exc}") from None

    return wrapper  # type: ignore[return-value]


# -- progress: a bar on a terminal, a line every few seconds elsewhere, nothing with -q --

_quiet = False
# Seconds between two progress lines where stderr is not a terminal (a log, CI, nohup).
PROGRESS_SECONDS_ENV = "DISCO_PROGRESS_SECONDS"


def set_quiet(value: bool) -> bool:
    """`-q/--quiet`: no progress bar, no progress line (a callback of the option)."""
    global _quiet
    _quiet = bool(value)
    return value


_bad_progress_seconds_told = False


def _progress_seconds() -> float:
    global _bad_progress_seconds_told
    text = os.environ.get(PROGRESS_SECONDS_ENV, "5")
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if math.isfinite(seconds) and seconds >= 0:
        return seconds
    if not _bad_progress_seconds_told:  # once, not at every progress bar
        _bad_progress_seconds_told = True
        warn(f"{PROGRESS_SECONDS_ENV}={text!r} is not a number of seconds >= 0; using 5")
    return 5.0


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def progress_line(
    description: str, done: float, total: float | None, seconds: float, since: float, unit: str
) -> str:
    """`build-db: 120/1000 (12%), 35.2 scans/s, 25 s left`: `done` of `total` after
    `seconds`, the rate of the `done - since` made in them."""
    rate = (done - since) / seconds if seconds > 0 else 0.0
    counts = f"{done:.0f}"
    if total:
        counts += f"/{total:.0f} ({100 * done / total:.0f}%)"
    line = f"{description}: {counts}, {rate:.1f} {unit}/s".replace(" /s", "/s")
    if total and rate > 0 and done < total:
        line += f", {_duration((total - done) / rate)} left"
    return line


class _Progress(Progress):
    """rich's Progress; where stderr is not a terminal (no bar), it prints one line per
    task every few seconds instead: what is done, the rate, the time left. A task's
    `note` field (training's losses) ends its line."""

    def __init__(self, *columns: Any, lines: bool, **kwargs: Any) -> None:
        super().__init__(*columns, **kwargs)
        self._lines = lines
        self._every = _progress_seconds()
        self._shown: dict[Any, float] = {}  # task -> when its last line was printed
        self._origin: dict[Any, tuple[float, float]] = {}  # task -> (time, done) the rate is from

    def add_task(self, *args: Any, **kwargs: Any) -> Any:
        task_id = super().add_task(*args, **kwargs)
        self._origin[task_id] = (time.monotonic(), 0.0)
        return task_id

    def update(self, task_id: Any, **kwargs: Any) -> None:  # type: ignore[override]
        super().update(task_id, **kwargs)
        self._line(task_id)

    def advance(self, task_id: Any, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._line(task_id)

    def _line(self, task_id: Any) -> None:
        if not self._lines:
            return
        now = time.monotonic()
        task = self._tasks[task_id]
        start, since = self._origin.setdefault(task_id, (now, 0.0))
        if task.completed < since:  # counting again (a new epoch): so does the rate
            start, since = self._origin[task_id] = (now, task.completed)
        if now - self._shown.get(task_id, start) < self._every:
            return
        self._shown[task_id] = now
        unit = str(task.fields.get("unit", ""))
        line = progress_line(task.description, task.completed, task.total, now - start, since, unit)
        note = task.fields.get("note")
        stderr.print(f"{line}; {note}" if note else line, soft_wrap=True, markup=False)


def progress(transient: bool = False) -> Progress:
    """A progress bar on stderr where it is a terminal, else a line every few seconds
    ($DISCO_PROGRESS_SECONDS, 5); neither with -q."""
    return _Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=stderr,
        transient=transient,
        disable=_quiet or not stderr.is_terminal,
        lines=not _quiet and not stderr.is_terminal,
    )


@contextmanager
def steps(description: str, total: int, unit: str = "scans") -> Iterator[Callable[[int], None]]:
    """A transient progress bar of `total` steps (`progress`); yields `advance(k)`."""
    with progress(transient=True) as bar:
        task = bar.add_task(description, total=total, rate="", unit=unit)
        yield lambda k: bar.advance(task, k)


@contextmanager
def rate_bar(description: str, total: int) -> Iterator[Callable[[int, int], None]]:
    """A progress bar (`progress`) of `total` scans that shows scans per second since it
    began; yields `update(done, counted)`, the rate being of the `counted` scans."""
    start = time.perf_counter()
    with progress() as bar:
        task = bar.add_task(description, total=total, rate="", unit="scans")

        def update(done: int, counted: int) -> None:
            rate = counted / max(time.perf_counter() - start, 1e-9)
            bar.update(task, completed=done, rate=f"{rate:.1f} scans/s")

        yield update


def in_blocks(groups: Iterable[list[Any]], size: int) -> Iterator[list[Any]]:
    """The items of `groups` (one list per input, say), joined `size` groups at a time,
    so that results print in blocks as they come; empty blocks are skipped."""
    block: list[Any] = []
    for i, group in enumerate(groups, 1):
        block += group
        if block and i % size == 0:
            yield block
            block = []
    if block:
        yield block


def _plain(value: Any) -> Any:
    """A JSON- and TSV-friendly version of a value (numpy scalars, NaN)."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _cell(value: Any, digits: int) -> str:
    value = _plain(value)
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


class RowWriter:
    """Writes result rows in one format, flushing each batch as it comes.

    A table is printed per `write` call (one query's matches, say); TSV writes
    its header once; JSONL writes one object per row.
    """

    def __init__(
        self,
        columns: Sequence[str],
        fmt: OutputFormat | None = None,
        title: str | None = None,
        digits: int = 4,
        table_omit: Sequence[str] = (),
    ):
        self.columns = list(columns)
        # Columns a table leaves out because its title already says them (the query path).
        self.table_columns = [c for c in self.columns if c not in table_omit]
        self.fmt = resolve_format(fmt)
        self.title = title
        self.digits = digits
        self._header_done = False
        self._out = Console(highlight=False, soft_wrap=True)

    def write(self, rows: Iterable[dict[str, Any]], title: str | None = None) -> None:
        rows = list(rows)
        if self.fmt is OutputFormat.table:
            cells = [[_cell(row.get(c), self.digits) for c in self.table_columns] for row in rows]
            print_table(self._out, self.table_columns, cells, title=title or self.title)
        elif self.fmt is OutputFormat.tsv:
            lines = []
            if not self._header_done:
                lines.append("\t".join(self.columns))
                self._header_done = True
            lines += [
                "\t".join(_cell(row.get(c), self.digits) for c in self.columns) for row in rows
            ]
            if lines:
                sys.stdout.write("\n".join(lines) + "\n")
        else:
            for row in rows:
                sys.stdout.write(json.dumps({k: _plain(v) for k, v in row.items()}) + "\n")
        sys.stdout.flush()
