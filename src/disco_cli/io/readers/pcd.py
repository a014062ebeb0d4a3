"""PCL .pcd scans: DATA ascii, binary and binary_compressed.

The header names the fields (any order), their byte SIZE, TYPE (F float,
U unsigned, I signed) and COUNT (elements per field); padding fields are
named `_`. Only x, y, z and an optional intensity field are kept (the first
element of a field with COUNT > 1).

binary_compressed data is two little-endian uint32 (compressed size,
uncompressed size) and an LZF stream; once expanded it holds the fields one
after another (all x, then all y, ...) instead of one record per point.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import assemble, pick_intensity

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8"}
_TYPES.update({("U", n): f"<u{n}" for n in (1, 2, 4, 8)})
_TYPES.update({("I", n): f"<i{n}" for n in (1, 2, 4, 8)})
# The header is small; a longer "header" means this is not a PCD file.
_MAX_HEADER_LINES = 64
# Elements per field: real files have a few (a normal's 3, a histogram's 33 or 308); a
# damaged COUNT must not reach np.dtype, which refuses shapes past a C int.
_MAX_COUNT = 1 << 16


def read(path: Path) -> np.ndarray:
    """The scan as float32 `N x 4`; points with a non-finite x, y or z (organized
    clouds mark missing returns with NaN) are dropped."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    header, body = _split_header(path, data)
    fields, dtype, n_points, kind = _parse_header(path, header)
    table: np.ndarray | dict[str, np.ndarray]
    if kind == "ascii":
        table = _read_ascii(path, body, dtype, n_points)
    elif kind == "binary":
        table = _read_binary(path, body, dtype, n_points)
    elif kind == "binary_compressed":
        table = _read_compressed(path, body, dtype, n_points)
    else:
        raise ScanReadError(
            path, f"PCD DATA {kind!r} is not supported (only ascii, binary, binary_compressed)"
        )
    inten = pick_intensity([f for f in fields if f != "_"])
    intensity = None
    if inten:
        intensity = table[inten]
        if intensity.ndim > 1:  # COUNT > 1: keep the first element
            intensity = intensity[:, 0]
    return assemble(path, table["x"], table["y"], table["z"], intensity)


def _split_header(path: Path, data: bytes) -> tuple[dict[str, list[str]], bytes]:
    """The header keywords and their values, and the bytes after the DATA line."""
    if not data:
        raise ScanReadError(path, "the file is empty (no points)")
    header: dict[str, list[str]] = {}
    pos = 0
    for _ in range(_MAX_HEADER_LINES):
        end = data.find(b"\n", pos)
        if end < 0:
            break
        line_bytes = data[pos:end]
        pos = end + 1
        try:
            line = line_bytes.decode("ascii").strip()
        except UnicodeDecodeError:
            break
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, data[pos:]
    raise ScanReadError(path, "not a PCD file (no DATA line in its header)")


def _parse_header(path: Path, h: dict[str, list[str]]) -> tuple[list[str], np.dtype, int, str]:
    """Field names, the record dtype, the point count and the DATA kind."""
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in h:
            raise ScanReadError(path, f"PCD header has no {key} line")
    fields = h["FIELDS"]
    counts = h.get("COUNT", ["1"] * len(fields))
    if not (len(fields) == len(h["SIZE"]) == len(h["TYPE"]) == len(counts)):
        raise ScanReadError(path, "PCD header FIELDS, SIZE, TYPE and COUNT differ in length")
    for c in ("x", "y", "z"):
        if c not in fields:
            raise ScanReadError(path, f"PCD has no field {c!r} (fields: {' '.join(fields)})")
    try:
        sizes = [int(s) for s in h["SIZE"]]
        counts_n = [int(c) for c in counts]
        if "POINTS" in h:
            n_points = int(h["POINTS"][0])
        else:
            n_points = int(h["WIDTH"][0]) * int(h.get("HEIGHT", ["1"])[0])
    except (ValueError, IndexError, KeyError):
        raise ScanReadError(
            path, "PCD header has a malformed SIZE, COUNT, WIDTH or POINTS"
        ) from None

    entries = []
    for i, (name, size, typ, count) in enumerate(zip(fields, sizes, h["TYPE"], counts_n)):
        code = _TYPES.get((typ.upper(), size))
        if code is None:
            raise ScanReadError(path, f"PCD field {name!r} has unsupported TYPE {typ} SIZE {size}")
        if not 1 <= count <= _MAX_COUNT:
            raise ScanReadError(path, f"PCD field {name!r} has COUNT {count}")
        if name in ("x", "y", "z") and count != 1:
            raise ScanReadError(path, f"PCD field {name!r} has COUNT {count}, expected 1")
        # Padding fields are all called `_`; numpy needs distinct names.
        key = f"_pad{i}" if name == "_" or name in [e[0] for e in entries] else name
        entries.append((key, code, (count,)) if count > 1 else (key, code))
    kind = h["DATA"][0].lower() if h["DATA"] else ""
    if n_points < 0:
        raise ScanReadError(path, f"PCD header says {n_points} points")
    return fields, np.dtype(entries), n_points, kind


