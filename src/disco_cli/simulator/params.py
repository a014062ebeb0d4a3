"""Town parameters: the knobs of the town generator, read from TOML or a world.json.

`TownParams` sets the layout and what stands in it (`style`, `terrain`);
`ChangeParams`, when given, switches on the change model: how much of each class
of objects differs between session 00 and a later session.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path

from disco_cli.errors import DiscoError

STYLES = ("grid", "suburban", "industrial", "park", "parking", "terrace", "boulevard")
TERRAINS = ("flat", "varied")
# The object classes of the change model, as named in ChangeParams and world.json.
CHANGE_CLASSES = ("cars", "trees", "hedges", "fences", "furniture", "buildings")


@dataclass
class ChangeParams:
    """How much of each class changes between session 00 and each later session.

    `fraction` is the share of each class's objects changed (`buildings`: a fifth of
    it, as construction is rarer); a class's own value replaces it.
    """

    fraction: float = 0.0
    cars: float | None = None  # parked cars that leave, or make room for another car
    trees: float | None = None  # felled, crown grown or shrunk, leaves lost
    hedges: float | None = None  # cut down or trimmed
    fences: float | None = None  # taken down or rebuilt to another height
    furniture: float | None = None  # bins, benches, signs, bushes: gone or moved
    buildings: float | None = None  # sheds, halls, houses, containers demolished
    cyclists_per_km: float = 4.0  # cyclists riding per km of street, each way (in-session)

    def rate(self, cls: str) -> float:
        """The share of class `cls`'s objects that a later session changes."""
        own = getattr(self, cls)
        if own is not None:
            return float(own)
        return self.fraction / 5 if cls == "buildings" else self.fraction

    def to_dict(self) -> dict:
        return {
            f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }

    @classmethod
    def from_dict(cls, data: dict, source: str = "change parameters") -> ChangeParams:
        if not isinstance(data, dict):
            raise DiscoError(f"{source}: [change] must be a table")
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise DiscoError(f"{source}: unknown change parameters: {', '.join(sorted(unknown))}")
        for key, value in data.items():
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise DiscoError(f"{source}: change {key} = {value!r} is not a number")
        out = cls(**{k: float(v) for k, v in data.items()})
        out.check(source)
        return out

    def check(self, source: str = "change parameters") -> None:
        given = {k: getattr(self, k) for k in ("fraction", *CHANGE_CLASSES)}
        bad = [k for k, v in given.items() if v is not None and not 0.0 <= v <= 1.0]
        if bad:
            raise DiscoError(f"{source}: change {', '.join(bad)} must be within 0..1")
        if self.cyclists_per_km < 0:
            raise DiscoError(f"{source}: change cyclists_per_km must be >= 0")


