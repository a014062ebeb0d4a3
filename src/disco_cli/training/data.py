"""Training data: BEVs precomputed once, positions and headings, and pair mining.

Sequences are KITTI-style folders (`velodyne/` + `poses.txt`, optional `calib.txt`), as
`disco simulate` writes them. Sequences in the same parent folder are sessions of one
world and share its frame, so positives are mined across them; scans of different worlds
are always negatives of each other.

A session may also be given as `PosedScans`: explicit scan files with their poses (a
dataset split that is not a whole folder, e.g. PointNetVLAD's Oxford training submaps).

Every scan is voxelized once, up front, with `polar_bev_batch`, and kept in memory as
uint8 (occupancy, counts) so that training is bound by the network, not by I/O.

Self-supervised mode (no poses): the positive of a scan is a copy of it rotated by a
random yaw, shifted by up to a few metres, thinned and noised; negatives are scans of
the same sequence far apart in time.

With poses, `variants=N` adds N augmented copies of every scan (`augment.augment_scan`:
fewer beams, fewer points, a wedge occluded, tilted, shifted in z), made from its points
at load time. A copy keeps the scan's pose and points back to it through `source`; it is
never a query, a positive or a negative itself, but the training loop shows it in place
of its scan now and then (`TrainOptions.augment_p`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, PoseFileError
from disco_cli.io.poses import find_pose_file, poses_for_scans, xy_yaw
from disco_cli.io.poses.geometry import keep_by_spacing
from disco_cli.io.readers import is_bag, list_scans, read_scan
from disco_cli.io.readers.bags import bag_poses
from disco_cli.model.bev import polar_bev_batch
from disco_cli.runtime.threads import get_threads
from disco_cli.training.augment import AugmentConfig, augment_scan

# Scans voxelized per call: bounds the memory held by raw point clouds.
_CHUNK = 64


@dataclass
class TrainData:
    """All scans of a training run, one row each."""

    bevs: np.ndarray  # [N, H, R, S] uint8 or float16
    xy: np.ndarray  # [N, 2] metres in the world of `group`
    heading_deg: np.ndarray  # [N] sensor yaw in the world
    group: np.ndarray  # [N] world id (sessions of one world share it)
    session: np.ndarray  # [N] sequence id
    frame: np.ndarray  # [N] index of the scan in its sequence
    source: np.ndarray  # [N] row of the original scan (itself, or the one a copy was made of)
    sessions: list[str] = field(default_factory=list)
    anchors: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.bevs)

    @property
    def sectors(self) -> int:
        return int(self.bevs.shape[-1])

    def float_bevs(self, idx: np.ndarray) -> np.ndarray:
        return self.bevs[idx].astype(np.float32)

    def variant_table(self) -> np.ndarray:
        """[N, V] rows of each row's augmented copies (`variants`), -1 where it has fewer."""
        rows = np.arange(len(self))
        copies = rows[self.source != rows]
        if self.anchors.size == 0 or len(copies) == 0:
            return np.full((len(self), 0), -1, np.int64)
        counts = np.bincount(self.source[copies], minlength=len(self))
        table = np.full((len(self), int(counts.max())), -1, np.int64)
        fill = np.zeros(len(self), np.int64)
        for c in copies:
            s = self.source[c]
            table[s, fill[s]] = c
            fill[s] += 1
        return table


@dataclass
class PosedScans:
    """A session given as its scans and their LiDAR poses `[N, 4, 4]`. Sessions with the
    same `world` share a frame (positives are mined across them); `format` is the scan
    format for `read_scan` (None: from the file)."""

    name: str
    scans: list[Path]
    poses: np.ndarray
    world: str
    format: str | None = None


def _is_session(folder: Path) -> bool:
    """A dataset session folder: a pose file beside scans (NCLT velodyne_sync/, MulRan
    sensor_data/Ouster/, ...)."""
    try:
        return find_pose_file(folder) is not None and bool(list_scans(folder))
    except DiscoError:
        return False


