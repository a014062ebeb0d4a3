"""ROS bags as scan inputs: ROS 1 `.bag`, ROS 2 bag folders (sqlite3 or MCAP) and `.mcap`.

A bag holds many scans, one per sensor_msgs/PointCloud2 message; each is named
`BAG#TOPIC@STAMP_NS` (the bag path as given, the topic, the message's header stamp in
nanoseconds), and that name is what the other commands, the database and
`read_scan` see. Bags are read through the pure-Python `rosbags` package (the
`disco-cli[ros]` extra), imported on first use.

An opened bag stays open for the process, with the index of its topics' stamps once
built, so reading every message of a bag by name is one pass through the bag: a cursor
follows the requests (which arrive in bag order, give or take the few that reading
threads reorder) and keeps the messages it passes over for a moment; a name out of
order seeks.

Poses of a bag's scans can come from its own nav_msgs/Odometry, geometry_msgs/
PoseStamped or PoseWithCovarianceStamped topic (`bag_poses`), associated with each scan
by time.
"""

from __future__ import annotations

import atexit
import os
import struct
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.io.poses import interpolate_poses, quat_to_matrix, read_extrinsic
from disco_cli.io.readers.pointcloud2 import decode_message

__all__ = [
    "POINTCLOUD2",
    "POSE_TYPES",
    "bag_poses",
    "list_messages",
    "message_name",
    "read_message",
    "split_name",
    "topics_of_type",
]

POINTCLOUD2 = "sensor_msgs/PointCloud2"
POSE_TYPES = (
    "nav_msgs/Odometry",
    "geometry_msgs/PoseStamped",
    "geometry_msgs/PoseWithCovarianceStamped",
)
INSTALL_HINT = "reading ROS bags needs the rosbags package: pip install 'disco-cli[ros]'"
# How far a message's log time may lie from its header stamp when a name is read back
# before the bag's index is built (the recorder logs a message just after its stamp).
_LOOK_BEFORE_NS = 1_000_000_000
_LOOK_AFTER_NS = 5_000_000_000
# Messages read past while following the requests, kept for a request that comes late.
_KEEP = 32
# A request at most this many messages ahead of the cursor is read up to, not sought.
_READ_AHEAD = 64


def split_name(name: str) -> tuple[str, str, int] | None:
    """(bag, topic, stamp_ns) of a `BAG#TOPIC@STAMP_NS` name, or None for any other path."""
    left, at, stamp = str(name).rpartition("@")
    if not at or not stamp.isdigit():
        return None
    bag, hash_, topic = left.rpartition("#")
    if not hash_ or not bag or not topic:
        return None
    return bag, topic, int(stamp)


def message_name(bag: str | Path, topic: str, stamp_ns: int) -> str:
    return f"{bag}#{topic}@{int(stamp_ns)}"


def _short_type(msgtype: str) -> str:
    # rosbags names ROS 1 and ROS 2 types alike, `pkg/msg/Name`; users write `pkg/Name`.
    return msgtype.replace("/msg/", "/")


def _header_stamp(raw: bytes | memoryview, ros2: bool) -> int:
    """The header stamp (ns) of a serialized message that starts with std_msgs/Header,
    read from its first bytes without deserializing the rest (the cloud)."""
    if ros2:
        # CDR: a 4-byte encapsulation header (its 2nd byte: 1 little endian, 0 big),
        # then builtin_interfaces/Time: int32 sec, uint32 nanosec.
        order = "<" if raw[1] & 1 else ">"
        sec, nsec = struct.unpack_from(order + "iI", raw, 4)
    else:
        # ROS 1: uint32 seq, then time: uint32 secs, uint32 nsecs.
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


@dataclass
class _Index:
    """One topic's messages in bag order: header stamps and log times (ns)."""

    stamps: list[int]
    logtimes: list[int]
    position: dict[int, int] = field(default_factory=dict)  # stamp -> first message


