"""Poses: pose files of several datasets, time interpolation, x/y/yaw helpers, revisits.

A pose is the 4 x 4 transform of a sensor into the world frame (`T_world<-sensor`).
One module per pose file format (`kitti`, `tum`, `nclt`, `mulran`, `oxford`,
`kitti360`); `scans.poses_for_scans` gives scans their LiDAR poses from any of them
(by frame number or by time), `interpolate.interpolate_poses` does the time part.

Yaw convention (docs/architecture.md): the relative yaw of a query to a match is the
yaw of `T_match^-1 @ T_query`, i.e. the heading of the query sensor in the match's
frame, wrapped to (-180, 180] degrees.
"""

from __future__ import annotations

from disco_cli.io.poses.geometry import (
    inverse,
    matrix_to_quat,
    pose_rows,
    quat_to_matrix,
    relative_yaw_deg,
    rpy_to_matrix,
    wrap_deg,
    xy_yaw,
    xyzrpy_to_4x4,
)
from disco_cli.io.poses.interpolate import default_max_gap, interpolate_poses, slerp
from disco_cli.io.poses.kitti import (
    read_calib_tr,
    read_kitti_poses,
    read_times,
    write_kitti_poses,
    write_times,
)
from disco_cli.io.poses.revisits import (
    gt_pairs,
    gt_pairs_within,
    nearest_distance,
    pair_distances,
    revisit_pairs,
)
from disco_cli.io.poses.scans import (
    POSE_FORMATS,
    PoseReport,
    ScanPoser,
    calib_arg,
    find_pose_file,
    guess_poses_format,
    poses_for_scans,
    read_extrinsic,
    read_poses,
    scan_times,
)

__all__ = [
    "POSE_FORMATS",
    "PoseReport",
    "ScanPoser",
    "calib_arg",
    "default_max_gap",
    "find_pose_file",
    "gt_pairs",
    "gt_pairs_within",
    "guess_poses_format",
    "interpolate_poses",
    "inverse",
    "matrix_to_quat",
    "nearest_distance",
    "pair_distances",
    "revisit_pairs",
    "pose_rows",
    "poses_for_scans",
    "quat_to_matrix",
    "read_calib_tr",
    "read_extrinsic",
    "read_kitti_poses",
    "read_poses",
    "read_times",
    "relative_yaw_deg",
    "rpy_to_matrix",
    "scan_times",
    "slerp",
    "wrap_deg",
    "write_kitti_poses",
    "write_times",
    "xy_yaw",
    "xyzrpy_to_4x4",
]
