"""`disco info`: what a map database holds, and (`--check`) whether it is sound."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from disco_cli.commands.options import OutputFormatOpt
from disco_cli.runtime.console import (
    OutputFormat,
    RowWriter,
    handle_errors,
    resolve_format,
    stderr,
)


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return str(n)


@handle_errors
def info(
    db_path: Annotated[Path, typer.Argument(help="The map database.", show_default=False)],
    check: Annotated[
        bool,
        typer.Option(
            "--check",
            help="Also run SQLite's integrity check and verify every row (its checksum, "
            "sizes and values: every check a query makes); lists the damaged scans.",
        ),
    ] = False,
    fmt: OutputFormatOpt = None,
) -> None:
    """Show a map database's scans, model, configuration and size."""
    # deferred: numpy and the map code (~0.2 s) load when the command runs, not for --help
    from disco_cli.maps.map_side_views import side_views_m
    from disco_cli.maps.store import open_store  # a file, or a milvus: address

    with open_store(db_path) as db:
        rows = [
            ("scans", len(db)),
            ("model", db.model.name),
            ("fingerprint", db.model.fingerprint),
            ("model_source", db.meta.get("model_source", "")),
            ("signature_dim", db.signature_dim),
            ("feature_shape", " x ".join(map(str, db.feature_shape)) + " float16"),
            ("poses", "yes" if db.has_poses() else "no"),
            ("side_views_m", side_views_m(db.side_offsets)),
            ("format_version", db.format_version),
            ("disco_version", db.meta.get("disco_version", "")),
            ("size", _size(db.size_bytes())),
            ("model_config", json.dumps(db.model.model_config, sort_keys=True)),
            ("bev_config", json.dumps(db.model.bev_config, sort_keys=True)),
        ]
        problems = db.check() if check else []
        damaged = sorted(db.damaged)
        if check:
            rows.append(("check", "ok" if not problems else f"{len(problems)} problems"))
            rows.append(("damaged_scans", len(damaged)))
        unverified = check and not db.checksummed
    if resolve_format(fmt) is OutputFormat.jsonl:
        # One object: the fields as keys, the configurations as objects rather than text.
        record = {k: json.loads(v) if k.endswith("_config") else v for k, v in rows}
        RowWriter(list(record), fmt).write([record])
    else:
        RowWriter(["field", "value"], fmt, title=str(db_path)).write(
            {"field": k, "value": v} for k, v in rows
        )
    for p in problems[:20]:
        stderr.print(f"[bold red]problem:[/] {db_path}: {p}", soft_wrap=True)
    if len(problems) > 20:
        stderr.print(f"... and {len(problems) - 20} more")
    if damaged:
        # Every damaged scan on one line, whatever their number, and the way out.
        stderr.print(f"damaged scans: {' '.join(map(str, damaged))}", soft_wrap=True)
        stderr.print(
            f"repair them: disco build-db SCANS -o {db_path} --repair "
            "(the inputs the map was built from)",
            soft_wrap=True,
        )
    if unverified:
        stderr.print(
            f"note: {db_path} is format 1: its rows carry no checksums, so damage inside "
            "a value goes unseen; writing to it (build-db --append or --repair) migrates it",
            soft_wrap=True,
        )
    if problems:
        raise typer.Exit(1)
