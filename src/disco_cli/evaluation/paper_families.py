"""Worlds calibrated to the paper's datasets: NCLT-, MulRan- and Oxford-like families.

Each family says how `disco simulate` draws its worlds and how they are scored (the
sampling, the radius within which a match is true, the submaps of the Oxford
benchmark). Their parameters were chosen on the calibration seeds so that the project's
Scan Context lands within +-0.05 of its Recall@1 on the paper's dataset; docs/simulator.md
("Calibrated families") records what was tried. `benchmarks/paper_table.py` runs them.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from disco_cli.evaluation.metrics import one_percent_n, precision_recall, wrap_deg
from disco_cli.io.poses import read_kitti_poses, xy_yaw
from disco_cli.io.readers import list_scans, read_scan
from disco_cli.maps.facade import Map

# Seeds, fixed before any calibration or tuning (one use each; 8601-8699 is this table's).
SEEDS = {
    "calibration": (8611, 8612, 8613),
    "selection": (8621, 8622, 8623),
    "report": (8641, 8642, 8643),
}

# The paper's figures (its Table "Detailed experiment results" and the yaw table).
PAPER = {
    "nclt": {"sc_r1": 0.636, "sc_r1p": 0.924, "disco_r1": 0.891, "disco_r1p": 0.991, "yaw": 2.81},
    "mulran": {"sc_r1": 0.526, "sc_r1p": 0.921, "disco_r1": 0.553, "disco_r1p": 0.933, "yaw": 1.99},
    "oxford": {"sc_r1": 0.646, "sc_r1p": 0.819, "disco_r1": 0.750, "disco_r1p": 0.884, "yaw": None},
}


@dataclass(frozen=True)
class Family:
    """How one family's worlds are simulated and scored."""

    name: str
    sensor: str
    style: str
    length_m: float
    step_m: float  # between map scans (and query scans)
    radius: float  # a match is true within this
    change: float  # `disco simulate --change`
    offset_m: float  # `--robot-offset`: the query run drives up to this far aside
    wobble_deg: float = 0.0  # `--wobble`: per-scan roll and pitch of every run
    jitter_m: float = 0.0  # `--robot-jitter`
    motion_distortion: bool = False
    submap: bool = False  # ground removed, cropped and cut to 4,096 points (Oxford)
    crop_m: float = 30.0  # the submaps' range
    terrain: str = "flat"
    query_every: int = 1  # every n-th scan of the query run is a query
    traffic_per_km: float | None = None  # moving cars per km and way (None: the town's)
    # The query run's ground truth lags its scans by this much along the track, as a
    # timestamp offset between the LiDAR and the reference poses does (the paper blames
    # MulRan's low Recall@1 on it); scoring only, the scans are where they are.
    gt_lag_m: float = 0.0
    # The share of the map run that goes into the map, from its start: below 1 the
    # query run drives on past the mapped streets, and its queries there have no true
    # match (the paper's NCLT run with 170 places the map never saw). Scoring only.
    map_fraction: float = 1.0
    extra: tuple[str, ...] = field(default_factory=tuple)

    def simulate_args(self, seed: int) -> list[str]:
        length = self.length_m
        cmd = ["--sessions", "2", "--length-m", f"{length:g}", "--step-m", f"{self.step_m:g}"]
        cmd += ["--sensor", self.sensor, "--seed", str(seed), "--style", self.style]
        cmd += ["--change", f"{self.change:g}", "--robot-offset", f"{self.offset_m:g}"]
        cmd += ["--terrain", self.terrain]
        if self.wobble_deg:
            cmd += ["--wobble", f"{self.wobble_deg:g}"]
        if self.jitter_m:
            cmd += ["--robot-jitter", f"{self.jitter_m:g}"]
        if self.motion_distortion:
            cmd += ["--motion-distortion"]
        return cmd + list(self.extra)

    def town_toml(self) -> str | None:
        """A `--town` file for what the options cannot say (busier streets), or None."""
        if self.traffic_per_km is None:
            return None
        return f"[town]\ntraffic_per_km = {self.traffic_per_km:g}\n"


