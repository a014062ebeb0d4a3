"""Scan readers: one module per file format, chosen here.

`read_scan(path)` returns the points of one LiDAR scan as a float32 `N x 4`
array (x, y, z, intensity; intensity 0 where the format has none), and
`list_scans(path)` expands a file or a folder into the scan files it holds.
Every bad file raises `ScanReadError(path, reason)`, never another exception.

The format comes from `format=` when given, else from the file: `.bin` under a
folder named `velodyne_sync` is NCLT, any other `.bin` is KITTI (MulRan uses
the same layout; under `pointcloud_20m[_10overlap]` PointNetVLAD's Oxford
submaps), and `.npy`, `.pcd`, `.ply` are what they say.

ROS bags (`.bag`, `.mcap`, a ROS 2 bag folder) hold many scans: `list_scans` expands a
bag into one name per sensor_msgs/PointCloud2 message, `BAG#TOPIC@STAMP_NS`, and
`read_scan` reads such a name back (`readers.bags`, needs the `rosbags` package).

This module imports no numpy, so that a command can import the format names
at its top and `disco --help` stays instant; a format module is imported the
first time a scan of that format is read.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING

from disco_cli.errors import ScanReadError

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "FORMATS",
    "FormatName",
    "ScanFormat",
    "guess_format",
    "is_bag",
    "is_bag_message",
    "list_scans",
    "natural_key",
    "read_scan",
]


@dataclass(frozen=True)
class ScanFormat:
    """One registered format: its name, file extensions and reader module."""

    name: str
    extensions: tuple[str, ...]
    module: str  # imported on first use; must define `read(path: Path) -> np.ndarray`
    description: str

    def reader(self) -> Callable[[Path], np.ndarray]:
        return importlib.import_module(self.module).read


# The registry: every format disco reads, in the order `--format` lists them.
FORMATS: dict[str, ScanFormat] = {
    "kitti": ScanFormat(
        "kitti",
        (".bin",),
        "disco_cli.io.readers.kitti",
        "KITTI / MulRan .bin: float32 x, y, z, intensity",
    ),
    "nclt": ScanFormat(
        "nclt",
        (".bin",),
        "disco_cli.io.readers.nclt",
        "NCLT velodyne_sync .bin: uint16 x, y, z (5 mm, -100 m), uint8 intensity, laser",
    ),
    "oxford": ScanFormat(
        "oxford",
        (".bin",),
        "disco_cli.io.readers.oxford",
        "PointNetVLAD Oxford submaps .bin: float64 x, y, z (4096 points)",
    ),
    "npy": ScanFormat("npy", (".npy",), "disco_cli.io.readers.npy", "NumPy .npy: N x 3 or N x 4"),
    "pcd": ScanFormat("pcd", (".pcd",), "disco_cli.io.readers.pcd", "PCL .pcd: ascii or binary"),
    "ply": ScanFormat("ply", (".ply",), "disco_cli.io.readers.ply", "PLY: ascii or binary"),
}

# The format names as a str Enum, for a command's `--format` choices.
FormatName = Enum("FormatName", {name: name for name in FORMATS}, type=str)  # type: ignore[misc]

# The .bin layouts, which have no header (readers/plausible.py checks what they read).
_HEADERLESS = ("kitti", "nclt", "oxford")
# The folder name that marks a .bin as NCLT rather than KITTI.
_NCLT_FOLDER = "velodyne_sync"
# The folders of PointNetVLAD's Oxford submaps (test and training).
_OXFORD_FOLDERS = ("pointcloud_20m", "pointcloud_20m_10overlap")
# Folder layouts searched first, in order: DIR/velodyne/*.bin (KITTI, MulRan
# after extraction), DIR/velodyne_sync/*.bin (NCLT) and DIR/pointcloud_20m/*.bin (an
# Oxford run's test submaps) and DIR/sensor_data/Ouster/*.bin (a MulRan sequence).
_SCAN_SUBFOLDERS = ("velodyne", _NCLT_FOLDER, _OXFORD_FOLDERS[0], "sensor_data/Ouster")


def _format_by_name(name: str, path: Path) -> ScanFormat:
    if isinstance(name, Enum):
        name = name.value
    try:
        return FORMATS[name.lower()]
    except KeyError:
        known = ", ".join(FORMATS)
        raise ScanReadError(path, f"unknown scan format {name!r} (known: {known})") from None


# What a scan in a bag is called in messages (it is no file format of its own).
BAG_FORMAT = "rosbag"
_BAG_SUFFIXES = (".bag", ".mcap")


# ROS 2 bag folders found so far: every scan name of a bag asks again, and listing the
# folder each time would cost more than reading the message.
_BAG_FOLDERS: set[str] = set()


def is_bag(path: str | Path) -> bool:
    """A ROS 1 .bag, an .mcap file, or a ROS 2 bag folder (metadata.yaml + .db3/.mcap)."""
    path = Path(path)
    if path.suffix.lower() in _BAG_SUFFIXES:
        return path.is_file()
    if str(path) in _BAG_FOLDERS:
        return True
    if path.is_dir() and (path / "metadata.yaml").is_file():
        if any(p.suffix in (".db3", ".mcap") for p in path.iterdir()):
            _BAG_FOLDERS.add(str(path))
            return True
    return False


def is_bag_message(path: str | Path) -> bool:
    """True for a `BAG#TOPIC@STAMP_NS` name whose bag exists (and which is no file)."""
    name = str(path)
    if "#" not in name or "@" not in name:
        return False
    left = name.rpartition("@")[0]
    bag = left.rpartition("#")[0]
    return bool(bag) and is_bag(Path(bag)) and not Path(name).is_file()


def guess_format(path: str | Path) -> str:
    """The format name of a scan file from its extension and folder."""
    if is_bag_message(path) or is_bag(Path(path)):
        return BAG_FORMAT
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".bin":
        if path.parent.name in _OXFORD_FOLDERS:
            return "oxford"
        return "nclt" if path.parent.name == _NCLT_FOLDER else "kitti"
    for fmt in FORMATS.values():
        if ext in fmt.extensions:
            return fmt.name
    if ext == ".db3":
        raise ScanReadError(path, "a ROS 2 bag's database: give the bag's folder (metadata.yaml)")
    known = ", ".join(sorted({e for f in FORMATS.values() for e in f.extensions}))
    raise ScanReadError(
        path,
        f"cannot tell the scan format from {ext or 'no extension'!r} "
        f"(known: {known}); pass --scan-format (format= in Python)",
    )


def read_scan(path: str | Path, format: str | None = None) -> np.ndarray:
    """The points of one scan as float32 `N x 4` (x, y, z, intensity).

    A KITTI .bin is returned as read by `np.fromfile` (no copy). A `BAG#TOPIC@STAMP_NS`
    name reads that PointCloud2 message of the bag (`format` does not apply). Raises
    `ScanReadError` for a missing, truncated, misaligned, empty or unparsable file.
    """
    if is_bag_message(path):
        # deferred: this module loads at start-up (--help), bag support only for bags
        from disco_cli.io.readers.bags import read_message

        return read_message(str(path))
    path = Path(path)
    if is_bag(path):
        raise ScanReadError(
            path, "a bag holds many scans: name one as BAG#TOPIC@STAMP_NS, or list them"
        )
    fmt = _format_by_name(format, path) if format else FORMATS[guess_format(path)]
    if not path.exists():
        raise ScanReadError(path, "no such file")
    if not path.is_file():
        raise ScanReadError(path, "not a file")
    points = fmt.reader()(path)
    if fmt.name in _HEADERLESS:  # any bytes read in these layouts: check they made a scan
        # deferred: numpy; this module loads at start-up (--help)
        from disco_cli.io.readers.plausible import check_layout

        check_layout(path, points, fmt.name)
    return points


def natural_key(path: str | Path) -> tuple:
    """Sort key that orders numbers by value: 2.bin before 10.bin."""
    parts = re.split(r"(\d+)", Path(path).name)
    # re.split puts text at even and digit runs at odd positions, so keys compare
    # like with like; the full name breaks ties between 7.bin and 007.bin.
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)) + (Path(path).name,)


def _visible(path: Path) -> bool:
    # Hidden files (macOS `._000001.bin` copies, editor backups) are not scans.
    return not path.name.startswith(".") and path.is_file()


def list_scans(path: str | Path, format: str | None = None, topic: str | None = None) -> list[Path]:
    """The scan files at `path`, in natural order.

    A file gives itself. A folder gives `DIR/velodyne/*.bin` (or
    `DIR/velodyne_sync/*.bin`) when that exists, else its own files with a scan
    extension (of `format` when given); hidden files are skipped. A ROS bag (.bag,
    .mcap, a ROS 2 bag folder), or a folder of bags, gives one `BAG#TOPIC@STAMP_NS`
    per PointCloud2 message of `topic` (which may be omitted when a bag has only one
    such topic), in bag order. Raises `ScanReadError` when the path is missing or holds
    no scans, or when a folder mixes formats and none was given.
    """
    path = Path(path)
    if is_bag(path):
        # deferred: this module loads at start-up (--help), bag support only for bags
        from disco_cli.io.readers.bags import list_messages

        return [Path(n) for n in list_messages(path, topic)]
    fmt = _format_by_name(format, path) if format else None
    if path.is_file():
        return [path]
    if not path.exists():
        raise ScanReadError(path, "no such file or folder")
    if not path.is_dir():
        raise ScanReadError(path, "not a file or folder")

    for sub in _SCAN_SUBFOLDERS:
        folder = path / sub
        if folder.is_dir() and (fmt is None or ".bin" in fmt.extensions):
            found = [p for p in folder.iterdir() if p.suffix.lower() == ".bin" and _visible(p)]
            if found:
                return sorted(found, key=natural_key)

    extensions = set(fmt.extensions) if fmt else {e for f in FORMATS.values() for e in f.extensions}
    found = [p for p in path.iterdir() if p.suffix.lower() in extensions and _visible(p)]
    if not found and fmt is None:
        # A folder of bags (one per recording session): their messages, bag after bag.
        bags = sorted((p for p in path.iterdir() if is_bag(p)), key=natural_key)
        if bags:
            return [s for bag in bags for s in list_scans(bag, topic=topic)]
    if not found:
        wanted = ", ".join(sorted(extensions))
        raise ScanReadError(path, f"no scan files ({wanted}) in this folder or in velodyne/")
    if fmt is None:
        # One folder, one format: a folder with both x.bin and x.ply is usually
        # two copies of the same scans, and reading both would count each twice.
        present = sorted({p.suffix.lower() for p in found})
        if len(present) > 1:
            raise ScanReadError(
                path,
                f"the folder holds several scan formats ({', '.join(present)}); "
                "pass the format to choose one",
            )
    return sorted(found, key=natural_key)
