"""`disco serve`: keep one map and its model loaded and answer queries over a local
socket (JSON lines, docs/serve.md), for programs that ask many times over their life.
The requests are `disco_cli/service/serve.py`, the connections `disco_cli/service/serve_net.py`; the
client is `disco_cli/service/client.py`."""

from __future__ import annotations

import os
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
from disco_cli.runtime.console import handle_errors, plural, stderr, warn

PANEL_LIMITS = "Limits"
PANEL_TCP = "TCP"


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
        typer.Option(
            "--port",
            min=1,
            max=65535,
            help="Listen on this TCP port instead; clients must show the token of --token-file.",
        ),
    ] = None,
    host: Annotated[
        str,
        typer.Option(
            "--host",
            help="The address --port listens on; anything but a loopback address "
            "needs --tls-cert (or --insecure-plaintext).",
            rich_help_panel=PANEL_TCP,
        ),
    ] = "127.0.0.1",
    token_file: Annotated[
        Optional[Path],
        typer.Option(
            "--token-file",
            metavar="PATH",
            help="With --port: write a new random token here at start (mode 0600; "
            "removed at exit). Default: disco-PORT.token in the current folder.",
            rich_help_panel=PANEL_TCP,
        ),
    ] = None,
    tls_cert: Annotated[
        Optional[Path],
        typer.Option(
            "--tls-cert",
            metavar="PEM",
            dir_okay=False,
            help="With --port: speak TLS with this certificate (chain); clients "
            "check it against their CA (--tls-ca).",
            rich_help_panel=PANEL_TCP,
        ),
    ] = None,
    tls_key: Annotated[
        Optional[Path],
        typer.Option(
            "--tls-key",
            metavar="PEM",
            dir_okay=False,
            help="The private key of --tls-cert (default: in the --tls-cert file).",
            rich_help_panel=PANEL_TCP,
        ),
    ] = None,
    insecure_plaintext: Annotated[
        bool,
        typer.Option(
            "--insecure-plaintext",
            help="Listen on a non-loopback --host without TLS: the token and the "
            "scans cross the network in clear.",
            rich_help_panel=PANEL_TCP,
        ),
    ] = False,
    scan_root: Annotated[
        Optional[Path],
        typer.Option(
            "--scan-root",
            file_okay=False,
            help="Read requests' scan files only under this folder (relative paths "
            "from it); also where the map's own scans are looked for, as in disco "
            "query. Default: the map's folder.",
        ),
    ] = None,
    topk: Annotated[int, topk_option("Matches per query when a request does not say.")] = 10,
    allow_append: Annotated[
        bool,
        typer.Option(
            "--allow-append",
            help="Also take append requests: the scans they send (files under "
            "--scan-root, or points inline) are embedded and added to the map, one "
            "request at a time. Off: the map is opened read-only.",
        ),
    ] = False,
    max_request_mb: Annotated[
        float,
        typer.Option(
            "--max-request-mb",
            min=0.001,
            max=4096,
            help="Longest request line accepted (MiB); a longer one is refused and its "
            "connection closed.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 64.0,
    max_buffer_mb: Annotated[
        float,
        typer.Option(
            "--max-buffer-mb",
            min=0.1,
            max=65536,
            help="Request bytes held at once across all connections (MiB); a "
            "connection that needs more is refused and closed.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 256.0,
    max_poses: Annotated[
        int,
        typer.Option(
            "--max-poses",
            min=1,
            max=10000,
            help="The most matches one request may ask a pose of (topk with pose or "
            "verify): each is an ICP run on the server's one worker.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 100,
    max_clients: Annotated[
        int,
        typer.Option(
            "--max-clients",
            min=1,
            max=10000,
            help="Clients connected at once (over TCP: those past the token); one "
            "more is told the server is full.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 64,
    max_pending: Annotated[
        int,
        typer.Option(
            "--max-pending",
            min=1,
            max=10000,
            help="TCP: connections that have not shown the token yet, apart from "
            "--max-clients; past it the one waiting longest is closed.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 16,
    auth_timeout: Annotated[
        float,
        typer.Option(
            "--auth-timeout",
            min=0.1,
            max=3600,
            help="TCP: seconds from connecting to showing the token (the TLS "
            "handshake included); a slower connection is closed.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 5.0,
    read_timeout: Annotated[
        float,
        typer.Option(
            "--read-timeout",
            min=0.1,
            help="Seconds a request line (or a reply) may take to cross; a slower "
            "connection is closed.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 30.0,
    idle_timeout: Annotated[
        float,
        typer.Option(
            "--idle-timeout",
            min=0,
            help="Seconds a connection may sit without a request before it is closed "
            "(disco_cli.service.client reconnects by itself); 0: never.",
            rich_help_panel=PANEL_LIMITS,
        ),
    ] = 600.0,
    model: Annotated[Optional[str], model_option(MODEL_OF_MAP)] = None,
    threads: ThreadsOpt = None,
) -> None:
    """Answer queries against one map over a local socket, loading it and the model once."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: after set_threads, which must come before torch and BLAS load
    from disco_cli.errors import DiscoError
    from disco_cli.maps.facade import Map
    from disco_cli.service.serve import QueryService, ServeOptions
    from disco_cli.service.serve_net import (
        NetOptions,
        is_loopback,
        make_server,
        serve_forever,
        tls_context,
        write_token,
    )

    if port is None and socket_path is None:
        socket_path = Path("disco.sock")
    if port is not None and socket_path is not None:
        raise typer.BadParameter("give --socket or --port, not both", param_hint="--port")
    for given, name in (
        (token_file, "--token-file"),
        (tls_cert, "--tls-cert"),
        (tls_key, "--tls-key"),
        (insecure_plaintext or None, "--insecure-plaintext"),
    ):
        if given is not None and port is None:
            raise typer.BadParameter("this is for --port only", param_hint=name)
    if tls_key is not None and tls_cert is None:
        raise typer.BadParameter("a key needs its --tls-cert", param_hint="--tls-key")
    if tls_cert is not None and insecure_plaintext:
        raise typer.BadParameter("TLS is not plain text", param_hint="--insecure-plaintext")
    if port is not None and tls_cert is None and not insecure_plaintext and not is_loopback(host):
        raise typer.BadParameter(
            f"{host} is not a loopback address, and without TLS the token and the scans "
            "would cross the network in clear: give --tls-cert and --tls-key (or "
            "--insecure-plaintext to accept the risk)",
            param_hint="--host",
        )
    tls = None if tls_cert is None else tls_context(tls_cert, tls_key)
    if max_request_mb > max_buffer_mb:
        raise typer.BadParameter(
            f"{max_request_mb:g} MiB requests cannot fit in {max_buffer_mb:g} MiB",
            param_hint="--max-buffer-mb",
        )
    root = scan_root if scan_root is not None else Path(db_path).absolute().parent
    if not root.is_dir():
        raise DiscoError(f"{root}: --scan-root is not a folder")
    if port is not None and tls is None and not is_loopback(host):
        warn(
            f"listening on {host}:{port} without TLS (--insecure-plaintext): the token "
            "and the scans cross the network in clear"
        )
    options = ServeOptions(
        topk=topk,
        max_request_bytes=int(max_request_mb * 1024 * 1024),
        scan_root=root,
        allow_append=allow_append,
        max_poses=max_poses,
    )
    net = NetOptions(
        max_clients=max_clients,
        max_buffer_bytes=int(max_buffer_mb * 1024 * 1024),
        read_timeout=read_timeout,
        idle_timeout=idle_timeout or None,
        auth_timeout=auth_timeout,
        max_pending=max_pending,
        tls=tls,
        insecure_plaintext=insecure_plaintext,
    )
    # Appends go through this process's own writer (the map's writable connection).
    with Map.open(db_path, writable=allow_append, model=model, scan_root=scan_root) as m:
        m.on_missing_scan = warn
        m.on_damaged = warn
        migrated = m.database.migrated_line() if allow_append else ""  # type: ignore[union-attr]
        if migrated:
            stderr.print(migrated, soft_wrap=True, highlight=False)
        service = QueryService(m, options)
        if port is not None:
            token_file = token_file or Path(f"disco-{port}.token")
            net.token = write_token(token_file)
        try:
            server = make_server(service, socket_path=socket_path, host=host, port=port, net=net)
        except DiscoError:
            if token_file is not None:
                token_file.unlink(missing_ok=True)
            raise
        where = str(socket_path) if socket_path is not None else f"{host}:{port}"
        if tls is not None:
            where += " (TLS)"
        if token_file is not None:
            where += f", token in {token_file}"

        def ready() -> None:
            takes = "; appends taken" if allow_append else ""
            stderr.print(
                f"{db_path}: {len(m)} scans; listening on {where}; scans read under "
                f"{os.path.realpath(root)}{takes} (Ctrl-C stops)",
                soft_wrap=True,
                highlight=False,
            )

        try:
            serve_forever(server, ready, token_file)
        except KeyboardInterrupt:
            pass
        # Ctrl-C and SIGTERM (a service manager's stop) end the same way.
        added = f" and {plural(service.appended, 'scan')} appended" if allow_append else ""
        stderr.print(f"stopped after {service.answered} queries{added}")
