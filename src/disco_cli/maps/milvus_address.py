"""`milvus:` map addresses and the connection to them (`milvus_store.py` has the map).

- `milvus:PATH`: Milvus Lite, embedded in this process, in the folder PATH (ending in
  `.db`); one process at a time.
- `milvus://HOST:PORT/NAME`: a Milvus server (standalone or cluster); the map's
  collections are prefixed NAME. Its token comes from `DISCO_MILVUS_TOKEN`, never the
  command line; reaching it takes at most `DISCO_MILVUS_TIMEOUT` seconds (default 5).
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from disco_cli.errors import DatabaseError, DiscoError

__all__ = [
    "INSTALL_HINT",
    "TOKEN_ENV",
    "MilvusAddress",
    "parse_address",
    "connect",
    "milvus_errors",
]

INSTALL_HINT = "a milvus: map needs pymilvus and milvus-lite: pip install 'disco-cli[milvus]'"
# The server's token (user:password or an API key) comes from here, never the command line.
TOKEN_ENV = "DISCO_MILVUS_TOKEN"
# Seconds to reach a server before giving up with one line (a firewall drops silently).
CONNECT_TIMEOUT_ENV = "DISCO_MILVUS_TIMEOUT"
CONNECT_TIMEOUT_S = 5.0
# Open clients per Milvus Lite folder in this process (`disconnect`).
_LITE_USERS: dict[str, int] = {}
_LITE_LOCK = threading.Lock()


class MilvusAddress:
    """A `milvus:` map address: `uri` for the client, `name` the collections' prefix.
    `os.fspath` of it is the Milvus Lite folder (relative paths of scans count from its
    parent), or the address itself for a server."""

    def __init__(self, text: str, uri: str, name: str, lite: bool):
        self.text, self.uri, self.name, self.lite = text, uri, name, lite

    def __str__(self) -> str:
        return self.text

    def __repr__(self) -> str:
        return f"MilvusAddress({self.text!r})"

    def __fspath__(self) -> str:
        return self.uri if self.lite else self.text

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MilvusAddress) and other.text == self.text

    def __hash__(self) -> int:
        return hash(self.text)

    @property
    def parent(self) -> Path:
        return Path(os.path.abspath(self.uri)).parent if self.lite else Path.cwd()

    def check_folder(self) -> None:
        """One line when a Milvus Lite map's folder cannot be made (its parent is missing)."""
        parent = os.path.dirname(os.path.abspath(self.uri))
        if self.lite and not os.path.isdir(parent):
            raise DatabaseError(self, f"folder {parent} does not exist; create it first")

    def exists(self) -> bool:
        """Whether a map is stored there (a server is asked)."""
        require_extra(self)
        if self.lite and not Path(self.uri).exists():
            return False
        client = connect(self)
        try:
            return client.has_collection(f"{self.name}_meta")
        finally:
            disconnect(self, client)


def parse_address(value: Any) -> MilvusAddress | None:
    """The `milvus:` address `value` names, or None for a plain path (an SQLite map).

    `milvus:PATH` is Milvus Lite in the folder PATH; `milvus://HOST:PORT/NAME` a server
    (its collections prefixed NAME). A path option may have folded `//` into `/`
    (`pathlib`), so `milvus:/HOST:PORT/NAME` is read as a server too."""
    if isinstance(value, MilvusAddress):
        return value
    text = os.fspath(value) if isinstance(value, os.PathLike) else str(value)
    if not text.startswith("milvus:"):
        return None
    rest = text[len("milvus:") :]
    server = rest.startswith("//")
    if not server and rest.startswith("/"):
        host = rest[1:].split("/", 1)[0]
        server = ":" in host and host.rsplit(":", 1)[1].isdigit()
    if server:
        hostport, _, name = rest.lstrip("/").partition("/")
        name = name.strip("/")
        host, _, port = hostport.rpartition(":")
        if not host or not port.isdigit():
            raise DiscoError(f"{text}: a Milvus server is milvus://HOST:PORT/NAME")
        if not name or not name.replace("_", "a").isalnum() or name[0].isdigit():
            raise DiscoError(
                f"{text}: NAME must be letters, digits and '_', not starting with a digit"
            )
        return MilvusAddress(f"milvus://{hostport}/{name}", f"http://{hostport}", name, False)
    if not rest:
        raise DiscoError("milvus:PATH needs a PATH (the Milvus Lite folder)")
    return MilvusAddress(text, rest, "disco", True)