# The calibrated families (docs/simulator.md#calibrated-families says how each value was
# chosen on the calibration seeds, and how many settings were tried).
FAMILIES = {
    # A campus ridden by a Segway: HDL-32, roll and pitch within +-4 deg from scan to scan,
    # a year between the runs (every changeable object changed: foliage, cars, hedges), the
    # other run up to 1.5 m aside; map scans 1 m apart, queries every 2 m; true within 1.5 m.
    "nclt": Family(
        name="nclt", sensor="hdl32", style="park", length_m=1000.0, step_m=1.0,
        radius=1.5, change=1.0, offset_m=1.5, wobble_deg=4.0, query_every=2,
    ),
    # A city driven by a fast car: OS1-64, raw scans (motion distortion), places every 5 m
    # in both runs, the query run up to 1.5 m aside plus +-3.5 m per place; true within
    # 3 m. Scored with the scans' true positions: a lag on the query run alone was set
    # against Scan Context's score and capped every method at 0.754 (issue 39); it is
    # the row of its own below.
    "mulran": Family(
        name="mulran", sensor="os1-64", style="grid", length_m=4000.0, step_m=5.0,
        radius=3.0, change=1.0, offset_m=1.5, jitter_m=3.5, motion_distortion=True,
    ),
    # PointNetVLAD's Oxford benchmark: submaps every 20 m, ground removed, 4,096 points,
    # another season's run (a fifth changed); true within 25 m.
    "oxford": Family(
        name="oxford", sensor="hdl32", style="suburban", length_m=6000.0, step_m=20.0,
        radius=25.0, change=0.2, offset_m=1.5, jitter_m=2.0, submap=True, crop_m=50.0,
    ),
}  # fmt: skip
# The MulRan-like worlds scored as the table did until issue 39: the query run's ground
# truth 1.75 m behind its scans (a timestamp offset, as the paper suspects of MulRan).
FAMILIES["mulran_lagged"] = replace(FAMILIES["mulran"], gt_lag_m=1.75)
# The NCLT-like worlds with the map's last fifth left out: the query run (the other
# direction) starts on streets the map never saw, as the paper's precision-recall run
# did (170 new places), so precision counts queries that have no true match.
FAMILIES["nclt_unseen"] = replace(FAMILIES["nclt"], map_fraction=0.8)

SUBMAP_POINTS = 4096
GROUND_ABOVE_M = 0.25  # points lower than this above the ground plane are ground


def submap(points: np.ndarray, mount_height: float, seed: int, crop_m: float) -> np.ndarray:
    """An Oxford-benchmark-like submap of one scan: ground removed (points within
    GROUND_ABOVE_M of the flat ground under the sensor), cropped to `crop_m`, then
    SUBMAP_POINTS of the rest drawn without replacement (all of them, repeated, if fewer)."""
    pts = points[np.isfinite(points[:, :3]).all(axis=1)]
    keep = pts[:, 2] > -mount_height + GROUND_ABOVE_M
    keep &= np.hypot(pts[:, 0], pts[:, 1]) <= crop_m
    pts = pts[keep]
    rng = np.random.default_rng(seed)
    if len(pts) == 0:
        return pts
    idx = rng.choice(len(pts), SUBMAP_POINTS, replace=len(pts) < SUBMAP_POINTS)
    return np.ascontiguousarray(pts[idx], dtype=np.float32)


def load_run(folder: Path) -> tuple[list[Path], np.ndarray]:
    return list_scans(folder), read_kitti_poses(folder / "poses.txt")


def map_run(fam: Family, folder: Path) -> tuple[list[Path], np.ndarray]:
    """The map run's scans and poses that go into the map (`map_fraction` of them)."""
    paths, poses = load_run(folder / "00")
    n = max(1, round(fam.map_fraction * len(paths)))
    return paths[:n], poses[:n]


def scan_points(fam: Family, path: Path, mount_height: float, seed: int) -> np.ndarray:
    pts = read_scan(path)
    return submap(pts, mount_height, seed, fam.crop_m) if fam.submap else pts


