"""Benchmark: relative pose and loop verification per candidate (budget: 30 ms, one core).

Times `estimate_relative_pose` (phase correlation + C++ ICP, two yaw hypotheses) on
30k-point scans: KITTI frame 0 from ../shared/realdata (a random 30k subset, the query a
transformed copy with 30 % of the points dropped and 2 cm noise, yaw hint off by up to
3 degrees), a wrong candidate (KITTI vs the HDL-32 scan from elsewhere: the rejection
path, where ICP does not converge), and reverse-direction revisits of the simulated
sample sessions. Without realdata, a synthetic street stands in for KITTI.

Baseline, in the same process: the same point-to-plane ICP (same clouds, seed, stages
and iterations) written with NumPy and SciPy's cKDTree, the way a Python user would.
Prints medians of wall time and of process CPU time (the machine may be shared).
Run: `.venv/bin/python benchmarks/bench_pose.py`.

`--calibrate` instead prints the fitness and rmse of correct and wrong pairs that
docs/relative_pose.md uses to justify the acceptance thresholds.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from _common import median_wall_cpu_ms, print_header

from disco_cli import _core
from disco_cli.query.relative_pose import PoseConfig, _icp_config, estimate_relative_pose

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "realdata"
SAMPLES = REPO / "data" / "samples"


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def read_bin(path: Path) -> np.ndarray:
    return np.fromfile(path, np.float32).reshape(-1, 4)


def subset(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= n:
        return points
    return np.ascontiguousarray(points[np.sort(rng.choice(len(points), n, replace=False))])


def query_from(match: np.ndarray, T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    keep = rng.random(len(match)) > 0.3
    q = match[keep].copy()
    Ti = np.linalg.inv(T)
    q[:, :3] = q[:, :3] @ Ti[:3, :3].T + Ti[:3, 3] + rng.normal(0, 0.02, (len(q), 3))
    return q


def synthetic_street(rng: np.random.Generator, n: int = 30000) -> np.ndarray:
    """Ground, two broken building rows and boxes: a stand-in when realdata is absent."""
    parts = [np.c_[rng.uniform(-40, 40, (n // 3, 2)), np.full(n // 3, -1.8)]]
    for side in (-1, 1):
        for x0 in np.arange(-40, 40, 12.0):
            m = n // 30
            parts.append(
                np.c_[
                    rng.uniform(x0, x0 + rng.uniform(6, 11), m),
                    np.full(m, side * rng.uniform(7, 12)),
                    rng.uniform(-1.8, 8, m),
                ]
            )
    for _ in range(12):
        c = rng.uniform(-35, 35, 2)
        m = n // 60
        parts.append(
            np.c_[c[0] + rng.uniform(-2, 2, m), np.full(m, c[1] + 1.0), rng.uniform(-1.8, 0.5, m)]
        )
    pts = np.concatenate(parts)
    return np.c_[pts, np.zeros(len(pts))].astype(np.float32)


# --- the NumPy + SciPy baseline: the same ICP, written the obvious way -------------------


def baseline_icp(
    source: np.ndarray, match: np.ndarray, initial: np.ndarray, config: PoseConfig
) -> np.ndarray:
    from scipy.spatial import cKDTree

    target = _core.icp_voxel_downsample(match, config.target_voxel)
    tree = cKDTree(target)
    # Normals from the 10 nearest neighbours of each target point.
    _, nn = tree.query(target, k=10)
    nb = target[nn] - target[nn].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normals = vecs[:, :, 0]
    T = initial.copy()
    for dist in config.stages:
        k2 = (dist / 3.0) ** 2
        for _ in range(config.max_iterations):
            q = source @ T[:3, :3].T + T[:3, 3]
            d, j = tree.query(q, distance_upper_bound=dist)
            ok = np.isfinite(d)
            n, qq = normals[j[ok]], q[ok]
            r = np.einsum("ij,ij->i", n, qq - target[j[ok]])
            w = (k2 / (k2 + r * r)) ** 2
            J = np.c_[np.cross(qq, n), n]
            H = (J * w[:, None]).T @ J
            delta = np.linalg.solve(H + 1e-9 * np.eye(6), -(J * (w * r)[:, None]).sum(0))
            angle = np.linalg.norm(delta[:3])
            R = np.eye(3)
            if angle > 1e-12:
                k = delta[:3] / angle
                K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
                R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
            step = np.eye(4)
            step[:3, :3], step[:3, 3] = R, delta[3:]
            T = step @ T
            if angle < 5e-4 and np.linalg.norm(delta[3:]) < 5e-4:
                break
    return T


# --- timing -------------------------------------------------------------------------------


def measure(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds of fn() (after one warm-up call)."""
    return median_wall_cpu_ms(fn, repeats, warmup=1)


