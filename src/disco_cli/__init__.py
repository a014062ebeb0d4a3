"""disco: LiDAR loop closure with DiSCO rotation-invariant signatures and yaw.

The library API (docs/python.md): `Map` (a map database: add scans, localize scans
against it as `Match`es), `LoopDetector` (online loop closure, returning `Loop`s),
`PoseGraph` and `correct` (odometry and loops to a corrected trajectory; the `[graph]`
extra), `load_model`, `read_scan`, the voxelizer, `set_threads` (the CPU threads it
computes on), and the `DiscoError` kinds it raises. It is
imported lazily so that `import disco_cli` (and `disco --help`) stays fast: torch and
the compiled core load only when first used.
"""

from __future__ import annotations

from importlib import import_module

# public name -> module that defines it
_LAZY = {
    "BEVConfig": "disco_cli.model.bev",
    "polar_bev": "disco_cli.model.bev",
    "polar_bev_batch": "disco_cli.model.bev",
    "read_scan": "disco_cli.io.readers",
    "list_scans": "disco_cli.io.readers",
    "load_model": "disco_cli.model",
    "signature": "disco_cli.embedding.batches",
    "Map": "disco_cli.maps.facade",
    "Match": "disco_cli.query.localize",
    "LoopDetector": "disco_cli.query.loop_detector",
    "Loop": "disco_cli.query.loop_detector",
    "PoseGraph": "disco_cli.graph.pose_graph",
    "correct": "disco_cli.graph.pose_graph",
    "set_threads": "disco_cli.runtime.threads",
    "get_threads": "disco_cli.runtime.threads",
    "DiscoError": "disco_cli.errors",
    "ScanReadError": "disco_cli.errors",
    "DatabaseError": "disco_cli.errors",
    "ModelError": "disco_cli.errors",
    "PoseFileError": "disco_cli.errors",
}

__all__ = ["__version__", *_LAZY]


def _version() -> str:
    # deferred: importlib.metadata and the scan of installed packages cost 50-150 ms, a
    # tenth of a one-scan query: only `--version` and writing a map need the version.
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("disco-cli")
    except PackageNotFoundError:  # running from a source tree without an install
        return "0+unknown"


def __getattr__(name: str):
    if name == "__version__":
        globals()["__version__"] = value = _version()
        return value
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'disco_cli' has no attribute {name!r}")
