"""PLY scans: ascii, binary_little_endian and binary_big_endian.

The `vertex` element must have x, y, z properties and may have an intensity
(or reflectance, scalar_intensity) property; other properties, list
properties and other elements (faces, ...) are skipped.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import assemble, pick_intensity

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# The same types as `struct` codes, for walking rows that hold lists.
_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
_SIZE = {code: struct.calcsize(c) for code, c in _STRUCT.items()}
_BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "<"}
_MAX_HEADER_BYTES = 1 << 16


@dataclass
class _Property:
    name: str
    type: str  # numpy code without byte order, e.g. "f4"
    count_type: str | None = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Property] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.count_type for p in self.props)


def read(path: Path) -> np.ndarray:
    """The scan as float32 `N x 4`; vertices with a non-finite x, y or z are dropped."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    if not data:
        raise ScanReadError(path, "the file is empty (no points)")
    fmt, elements, pos = _parse_header(path, data)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise ScanReadError(path, "PLY has no vertex element")
    names = [p.name for p in vertex.props]
    for c in ("x", "y", "z"):
        if c not in names:
            raise ScanReadError(path, f"PLY vertex has no property {c!r} (has: {' '.join(names)})")
    for p in vertex.props:
        if p.name in ("x", "y", "z") and p.count_type:
            raise ScanReadError(path, f"PLY vertex property {p.name!r} is a list")
    if vertex.count == 0:
        raise ScanReadError(path, "the scan has no points (element vertex 0)")
    inten = pick_intensity([p.name for p in vertex.props if not p.count_type])
    wanted = ["x", "y", "z"] + ([inten] if inten else [])

    try:
        if fmt == "ascii":
            cols = _read_ascii(path, data[pos:], elements, vertex, wanted)
        else:
            cols = _read_binary(path, data, pos, _BYTE_ORDER[fmt], elements, vertex, wanted)
    except struct.error:
        raise ScanReadError(path, "truncated: the data ends inside an element") from None
    return assemble(path, cols["x"], cols["y"], cols["z"], cols[inten] if inten else None)


def _parse_header(path: Path, data: bytes) -> tuple[str, list[_Element], int]:
    """The data format, the elements in file order and the offset of the data."""
    if not data.startswith(b"ply"):
        raise ScanReadError(path, "not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header", 0, _MAX_HEADER_BYTES)
    if end < 0:
        raise ScanReadError(path, "PLY header has no end_header line")
    # The data starts after the newline that ends the end_header line.
    newline = data.find(b"\n", end)
    if newline < 0:
        raise ScanReadError(path, "the scan has no points (nothing after end_header)")
    try:
        lines = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise ScanReadError(path, "PLY header holds non-ascii bytes") from None

    fmt = None
    elements: list[_Element] = []
    for number, raw in enumerate(lines[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in _BYTE_ORDER:
                    raise ScanReadError(path, f"unknown PLY format {fmt!r}")
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2])))
                if elements[-1].count < 0:
                    raise ValueError
            elif words[0] == "property":
                if not elements:
                    raise ValueError
                if words[1] == "list":
                    prop = _Property(words[4], _TYPES[words[3]], _TYPES[words[2]])
                else:
                    prop = _Property(words[2], _TYPES[words[1]])
                elements[-1].props.append(prop)
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise ScanReadError(
                path, f"PLY header line {number} is malformed: {raw.strip()!r}"
            ) from None
    if fmt is None:
        raise ScanReadError(path, "PLY header has no format line")
    return fmt, elements, newline + 1