class _Bag:
    """One open bag: its reader, per-topic indexes and the cursor that serves reads."""

    def __init__(self, path: Path):
        try:
            # deferred: optional extra (pip install 'disco-cli[ros]')
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise ScanReadError(path, INSTALL_HINT) from None
        self.path = path
        self.lock = threading.Lock()
        try:
            # ROS 2 bags before Iron carry no message definitions: the standard ones serve.
            self.reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
            self.reader.open()
        except Exception as exc:  # rosbags raises many kinds for a bad file
            raise ScanReadError(path, f"cannot open as a ROS bag ({_reason(exc)})") from None
        self.ros2 = self.reader.is2
        self.types: dict[str, str] = {}
        self.connections: dict[str, list] = {}
        for c in self.reader.connections:
            self.types.setdefault(c.topic, _short_type(c.msgtype))
            self.connections.setdefault(c.topic, []).append(c)
        self.indexes: dict[str, _Index] = {}
        self._gen: Iterator | None = None
        self._gen_topic: str | None = None
        # Position and log time of the last message the cursor read (None: unknown).
        self._last: int | None = None
        self._last_lt: int | None = None
        self._kept: OrderedDict[tuple[str, int], bytes] = OrderedDict()

    def close(self) -> None:
        self._stop()
        try:
            self.reader.close()
        except Exception:
            pass

    def _stop(self) -> None:
        if self._gen is not None:
            self._gen.close()
        self._gen, self._gen_topic, self._last, self._last_lt = None, None, None, None

    def _check_topic(self, topic: str, kinds: tuple[str, ...]) -> None:
        if topic not in self.types:
            raise ScanReadError(self.path, f"no topic {topic!r} in this bag")
        if self.types[topic] not in kinds:
            raise ScanReadError(
                self.path, f"topic {topic!r} is {self.types[topic]}, not {' or '.join(kinds)}"
            )

    def index(self, topic: str) -> _Index:
        """The stamps of a topic's messages, read once (one pass over that topic)."""
        if topic not in self.indexes:
            self._stop()
            stamps, logtimes = [], []
            try:
                for _, lt, raw in self.reader.messages(connections=self.connections[topic]):
                    stamps.append(_header_stamp(raw, self.ros2))
                    logtimes.append(lt)
            except Exception as exc:
                raise ScanReadError(
                    self.path, f"cannot read topic {topic} ({_reason(exc)})"
                ) from None
            idx = _Index(stamps, logtimes)
            for i, s in enumerate(stamps):
                idx.position.setdefault(s, i)
            self.indexes[topic] = idx
        return self.indexes[topic]

    def _seek(self, topic: str, start_ns: int, position: int | None = None) -> None:
        """Start the cursor at the first message logged at or after `start_ns`
        (`position`: the index of the message before it, when known)."""
        self._stop()
        self._gen = self.reader.messages(
            connections=self.connections[topic], start=max(0, start_ns)
        )
        self._gen_topic, self._last = topic, position

    def _read_until(self, topic: str, stamp: int, stop_ns: int, limit: int) -> bytes | None:
        """Follow the cursor to the message stamped `stamp`, keeping those passed over;
        None when the log time passes `stop_ns`, `limit` messages were read, or the bag
        ends."""
        assert self._gen is not None
        for _ in range(limit):
            try:
                _, lt, raw = next(self._gen)
            except StopIteration:
                self._stop()
                return None
            s = _header_stamp(raw, self.ros2)
            self._last_lt = lt
            if self._last is not None:
                self._last += 1
            if s == stamp:
                return raw
            self._kept[(topic, s)] = raw
            if len(self._kept) > _KEEP:
                self._kept.popitem(last=False)
            if lt > stop_ns:
                return None
        return None

    def raw(self, topic: str, stamp: int) -> bytes:
        """The serialized message of `topic` stamped `stamp`."""
        key = (topic, stamp)
        if key in self._kept:
            return self._kept.pop(key)
        idx = self.indexes.get(topic)
        if idx is None:
            # Not indexed yet: look near the stamp first (log time follows it closely).
            near = (
                self._gen is not None
                and self._gen_topic == topic
                and self._last_lt is not None
                and stamp - _LOOK_BEFORE_NS <= self._last_lt <= stamp
            )
            if not near:
                self._seek(topic, stamp - _LOOK_BEFORE_NS)
            found = self._read_until(topic, stamp, stamp + _LOOK_AFTER_NS, 100_000)
            if found is not None:
                return found
            idx = self.index(topic)
        pos = idx.position.get(stamp)
        if pos is None:
            raise ScanReadError(
                message_name(self.path, topic, stamp), "no message with this header stamp"
            )
        ahead = pos - self._last if self._last is not None else -1
        if not (self._gen is not None and self._gen_topic == topic and 0 < ahead <= _READ_AHEAD):
            # Start at the first message logged at that time.
            lt = idx.logtimes[pos]
            first = pos
            while first > 0 and idx.logtimes[first - 1] == lt:
                first -= 1
            self._seek(topic, lt, first - 1)
            ahead = pos - first + 1
        found = self._read_until(topic, stamp, 2**63 - 1, ahead + _KEEP)
        if found is None:
            raise ScanReadError(
                message_name(self.path, topic, stamp), "the message could not be read back"
            )
        return found

    def deserialize(self, raw: bytes, topic: str) -> Any:
        conn = self.connections[topic][0]
        return self.reader.deserialize(raw, conn.msgtype)


