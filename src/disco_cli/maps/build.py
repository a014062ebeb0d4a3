"""`disco build-db`'s entry points on a map: open one to add scan files to (new,
resumed or appended) and repair its damaged rows.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from disco_cli.errors import DatabaseError
from disco_cli.maps.facade import Map
from disco_cli.maps.map_side_views import side_offsets
from disco_cli.maps.writing import map_address

__all__ = ["open_for_adding", "repair_files"]


def open_for_adding(
    path: Path,
    names: list[str],
    model: Any = "default",
    *,
    append: bool = False,
    device="cpu",
    side_views: float | None = None,
) -> tuple[Map, int, int]:
    """`disco build-db`'s map: `path` opened to add the scan files `names` (a new map when
    there is no file), with how many files they are and how many of them it holds
    already (by absolute path). A map that holds other scans is refused unless `append`,
    so that a resumed build never mixes in another. `side_views` (metres, None: the
    map's own setting, 0 for a new map) must agree with an existing map's."""
    given = {os.path.abspath(p) for p in names}
    if not map_address(path).exists():
        return Map.create(path, model, device=device, side_views=side_views or 0.0), len(given), 0
    m = Map.open(path, writable=True, model=model, device=device)
    if side_views is not None and side_offsets(side_views) != m.side_offsets:
        have = m.side_views
        m.close()
        raise DatabaseError(
            path,
            f"was built with --side-views {have:g}, not {side_views:g}; "
            "keep the map's setting or build a new map",
        )
    stored = {os.path.abspath(p) for p in m.names()}  # an old map's relative paths too
    if not append and not stored.issubset(given):
        m.close()
        raise DatabaseError(
            path,
            "exists and holds other scans; pass --append to add to it, or choose another --output",
        )
    return m, len(given), len(stored & given)


def repair_files(
    path: Path,
    scans: Any,
    model: Any,
    scan_format: str | None,
    batch: int,
    threads: int | None,
    device: str = "cpu",
) -> str:
    """`disco build-db --repair`: `Map.repair` of the map at `path` from `scans` (a
    `collect_scans` result: paths, poses, times). The line that says what was done;
    one `DatabaseError` line when something could not be repaired."""
    if not map_address(path).exists():
        raise DatabaseError(path, "no such database to repair")
    # The map's own model unless another was named (build-db's default names "default").
    named = None if model == "default" else model
    with Map.open(path, writable=True, model=named, device=device) as m:
        migrated = m.database.migrated_line()  # type: ignore[union-attr]
        result = m.repair(
            scans.paths,
            poses=scans.poses,
            times=scans.times,
            batch=batch,
            threads=threads,
            scan_format=scan_format,
        )
    done = f"{path}: repaired {len(result.repaired)} damaged scans"
    errors = [
        f"scan {rid} ({name}) is damaged and none of the given scans is it"
        for rid, name in result.unplaced.items()
    ] + result.problems
    if errors:
        raise DatabaseError(
            path, f"{done}; not repaired: {'; '.join(errors)}; rebuild it with disco build-db"
        )
    return f"{migrated}\n{done}" if migrated else done
