"""What each town style is made of (see `TownParams.style` and docs/simulator.md).

A grid town mixes five characters of street side; the other styles are each made
of their own. `terrace` is the repetitive one: rows of houses of one height, 0.3 m
apart, front gardens, a tree row and cars parked along both kerbs, street after
street. `boulevard` is the street that looks alike both ways: long and straight
(with the suite's town), both sides of a street drawing one character (building
height, setback, wall or hedge, tree spacing, parking), plain buildings 11-24 m from
the driving line, hedges or walls at 6.5-8 m, trees and lights at 4.5-9 m, cars
parked along both kerbs, and hardly anything else. A side style sets building
heights (m), density (share of lots built), setback (m), frontage shares (none /
wall / fence / hedge), the chance of a tree row, lot width and building depth (m).
"""

from __future__ import annotations

SIDE_STYLES: dict[str, tuple[list[str], list[float]]] = {
    "grid": (
        ["downtown", "residential", "industrial", "park", "mixed"],
        [0.25, 0.3, 0.15, 0.1, 0.2],
    ),
    "suburban": (["suburban"], [1.0]),
    "industrial": (["hall", "industrial"], [0.8, 0.2]),
    "park": (["parkroad"], [1.0]),
    "parking": (["lot", "mixed"], [0.7, 0.3]),
    "terrace": (["terrace"], [1.0]),
    "boulevard": (["boulevard"], [1.0]),
}
HEIGHTS = {
    "downtown": (12, 40),
    "residential": (5, 12),
    "industrial": (6, 14),
    "park": (3, 6),
    "mixed": (5, 22),
    "suburban": (5, 9),
    "hall": (7, 14),
    "parkroad": (3, 5),
    "lot": (4, 9),
    "terrace": (7, 10),  # one height per street, each house within 0.4 m of it
    "boulevard": (8, 16),  # one height per street, each building within 1 m of it
}
DENSITY = {
    "downtown": 1.0,
    "residential": 0.85,
    "industrial": 0.75,
    "park": 0.25,
    "mixed": 0.85,
    "suburban": 0.9,
    "hall": 0.9,
    "parkroad": 0.06,
    "lot": 0.5,
    "terrace": 1.0,
    "boulevard": 0.95,
}
SETBACK = {
    "downtown": (0.3, 1.0),
    "residential": (1.0, 4.5),
    "industrial": (2.0, 8.0),
    "park": (5.0, 15.0),
    "mixed": (0.5, 5.0),
    "suburban": (4.0, 8.0),
    "hall": (4.0, 12.0),
    "parkroad": (10.0, 20.0),
    "lot": (2.0, 4.0),
    "terrace": (2.0, 3.5),
    "boulevard": (4.5, 15.5),
}
_FRONTAGE = [0.3, 0.25, 0.2, 0.25]
FRONTAGE = {
    "downtown": [0.8, 0.2, 0, 0],
    "residential": _FRONTAGE,
    "industrial": _FRONTAGE,
    "park": _FRONTAGE,
    "mixed": _FRONTAGE,
    "suburban": [0.15, 0.1, 0.3, 0.45],
    "hall": [0.2, 0.1, 0.7, 0.0],
    "parkroad": [0.4, 0.0, 0.1, 0.5],
    "lot": [0.5, 0.0, 0.2, 0.3],
    "terrace": [0.1, 0.3, 0.15, 0.45],
    "boulevard": [0.0, 0.5, 0.0, 0.5],
}
TREE_ROW = {
    "park": 0.95,
    "residential": 0.7,
    "suburban": 0.6,
    "hall": 0.15,
    "parkroad": 1.0,
    "terrace": 0.8,
    "boulevard": 1.0,
}
LOT_WIDTH = {"suburban": (14, 24), "hall": (30, 70), "terrace": (5.0, 7.0), "boulevard": (16, 30)}
DEPTH = {"suburban": (8, 12), "hall": (20, 45), "terrace": (9, 11), "boulevard": (10, 16)}
# Around and inside the blocks: one thing per so many m2, the shares of trees / bushes / mounds
# (the rest are sheds or halls) and the size of those (width, depth, height ranges).
OUTSKIRTS = {
    "grid": (200, (0.6, 0.75, 0.9), ((4, 30), (4, 20), (2.5, 12))),
    "suburban": (200, (0.55, 0.8, 0.88), ((4, 12), (4, 10), (2.5, 8))),
    "industrial": (200, (0.3, 0.4, 0.5), ((20, 60), (15, 40), (6, 14))),
    "park": (110, (0.75, 0.92, 0.98), ((3, 8), (3, 6), (2.5, 4))),
    "parking": (200, (0.5, 0.65, 0.8), ((8, 30), (8, 20), (3, 8))),
    "terrace": (200, (0.55, 0.8, 0.88), ((4, 10), (4, 8), (2.5, 5))),
    "boulevard": (500, (0.6, 0.8, 0.9), ((6, 14), (6, 12), (3, 6))),
}

# The town the validation suite builds its boulevards in (benchmarks/ood_suite.py, also
# in docs/simulator.md): long straight streets, 9.5-10.5 m kerb to kerb.
BOULEVARD_TOWN = {
    "style": "boulevard",
    "blocks_x": 3,
    "blocks_y": 2,
    "block_min_m": 140.0,
    "block_max_m": 200.0,
    "node_jitter_m": 0.0,
    "link_drop": 0.0,
    "road_width_m": (9.5, 10.5),
    "sidewalk_m": (1.8, 2.6),
}


# The change the suite's boulevards see at level f: about f x 2 of the parked cars,
# hedges and walls gone (half of those changed leave) and f of the trees changed; at
# f = 0.25, half and a quarter.
def boulevard_change(f: float) -> dict:
    return {
        "fraction": f,
        "cars": min(1.0, 4 * f),
        "hedges": min(1.0, 4 * f),
        "fences": min(1.0, 4 * f),
        "trees": f,
        "buildings": 0.0,
    }


def boulevard_toml(change: float, wide: bool = False) -> str:
    """The suite's boulevard town and its change at level `change`, as the TOML that
    `disco simulate --town` reads; `wide`: 19-22 m kerb to kerb (room for two cars 8 m
    apart and a kerb), for revisits to the side."""
    town = dict(BOULEVARD_TOWN)
    if wide:
        town["road_width_m"] = (19.0, 22.0)

    def value(v: object) -> str:
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, tuple):
            return "[" + ", ".join(f"{x:g}" for x in v) + "]"
        return f"{v:g}"

    lines = ["[town]"] + [f"{k} = {value(v)}" for k, v in town.items()]
    lines += ["", "[change]"] + [f"{k} = {v:g}" for k, v in boulevard_change(change).items()]
    return "\n".join(lines) + "\n"
