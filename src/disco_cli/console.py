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
from collections.abc import Callable, Iterable, Sequence
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
from rich.table import Table

from disco_cli.errors import DiscoError

stderr = Console(stderr=True, highlight=False)

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
    one line too (the last resort: `disco_cli.database` names the file itself)."""

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


def progress(transient: bool = False) -> Progress:
    """A progress bar on stderr; hidden when stderr is not a terminal."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=stderr,
        transient=transient,
        disable=not stderr.is_terminal,
    )


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


# Columns that hold text (paths, reasons) rather than numbers.
_TEXT_COLUMNS = {"query", "match", "path", "query_seq", "match_seq", "reason"}


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
            table = Table(title=title or self.title, title_justify="left")
            for col in self.table_columns:
                if col in _TEXT_COLUMNS:
                    # Paths are what a person reads first: wrap them, never cut them.
                    table.add_column(col, justify="left", overflow="fold")
                else:
                    table.add_column(col, justify="right", no_wrap=True)
            for row in rows:
                table.add_row(*(_cell(row.get(c), self.digits) for c in self.table_columns))
            self._out.print(table)
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
