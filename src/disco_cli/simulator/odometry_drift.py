"""Drifted odometry: what a LiDAR or wheel odometry would report along true poses.

`drift_odometry(poses, ...)` chains the true poses' relative motions, each with the
errors an odometry makes: a scale error on the distance driven, a yaw bias per step
(the slow turn of a gyro's bias or of an uneven tyre), and white noise on translation
and yaw. The result starts at the first true pose, so a trajectory with no error at
all is the truth itself. `disco simulate --odometry-drift` writes it as
`odometry.txt` beside `poses.txt`; `disco correct` takes it back out of the drift.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io.poses import read_kitti_poses, read_times, write_kitti_poses, write_times

__all__ = ["Drift", "drift_odometry", "write_odometry"]


@dataclass(frozen=True)
class Drift:
    """The errors of one odometry. `scale`: relative error of every step's length
    (0.02: 2 % too long); `yaw_bias_deg`: degrees of yaw added to every step;
    `noise_m`, `noise_deg`: standard deviations of the white noise on each step's
    translation (per axis, x and y) and yaw; `seed`: the noise's."""

    scale: float = 0.02
    yaw_bias_deg: float = 0.04
    noise_m: float = 0.01
    noise_deg: float = 0.02
    seed: int = 0

    def check(self) -> None:
        if not -0.5 < self.scale < 0.5:
            raise DiscoError(f"odometry scale error must be within (-0.5, 0.5), not {self.scale}")
        if not abs(self.yaw_bias_deg) <= 5.0:
            raise DiscoError(
                f"odometry yaw bias must be within +-5 degrees a step, not {self.yaw_bias_deg}"
            )
        if not (0.0 <= self.noise_m <= 1.0 and 0.0 <= self.noise_deg <= 5.0):
            raise DiscoError("odometry noise must be within 0..1 m and 0..5 degrees a step")

    @classmethod
    def parse(cls, text: str, seed: int = 0) -> Drift:
        """`SCALE,YAW_BIAS_DEG[,NOISE_M[,NOISE_DEG]]` (`0.02,0.04,0.01,0.02`)."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise DiscoError(f"{text!r} is not SCALE,YAW_BIAS_DEG[,NOISE_M[,NOISE_DEG]]") from None
        if not 2 <= len(values) <= 4 or not np.all(np.isfinite(values)):
            raise DiscoError(f"{text!r} is not SCALE,YAW_BIAS_DEG[,NOISE_M[,NOISE_DEG]]")
        fields = dict(zip(("scale", "yaw_bias_deg", "noise_m", "noise_deg"), values))
        drift = cls(**fields, seed=seed)
        drift.check()
        return drift

    def spec(self) -> str:
        return f"{self.scale:g},{self.yaw_bias_deg:g},{self.noise_m:g},{self.noise_deg:g}"


def _rz(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def drift_odometry(poses: np.ndarray, drift: Drift | None = None) -> np.ndarray:
    """Odometry `[N, 4, 4]` along true poses `[N, 4, 4]` (sensor in the world) with
    `drift`'s errors on each step's relative motion; it starts at `poses[0]`."""
    drift = drift or Drift()
    drift.check()
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    if n == 0:
        return poses.copy()
    rng = np.random.default_rng([drift.seed, 41])
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]  # T_i<-i+1, the true steps
    steps = rel.copy()
    steps[:, :3, 3] *= 1.0 + drift.scale
    steps[:, :2, 3] += rng.normal(0.0, drift.noise_m, (n - 1, 2))
    yaw = np.radians(drift.yaw_bias_deg + rng.normal(0.0, drift.noise_deg, n - 1))
    steps[:, :3, :3] = _rz(yaw) @ steps[:, :3, :3]  # turned a little more at each step
    out = np.empty_like(poses)
    out[0] = poses[0]
    for i in range(n - 1):
        out[i + 1] = out[i] @ steps[i]
    return out


def write_odometry(out: str | Path, drift: Drift, join: bool = False) -> list[Path]:
    """After `simulate(out, ...)`: `odometry.txt` (KITTI lines, drifted by `drift`) beside
    each session's `poses.txt`; with `join`, also `out/joined`, every session one after
    the other as one sequence (its scans linked, or copied where links cannot be made,
    with `poses.txt`, `times.txt` and its own drifted `odometry.txt`), as a map session
    followed by a revisiting one. Session k's noise is seeded by `drift.seed` and k.
    Returns the odometry files written; world.json records the drift."""
    out = Path(out)
    meta_path = out / "world.json"
    meta = json.loads(meta_path.read_text())
    names = [s["name"] for s in meta["sessions"]]
    written = []
    for k, name in enumerate(names):
        folder = out / name
        truth = read_kitti_poses(folder / "poses.txt")
        odo = drift_odometry(truth, replace(drift, seed=drift.seed * 100 + k))
        write_kitti_poses(folder / "odometry.txt", odo)
        written.append(folder / "odometry.txt")
    if join:
        written.append(_join(out, names, replace(drift, seed=drift.seed * 100 + 99)))
    meta["odometry_drift"] = {**asdict(drift), "joined": bool(join)}
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return written


def _join(out: Path, names: list[str], drift: Drift) -> Path:
    joined = out / "joined"
    if joined.exists():
        shutil.rmtree(joined)
    (joined / "velodyne").mkdir(parents=True)
    poses, times, i = [], [], 0
    for name in names:
        folder = out / name
        scans = sorted((folder / "velodyne").glob("*.bin"))
        for scan in scans:
            target = joined / "velodyne" / f"{i:06d}.bin"
            try:
                os.link(scan, target)
            except OSError:
                shutil.copyfile(scan, target)
            i += 1
        poses.append(read_kitti_poses(folder / "poses.txt"))
        t = read_times(folder / "times.txt")
        start = times[-1][-1] + (t[1] - t[0] if len(t) > 1 else 0.1) if times else 0.0
        times.append(t - t[0] + start)
    truth = np.concatenate(poses)
    write_kitti_poses(joined / "poses.txt", truth)
    write_times(joined / "times.txt", np.concatenate(times))
    write_kitti_poses(joined / "odometry.txt", drift_odometry(truth, drift))
    return joined / "odometry.txt"