_BAGS: dict[str, _Bag] = {}
_BAGS_LOCK = threading.Lock()


def _open(path: str | Path) -> _Bag:
    """The open bag at `path` (opened on first use, shared by all threads)."""
    key = os.path.realpath(path)
    with _BAGS_LOCK:
        bag = _BAGS.get(key)
        if bag is None:
            if not Path(path).exists():
                raise ScanReadError(path, "no such bag")
            bag = _BAGS[key] = _Bag(Path(path))
        return bag


@atexit.register
def _close_all() -> None:
    with _BAGS_LOCK:
        for bag in _BAGS.values():
            bag.close()
        _BAGS.clear()


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def topics_of_type(path: str | Path, kinds: tuple[str, ...] = (POINTCLOUD2,)) -> list[str]:
    """The topics of a bag whose message type is one of `kinds` (e.g. POSE_TYPES)."""
    bag = _open(path)
    return sorted(t for t, k in bag.types.items() if k in kinds)


def pose_topics(path: str | Path) -> dict[str, str]:
    """{topic: type} of a bag's pose topics (nav_msgs/Odometry, geometry_msgs/PoseStamped,
    ...), for the hint when a bag's scans are read without --pose-topic."""
    bag = _open(path)
    return {t: k for t, k in bag.types.items() if k in POSE_TYPES}


def _choose_topic(path: str | Path, topic: str | None, kinds: tuple[str, ...], flag: str) -> str:
    """`topic` when given (checked), else the bag's only topic of that type."""
    bag = _open(path)
    if topic is not None:
        bag._check_topic(topic, kinds)
        return topic
    found = topics_of_type(path, kinds)
    what = " or ".join(kinds)
    if not found:
        raise ScanReadError(path, f"no {what} topic in this bag")
    if len(found) > 1:
        raise ScanReadError(
            path, f"{len(found)} {what} topics ({', '.join(found)}); choose one with {flag}"
        )
    return found[0]


def list_messages(path: str | Path, topic: str | None = None) -> list[str]:
    """The scan names `BAG#TOPIC@STAMP_NS` of a bag's PointCloud2 messages, in bag order.

    `topic` chooses the PointCloud2 topic; without it the bag must have exactly one
    (`ScanReadError` lists them otherwise). A message stamped like an earlier one of
    its topic cannot be named apart and is left out.
    """
    topic = _choose_topic(path, topic, (POINTCLOUD2,), "--topic")
    bag = _open(path)
    with bag.lock:
        idx = bag.index(topic)
    return [message_name(path, topic, s) for s in idx.position]


