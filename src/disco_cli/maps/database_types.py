"""The values the map database takes and gives: the model a map records (`ModelInfo`),
scans to append (`ScanBatch`), stored rows read back (`MatchRows`), and damaged rows
(`DamagedRows`, `damaged_line`). Imported through `disco_cli.maps.database`."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError

# How many damaged scans a warning names before "and N more".
_NAMED = 20


@dataclass(frozen=True)
class ModelInfo:
    """What a database records about the model that built it; another model is refused."""

    name: str
    fingerprint: str
    model_config: dict
    bev_config: dict

    @classmethod
    def of(cls, model: Any) -> ModelInfo:
        return cls(
            name=str(model.name),
            fingerprint=str(model.fingerprint),
            model_config=_jsonable(model.config_dict()),
            bev_config=_jsonable(model.bev_config.to_dict()),
        )


def _jsonable(d: dict) -> dict:
    # A round trip through JSON so that comparisons see what the database stores.
    return json.loads(json.dumps(d, sort_keys=True, default=_json_default))


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


@dataclass
class ScanBatch:
    """Scans to append: `poses` is `[B, 4]` (x, y, z, yaw rad) and `times` `[B]`, NaN = unknown."""

    paths: list[str]
    signatures: np.ndarray
    features: np.ndarray
    poses: np.ndarray | None = None
    times: np.ndarray | None = None
    rel_paths: list[str | None] | None = None  # relative to the database's folder
    # Side views (`map_side_views.py`): the offsets and `[B, V, D]` signatures, or none.
    side_offsets: tuple[float, ...] = ()
    side_signatures: np.ndarray | None = None

    def __post_init__(self) -> None:
        b = len(self.paths)
        self.side_offsets = tuple(float(o) for o in self.side_offsets)
        if self.side_offsets:
            v = len(self.side_offsets)
            self.side_signatures = np.asarray(self.side_signatures, dtype=np.float32)
            if self.side_signatures.shape[:2] != (b, v) or self.side_signatures.ndim != 3:
                raise ValueError(
                    f"side signatures must be [{b}, {v}, D], got {self.side_signatures.shape}"
                )
        elif self.side_signatures is not None and np.size(self.side_signatures):
            raise ValueError("side signatures given without their offsets")
        if self.rel_paths is None:
            self.rel_paths = [None] * b
        if len(self.rel_paths) != b:
            raise ValueError(f"rel_paths must have {b} entries, got {len(self.rel_paths)}")
        self.signatures = np.asarray(self.signatures, dtype=np.float32)
        self.features = np.asarray(self.features, dtype=np.float32)
        if self.signatures.ndim != 2 or len(self.signatures) != b:
            raise ValueError(f"signatures must be [{b}, D], got {self.signatures.shape}")
        if self.features.ndim < 2 or len(self.features) != b:
            raise ValueError(f"features must be [{b}, ...], got {self.features.shape}")
        if self.poses is None:
            self.poses = np.full((b, 4), np.nan)
        self.poses = np.asarray(self.poses, dtype=np.float64)
        if self.poses.shape != (b, 4):
            raise ValueError(f"poses must be [{b}, 4], got {self.poses.shape}")
        if self.times is None:
            self.times = np.full(b, np.nan)
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        if self.times.shape != (b,):
            raise ValueError(f"times must be [{b}], got {self.times.shape}")


class MatchRows:
    """Stored data of some scans, in the order asked for: `ids`, `paths`, `poses` [K, 4]
    (x, y, z, yaw in rad; NaN = unknown) and `features` [K, ...] float32.

    A store that holds each row's features apart (the rows' cache) hands them over as
    `feature_rows`, one array per row: the query's re-ranking reads them where they lie,
    and `features` is stacked from them only when first asked for."""

    __slots__ = ("ids", "paths", "poses", "feature_rows", "_features")

    def __init__(
        self,
        ids: np.ndarray,
        paths: list[str],
        poses: np.ndarray,
        features: np.ndarray | None = None,
        *,
        feature_rows: Sequence[np.ndarray] | None = None,
    ):
        if (features is None) == (feature_rows is None):
            raise ValueError("MatchRows takes either features or feature_rows")
        self.ids, self.paths, self.poses = ids, paths, poses
        self.feature_rows = None if feature_rows is None else tuple(feature_rows)
        self._features = features

    @property
    def features(self) -> np.ndarray:
        if self._features is None:
            assert self.feature_rows  # an empty answer is given as `features`
            self._features = np.stack(self.feature_rows)
        return self._features

    def features_at(self, index: Any) -> np.ndarray:
        """`features[index]` for a position or an array of positions, without stacking
        the rows not asked for (a single row may be the store's own, read-only array)."""
        rows = self.feature_rows
        if self._features is not None or rows is None:
            return self.features[index]
        if np.ndim(index) == 0:
            return rows[int(index)]
        picked = [rows[i] for i in np.asarray(index, np.int64).reshape(-1).tolist()]
        return np.stack(picked) if picked else np.empty((0, *rows[0].shape), np.float32)


class DamagedRows(DatabaseError):
    """Rows asked for by `Database.rows` that fail their checksum or values: `ids`."""

    def __init__(self, path: Path, damaged: dict[int, str]):
        self.ids = sorted(damaged)
        super().__init__(path, damaged_line(damaged, path))


def damaged_line(damaged: dict[int, str], path: Any) -> str:
    """One line naming damaged scans (`{id: what}`) and the way out."""
    named = ", ".join(f"scan {i} ({damaged[i]})" for i in sorted(damaged)[:_NAMED])
    more = f" and {len(damaged) - _NAMED} more" if len(damaged) > _NAMED else ""
    rows = "row" if len(damaged) == 1 else "rows"
    return (
        f"{len(damaged)} damaged {rows} skipped: {named}{more}; `disco info --check` "
        "lists them, `disco build-db SCANS -o MAP --repair` rewrites them"
    )
