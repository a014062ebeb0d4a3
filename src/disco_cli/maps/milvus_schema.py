"""A Milvus map's collections: created, loaded, and its meta read (`milvus_store.py`)."""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.maps.database_codec import (
    _encode_features,
    _feature_crc,
    _scaled,
    _scan_crc,
    _view_crc,
)
from disco_cli.maps.database_file import FORMAT_VERSION
from disco_cli.maps.database_types import ScanBatch
from disco_cli.maps.milvus_address import MilvusAddress, reason_of
from disco_cli.maps.milvus_lock import _rows, fold_state, is_protocol_key

__all__ = [
    "create_collections",
    "load_collections",
    "read_meta",
    "encode_rows",
    "row_crc",
    "PATH_MAX",
    "VARCHAR_MAX",
]

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
        rows = _rows(client, f"{address.name}_meta")
    except DiscoError:
        raise
    except Exception as exc:
        raise DatabaseError(address, f"Milvus error ({reason_of(exc)})") from None
    # The write protocol's rows (`milvus_lock.py`) share the collection; they are no
    # meta, but hold the counters (each the largest of its rows).
    meta = {k: v for k, v in rows.items() if not is_protocol_key(k)}
    if "next_id" in meta and "generation" in meta:
        try:
            state = fold_state(rows)
            meta["next_id"], meta["generation"] = str(state.next_id), str(state.generation)
        except ValueError:
            raise DatabaseError(address, "corrupt map: unreadable counters") from None
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
    from pymilvus import DataType  # deferred: the optional [milvus] extra

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


def _null(v: float) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def vector_bytes(vec: Any) -> bytes:
    return np.asarray(vec, dtype="<f4").tobytes()


def row_crc(rid: int, row: dict) -> int:
    """The scan row's checksum: `database._scan_crc`'s layout over the stored values,
    with the float32 vector's bytes as the signature."""
    return _scan_crc(
        rid,
        row["path"],
        row["rel_path"],
        row["time"],
        row["x"],
        row["y"],
        row["z"],
        row["yaw"],
        vector_bytes(row["sig"]),
        1.0,
    )


def encode_rows(
    where: Any, ids: list[int], batch: ScanBatch, rels: list
) -> tuple[list[dict], list[dict]]:
    """A batch's rows for the scans and views collections, checksummed: the signature as
    the float16-rounded values the SQLite map reads back (both maps search the same
    vectors), the features as the SQLite map's deflated blob in base64."""
    rows, views = [], []
    for k, rid in enumerate(ids):
        sig16, scale = _scaled(batch.signatures[k], np.dtype("<f2"))
        vec = np.frombuffer(sig16, "<f2").astype(np.float32) * np.float32(scale)
        data, fscale = _encode_features(batch.features[k])
        text = base64.b64encode(data).decode("ascii")
        if len(text) > VARCHAR_MAX:
            raise DatabaseError(
                where, f"a scan's features take {len(text)} bytes, over Milvus's 65535"
            )
        path = str(batch.paths[k])
        if len(path.encode("utf-8", "surrogateescape")) > PATH_MAX:
            raise DatabaseError(where, f"{path[:60]}...: path longer than {PATH_MAX}")
        x, y, z, yaw = (_null(v) for v in batch.poses[k])  # type: ignore[index]
        row = {
            "id": rid,
            "sig": vec.tolist(),
            "path": path,
            "rel_path": rels[k],  # type: ignore[index]
            "time": _null(batch.times[k]),  # type: ignore[index]
            "x": x,
            "y": y,
            "z": z,
            "yaw": yaw,
            "features": text,
            "feature_scale": float(fscale),
        }
        row["crc"] = row_crc(rid, row)
        row["feature_crc"] = _feature_crc(rid, fscale, data)
        rows.append(row)
        for j, offset in enumerate(batch.side_offsets):
            vsig, vscale = _scaled(batch.side_signatures[k, j], np.dtype("<f2"))  # type: ignore[index]
            vvec = np.frombuffer(vsig, "<f2").astype(np.float32) * np.float32(vscale)
            views.append(
                {
                    "key": rid * 64 + j,
                    "scan_id": rid,
                    "offset_m": float(offset),
                    "sig": vvec.tolist(),
                    "crc": _view_crc(rid, float(offset), vector_bytes(vvec), 1.0),
                }
            )
    return rows, views
