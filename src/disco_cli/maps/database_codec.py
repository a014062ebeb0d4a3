"""How a map row's values become stored bytes and checksums (format 2): signatures as
float16 divided by their largest magnitude, features also rounded to 9 significant bits
and deflated, and the CRC-32 of each row's payload (docs/database.md has the layout).
Imported through `disco_cli.maps.database`."""

from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np

from disco_cli.maps.database_types import ScanBatch

_SIG_DTYPE = np.dtype("<f2")
_SIG_DTYPE_V1 = np.dtype("<f4")
_FEAT_DTYPE = np.dtype("<f2")
# zlib level 6: 39 % of the float16 bytes on the samples; deflating is only at writing.
_DEFLATE_LEVEL = 6
# Features keep 9 significant bits of float16's 11 (rounded to nearest: a relative error
# <= 2^-9); docs/database.md has what that costs in yaw and matches.
_FEATURE_DROP_BITS = 2
# One scan row as stored and checksummed: id, path, rel_path, time, x, y, z, yaw,
# signature, signature_scale, crc.
_SCAN_ROW = "id, path, rel_path, time, x, y, z, yaw, signature, signature_scale, crc"


def _f64(v: Any) -> float:
    return np.nan if v is None else float(v)


def _scan_crc(
    rid: int,
    path: str,
    rel: str | None,
    time: Any,
    x: Any,
    y: Any,
    z: Any,
    yaw: Any,
    sig: bytes,
    sig_scale: Any,
) -> int:
    """CRC-32 of a scan row's payload. NULL reals count as NaN, a NULL rel_path as one
    0xFF byte (no UTF-8 text is that), so every stored value changes the checksum."""
    nan = np.nan
    head = struct.pack(
        "<q6d",
        rid,
        nan if time is None else time,
        nan if x is None else x,
        nan if y is None else y,
        nan if z is None else z,
        nan if yaw is None else yaw,
        nan if sig_scale is None else sig_scale,
    )
    text = path.encode("utf-8", "surrogateescape") + b"\x00"
    text += b"\xff" if rel is None else rel.encode("utf-8", "surrogateescape")
    return zlib.crc32(sig, zlib.crc32(text, zlib.crc32(head)))


def _feature_crc(rid: int, scale: Any, data: bytes) -> int:
    return zlib.crc32(data, zlib.crc32(struct.pack("<qd", rid, _f64(scale))))


def _view_crc(rid: int, offset: Any, sig: bytes, sig_scale: Any) -> int:
    head = struct.pack("<q2d", rid, _f64(offset), _f64(sig_scale))
    return zlib.crc32(sig, zlib.crc32(head))


def _none_if_nan(v: float) -> float | None:
    return None if not np.isfinite(v) else float(v)


def _scaled(v: np.ndarray, dtype: np.dtype) -> tuple[bytes, float]:
    """`v` divided by its largest magnitude (1 if all zero), as `dtype` bytes: float16
    then neither overflows (65504) nor flushes small values to zero."""
    scale = float(np.max(np.abs(v))) if v.size else 0.0
    if not np.isfinite(scale):
        raise ValueError("values are not finite")
    if scale == 0.0:
        scale = 1.0
    return (v / scale).astype(dtype).tobytes(), scale


def _encode_features(f: np.ndarray) -> tuple[bytes, float]:
    raw, scale = _scaled(f, _FEAT_DTYPE)
    # Round away the float16's lowest mantissa bits (to nearest, in the bit pattern,
    # which orders magnitudes; values are <= 1 here, far from the infinities): the
    # deflated blob shrinks by about 11 % (real KITTI scans: 9.9 -> 8.8 KB).
    step = 1 << _FEATURE_DROP_BITS
    bits = np.frombuffer(raw, dtype="<u2")
    raw = ((bits + np.uint16(step >> 1)) & np.uint16(0xFFFF ^ (step - 1))).astype("<u2").tobytes()
    packer = zlib.compressobj(_DEFLATE_LEVEL, zlib.DEFLATED, -15)  # raw: the crc is ours
    return packer.compress(raw) + packer.flush(), scale


def _bad_signatures(sigs: np.ndarray) -> np.ndarray:
    """Which signatures would derail the search (NaN, or so large that the squared norm
    overflows float32): the check every signature read and `check()` share."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.einsum("ij,ij->i", sigs, sigs, dtype=np.float64)
    return ~(np.isfinite(norms) & (norms < np.finfo(np.float32).max))


def _encode_batch(batch: ScanBatch) -> list[tuple]:
    """Each scan's stored blobs: (signature, its scale, features, their scale, views)."""
    out = []
    for i in range(len(batch.paths)):
        sig, sig_scale = _scaled(batch.signatures[i], _SIG_DTYPE)
        feats, scale = _encode_features(batch.features[i])
        views = [
            (float(o), *_scaled(batch.side_signatures[i, k], _SIG_DTYPE))  # type: ignore[index]
            for k, o in enumerate(batch.side_offsets)
        ]
        out.append((sig, sig_scale, feats, scale, views))
    return out