def expand_sequences(paths: list[Path | PosedScans]) -> list[Path | PosedScans]:
    """Sequence folders: each path itself if it holds velodyne/ (or is a ROS bag), else its
    subfolders that do (and the bags in it); a `PosedScans` stays as it is."""
    out: list[Path | PosedScans] = []
    for p in paths:
        if isinstance(p, PosedScans):
            out.append(p)
            continue
        p = Path(p)
        if is_bag(p):
            out.append(p)
            continue
        if not p.is_dir():
            raise DiscoError(f"{p}: not a folder")
        if (p / "velodyne").is_dir() or _is_session(p):
            out.append(p)
            continue
        subs = sorted(
            d
            for d in p.iterdir()
            if is_bag(d) or (d.is_dir() and ((d / "velodyne").is_dir() or _is_session(d)))
        )
        if not subs:
            raise DiscoError(f"{p}: no velodyne/ folder in it or in its subfolders")
        out.extend(subs)
    return out


def _compact(bevs: np.ndarray) -> np.ndarray:
    """uint8 when the BEV values are small integers (occupancy, counts), else float16."""
    if bevs.size and bevs.min() >= 0 and bevs.max() <= 255 and np.all(bevs == np.round(bevs)):
        return bevs.astype(np.uint8)
    return bevs.astype(np.float16)


def _read_poses(seq: Path, scans: list[Path]) -> np.ndarray:
    """LiDAR poses `[N, 4, 4]` of a sequence's scans from the pose file beside them
    (`disco_cli.io.poses.poses_for_scans`; NaN for a scan without a pose, named in one warning)."""
    poses_file = find_pose_file(seq)
    if poses_file is None:
        raise PoseFileError(
            f"{seq / 'poses.txt'}: missing (train with --self-supervised for data without poses)"
        )
    T, report = poses_for_scans(scans, poses_file)
    if report.warning():
        # deferred: the CLI's console (typer, rich); the library imports without them
        from disco_cli.runtime.console import warn

        warn(report.warning())
    return T