def _read_binary(
    path: Path,
    data: bytes,
    pos: int,
    order: str,
    elements: list[_Element],
    vertex: _Element,
    wanted: list[str],
) -> dict[str, np.ndarray]:
    for element in elements:
        if element is vertex:
            break
        pos = _skip_binary(data, pos, order, element)
    if not vertex.has_lists:
        dtype = np.dtype([(f"{i}_{p.name}", order + p.type) for i, p in enumerate(vertex.props)])
        need = vertex.count * dtype.itemsize
        if len(data) - pos < need:
            raise ScanReadError(
                path,
                f"truncated: {vertex.count} vertices need {need} bytes of data, "
                f"found {len(data) - pos}",
            )
        table = np.frombuffer(data, dtype=dtype, count=vertex.count, offset=pos)
        first = {}
        for i, p in enumerate(vertex.props):
            first.setdefault(p.name, table[f"{i}_{p.name}"])
        return {name: first[name] for name in wanted}
    # Vertices with list properties have no fixed size: walk them one by one,
    # after checking that the data can hold even empty lists (a damaged count
    # must not make us allocate terabytes).
    least = sum(_SIZE[p.count_type or p.type] for p in vertex.props)
    if vertex.count * least > len(data) - pos:
        raise ScanReadError(
            path,
            f"truncated: {vertex.count} vertices need at least {vertex.count * least} "
            f"bytes of data, found {len(data) - pos}",
        )
    out = {name: np.empty(vertex.count, dtype=np.float64) for name in wanted}
    for row in range(vertex.count):
        for p in vertex.props:
            if p.count_type:
                (n,) = struct.unpack_from(order + _STRUCT[p.count_type], data, pos)
                pos += _SIZE[p.count_type] + n * _SIZE[p.type]
            else:
                if p.name in out:
                    out[p.name][row] = struct.unpack_from(order + _STRUCT[p.type], data, pos)[0]
                pos += _SIZE[p.type]
    if pos > len(data):
        raise struct.error("past the end")
    return out


def _skip_binary(data: bytes, pos: int, order: str, element: _Element) -> int:
    """The offset just after `element`'s data."""
    if not element.has_lists:
        return pos + element.count * sum(_SIZE[p.type] for p in element.props)
    for _ in range(element.count):
        for p in element.props:
            if p.count_type:
                (n,) = struct.unpack_from(order + _STRUCT[p.count_type], data, pos)
                pos += _SIZE[p.count_type] + n * _SIZE[p.type]
            else:
                pos += _SIZE[p.type]
    return pos


def _read_ascii(
    path: Path, body: bytes, elements: list[_Element], vertex: _Element, wanted: list[str]
) -> dict[str, np.ndarray]:
    try:
        lines = body.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise ScanReadError(path, "ascii PLY data holds non-ascii bytes") from None
    lines = [line for line in lines if line.strip()]
    # Each element row is one line, so the rows before the vertices are skipped by count.
    start = 0
    for element in elements:
        if element is vertex:
            break
        start += element.count
    rows = lines[start : start + vertex.count]
    if len(rows) < vertex.count:
        raise ScanReadError(
            path, f"truncated: {vertex.count} vertices expected, found {len(rows)} lines"
        )
    try:
        if not vertex.has_lists:
            values = np.asarray(" ".join(rows).split(), dtype=np.float64)
            if values.size != vertex.count * len(vertex.props):
                raise ScanReadError(
                    path, f"ascii PLY vertex rows do not all have {len(vertex.props)} values"
                )
            values = values.reshape(vertex.count, len(vertex.props))
            names = [p.name for p in vertex.props]
            return {name: values[:, names.index(name)] for name in wanted}
        out = {name: np.empty(vertex.count, dtype=np.float64) for name in wanted}
        for r, line in enumerate(rows):
            tokens = line.split()
            col = 0
            for p in vertex.props:
                if p.count_type:
                    col += 1 + int(tokens[col])
                else:
                    if p.name in out:
                        out[p.name][r] = float(tokens[col])
                    col += 1
            if col != len(tokens):
                raise ValueError(f"row {r} has {len(tokens)} values, expected {col}")
        return out
    except (ValueError, IndexError) as exc:
        raise ScanReadError(path, f"ascii PLY vertex data is malformed ({exc})") from None
