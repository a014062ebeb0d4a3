"""A Milvus map's collections: created, loaded, and its meta read (`milvus_store.py`)."""

from __future__ import annotations

import json
from typing import Any

from disco_cli.database import FORMAT_VERSION
from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.milvus_address import MilvusAddress, reason_of

__all__ = ["create_collections", "load_collections", "read_meta", "PATH_MAX", "VARCHAR_MAX"]

# Milvus's largest VARCHAR; the deflated features of the default model are ~9 KB.
VARCHAR_MAX = 65535
PATH_MAX = 4096


def load_collections(address: MilvusAddress, client: Any) -> None:
    """Load the map's collections (Milvus answers only loaded ones; Lite starts with
    them released)."""
    try:
        for part in ("meta", "scans", "views"):
            name = f"{address.name}_{part}"
            if client.has_collection(name):
                client.load_collection(name)
    except Exception as exc:
        raise DatabaseError(address, f"Milvus error ({reason_of(exc)})") from None


def read_meta(address: MilvusAddress, client: Any) -> dict[str, str]:
    try:
        if not client.has_collection(f"{address.name}_meta"):
            raise DatabaseError(address, "no such database")
        got = client.query(
            f"{address.name}_meta",
            filter='key != ""',
            output_fields=["key", "value"],
            limit=1000,
            consistency_level="Strong",
        )
    except DiscoError:
        raise
    except Exception as exc:
        raise DatabaseError(address, f"Milvus error ({reason_of(exc)})") from None
    meta = {r["key"]: r["value"] for r in got}
    needed = (
        "format_version",
        "model_name",
        "fingerprint",
        "model_config",
        "bev_config",
        "signature_dim",
        "feature_shape",
        "generation",
        "next_id",
    )
    missing = [k for k in needed if k not in meta]
    if missing:
        raise DatabaseError(address, f"not a whole disco map: meta lacks {', '.join(missing)}")
    try:
        json.loads(meta["model_config"]), json.loads(meta["bev_config"])
        json.loads(meta["feature_shape"]), int(meta["signature_dim"]), int(meta["next_id"])
        json.loads(meta.get("side_views_m", "[]"))
    except (ValueError, TypeError):
        raise DatabaseError(address, "corrupt map: unreadable meta values") from None
    if int(meta["format_version"]) > FORMAT_VERSION:
        raise DatabaseError(address, "map format is newer than this disco supports; upgrade disco")
    return meta


def create_collections(
    address: MilvusAddress, client: Any, dim: int, views: bool, overwrite: bool
) -> None:
    from pymilvus import DataType

    names = [f"{address.name}_{s}" for s in ("scans", "views", "meta")]
    if client.has_collection(names[2]) and not overwrite:
        raise DatabaseError(address, "already exists")
    for name in names:  # a map without meta is a leftover of an interrupted create
        if client.has_collection(name):
            client.drop_collection(name)

    def make(name: str, fields: list[tuple], vector: str, vdim: int) -> None:
        schema = client.create_schema(auto_id=False, enable_dynamic_field=False)
        for fname, dtype, kw in fields:
            schema.add_field(fname, dtype, **kw)
        params = client.prepare_index_params()
        params.add_index(field_name=vector, index_type="FLAT", metric_type="L2")
        client.create_collection(
            name, schema=schema, index_params=params, consistency_level="Strong"
        )

    nullable = {"nullable": True}
    make(
        names[0],
        [
            ("id", DataType.INT64, {"is_primary": True}),
            ("sig", DataType.FLOAT_VECTOR, {"dim": dim}),
            ("path", DataType.VARCHAR, {"max_length": PATH_MAX}),
            ("rel_path", DataType.VARCHAR, {"max_length": PATH_MAX, **nullable}),
            ("time", DataType.DOUBLE, nullable),
            ("x", DataType.DOUBLE, nullable),
            ("y", DataType.DOUBLE, nullable),
            ("z", DataType.DOUBLE, nullable),
            ("yaw", DataType.DOUBLE, nullable),
            ("features", DataType.VARCHAR, {"max_length": VARCHAR_MAX}),
            ("feature_scale", DataType.DOUBLE, {}),
            ("crc", DataType.INT64, {}),
            ("feature_crc", DataType.INT64, {}),
        ],
        "sig",
        dim,
    )
    if views:
        make(
            names[1],
            [
                ("key", DataType.INT64, {"is_primary": True}),
                ("scan_id", DataType.INT64, {}),
                ("offset_m", DataType.DOUBLE, {}),
                ("sig", DataType.FLOAT_VECTOR, {"dim": dim}),
                ("crc", DataType.INT64, {}),
            ],
            "sig",
            dim,
        )
    make(
        names[2],
        [
            ("key", DataType.VARCHAR, {"is_primary": True, "max_length": 64}),
            ("value", DataType.VARCHAR, {"max_length": VARCHAR_MAX}),
            ("v", DataType.FLOAT_VECTOR, {"dim": 2}),
        ],
        "v",
        2,
    )