@dataclass
class TownParams:
    blocks_x: int = 4
    blocks_y: int = 4
    block_min_m: float = 55.0
    block_max_m: float = 95.0
    node_jitter_m: float = 6.0
    link_drop: float = 0.15  # share of inner links removed (keeps every junction >= 2 links)
    road_width_m: tuple[float, float] = (8.0, 13.0)
    sidewalk_m: tuple[float, float] = (1.8, 3.5)
    max_slope: float = 0.02  # ground gradient (2 % = gentle)
    outskirts_m: float = 70.0  # depth of the scattered trees and sheds around the town
    cell_size_m: float = 4.0  # ray-casting grid
    traffic_per_km: float = 8.0  # moving cars per km of street, each way
    pedestrians_per_km: float = 10.0  # people walking per km of sidewalk, each side
    foliage: tuple[float, float] = (0.6, 1.15)  # per-session factor on crowns' hit chance
    style: str = "grid"  # grid, suburban, industrial, park, parking, terrace, boulevard
    terrain: str = "flat"  # flat, or varied: crowned roads, high kerbs, hills
    change: ChangeParams | None = None  # the change model; None: the classic draw

    def to_dict(self) -> dict:
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, ChangeParams):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            if v is not None:
                out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, data: dict, source: str = "town parameters") -> TownParams:
        """Parameters from a dict (unknown keys and bad values raise DiscoError)."""
        known = {f.name: f for f in fields(cls)}
        unknown = set(data) - set(known)
        if unknown:
            raise DiscoError(f"{source}: unknown town parameters: {', '.join(sorted(unknown))}")
        default = cls()
        values: dict = {}
        for key, value in data.items():
            if key == "change":
                values[key] = ChangeParams.from_dict(value, source)
                continue
            want = getattr(default, key)
            if isinstance(want, str):
                ok = isinstance(value, str)
            elif isinstance(want, tuple):
                ok = (
                    isinstance(value, (list, tuple))
                    and len(value) == 2
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
                )
                value = tuple(float(v) for v in value) if ok else value
            else:
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                if ok and isinstance(want, int) and float(value) != int(value):
                    ok = False
                value = type(want)(value) if ok else value
            if not ok:
                raise DiscoError(f"{source}: {key} = {value!r} is not like {want!r}")
            values[key] = value
        params = cls(**values)
        params.check(source)
        return params

    def check(self, source: str = "town parameters") -> None:
        """Raise DiscoError on values that cannot make a town."""
        problems = []
        if self.blocks_x < 1 or self.blocks_y < 1 or self.blocks_x * self.blocks_y > 400:
            problems.append("blocks_x and blocks_y must be >= 1 (at most 400 blocks)")
        if not 20 <= self.block_min_m <= self.block_max_m <= 1000:
            problems.append("need 20 <= block_min_m <= block_max_m <= 1000")
        for key in ("road_width_m", "sidewalk_m", "foliage"):
            lo, hi = getattr(self, key)
            if not 0 < lo <= hi:
                problems.append(f"{key} must be a range 0 < low <= high")
        if self.road_width_m[1] + 2 * self.sidewalk_m[1] >= self.block_min_m:
            problems.append("roads and sidewalks must be narrower than the smallest block")
        if not 0 <= self.link_drop < 1 or not 0 <= self.max_slope <= 0.2:
            problems.append("need 0 <= link_drop < 1 and 0 <= max_slope <= 0.2")
        if not 0 <= self.node_jitter_m < self.block_min_m / 4:
            problems.append("node_jitter_m must be within 0 .. block_min_m / 4")
        if self.cell_size_m <= 0.5 or self.outskirts_m < 0:
            problems.append("cell_size_m must be > 0.5 and outskirts_m >= 0")
        if self.traffic_per_km < 0 or self.pedestrians_per_km < 0:
            problems.append("traffic_per_km and pedestrians_per_km must be >= 0")
        if self.style not in STYLES:
            problems.append(f"style must be one of {', '.join(STYLES)}")
        if self.terrain not in TERRAINS:
            problems.append(f"terrain must be one of {', '.join(TERRAINS)}")
        if problems:
            raise DiscoError(f"{source}: " + "; ".join(problems))
        if self.change is not None:
            self.change.check(source)

    @classmethod
    def load(cls, path: str | Path) -> TownParams:
        """From a TOML file (keys at the top or under [town], the change model under
        [change]) or a world.json."""
        import tomllib  # deferred: Python 3.11+; on 3.10 only a TOML town cannot be read

        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise DiscoError(f"{path}: cannot read ({exc.strerror})") from None
        try:
            if path.suffix == ".json":
                data = json.loads(text)["town"]["params"]
            else:
                data = tomllib.loads(text)
                if "town" in data:
                    extra = set(data) - {"town", "change"}
                    if extra:
                        raise DiscoError(
                            f"{path}: unknown sections or keys beside [town]: "
                            + ", ".join(sorted(extra))
                        )
                    town = data["town"]
                    if "change" in data:
                        if not isinstance(town, dict):
                            raise TypeError("[town] is not a table")
                        town = {**town, "change": data["change"]}
                    data = town
        except (ValueError, KeyError, TypeError) as exc:
            raise DiscoError(f"{path}: not a town TOML or world.json ({exc})") from None
        if not isinstance(data, dict):
            raise DiscoError(f"{path}: not a town TOML or world.json")
        return cls.from_dict(data, str(path))
