"""What moves within a session: cars driving on their right, cyclists near the kerb,
people walking on the sidewalks.

Each mover is one row: street, heading (+-1), start (m), speed (m/s), offset right
of its heading (m), length, width, height, reflectivity, kind (0 car, 1 person,
2 cyclist), span start and span length along its street; `mover_rows` places them
at a time `t`, wrapping at the end of their street's span.
"""

from __future__ import annotations

import numpy as np

from disco_cli.simulator.objects import BOX, CYLINDER
from disco_cli.simulator.scenery import Scenery


class Movers(Scenery):
    """The traffic and walkers of a session (a part of `Town`)."""

    def _movers(self, rng: np.random.Generator) -> np.ndarray:
        """This session's traffic and walkers, one row each: street, heading (+-1), start
        (m), speed (m/s), offset right of the heading (m), length, width, height,
        reflectivity, kind (0 car, 1 person), span start, span length."""
        p = self.params
        rows = []
        for k, s in enumerate(self.streets):
            lo = self.node_clear[self.links[k][0]]
            span = s.length - lo - self.node_clear[self.links[k][1]]
            if span < 10:
                continue
            for heading in (1.0, -1.0):
                for _ in range(rng.poisson(span * p.traffic_per_km / 1000)):
                    rows.append(
                        [
                            k,
                            heading,
                            rng.uniform(0, span),
                            rng.uniform(6, 14),
                            rng.uniform(1.5, 2.1),
                            rng.uniform(3.8, 5.2),
                            rng.uniform(1.7, 2.0),
                            rng.uniform(1.4, 2.0),
                            rng.choice([0.08, 0.2, 0.5, 0.8]),
                            0,
                            lo,
                            span,
                        ]
                    )
                for _ in range(rng.poisson(span * p.pedestrians_per_km / 1000)):
                    off = s.half_width + rng.uniform(0.4, max(0.5, s.sidewalk - 0.4))
                    h = rng.uniform(1.5, 1.95)
                    rows.append(
                        [
                            k,
                            rng.choice([1.0, -1.0]),
                            rng.uniform(0, span),
                            rng.uniform(0.8, 1.7),
                            heading * off,
                            0.5,
                            0.5,
                            h,
                            0.35,
                            1,
                            lo,
                            span,
                        ]
                    )
        return np.array(rows, np.float64).reshape(-1, 12)

    def mover_rows(
        self, movers: np.ndarray, t: float, xy: np.ndarray | None, keep_clear_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Primitive rows of the movers at time `t` (cars: body and cabin; people: a
        cylinder); none within `keep_clear_m` of `xy`."""
        k = movers[:, 0].astype(int)
        heading, s0, speed, right = movers[:, 1], movers[:, 2], movers[:, 3], movers[:, 4]
        a = np.array([self.streets[i].a for i in k]).reshape(-1, 2)
        d = np.array([self.streets[i].dir for i in k]).reshape(-1, 2)
        left = np.array([self.streets[i].left for i in k]).reshape(-1, 2)
        along = movers[:, 10] + np.mod(s0 + heading * speed * t, movers[:, 11])
        pos = a + d * along[:, None] - left * (heading * right)[:, None]
        keep = np.ones(len(movers), bool)
        if xy is not None:
            keep = np.hypot(*(pos - np.asarray(xy)[:2]).T) > keep_clear_m
        yaw = np.array([self.streets[i].yaw for i in k])
        g = self.ground_z(pos[:, 0], pos[:, 1])
        length, width, height = movers[:, 5], movers[:, 6], movers[:, 7]
        rows, refl, drop = [], [], []
        for i in np.flatnonzero(keep):
            x, y = pos[i]
            if movers[i, 9] == 0:  # a car: body, then a narrower cabin of glass
                body = 0.55 * height[i]
                rows.append(
                    [
                        BOX,
                        x,
                        y,
                        g[i] + (0.25 + body) / 2,
                        length[i] / 2,
                        width[i] / 2,
                        (body - 0.25) / 2,
                        yaw[i],
                        1.0,
                    ]
                )
                refl.append(movers[i, 8])
                drop.append(0.03)
                rows.append(
                    [
                        BOX,
                        x,
                        y,
                        g[i] + (body + height[i]) / 2,
                        0.3 * length[i],
                        0.45 * width[i],
                        (height[i] - body) / 2,
                        yaw[i],
                        1.0,
                    ]
                )
                refl.append(0.1)
                drop.append(0.4)
            elif movers[i, 9] == 2:  # a cyclist: bike and rider, seen side on
                rows.append(
                    [
                        BOX,
                        x,
                        y,
                        g[i] + height[i] / 2,
                        length[i] / 2,
                        width[i] / 2,
                        height[i] / 2,
                        yaw[i],
                        1.0,
                    ]
                )
                refl.append(movers[i, 8])
                drop.append(0.1)
            else:  # a person
                rows.append(
                    [CYLINDER, x, y, g[i] + height[i] / 2, 0.25, 0.25, height[i] / 2, 0.0, 1.0]
                )
                refl.append(movers[i, 8])
                drop.append(0.05)
        return (
            np.array(rows, np.float64).reshape(-1, 9),
            np.array(refl, np.float32),
            np.array(drop, np.float32),
        )

    def _cyclists(self, rng: np.random.Generator) -> np.ndarray:
        """This session's cyclists (mover rows of kind 2), near the right kerb."""
        per_km = self.params.change.cyclists_per_km if self.params.change else 0.0
        rows = []
        for k, s in enumerate(self.streets):
            lo = self.node_clear[self.links[k][0]]
            span = s.length - lo - self.node_clear[self.links[k][1]]
            if span < 10:
                continue
            for heading in (1.0, -1.0):
                for _ in range(rng.poisson(span * per_km / 1000)):
                    # Near the kerb, or outside the parked cars where there may be some.
                    kerb = s.half_width - (2.6 if s.half_width >= 5.0 else 0.6)
                    right = kerb - rng.uniform(0.0, 0.4)
                    h = rng.uniform(1.6, 1.9)
                    rows.append(
                        [
                            k,
                            heading,
                            rng.uniform(0, span),
                            rng.uniform(3, 7),
                            right,
                            1.8,
                            0.6,
                            h,
                            0.3,
                            2,
                            lo,
                            span,
                        ]
                    )
        return np.array(rows, np.float64).reshape(-1, 12)