def _read_binary(path: Path, body: bytes, dtype: np.dtype, n_points: int) -> np.ndarray:
    need = n_points * dtype.itemsize
    if n_points == 0:
        raise ScanReadError(path, "the scan has no points (POINTS 0)")
    if len(body) < need:
        raise ScanReadError(
            path,
            f"truncated: {n_points} points of {dtype.itemsize} bytes need {need} bytes "
            f"of data, found {len(body)}",
        )
    return np.frombuffer(body, dtype=dtype, count=n_points)


def _read_compressed(
    path: Path, body: bytes, dtype: np.dtype, n_points: int
) -> dict[str, np.ndarray]:
    if n_points == 0:
        raise ScanReadError(path, "the scan has no points (POINTS 0)")
    if len(body) < 8:
        raise ScanReadError(path, "truncated: binary_compressed data has no size fields")
    packed, unpacked = struct.unpack_from("<II", body)
    need = n_points * dtype.itemsize
    if unpacked != need:
        raise ScanReadError(
            path,
            f"binary_compressed data expands to {unpacked} bytes, but {n_points} points "
            f"of {dtype.itemsize} bytes need {need}",
        )
    if len(body) - 8 < packed:
        raise ScanReadError(
            path, f"truncated: {packed} bytes of compressed data expected, found {len(body) - 8}"
        )
    try:
        raw = lzf_decompress(body[8 : 8 + packed], unpacked)
    except ValueError as exc:
        raise ScanReadError(path, f"damaged binary_compressed data ({exc})") from None
    out: dict[str, np.ndarray] = {}
    offset = 0
    for k in dtype.names:
        field = dtype[k]
        elements = int(np.prod(field.shape))
        column = np.frombuffer(raw, dtype=field.base, count=n_points * elements, offset=offset)
        out[k] = column.reshape(n_points, elements) if elements > 1 else column
        offset += n_points * field.itemsize
    return out


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Expand an LZF stream (liblzf's format) that must give exactly `size` bytes.

    A control byte below 32 starts a run of ctrl + 1 literal bytes; otherwise its
    top 3 bits are a copy length - 2 (7: add the next byte) and its low 5 bits
    with the next byte an offset - 1 back into the output. Raises ValueError.
    """
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            run = ctrl + 1
            if i + run > n:
                raise ValueError("a literal run goes past the end")
            out += data[i : i + run]
            i += run
        else:
            length = ctrl >> 5
            if length == 7:
                if i >= n:
                    raise ValueError("a copy length goes past the end")
                length += data[i]
                i += 1
            length += 2
            if i >= n:
                raise ValueError("a copy offset goes past the end")
            start = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
            i += 1
            if start < 0:
                raise ValueError("a copy reaches before the start")
            period = len(out) - start
            if length <= period:
                out += out[start : start + length]
            else:  # the copy overlaps what it writes: the last `period` bytes repeat
                pattern = bytes(out[start:])
                out += (pattern * (length // period + 1))[:length]
        if len(out) > size:
            raise ValueError(f"expands past the {size} bytes announced")
    if len(out) != size:
        raise ValueError(f"expands to {len(out)} bytes, not the {size} announced")
    return bytes(out)


def _read_ascii(path: Path, body: bytes, dtype: np.dtype, n_points: int) -> dict[str, np.ndarray]:
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise ScanReadError(path, "ascii PCD data holds non-ascii bytes") from None
    per_point = sum(int(np.prod(dtype[k].shape)) for k in dtype.names)
    tokens = text.split()
    if n_points == 0 or not tokens:
        raise ScanReadError(path, "the scan has no points")
    if len(tokens) < n_points * per_point:
        raise ScanReadError(
            path,
            f"truncated: {n_points} points of {per_point} values need "
            f"{n_points * per_point} numbers, found {len(tokens)}",
        )
    if len(tokens) != n_points * per_point:
        raise ScanReadError(
            path, f"{len(tokens)} numbers do not make {n_points} points of {per_point} values"
        )
    try:
        values = np.asarray(tokens, dtype=np.float64).reshape(n_points, per_point)
    except ValueError as exc:
        raise ScanReadError(path, f"ascii PCD data is not numeric ({exc})") from None
    # Column of each field in the flattened row: COUNT widens a field.
    out: dict[str, np.ndarray] = {}
    col = 0
    for k in dtype.names:
        width = int(np.prod(dtype[k].shape))
        out[k] = values[:, col]
        col += width
    return out
