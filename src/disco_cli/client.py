"""A client of `disco serve` (docs/serve.md), in the standard library alone, so that
it starts in a few tens of milliseconds:

    from disco_cli.client import Client
    with Client(socket="disco.sock") as c:
        for row in c.query("scans/000123.bin", topk=3):
            print(row["match"], row["distance"], row["yaw_deg"])

and from a shell, one reply line (JSON) per scan path read from the arguments or stdin:

    find scans -name '*.bin' | python -m disco_cli.client --socket disco.sock -
"""

from __future__ import annotations

import argparse
import base64
import json
import socket
import sys
from pathlib import Path
from typing import Any

__all__ = ["Client", "ServerError"]


class ServerError(Exception):
    """The server refused a request: its one-line reason."""


class Client:
    """One connection to a `disco serve` server, on a Unix socket or a TCP port.
    Requests are answered in order; a refused one raises `ServerError` and the
    connection stays usable."""

    def __init__(
        self,
        socket: str | Path | None = None,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        timeout: float | None = 60.0,
    ):
        if (socket is None) == (port is None):
            raise ValueError("give a socket path or a port")
        self._sock = _connect(socket, host, port, timeout)
        self._reader = self._sock.makefile("rb")
        self._next_id = 0

    def close(self) -> None:
        self._reader.close()
        self._sock.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request(self, fields: dict[str, Any]) -> dict[str, Any]:
        """Send one request and return the whole reply (ok or not)."""
        self._next_id += 1
        line = json.dumps({"id": self._next_id, **fields}).encode() + b"\n"
        self._sock.sendall(line)
        reply = self._reader.readline()
        if not reply:
            raise ConnectionError("the server closed the connection")
        return json.loads(reply)

    def query(self, scan: Any, *, topk: int | None = None, pose: bool = False, **fields) -> list:
        """The rows of `disco query --format jsonl` for one scan: a file path (read
        by the server) or an N x 3 / N x 4 array of points (sent inline)."""
        req: dict[str, Any] = dict(fields)
        if isinstance(scan, (str, Path)):
            req["scan"] = str(scan)
        else:
            import numpy as np

            pts = np.ascontiguousarray(scan, dtype="<f4")
            req["points"] = {
                "shape": list(pts.shape),
                "data": base64.b64encode(pts.tobytes()).decode(),
            }
        if topk is not None:
            req["topk"] = topk
        if pose:
            req["pose"] = True
        reply = self.request(req)
        if not reply.get("ok"):
            raise ServerError(reply.get("error", "refused"))
        return reply["rows"]

    def ping(self) -> bool:
        return bool(self.request({"op": "ping"}).get("ok"))


def _connect(path: Any, host: str, port: int | None, timeout: float | None) -> socket.socket:
    if path is not None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        address: Any = str(path)
    else:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        address = (host, port)
    s.settimeout(timeout)
    try:
        s.connect(address)
    except OSError:
        s.close()
        raise
    return s


def main(argv: list[str] | None = None) -> int:
    """`python -m disco_cli.client`: one JSON reply line per scan path (read by the
    server: relative paths are taken from the server's working folder)."""
    ap = argparse.ArgumentParser(
        prog="python -m disco_cli.client",
        description="Ask a running `disco serve` about scans: one JSON reply line per scan.",
    )
    ap.add_argument("scans", nargs="+", help="scan files, or - to read paths from stdin")
    ap.add_argument("--socket", help="the server's Unix socket (default: disco.sock)")
    ap.add_argument("--port", type=int, help="the server's TCP port instead")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--topk", "-k", type=int, help="matches per query (server's default)")
    ap.add_argument("--pose", action="store_true", help="add the verified relative pose")
    args = ap.parse_args(argv)
    sock = None if args.port is not None else (args.socket or "disco.sock")
    paths = (
        (line.strip() for line in sys.stdin if line.strip())
        if args.scans == ["-"]
        else iter(args.scans)
    )
    failed = 0
    try:
        with Client(sock, host=args.host, port=args.port) as c:
            for path in paths:
                req: dict[str, Any] = {"scan": path}
                if args.topk is not None:
                    req["topk"] = args.topk
                if args.pose:
                    req["pose"] = True
                reply = c.request(req)
                failed += not reply.get("ok")
                sys.stdout.write(json.dumps(reply) + "\n")
                sys.stdout.flush()
    except OSError as exc:
        where = sock or f"{args.host}:{args.port}"
        print(f"error: {where}: cannot reach the server ({exc})", file=sys.stderr)
        return 1
    except BrokenPipeError:
        return 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