def augment_points(
    points: np.ndarray,
    rng: np.random.Generator,
    yaw_deg: float,
    max_shift: float,
    keep: float,
    noise: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A scan seen from a nearby pose: rotated by yaw_deg (points R(a) p), shifted, thinned, noised.

    Returns the points and the xy offset of the new sensor origin in the old frame.
    """
    a = np.radians(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    offset = rng.uniform(-max_shift, max_shift, size=2)
    sel = rng.random(len(points)) < keep
    pts = points[sel].astype(np.float32, copy=True)
    # Move the sensor to `offset` (points shift by -offset), then rotate by a.
    x = pts[:, 0] - offset[0]
    y = pts[:, 1] - offset[1]
    pts[:, 0] = c * x - s * y
    pts[:, 1] = s * x + c * y
    pts[:, :3] += rng.normal(0.0, noise, size=(len(pts), 3)).astype(np.float32)
    return pts, offset


def load_training_data(
    paths: list[Path | PosedScans],
    bev_config: Any,
    self_supervised: bool = False,
    spacing: float = 0.0,
    copies: int = 2,
    max_shift: float = 2.0,
    seed: int = 0,
    threads: int | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    topic: str | None = None,
    pose_topic: str | None = None,
    variants: int = 0,
    augment: AugmentConfig | None = None,
) -> TrainData:
    """Read, voxelize and index every sequence (see the module docstring).

    A ROS bag is a sequence of its `topic`'s scans, posed from its `pose_topic` (scans
    without a pose near their stamp are left out)."""
    threads = get_threads() if threads is None else threads  # the voxelizer's threads

    seqs = expand_sequences(paths)
    rng = np.random.default_rng(seed)
    # Its own stream, so that adding variants leaves everything else as it was.
    aug_rng = np.random.default_rng([seed, 1])
    variants = 0 if self_supervised else variants
    plan: list[tuple[int, int, str | None, list[Path], np.ndarray, np.ndarray]] = []
    groups: dict[str, int] = {}
    for sid, seq in enumerate(seqs):
        fmt = seq.format if isinstance(seq, PosedScans) else None
        scans = list(seq.scans) if isinstance(seq, PosedScans) else list_scans(seq, topic=topic)
        if not scans:
            raise DiscoError(f"{seq}: no scans")
        if isinstance(seq, PosedScans) and not self_supervised:
            x, y, yaw = xy_yaw(np.asarray(seq.poses))
            xy = np.stack([x, y], axis=1)
            heading = np.degrees(yaw)
            gid = groups.setdefault(seq.world, len(groups))
        elif not self_supervised and is_bag(seq):
            if pose_topic is None:
                raise PoseFileError(
                    f"{seq}: a bag's poses come from --pose-topic (or train with --self-supervised)"
                )
            poses, _ = bag_poses([str(s) for s in scans], pose_topic)
            posed = np.isfinite(poses[:, 0, 0])
            scans = [s for s, ok in zip(scans, posed) if ok]
            if not scans:
                raise PoseFileError(f"{seq}: no scan has a pose on {pose_topic}")
            x, y, yaw = xy_yaw(poses[posed])
            xy = np.stack([x, y], axis=1)
            heading = np.degrees(yaw)
            gid = groups.setdefault(str(seq.resolve().parent), len(groups))
        elif self_supervised:
            xy = np.zeros((len(scans), 2))
            heading = np.zeros(len(scans))
            gid = len(groups)
            groups[str(seq)] = gid
        else:
            poses = _read_poses(seq, scans)
            has = np.isfinite(poses[:, 0, 3])
            scans, poses = [s for s, h in zip(scans, has) if h], poses[has]
            if not scans:
                raise PoseFileError(f"{seq}: no scan has a pose")
            x, y, yaw = xy_yaw(poses)
            xy = np.stack([x, y], axis=1)
            heading = np.degrees(yaw)
            gid = groups.setdefault(str(seq.resolve().parent), len(groups))
        keep = keep_by_spacing(xy, spacing) if not self_supervised else np.arange(len(scans))
        plan.append((sid, gid, fmt, [scans[i] for i in keep], xy[keep], heading[keep]))

    total = sum(len(p[3]) for p in plan) * (1 + (copies if self_supervised else variants))
    done = 0
    bevs, xys, heads, grp, sess, frm, src = [], [], [], [], [], [], []
    row = 0
    for sid, gid, fmt, scans, xy, heading in plan:
        for start in range(0, len(scans), _CHUNK):
            batch = scans[start : start + _CHUNK]
            clouds = [read_scan(p, fmt) for p in batch]
            n = len(clouds)
            rows = np.arange(row, row + n)
            meta_xy = [xy[start : start + n]]
            meta_head = [heading[start : start + n]]
            meta_src = [rows]
            if self_supervised:
                extra = []
                for _ in range(copies):
                    for i, pts in enumerate(clouds):
                        a = rng.uniform(-180.0, 180.0)
                        keep = rng.uniform(0.5, 0.9)
                        aug, off = augment_points(pts, rng, a, max_shift, keep, 0.03)
                        extra.append(aug)
                        meta_xy.append(off[None])
                        # Points turned by +a: the sensor is turned by -a.
                        meta_head.append(np.array([-a]))
                        meta_src.append(rows[i : i + 1])
                clouds = clouds + extra
            if variants:
                extra = []
                for _ in range(variants):
                    for i, pts in enumerate(clouds[:n]):
                        extra.append(augment_scan(pts, aug_rng, augment))
                        meta_xy.append(xy[start + i : start + i + 1])
                        meta_head.append(heading[start + i : start + i + 1])
                        meta_src.append(rows[i : i + 1])
                clouds = clouds + extra
            vox = polar_bev_batch(clouds, bev_config, threads=threads)
            m = len(clouds)
            bevs.append(_compact(np.asarray(vox)))
            xys.append(np.concatenate(meta_xy))
            heads.append(np.concatenate(meta_head))
            grp.append(np.full(m, gid))
            sess.append(np.full(m, sid))
            frames = np.arange(start, start + n)
            frm.append(np.tile(frames, m // n))
            src.append(np.concatenate(meta_src))
            row += m
            done += m
            if on_progress:
                on_progress(done, total)
    data = TrainData(
        bevs=np.concatenate(bevs),
        xy=np.concatenate(xys).astype(np.float64),
        heading_deg=np.concatenate(heads).astype(np.float64),
        group=np.concatenate(grp),
        session=np.concatenate(sess),
        frame=np.concatenate(frm),
        source=np.concatenate(src),
        sessions=[s.name if isinstance(s, PosedScans) else str(s) for s in seqs],
    )
    # Anchors: original scans (copies are positives only).
    data.anchors = np.flatnonzero(data.source == np.arange(len(data)))
    return data
