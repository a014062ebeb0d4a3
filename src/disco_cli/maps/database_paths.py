"""Where a map's stored scans are now (`Database.locate`'s order) and what a map stores
for scans given by path. Imported through `disco_cli.maps.database`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from disco_cli.io.readers import is_bag_message


def _locate(
    stored: str, rel: str | None, db_path: Path, scan_root: str | Path | None
) -> Path | None:
    """The resolution order of `Database.locate`. A scan in a ROS bag
    (`BAG#TOPIC@STAMP_NS`) exists when its bag does."""

    def exists(p: Path) -> bool:
        return p.exists() or is_bag_message(p)

    first = Path(stored)
    if exists(first):
        return first if first.is_absolute() else Path(os.path.abspath(first))
    if rel:
        beside = Path(os.path.abspath(db_path)).parent / rel
        if exists(beside):
            return Path(os.path.normpath(beside))
    if scan_root is not None:
        parts = [p for p in first.parts if p not in (first.anchor, "..", ".")]
        for k in range(len(parts)):
            candidate = Path(scan_root, *parts[k:])
            if exists(candidate):
                return Path(os.path.abspath(candidate))
    return None


def stored_paths(paths: Sequence[str], db_path: str | Path) -> tuple[list[str], list[str | None]]:
    """What a database at `db_path` stores for scans given as `paths`: the absolute
    path, and the path relative to the database's folder (None where there is none,
    e.g. on another Windows drive)."""
    folder = os.path.dirname(os.path.abspath(db_path))
    absolute = [os.path.abspath(p) for p in paths]
    rel: list[str | None] = []
    for p in absolute:
        try:
            rel.append(os.path.relpath(p, folder))
        except ValueError:
            rel.append(None)
    return absolute, rel
