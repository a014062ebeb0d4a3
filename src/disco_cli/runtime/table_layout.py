"""Terminal tables that fit the terminal without hiding data.

rich shrinks a table that is too wide by cutting its cells (`0.3…`) and, past a
point, by dropping whole columns. Here the widths are decided before rich draws:

1. every column at its natural width, when the table fits;
2. else paths shortened from the left at a `/` (`…/velodyne/000004.bin`), never
   below the shortest ending that tells the column's paths apart, and long text
   wrapped between words;
3. else the columns split into several tables stacked one above the other, each
   repeating the key column (the rank, say) so that a row can be followed across;
4. else (more than three such tables), on a narrow terminal, one block of
   `name value` lines per record.

A number or a name is never cut: its column is as wide as its widest cell.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from rich.console import Console
from rich.table import Table
from rich.text import Text

# Columns holding paths (shortened from the left) and free text (wrapped).
PATH_COLUMNS = frozenset({"query", "match", "path", "query_seq", "match_seq"})
WRAP_COLUMNS = frozenset({"reason", "value"})
# A word of free text longer than this may fold inside its column rather than widen it.
_WRAP_MIN = 24
ELLIPSIS = "…"
# The most tables a result is split into side by side before it is shown as records.
MAX_TABLES = 3
# What one column costs besides its cells in rich's default box: a space either side
# and one rule; the table's last rule is the +1 in `_table_width`.
_PER_COLUMN = 3


def _table_width(widths: Sequence[int]) -> int:
    return sum(widths) + _PER_COLUMN * len(widths) + 1


def short_path(path: str, width: int) -> str:
    """`path` in at most `width` characters, shortened from the left at a `/` with `…/`
    in front; the file name is always kept whole, even when it alone is wider."""
    if len(path) <= width:
        return path
    parts = path.split("/")
    kept = parts[-1]
    for part in reversed(parts[:-1]):
        longer = f"{part}/{kept}"
        if len(ELLIPSIS) + 1 + len(longer) > width:
            break
        kept = longer
    return f"{ELLIPSIS}/{kept}"


def _distinct_width(paths: Sequence[str]) -> int:
    """The narrowest width at which `short_path` still tells every path apart: each
    keeps the fewest trailing parts that no other path of the column ends with."""
    distinct = set(paths)
    split = {p: p.split("/") for p in distinct}
    depth = max((len(s) for s in split.values()), default=0)
    counts = [Counter("/".join(s[-k:]) for s in split.values()) for k in range(1, depth + 1)]
    widest = 0
    for p, parts in split.items():
        for k in range(1, len(parts) + 1):
            if k == len(parts) or counts[k - 1]["/".join(parts[-k:])] == 1:
                tail = "/".join(parts[-k:])
                widest = max(widest, len(p) if k == len(parts) else min(len(p), len(tail) + 2))
                break
    return widest


@dataclass
class _Column:
    name: str
    kind: str  # "path", "wrap" or "fixed"
    natural: int  # the widest cell or the header
    minimum: int  # the narrowest it may be drawn
    right: bool  # numbers are right-justified


def _columns(names: Sequence[str], rows: Sequence[Sequence[str]]) -> list[_Column]:
    cols = []
    for j, name in enumerate(names):
        cells = [r[j] for r in rows]
        natural = max([len(name), *map(len, cells)])
        if name in PATH_COLUMNS:
            kind, minimum = "path", max(len(name), _distinct_width(cells))
        elif name in WRAP_COLUMNS:
            words = [len(w) for c in cells for w in c.split()]
            kind, minimum = "wrap", max(len(name), min(max(words, default=0), _WRAP_MIN))
        else:
            kind, minimum = "fixed", natural
        right = kind == "fixed" and all(_numeric(c) for c in cells if c)
        cols.append(_Column(name, kind, natural, min(minimum, natural), right))
    return cols


def _numeric(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return cell in ("true", "false")
    return True


def _widths(cols: Sequence[_Column], width: int) -> list[int] | None:
    """Widths for `cols` in `width` characters: natural when they fit, else the minimum
    with what is left given to the paths and text in order; None when even the minimum
    does not fit."""
    if _table_width([c.natural for c in cols]) <= width:
        return [c.natural for c in cols]
    widths = [c.minimum for c in cols]
    spare = width - _table_width(widths)
    if spare < 0:
        return None
    for i, c in enumerate(cols):
        grow = min(spare, c.natural - widths[i])
        widths[i] += grow
        spare -= grow
    return widths


def _pack(cols: list[_Column], width: int, keys: int, loose: bool) -> list[list[int]] | None:
    """The columns (by index) of each stacked table, each starting with the `keys`
    first columns, filled in order while they fit at their natural widths (`loose`) or
    at their narrowest; None when the keys and one more column do not fit."""

    def fits(group: list[int]) -> bool:
        chosen = [cols[i] for i in group]
        if loose:
            return _table_width([c.natural for c in chosen]) <= width
        return _widths(chosen, width) is not None

    head = list(range(min(keys, len(cols))))
    groups: list[list[int]] = []
    group = list(head)
    for j in range(len(head), len(cols)):
        if fits(group + [j]):
            group.append(j)
        elif len(group) > len(head) and fits(head + [j]):
            groups.append(group)
            group = head + [j]
        else:
            return None
    groups.append(group)
    # (A table of the keys alone, too wide itself, is shown as records.)
    return groups if all(fits(g) for g in groups) else None


def _groups(cols: list[_Column], width: int, keys: int) -> list[list[int]] | None:
    """One table when the columns fit side by side; else the fewest stacked tables,
    with whole paths where that takes no more tables; None: records instead."""
    if _widths(cols, width) is not None:
        return [list(range(len(cols)))]
    tight = _pack(cols, width, keys, loose=False)
    loose = _pack(cols, width, keys, loose=True)
    best = loose if tight is None or (loose is not None and len(loose) <= len(tight)) else tight
    # Past a few tables a row is hard to follow: one block per record reads better.
    return best if best is not None and len(best) <= MAX_TABLES else None


def _fitted(cell: str, col: _Column, width: int) -> str:
    return short_path(cell, width) if col.kind == "path" else cell


def print_table(
    console: Console,
    names: Sequence[str],
    rows: Sequence[Sequence[str]],
    title: str | None = None,
    keys: int = 1,
) -> None:
    """Print `rows` (cells already text) under the headers `names` within the console's
    width, by the rules in this module's docstring; `keys` first columns repeat in every
    stacked table."""
    width = console.width
    if title:
        console.print(Text(title, style="italic"))
    cols = _columns(names, rows)
    groups = _groups(cols, width, keys)
    if groups is None:
        _print_records(console, names, rows)
        return
    for group in groups:
        gcols = [cols[i] for i in group]
        widths = _widths(gcols, width)
        assert widths is not None  # _groups checked every group
        shown = [[_fitted(row[i], cols[i], w) for i, w in zip(group, widths)] for row in rows]
        # A shortened path may come out narrower than its column: the column follows it.
        widths = [
            max([len(c.name), *(len(r[k]) for r in shown)]) if c.kind == "path" else w
            for k, (c, w) in enumerate(zip(gcols, widths))
        ]
        table = Table()
        for c, w in zip(gcols, widths):
            table.add_column(
                c.name,
                justify="right" if c.right else "left",
                width=w,
                no_wrap=c.kind != "wrap",
                overflow="fold",
            )
        for cells in shown:
            table.add_row(*cells)
        console.print(table)


def _print_records(console: Console, names: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    """One block of `name  value` lines per row, whole values, a blank line between."""
    pad = max(map(len, names), default=0)
    blocks = []
    for row in rows:
        blocks.append("\n".join(f"{n.ljust(pad)}  {v}" for n, v in zip(names, row)))
    if not rows:  # an empty result still shows what it would have held
        blocks.append(" ".join(names))
    console.print(Text("\n\n".join(blocks)))
