"""sensor_msgs/PointCloud2 decoded from its field list: the cloud of one bag message.

A PointCloud2 is `height` rows of `width` points, each point `point_step` bytes, each
row `row_step` bytes (rows may end in padding), in the byte order `is_bigendian` says.
`fields` names where each channel sits in a point (offset, datatype, count); drivers
differ in which channels they publish, their types and the padding between them:

- Velodyne (velodyne_pointcloud): x, y, z, intensity float32, ring uint16, time float32;
- Ouster (ouster-ros): x, y, z float32, 4 bytes padding, intensity float32, t uint32,
  reflectivity uint16, ring uint8 or uint16, ambient uint16, range uint32 (48 bytes);
- Hesai (HesaiLidar_ROS_2.0): x, y, z float32, intensity uint8 (or float32), ring
  uint16, timestamp float64;
- Livox (livox_ros_driver2, PointCloud2 mode): x, y, z, intensity float32, tag, line
  uint8, timestamp float64.

Only x, y, z and an intensity channel are read (by name, wherever they sit): x, y, z
must be float32 or float64; intensity is `intensity`, else `reflectivity`, else one of
the names other formats use, of any numeric type, as float32 (0 when there is none).
Organized clouds (height > 1) mark missing returns with NaN; those points are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import INTENSITY_NAMES, assemble

__all__ = ["DATATYPES", "PointField", "decode_pointcloud2", "decode_message"]

# sensor_msgs/PointField datatype codes -> NumPy type (byte order added per message).
DATATYPES: dict[int, str] = {
    1: "i1",  # INT8
    2: "u1",  # UINT8
    3: "i2",  # INT16
    4: "u2",  # UINT16
    5: "i4",  # INT32
    6: "u4",  # UINT32
    7: "f4",  # FLOAT32
    8: "f8",  # FLOAT64
}
# The datatype names of sensor_msgs/PointField, for messages.
_TYPE_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32",
               7: "FLOAT32", 8: "FLOAT64"}  # fmt: skip
# Intensity channel names, in order of preference: Ouster publishes both intensity
# (signal strength) and reflectivity (calibrated); either serves.
_INTENSITY = ("intensity", "reflectivity", *INTENSITY_NAMES[1:], "i")


@dataclass(frozen=True)
class PointField:
    """One entry of a PointCloud2's field list."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def decode_message(msg: Any, name: str) -> np.ndarray:
    """A deserialized PointCloud2 message (any object with its attributes) as N x 4."""
    try:
        fields = [
            PointField(str(f.name), int(f.offset), int(f.datatype), int(f.count))
            for f in msg.fields
        ]
        return decode_pointcloud2(
            fields,
            msg.data,
            height=int(msg.height),
            width=int(msg.width),
            point_step=int(msg.point_step),
            row_step=int(msg.row_step),
            is_bigendian=bool(msg.is_bigendian),
            name=name,
        )
    except AttributeError as exc:
        raise ScanReadError(name, f"not a sensor_msgs/PointCloud2 message ({exc})") from None


def decode_pointcloud2(
    fields: list[PointField],
    data: bytes | np.ndarray,
    *,
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    is_bigendian: bool,
    name: str,
) -> np.ndarray:
    """x, y, z, intensity of a PointCloud2's bytes as float32 `N x 4`, NaN points dropped.

    `name` (the scan's `BAG#TOPIC@STAMP_NS`) is what a `ScanReadError` names.
    """
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    buf = buf.reshape(-1).view(np.uint8)
    by_name = {f.name: f for f in fields}
    order = ">" if is_bigendian else "<"

    def field_type(f: PointField) -> np.dtype:
        if f.datatype not in DATATYPES:
            raise ScanReadError(name, f"field {f.name!r} has unknown datatype {f.datatype}")
        dt = np.dtype(order + DATATYPES[f.datatype])
        if f.offset < 0 or f.offset + dt.itemsize * max(f.count, 1) > point_step:
            raise ScanReadError(
                name,
                f"field {f.name!r} (offset {f.offset}, {dt.itemsize * max(f.count, 1)} bytes) "
                f"lies outside the {point_step}-byte point",
            )
        return dt

    missing = [c for c in "xyz" if c not in by_name]
    if missing:
        present = ", ".join(by_name) or "none"
        raise ScanReadError(name, f"no {'/'.join(missing)} field (fields: {present})")
    names, formats, offsets = [], [], []
    for c in "xyz":
        f = by_name[c]
        dt = field_type(f)
        if dt.kind != "f":
            raise ScanReadError(
                name,
                f"field {c!r} is {_TYPE_NAMES[f.datatype]}; x, y, z must be FLOAT32 or FLOAT64",
            )
        names.append(c)
        formats.append(dt)
        offsets.append(f.offset)
    lowered = {n.lower(): f for n, f in by_name.items()}
    inten = next((lowered[n] for n in _INTENSITY if n in lowered), None)
    if inten is not None:
        names.append("intensity")
        formats.append(field_type(inten))
        offsets.append(inten.offset)

    if height < 0 or width < 0:
        raise ScanReadError(name, f"bad cloud size {height} x {width}")
    if point_step <= 0:
        raise ScanReadError(name, f"point_step is {point_step}")
    if height * width == 0:
        raise ScanReadError(name, "the cloud has no points (height x width is 0)")
    row_bytes = width * point_step
    if row_step < row_bytes:
        raise ScanReadError(
            name, f"row_step {row_step} is less than width x point_step ({width} x {point_step})"
        )
    # The last row's padding may be left out; anything shorter is truncated.
    need = (height - 1) * row_step + row_bytes
    if buf.size < need:
        raise ScanReadError(
            name,
            f"data holds {buf.size} bytes, {height} rows of {row_step} bytes need {need}: "
            "truncated",
        )
    if row_step == row_bytes or height == 1:  # one row: its padding never matters
        points = buf[: height * row_bytes]
    else:
        # Rows end in padding: keep each row's points only, through a strided view of
        # the bytes checked above (never an array of height x row_step, which a damaged
        # row_step would make huge; with 2+ rows, row_step <= the data's size).
        rows = np.lib.stride_tricks.as_strided(
            buf, shape=(height, row_bytes), strides=(row_step, 1), writeable=False
        )
        points = np.ascontiguousarray(rows).reshape(-1)
    record = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    cloud = np.frombuffer(points, dtype=record, count=height * width)
    cols = [cloud[c] for c in ("x", "y", "z")]
    inten_col = cloud["intensity"] if inten is not None else None
    # Missing returns (NaN): tested column by column, cheaper than on the N x 3 result.
    keep = np.isfinite(cols[0])
    keep &= np.isfinite(cols[1])
    keep &= np.isfinite(cols[2])
    if not keep.all():
        if not keep.any():
            raise ScanReadError(name, f"none of its {len(keep)} points has finite x, y, z")
        cols = [c[keep] for c in cols]
        inten_col = inten_col[keep] if inten_col is not None else None
    # A finite FLOAT64 coordinate can still be beyond float32's range: then the
    # float32 result is checked again (Inf rows dropped).
    wide = any(dt.itemsize == 8 for dt in formats[:3])
    return assemble(name, *cols, inten_col, drop_nonfinite=wide)  # type: ignore[arg-type]
