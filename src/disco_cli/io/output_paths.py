"""Output paths: checked before the work starts, written atomically.

One rule for every command that writes a file or a folder (`-o`, `--report`): the
folder it goes into must exist already (a mistyped parent is refused in one line,
never created), must take a new file (tried, since a root process passes every
permission test but still cannot write into /proc), and the target must not be a
folder when a file is asked for (or a file when a folder is). Files are written under
a temporary name in the same folder and renamed into place, so an error or a crash
leaves either the old file or the new one, and no temporary behind.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from disco_cli.errors import DiscoError
from disco_cli.maps.milvus_address import parse_address


def _check_folder(path: Path, what: str) -> None:
    """The folder `path` goes into exists and takes a new file."""
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise DiscoError(f"{path}: folder {parent} does not exist; create it first")
    if not parent.is_dir():
        raise DiscoError(f"{path}: {parent} is not a folder")
    try:  # the honest test: make (and remove) a file where the output will go
        fd, probe = tempfile.mkstemp(dir=parent, prefix=f".{path.name}.", suffix=".probe")
    except OSError as exc:
        raise DiscoError(
            f"{path}: cannot write {what} in {parent} ({exc.strerror or exc})"
        ) from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(
    path: str | Path, *, exists_ok: bool = True, what: str = "a file", hint: str = ""
) -> Path:
    """`path` as a Path if a file can be written there; else one-line `DiscoError`.

    `exists_ok=False` refuses an existing file (`hint` says what to do instead)."""
    path = Path(path)
    if path.is_dir():
        raise DiscoError(f"{path}: is a folder; give a file name")
    if path.exists() and not exists_ok:
        raise DiscoError(f"{path}: exists{'; ' + hint if hint else ''}")
    _check_folder(path, what)
    return path


def check_output_folder(path: str | Path | None, *, what: str = "files") -> Path | None:
    """`path` as a Path if it is a folder that takes files, or can be made one (its
    parent exists); else one-line `DiscoError`. The folder itself is not created.
    None (no such output asked for) passes as None."""
    if path is None:
        return None
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise DiscoError(f"{path}: is a file, not a folder; give a folder (new or existing)")
    if path.is_dir():
        _check_folder(path / "x", what)
    else:
        _check_folder(path, what)
    return path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside `path` (same suffix, so writers that add one do not) to
    write to; renamed onto `path` when the block ends, removed when it raises."""
    path = Path(path)
    fd, name = tempfile.mkstemp(
        dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=path.suffix
    )
    os.close(fd)
    mask = os.umask(0)  # mkstemp makes the file private; the output gets the usual mode
    os.umask(mask)
    os.chmod(name, 0o666 & ~mask)
    tmp = Path(name)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomic(path: str | Path, write: Callable[[Path], object]) -> None:
    """`write(tmp)` then rename onto `path`; an OSError becomes one line naming `path`."""
    try:
        with atomic_path(path) as tmp:
            write(tmp)
    except OSError as exc:
        raise DiscoError(f"{path}: cannot write ({exc.strerror or exc})") from None


def write_text_atomic(path: str | Path, text: str) -> None:
    """`text` into `path`, atomically."""
    write_atomic(path, lambda tmp: tmp.write_text(text))


def check_map_output(output: Path) -> Any:
    """The map a build writes: a Milvus address (`milvus:...`, its folder checked) or the
    file path, checked by `check_output_file`; either before any scan is embedded."""
    address = parse_address(output)
    if address is None:
        check_output_file(output, what="the database")
        return output
    address.check_folder()
    return address
