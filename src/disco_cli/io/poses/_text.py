"""Reading pose files as text: lines, numbers and the one-line errors they raise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError


def read_lines(path: str | Path) -> list[str]:
    """The file's lines, without trailing blank lines; `PoseFileError` if missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: no such file")
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise PoseFileError(f"{path}: cannot read ({exc})") from None
    while lines and not lines[-1].strip():
        lines.pop()
    return lines


def floats(
    path: str | Path, lineno: int, fields: list[str], want: int, allow_nan: bool = False
) -> np.ndarray:
    """`want` finite numbers from one line's fields, or `PoseFileError` naming the line.

    With `allow_nan`, NaN fields are returned as NaN (the caller drops such rows)."""
    if len(fields) != want:
        raise PoseFileError(f"{path}, line {lineno}: expected {want} numbers, found {len(fields)}")
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        bad = " ".join(fields)
        raise PoseFileError(f"{path}, line {lineno}: not a number in {bad!r}") from None
    if not np.all(np.isfinite(values)) and not (allow_nan and not np.isinf(values).any()):
        raise PoseFileError(f"{path}, line {lineno}: NaN or Inf")
    return values


def split_fields(line: str) -> list[str]:
    """The fields of a line separated by commas and/or white space."""
    return line.replace(",", " ").split()


def has_header(line: str) -> bool:
    """Whether a CSV's first line is a header (its first field is not a number)."""
    fields = split_fields(line)
    if not fields:
        return False
    try:
        float(fields[0])
    except ValueError:
        return True
    return False


def numeric_table(
    path: str | Path, want: int, what: str, allow_nan: bool = False
) -> tuple[np.ndarray, int]:
    """Rows of `want` numbers from a text or CSV file (an optional header line is skipped;
    `#` lines are comments). With `allow_nan`, rows holding NaN are dropped.

    Returns the `[N, want]` table and the number of rows dropped for NaN.
    """
    lines = read_lines(path)
    skip = 1 if lines and has_header(lines[0]) else 0
    rows = [
        floats(path, i + 1, split_fields(line), want, allow_nan)
        for i, line in enumerate(lines)
        if i >= skip and line.strip() and not line.lstrip().startswith("#")
    ]
    table = np.stack(rows) if rows else np.zeros((0, want))
    ok = np.isfinite(table).all(axis=1)
    if not ok.any():
        raise PoseFileError(f"{path}: no {what}")
    return table[ok], int((~ok).sum())


def to_4x4(values12: np.ndarray) -> np.ndarray:
    """A row-major 3 x 4 (12 numbers, or [N, 12]) as 4 x 4 (or [N, 4, 4])."""
    v = np.asarray(values12, dtype=np.float64)
    flat = v.reshape(-1, 12)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    T[:, :3, :4] = flat.reshape(-1, 3, 4)
    return T[0] if v.ndim == 1 else T
