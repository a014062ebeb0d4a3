"""A small PNG writer: 8-bit grayscale or RGB images, zlib from the standard library.

`disco bev` writes its pictures with this so that it needs no imaging library.
The format (PNG spec, ISO/IEC 15948): an 8-byte signature, then chunks of
`length, type, data, crc32`: IHDR (size, depth, colour type), IDAT (the
zlib-compressed rows, each prefixed by a filter byte) and IEND.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_GRAY, _RGB = 0, 2  # PNG colour types

# Viridis, sampled at 9 evenly spaced points: dark blue for little, yellow for
# much, readable in grayscale and by colour-blind readers. Linear in between.
_VIRIDIS = np.array(
    [
        [68, 1, 84],
        [71, 44, 122],
        [59, 81, 139],
        [44, 113, 142],
        [33, 144, 141],
        [39, 173, 129],
        [92, 200, 99],
        [170, 220, 50],
        [253, 231, 37],
    ],
    dtype=np.float64,
)
BACKGROUND = (0, 0, 0)  # empty cells: black, darker than the colormap's low end


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def encode_png(image: np.ndarray, compression: int = 6) -> bytes:
    """PNG bytes of a uint8 image: `H x W` (grayscale) or `H x W x 3` (RGB)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {image.dtype}")
    if image.ndim == 2:
        colour = _GRAY
    elif image.ndim == 3 and image.shape[2] == 3:
        colour = _RGB
    else:
        raise ValueError(f"image must be H x W or H x W x 3, got shape {image.shape}")
    height, width = image.shape[:2]
    if height == 0 or width == 0:
        raise ValueError(f"image must not be empty, got shape {image.shape}")
    rows = np.ascontiguousarray(image).reshape(height, -1)
    # Filter type 0 (None) on every row: a zero byte before each row.
    raw = np.concatenate([np.zeros((height, 1), np.uint8), rows], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)
    return (
        SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw, compression))
        + _chunk(b"IEND", b"")
    )


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a uint8 `H x W` or `H x W x 3` image as a PNG file."""
    Path(path).write_bytes(encode_png(image))


def colormap(values: np.ndarray, empty: np.ndarray | None = None) -> np.ndarray:
    """RGB uint8 (`... x 3`) of values in [0, 1] through viridis; cells where
    `empty` is True are painted BACKGROUND so that "nothing here" stands out."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64)), 0.0, 1.0)
    pos = v * (len(_VIRIDIS) - 1)
    lo = np.minimum(pos.astype(np.int64), len(_VIRIDIS) - 2)
    frac = (pos - lo)[..., None]
    rgb = _VIRIDIS[lo] * (1.0 - frac) + _VIRIDIS[lo + 1] * frac
    out = np.rint(rgb).astype(np.uint8)
    if empty is not None:
        out[np.asarray(empty, dtype=bool)] = BACKGROUND
    return out


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement by an integer factor along both image axes."""
    if factor < 1:
        raise ValueError(f"scale factor must be >= 1, got {factor}")
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)