def _pymilvus() -> Any:
    try:
        import pymilvus  # deferred: the optional [milvus] extra
    except ImportError:
        raise DiscoError(INSTALL_HINT) from None
    return pymilvus


def require_extra(address: MilvusAddress) -> None:
    """One line naming the extra when its packages are missing (before anything else)."""
    _pymilvus()
    if address.lite:
        try:
            import milvus_lite  # noqa: F401  # deferred: the optional [milvus] extra
        except ImportError:
            raise DiscoError(INSTALL_HINT) from None


def connect(address: MilvusAddress) -> Any:
    """A `MilvusClient` for `address`, within a bounded time; one `DatabaseError` line
    when it cannot be reached or opened."""
    require_extra(address)
    pymilvus = _pymilvus()
    # pymilvus logs every failed call with its traceback; disco says it in one line.
    for name in ("pymilvus", "milvus_lite"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if address.lite:
        uri = os.path.abspath(address.uri)
        if not uri.endswith(".db"):
            # pymilvus starts Milvus Lite only for a path ending in .db
            raise DatabaseError(address, "a Milvus Lite map's PATH must end in .db")
        if os.path.exists(uri) and not os.path.isdir(uri):
            raise DatabaseError(address, "is a file, not a Milvus Lite folder")
        address.check_folder()
        token = ""
    else:
        uri = address.uri
        token = os.environ.get(TOKEN_ENV, "")
    try:
        timeout = float(os.environ.get(CONNECT_TIMEOUT_ENV, CONNECT_TIMEOUT_S))
    except ValueError:
        raise DiscoError(f"{CONNECT_TIMEOUT_ENV}: a number of seconds") from None
    try:
        client = pymilvus.MilvusClient(uri=uri, token=token, timeout=timeout)
    except Exception as exc:  # pymilvus raises its own and grpc's errors
        reason = reason_of(exc)
        if address.lite:
            raise DatabaseError(
                address,
                f"cannot open Milvus Lite ({reason}); another process may hold it: "
                "Milvus Lite takes one process per map (several need a server)",
            ) from None
        raise DatabaseError(
            address, f"cannot reach the Milvus server within {timeout:g} s ({reason})"
        ) from None
    if address.lite:
        with _LITE_LOCK:
            _LITE_USERS[uri] = _LITE_USERS.get(uri, 0) + 1
    return client


def disconnect(address: MilvusAddress, client: Any) -> None:
    """Close `client`; the last one of a Milvus Lite folder in this process stops its
    embedded server, which frees the folder for another process."""
    try:
        client.close()
    finally:
        if address.lite:
            uri = os.path.abspath(address.uri)
            with _LITE_LOCK:
                left = _LITE_USERS.get(uri, 1) - 1
                _LITE_USERS[uri] = left
            if left <= 0:
                _LITE_USERS.pop(uri, None)
                # deferred: the optional [milvus] extra
                from milvus_lite import server_manager_instance

                server_manager_instance.release_server(uri)


def reason_of(exc: BaseException) -> str:
    """A Milvus error's message on one short line."""
    return " ".join(str(getattr(exc, "message", "") or exc).split())[:200]


def milvus_errors(func: Callable) -> Callable:
    """A Milvus error met while reading or writing becomes one `DatabaseError`."""

    @functools.wraps(func)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return func(self, *args, **kwargs)
        except DiscoError:
            raise
        except Exception as exc:
            if type(exc).__module__.split(".")[0] not in ("pymilvus", "grpc", "milvus_lite"):
                raise
            raise DatabaseError(self.path, f"Milvus error ({reason_of(exc)})") from None

    return wrapper
