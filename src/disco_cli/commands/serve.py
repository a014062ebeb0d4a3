"""`disco serve`: keep one map and its model loaded and answer queries over a local
socket (JSON lines, docs/serve.md), for programs that ask many times over their life.
The work is `disco_cli/serve.py`; the client is `disco_cli/client.py`."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    MODEL_OF_MAP,
    ThreadsOpt,
    db_option,
    model_option,
    topk_option,
)
from disco_cli.console import handle_errors, stderr, warn


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@handle_errors
def serve(
    db_path: Annotated[Path, db_option("The map database (from disco build-db).")] = Path("map.db"),
    socket_path: Annotated[
        Optional[Path],
        typer.Option(
            "--socket",
            metavar="PATH",
            help="Listen on this Unix socket (mode 0600: this user only). The default "
            "when no --port is given: disco.sock in the current folder.",
        ),
    ] = None,
    port: Annotated[
        Optional[int],
        typer.Option("--port", min=1, max=65535, help="Listen on this TCP port instead."),
    ] = None,
    host: Annotated[
        str,
        typer.Option(
            "--host",
            help="The address --port listens on; anything but a loopback address "
            "exposes the map to the network.",
        ),
    ] = "127.0.0.1",
    topk: Annotated[int, topk_option("Matches per query when a request does not say.")] = 10,
    max_request_mb: Annotated[
        float,
        typer.Option(
            "--max-request-mb",
            min=0.001,
            max=4096,
            help="Longest request line accepted (MiB); a longer one is refused and its "
            "connection closed.",
        ),
    ] = 64.0,
    model: Annotated[Optional[str], model_option(MODEL_OF_MAP)] = None,
    threads: ThreadsOpt = None,
) -> None:
    """Answer queries against one map over a local socket, loading it and the model once."""
    from disco_cli.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load

    from disco_cli.map import Map
    from disco_cli.serve import QueryService, ServeOptions, make_server, serve_forever

    if port is None and socket_path is None:
        socket_path = Path("disco.sock")
    if port is not None and socket_path is not None:
        raise typer.BadParameter("give --socket or --port, not both", param_hint="--port")
    if port is not None and not _loopback(host):
        warn(f"listening on {host}:{port}: any host that reaches it can query this map")
    options = ServeOptions(topk=topk, max_request_bytes=int(max_request_mb * 1024 * 1024))
    with Map.open(db_path, model=model) as m:
        m.on_missing_scan = warn
        m.on_damaged = warn
        service = QueryService(m, options)
        server = make_server(service, socket_path=socket_path, host=host, port=port)
        where = str(socket_path) if socket_path is not None else f"{host}:{port}"

        def ready() -> None:
            stderr.print(f"{db_path}: {len(m)} scans; listening on {where} (Ctrl-C stops)")

        try:
            serve_forever(server, ready)
        except KeyboardInterrupt:
            stderr.print(f"stopped after {service.answered} queries")