def labelled_xy(fam: Family, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> tuple:
    """Where the query run's ground truth puts its scans: `gt_lag_m` behind them along
    their heading (the scans themselves are where they are)."""
    return x - fam.gt_lag_m * np.cos(yaw), y - fam.gt_lag_m * np.sin(yaw)


def evaluate(fam: Family, folder: Path, method: str, policy: dict | None = None) -> list[dict]:
    """One row per query of run 01 against a map of run 00 (`benchmarks/paper_table.py`
    says what is in a row); `policy`: fields of the model's `QueryPolicy` to change."""
    world = json.loads((folder / "world.json").read_text())
    mount = float(world["sensor"]["mount_height"])
    map_paths, map_poses = map_run(fam, folder)
    q_paths, q_poses = load_run(folder / "01")
    mx, my, myaw = xy_yaw(map_poses)
    qx, qy, qyaw = xy_yaw(q_poses)
    qx, qy = labelled_xy(fam, qx, qy, qyaw)
    n1p = one_percent_n(len(map_paths))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # The map's scans as files, as a user's map has them (the geometric check reads
        # them); a submap family's are written out, the others are the world's own.
        names = [str(p) for p in map_paths]
        if fam.submap:
            names = [str(Path(tmp) / f"{i:06d}.bin") for i in range(len(map_paths))]
            for i, p in enumerate(map_paths):
                scan_points(fam, p, mount, i).tofile(names[i])
        row_of = {name: i for i, name in enumerate(names)}
        m = Map.create(Path(tmp) / "map.db", method)
        m.add_many((read_scan(n), n, map_poses[i]) for i, n in enumerate(names))
        m.close()
        with Map.open(Path(tmp) / "map.db") as m:
            rule = replace(m.model.query_policy, **policy) if policy else None
            for i, p in enumerate(q_paths):
                if i % fam.query_every:
                    continue
                pts = scan_points(fam, p, mount, 10**6 + i)
                t0 = time.perf_counter()
                matches = m.query(pts, topk=max(n1p, 1), name=str(p), policy=rule)
                ms = 1000 * (time.perf_counter() - t0)
                d_all = np.hypot(mx - qx[i], my - qy[i])
                rowsof = [row_of[mt.name] for mt in matches]
                hits = [bool(d_all[r] <= fam.radius) for r in rowsof]
                yaw_err = None
                if hits and hits[0]:
                    true = wrap_deg(math.degrees(qyaw[i] - myaw[rowsof[0]]))
                    yaw_err = float(abs(wrap_deg(matches[0].yaw_deg - true)))
                rows.append(
                    {
                        "query": i,
                        "near_m": round(float(d_all.min()), 3),
                        "has": bool(d_all.min() <= fam.radius),
                        "d1": float(matches[0].distance) if matches else None,
                        "c1": matches[0].confidence if matches else None,
                        # How far the top 1 stands from the query's labelled position:
                        # a wrong top 1 just past the radius is a near miss, not a
                        # wrong place.
                        "m1": round(float(d_all[rowsof[0]]), 2) if matches else None,
                        "ms": round(ms, 2),
                        "r1": bool(any(hits[:1])),
                        "r1p": bool(any(hits[:n1p])),
                        "yaw_err": yaw_err,
                    }
                )
    return rows


def oracle_rows(fam: Family, folder: Path) -> list[dict]:
    """The family's ceiling: rows as `evaluate` writes them for a method whose top 1 is
    always the map scan nearest the query's real position (its `d1`, that scan's
    distance in metres). Below 1 only where the ground truth lags (`gt_lag_m`)."""
    map_paths, map_poses = map_run(fam, folder)
    q_paths, q_poses = load_run(folder / "01")
    mx, my, _ = xy_yaw(map_poses)
    qx, qy, qyaw = xy_yaw(q_poses)
    hx, hy = labelled_xy(fam, qx, qy, qyaw)
    rows = []
    for i in range(0, len(q_paths), fam.query_every):
        real = np.hypot(mx - qx[i], my - qy[i])
        label = np.hypot(mx - hx[i], my - hy[i])
        hit = bool(label[int(np.argmin(real))] <= fam.radius)
        rows.append(
            {
                "query": i,
                "near_m": round(float(label.min()), 3),
                "has": bool(label.min() <= fam.radius),
                "d1": float(real.min()),
                "r1": hit,
                "r1p": hit,
                "yaw_err": None,  # it has no yaw
            }
        )
    return rows


# A top 1 at least this confident counts as one a user would act on (disco loops' bar).
CONFIDENT = 0.85


def summarize(rows: list[dict], radius: float | None = None) -> dict[str, float]:
    """The table's metrics over one family's rows (all its seeds together); with the
    family's `radius`, how many wrong top 1s of confidence >= CONFIDENT there were and
    how many of them stood farther than twice the radius (a wrong place, not a near
    miss)."""
    nan = float("nan")
    has = np.array([r["has"] for r in rows], bool)
    n = int(has.sum())
    r1 = np.array([r["r1"] for r in rows], bool)
    r1p = np.array([r["r1p"] for r in rows], bool)
    d1 = np.array([np.inf if r["d1"] is None else r["d1"] for r in rows], float)
    curve = precision_recall(d1, r1 & has, has)
    # The same over the top 1's confidence (highest first; none: never accepted).
    c1 = np.array([_or_nan(r.get("c1")) for r in rows], float)
    by_conf = precision_recall(np.where(np.isfinite(c1), -c1, np.inf), r1 & has, has)
    ms = np.array([r["ms"] for r in rows if r.get("ms") is not None], float)
    errs = np.array(
        [r["yaw_err"] for r in rows if r["has"] and r["r1"] and r["yaw_err"] is not None]
    )
    out = {
        "queries": n,
        "r1": float((r1 & has).sum() / n) if n else nan,
        "r1p": float((r1p & has).sum() / n) if n else nan,
        "r100p": curve.recall_at_full_precision,
        "f1max": curve.f1_max,
        "r100p_conf": by_conf.recall_at_full_precision if np.isfinite(c1).any() else nan,
        "f1max_conf": by_conf.f1_max if np.isfinite(c1).any() else nan,
        "median_ms": float(np.median(ms)) if len(ms) else nan,
        **_confident_wrong(rows, r1 & has, c1, radius),
        "yaw_mean": float(errs.mean()) if len(errs) else nan,
        "yaw_median": float(np.median(errs)) if len(errs) else nan,
        "yaw_over10": int((errs > 10.0).sum()),
    }
    for p in (0.99, 1.0):  # the largest threshold with precision >= p, and its recall
        ok = np.flatnonzero(curve.precision >= p)
        key = f"p{round(100 * p)}"
        out[f"{key}_distance"] = float(curve.thresholds[ok[-1]]) if ok.size else nan
        out[f"{key}_recall"] = float(curve.recall[ok[-1]]) if ok.size else 0.0
    return out


def _confident_wrong(
    rows: list[dict], right: np.ndarray, c1: np.ndarray, radius: float | None
) -> dict[str, int]:
    if radius is None or not np.isfinite(c1).any():
        return {}
    wrong = np.flatnonzero(~right & (np.nan_to_num(c1, nan=-1.0) >= CONFIDENT))
    far = [i for i in wrong if rows[i].get("m1") is not None and rows[i]["m1"] > 2 * radius]
    return {"confident_wrong": int(len(wrong)), "confident_wrong_far": len(far)}


def _or_nan(x: float | None) -> float:
    return float("nan") if x is None else float(x)


def write_submaps(world: Path) -> int:
    """Rewrite every scan of a simulated world as its Oxford-like submap (`submap`), in
    place, for training on that family; returns how many scans were rewritten."""
    meta = json.loads((Path(world) / "world.json").read_text())
    mount = float(meta["sensor"]["mount_height"])
    n = 0
    for k, session in enumerate(sorted(Path(world).glob("[0-9][0-9]"))):
        for i, path in enumerate(sorted((session / "velodyne").glob("*.bin"))):
            submap(read_scan(path), mount, 10**7 * (k + 1) + i, FAMILIES["oxford"].crop_m).tofile(
                path
            )
            n += 1
    return n
