"""NumPy .npy scans: a numeric N x 3 (x, y, z) or N x 4 (x, y, z, intensity) array,
or a structured array with fields x, y, z and optionally an intensity field."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import assemble, pick_intensity


def read(path: Path) -> np.ndarray:
    """The scan as float32 `N x 4`; rows with a non-finite x, y or z are dropped."""
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":
            raise ScanReadError(path, "not an .npy file (no NUMPY magic at the start)")
        _check_claimed_size(path)
        # No pickles: a scan file must not be able to run code.
        arr = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    except ScanReadError:
        raise
    except Exception as exc:  # noqa: BLE001
        # np.load parses a damaged header with Python's tokenizer and can raise
        # nearly anything (ValueError, SyntaxError, TokenError, EOFError...).
        reason = f"not a readable .npy array ({type(exc).__name__}: {exc})"
        raise ScanReadError(path, reason) from None
    return from_array(arr, path)


def _check_claimed_size(path: Path) -> None:
    """Refuse a header whose shape needs more bytes than the file holds, before np.load
    allocates them (a damaged shape can claim terabytes)."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            return  # a version np.load checks itself
        data = path.stat().st_size - f.tell()
    if dtype.hasobject:
        return  # np.load refuses it without unpickling
    need = math.prod(shape) * dtype.itemsize
    if need > data:
        raise ScanReadError(
            path,
            f"truncated: its header's shape {shape} of {dtype} needs {need} bytes, "
            f"the file holds {data}",
        )


def from_array(arr: np.ndarray, path: str | Path) -> np.ndarray:
    """An array as a float32 `N x 4` scan, with the checks and messages of an .npy file
    (the library API takes arrays through here; `path` names the array in errors)."""
    if arr.dtype.names:
        names = list(arr.dtype.names)
        missing = [c for c in ("x", "y", "z") if c not in names]
        if missing or arr.ndim != 1:
            raise ScanReadError(
                path, f"structured array needs 1-d fields x, y, z (has {', '.join(names)})"
            )
        inten = pick_intensity(names)
        cols = [arr["x"], arr["y"], arr["z"], arr[inten] if inten else None]
    else:
        if arr.ndim != 2 or arr.shape[1] not in (3, 4):
            raise ScanReadError(path, f"expected an N x 3 or N x 4 array, got shape {arr.shape}")
        if not (np.issubdtype(arr.dtype, np.number) and not np.iscomplexobj(arr)):
            raise ScanReadError(path, f"expected a real numeric array, got dtype {arr.dtype}")
        cols = [arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3] if arr.shape[1] == 4 else None]
    try:
        return assemble(path, *cols)
    except (TypeError, ValueError) as exc:
        raise ScanReadError(path, f"fields are not numeric ({exc})") from None