def pose_error(T_true: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(T_true) @ T
    ang = math.degrees(math.acos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(E[:3, 3])), ang


def calibrate(config: PoseConfig) -> None:
    """Fitness and rmse of correct and wrong pairs: the evidence for the thresholds."""
    rng = np.random.default_rng(1)

    def report(name: str, results: list) -> None:
        if not results:
            print(f"{name}: no data")
            return
        f = np.array([r.fitness for r in results])
        e = np.array([r.rmse for r in results])
        print(
            f"{name}: {len(results)} pairs, fitness {f.min():.2f}-{f.max():.2f}, "
            f"rmse {np.nanmin(e):.2f}-{np.nanmax(e):.2f} m, accepted "
            f"{sum(r.accepted for r in results)}"
        )

    if (SAMPLES / "00" / "poses.txt").is_file():
        from disco_cli.io.poses import read_kitti_poses

        poses = {s: read_kitti_poses(SAMPLES / s / "poses.txt") for s in ("00", "01")}

        def scan(s: str, i: int) -> np.ndarray:
            return read_bin(SAMPLES / s / "velodyne" / f"{i:06d}.bin")

        right, wrong = [], []
        items = [(s, i) for s in poses for i in range(len(poses[s]))]
        for a in items:
            for b in items:
                if a[0] == b[0] and abs(a[1] - b[1]) < 5:
                    continue  # same session, neighbouring frames: not a revisit
                T = np.linalg.inv(poses[b[0]][b[1]]) @ poses[a[0]][a[1]]
                if np.linalg.norm(T[:2, 3]) < 3.0 and a[0] <= b[0]:
                    yaw = math.degrees(math.atan2(T[1, 0], T[0, 0])) + rng.uniform(-3, 3)
                    right.append(estimate_relative_pose(scan(*a), scan(*b), yaw, config))
        for _ in range(60):
            a, b = items[rng.integers(len(items))], items[rng.integers(len(items))]
            T = np.linalg.inv(poses[b[0]][b[1]]) @ poses[a[0]][a[1]]
            if np.linalg.norm(T[:2, 3]) > 20.0:
                wrong.append(
                    estimate_relative_pose(scan(*a), scan(*b), rng.uniform(-180, 180), config)
                )
        report("simulated revisits within 3 m (data/samples)", right)
        # Farther pairs, 3-14 m (beyond max_translation some must fail): the fitness of
        # those registered right (within 0.2 m of the truth) and of those registered wrong.
        good, bad = [], []
        for a in items:
            for b in items:
                T = np.linalg.inv(poses[b[0]][b[1]]) @ poses[a[0]][a[1]]
                d = float(np.linalg.norm(T[:2, 3]))
                if not (3.0 <= d < 14.0 and a[0] <= b[0] and a != b):
                    continue
                yaw = math.degrees(math.atan2(T[1, 0], T[0, 0])) + rng.uniform(-3, 3)
                r = estimate_relative_pose(scan(*a), scan(*b), yaw, config)
                err = float(np.linalg.norm((np.linalg.inv(T) @ r.T)[:3, 3]))
                (good if err < 0.2 else bad).append((d, r.fitness))
        g, w = np.array(good), np.array(bad)
        print(
            f"simulated pairs 3-14 m apart: {len(g)} registered within 0.2 m, fitness min "
            f"{g[:, 1].min():.2f} (min {g[g[:, 0] < 10, 1].min():.2f} within 10 m); "
            f"{len(w)} registered wrong, fitness max {w[:, 1].max():.2f}"
        )
        report("simulated wrong places (> 20 m apart, random yaw)", wrong)
        # Why ground-like points are left out of fitness: ICP from identity on wrong pairs.
        icp = _icp_config(config)
        ratios = []
        for _ in range(20):
            a, b = items[rng.integers(len(items))], items[rng.integers(len(items))]
            T = np.linalg.inv(poses[b[0]][b[1]]) @ poses[a[0]][a[1]]
            if np.linalg.norm(T[:2, 3]) > 20.0:
                r = _core.PlaneTarget(scan(*b), icp).align(
                    _core.icp_prepare_source(scan(*a), icp), np.eye(4)
                )
                ratios.append((r.fitness, r.fitness_all))
        f = np.array(ratios)
        print(
            f"  wrong places, ICP from identity: fitness without ground-like points max "
            f"{f[:, 0].max():.2f}, with them max {f[:, 1].max():.2f}"
        )
    if (REAL / "kitti00").is_dir():
        from disco_cli.io.poses import read_kitti_poses

        d = REAL / "kitti00"
        poses = read_kitti_poses(d / "poses.txt", d / "calib.txt")
        frame0 = read_bin(d / "velodyne" / "000000.bin")
        real = []
        for i in range(1, 11):
            T = np.linalg.inv(poses[0]) @ poses[i]
            yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
            real.append(
                estimate_relative_pose(
                    read_bin(d / "velodyne" / f"{i:06d}.bin"), frame0, yaw, config
                )
            )
        h = REAL / "hdl32_pair"
        real.append(
            estimate_relative_pose(
                read_bin(h / "source.bin"), read_bin(h / "target.bin"), 0.0, config
            )
        )
        report("real consecutive scans (KITTI 0 vs 1..10, HDL-32 pair)", real)
        other = read_bin(h / "source.bin")
        cross = [
            estimate_relative_pose(q, m, yaw, config)
            for q, m in ((frame0, other), (other, frame0))
            for yaw in (0.0, 90.0, -135.0)
        ]
        report("real wrong places (KITTI frame 0 vs HDL-32 scan)", cross)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=10, help="random transforms per case")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per pair")
    parser.add_argument(
        "--calibrate",
        action="store_true",
        help="print fitness/rmse of correct and wrong pairs instead of timings",
    )
    args = parser.parse_args()
    print_header("bench_pose")
    rng = np.random.default_rng(0)
    config = PoseConfig()
    if args.calibrate:
        calibrate(config)
        return

    kitti = REAL / "kitti00" / "velodyne" / "000000.bin"
    full = None
    if kitti.is_file():
        full = read_bin(kitti)
        match, source = subset(full, 30000, rng), "KITTI 00 frame 0, 30k subset"
        other = subset(read_bin(REAL / "hdl32_pair" / "source.bin"), 30000, rng)
    else:
        match, source = synthetic_street(rng), "synthetic street (realdata absent)"
        other = synthetic_street(np.random.default_rng(99))
    print(f"data: {source}")

    rows = []
    walls, cpus, base_walls, icp_walls, errors = [], [], [], [], []
    for _ in range(args.pairs):
        yaw = rng.uniform(-180, 180)
        ang, r = rng.uniform(0, 2 * np.pi), rng.uniform(0, 4)
        T = np.eye(4)
        T[:3, :3] = rot_z(yaw)
        T[:3, 3] = (r * math.cos(ang), r * math.sin(ang), rng.uniform(-0.2, 0.2))
        query = query_from(match, T, rng)
        hint = yaw + rng.uniform(-3, 3)
        res = estimate_relative_pose(query, match, hint, config)
        errors.append(pose_error(T, res.T) + (res.accepted,))
        w, c = measure(lambda: estimate_relative_pose(query, match, hint, config), args.repeats)
        walls.append(w)
        cpus.append(c)
        # Baseline: the ICP alone (no phase correlation, one hypothesis), seeded at truth
        # plus the hint's yaw error: less work than the full estimate, so a fair lower bound.
        src = _core.icp_prepare_source(query, _icp_config(config))
        seed = T.copy()
        seed[:3, :3] = rot_z(hint)
        bw, _ = measure(lambda: baseline_icp(src, match, seed, config), 1)
        base_walls.append(bw)
        icp = _icp_config(config)
        cw, _ = measure(lambda: _core.PlaneTarget(match, icp).align(src, seed), args.repeats)
        icp_walls.append(cw)
    err = np.array(errors)
    rows.append(("correct candidate (30k pts)", np.median(walls), np.median(cpus)))
    print(
        f"\ncorrect candidates, {args.pairs} random transforms (yaw +-180, up to 4 m), "
        f"median of {args.repeats} calls each:"
    )
    print(
        f"  estimate_relative_pose  wall {np.median(walls):6.1f} ms  "
        f"cpu {np.median(cpus):6.1f} ms"
        f"  (max of medians: wall {max(walls):.1f} ms)"
    )
    print(
        f"  NumPy/SciPy ICP alone   wall {np.median(base_walls):6.1f} ms"
        f"   -> whole C++ pipeline {np.median(base_walls) / np.median(walls):.1f}x faster"
    )
    print(
        f"  C++ ICP alone (same)    wall {np.median(icp_walls):6.1f} ms"
        f"   -> {np.median(base_walls) / np.median(icp_walls):.1f}x the NumPy/SciPy ICP"
    )
    print(
        f"  errors: translation max {err[:, 0].max():.3f} m, rotation max {err[:, 1].max():.3f} "
        f"deg, accepted {int(err[:, 2].sum())}/{len(err)}"
    )

    if full is not None:
        T = np.eye(4)
        T[:3, :3] = rot_z(130.0)
        T[:3, 3] = (2.0, -3.0, 0.1)
        query = query_from(full, T, rng)
        res = estimate_relative_pose(query, full, 128.0, config)
        w, c = measure(lambda: estimate_relative_pose(query, full, 128.0, config), args.repeats * 3)
        rows.append((f"full KITTI scan ({len(full) // 1000}k pts)", w, c))
        dt, dr = pose_error(T, res.T)
        print(
            f"\nfull KITTI scan ({len(full)} points, query {len(query)}): wall {w:6.1f} ms  "
            f"cpu {c:6.1f} ms; error {dt:.3f} m, {dr:.3f} deg, accepted {res.accepted}"
        )

    w, c = measure(lambda: estimate_relative_pose(match, other, 40.0, config), args.repeats * 3)
    res = estimate_relative_pose(match, other, 40.0, config)
    rows.append(("wrong candidate (30k pts)", w, c))
    print(
        f"\nwrong candidate (KITTI vs elsewhere): wall {w:6.1f} ms  cpu {c:6.1f} ms  "
        f"accepted {res.accepted} ({res.reason})"
    )

    if (SAMPLES / "00" / "poses.txt").is_file():
        from disco_cli.io.poses import read_kitti_poses

        p0 = read_kitti_poses(SAMPLES / "00" / "poses.txt")
        p1 = read_kitti_poses(SAMPLES / "01" / "poses.txt")
        sw, sc, serr = [], [], []
        for i in range(len(p1)):
            for j in range(len(p0)):
                T = np.linalg.inv(p0[j]) @ p1[i]
                yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
                if np.linalg.norm(T[:2, 3]) >= 3.0 or abs(yaw) <= 150:
                    continue
                q = read_bin(SAMPLES / "01" / "velodyne" / f"{i:06d}.bin")
                m = read_bin(SAMPLES / "00" / "velodyne" / f"{j:06d}.bin")
                hint = yaw + rng.uniform(-3, 3)
                res = estimate_relative_pose(q, m, hint, config)
                serr.append(pose_error(T, res.T) + (res.accepted, res.fitness))
                w, c = measure(lambda: estimate_relative_pose(q, m, hint, config), args.repeats)
                sw.append(w)
                sc.append(c)
        if sw:
            e = np.array(serr)
            rows.append(
                (
                    f"simulated reverse revisit (~{len(q) // 1000}k pts)",
                    np.median(sw),
                    np.median(sc),
                )
            )
            print(
                f"\nsimulated reverse-direction revisits (data/samples 01 vs 00, within 3 m, "
                f"|yaw| > 150): {len(sw)} pairs"
            )
            print(
                f"  wall {np.median(sw):6.1f} ms  cpu {np.median(sc):6.1f} ms; errors max "
                f"{e[:, 0].max():.3f} m, {e[:, 1].max():.3f} deg; accepted {int(e[:, 2].sum())}"
                f"/{len(e)}; fitness {e[:, 3].min():.2f}-{e[:, 3].max():.2f}"
            )

    print("\n| case | median wall (ms) | median CPU (ms) |\n| --- | --- | --- |")
    for name, w, c in rows:
        print(f"| {name} | {w:.1f} | {c:.1f} |")


if __name__ == "__main__":
    main()