def read_message(name: str) -> np.ndarray:
    """The points (float32 N x 4) of the PointCloud2 message named `BAG#TOPIC@STAMP_NS`."""
    parts = split_name(name)
    if parts is None:
        raise ScanReadError(name, "not a bag message name (BAG#TOPIC@STAMP_NS)")
    path, topic, stamp = parts
    bag = _open(path)
    bag._check_topic(topic, (POINTCLOUD2,))
    with bag.lock:
        try:
            raw = bag.raw(topic, stamp)
        except DiscoError:
            raise
        except Exception as exc:
            raise ScanReadError(name, f"cannot read the message ({_reason(exc)})") from None
    # Deserializing and decoding need no lock: reading threads overlap here.
    try:
        msg = bag.deserialize(raw, topic)
    except Exception as exc:
        raise ScanReadError(name, f"cannot deserialize PointCloud2 ({_reason(exc)})") from None
    return decode_message(msg, name)


def _pose_of(msg: Any) -> Any:
    pose = msg.pose
    # Odometry and PoseWithCovarianceStamped nest the pose one level deeper.
    return pose.pose if hasattr(pose, "pose") else pose


def read_pose_topic(path: str | Path, topic: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [M] seconds, poses [M, 4, 4]) of a bag's Odometry / PoseStamped topic.

    Each pose is that of the message's child frame (Odometry) or of the tracked frame
    in `header.frame_id`, stamped with the header stamp. `topic` may be omitted when the
    bag has one such topic.
    """
    topic = _choose_topic(path, topic, POSE_TYPES, "--pose-topic")
    bag = _open(path)
    stamps, rows = [], []
    with bag.lock:
        bag._stop()
        try:
            for _, _, raw in bag.reader.messages(connections=bag.connections[topic]):
                msg = bag.deserialize(raw, topic)
                p = _pose_of(msg)
                st = msg.header.stamp
                stamps.append(st.sec * 1_000_000_000 + st.nanosec)
                q, t = p.orientation, p.position
                rows.append((t.x, t.y, t.z, q.x, q.y, q.z, q.w))
        except Exception as exc:
            raise ScanReadError(path, f"cannot read pose topic {topic} ({_reason(exc)})") from None
    if not rows:
        raise ScanReadError(path, f"pose topic {topic} has no messages")
    table = np.asarray(rows, dtype=np.float64)
    T = np.tile(np.eye(4), (len(table), 1, 1))
    T[:, :3, :3] = quat_to_matrix(table[:, 3:7])
    T[:, :3, 3] = table[:, :3]
    return np.asarray(stamps, dtype=np.float64) * 1e-9, T


def scan_stamps(names: list[str]) -> np.ndarray:
    """The header stamps (s) of scans named `BAG#TOPIC@STAMP_NS` (NaN for other names)."""
    out = np.full(len(names), np.nan)
    for i, n in enumerate(names):
        parts = split_name(n)
        if parts is not None:
            out[i] = parts[2] * 1e-9
    return out


def bag_poses(
    names: list[str],
    pose_topic: str | None,
    max_gap: float | None = None,
    extrinsic: np.ndarray | str | Path | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Poses `[N, 4, 4]` of bag scans from each bag's pose topic, by time (NaN: no pose).

    Each scan takes the pose at its header stamp, interpolated between the two nearest
    pose messages (linear translation, SLERP rotation) when both lie within `max_gap`
    seconds (default: three median pose periods). `extrinsic` (a 4 x 4, or a file of
    one): the LiDAR's pose in the topic's tracked frame, applied after interpolation.
    Returns the poses and the names of the scans left without one. Scans not in a bag
    get no pose.
    """
    E = None
    if extrinsic is not None:
        E = read_extrinsic(extrinsic) if isinstance(extrinsic, (str, Path)) else extrinsic

    out = np.full((len(names), 4, 4), np.nan)
    by_bag: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        parts = split_name(n)
        if parts is not None:
            by_bag.setdefault(parts[0], []).append(i)
    for bag, rows in by_bag.items():
        stamps, T = read_pose_topic(bag, pose_topic)
        times = scan_stamps([names[i] for i in rows])
        poses, found = interpolate_poses(stamps, T, times, max_gap)
        if E is not None:
            poses[found] = poses[found] @ E
        sel = np.asarray(rows)[found]
        out[sel] = poses[found]
    missing = [names[i] for i in range(len(names)) if not np.isfinite(out[i, 0, 0])]
    return out, missing
