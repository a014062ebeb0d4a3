"""Driving sessions through a town: routes, ray casting, noise, and the files they make.

`simulate(out, ...)` writes KITTI-style sessions `out/00`, `out/01`, ... of one
town (scans, poses, times) and `out/world.json` with every parameter, so that the
same call regenerates the same bytes. `scan(world, pose, sensor, ...)` casts one
scan, for tests and experiments.

Ray casting runs in C++ (`disco_cli._core.RaycastWorld`, threads, GIL released);
noise, dropout and intensity are applied here with NumPy, seeded per scan.
"""

from __future__ import annotations

import json
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io.poses import write_kitti_poses, write_times
from disco_cli.simulator.params import ChangeParams
from disco_cli.simulator.robots import RobotParams, draw_robot, jitter_stations
from disco_cli.simulator.routes import (
    RoadGraph,
    lane_path,
    loop_route,
    loop_stations,
    open_stations,
    revisit_route,
    sensor_poses,
)
from disco_cli.simulator.sensors import Sensor, get_sensor
from disco_cli.simulator.world import SessionWorld, Town, TownParams

FORMAT = "disco-simulate/1"


@dataclass
class SimulatedSession:
    name: str
    poses: np.ndarray  # [N, 4, 4] sensor -> world
    times: np.ndarray  # [N] s
    route: list[int]  # junctions driven through
    closed: bool
    offset_m: float  # right of the centre line
    sensor: Sensor | None = None  # None: the one asked for
    mount: tuple[float, float, float] | None = None  # height (m), roll, pitch (deg)


def _scan_seed(seed: int, session: int, frame: int) -> int:
    return int(np.random.SeedSequence([seed, 7, session, frame]).generate_state(1, np.uint64)[0])


def cast(
    world: SessionWorld,
    poses: np.ndarray,
    sensor: Sensor,
    seeds: np.ndarray,
    threads: int = 1,
    poses_end: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw ray casting of `B` scans: ranges `[B, R]` (0: no return), hit ids, |cos incidence|.

    With `poses_end`, the sensor moves from `poses` to `poses_end` during each sweep
    (see `Sensor.fractions`); ranges are then as a raw sensor measures them, each in
    the sensor frame of its own firing time.
    """
    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    seeds = np.ascontiguousarray(seeds, dtype=np.uint64).reshape(-1)
    if poses_end is None:
        return world.caster.cast_scans(poses, sensor.directions(), sensor.max_range, seeds, threads)
    poses_end = np.ascontiguousarray(poses_end, dtype=np.float64).reshape(-1, 4, 4)
    return world.caster.cast_scans(
        poses, sensor.directions(), sensor.max_range, seeds, threads, poses_end, sensor.fractions()
    )


# The fastest a simulated platform drives during one sweep (m/s, about 54 km/h). Scans
# further apart than one sweep at this speed (`--step-m 5` samples a car's places, it
# does not make the car go 50 m/s) are distorted as at this speed.
MAX_SWEEP_SPEED = 15.0


def sweep_poses(poses: np.ndarray, fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Sensor poses at the start and the end of each sweep, `([N, 4, 4], [N, 4, 4])`.

    A scan's pose is the pose half-way through its sweep; the sweep runs from half
    way from the previous scan's pose to half way to the next one (extrapolated at
    the ends of a session), or `fraction` of that around the scan's pose.
    """
    from scipy.spatial.transform import Rotation  # deferred: scipy.spatial costs ~0.4 s

    def blend(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
        out = np.tile(np.eye(4), (len(a), 1, 1))
        rel = Rotation.from_matrix(np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3])
        out[:, :3, :3] = a[:, :3, :3] @ Rotation.from_rotvec(w * rel.as_rotvec()).as_matrix()
        out[:, :3, 3] = a[:, :3, 3] + w * (b[:, :3, 3] - a[:, :3, 3])
        return out

    poses = np.asarray(poses, float)
    if len(poses) < 2:
        return poses.copy(), poses.copy()
    prev = np.concatenate([blend(poses[:1], poses[1:2], -1.0), poses[:-1]])
    nxt = np.concatenate([poses[1:], blend(poses[-1:], poses[-2:-1], -1.0)])
    return blend(poses, prev, 0.5 * fraction), blend(poses, nxt, 0.5 * fraction)


def finish_scan(
    rng: np.random.Generator,
    sensor: Sensor,
    dirs: np.ndarray,
    pose: np.ndarray,
    rng_range: np.ndarray,
    ids: np.ndarray,
    cosi: np.ndarray,
    world: SessionWorld,
    town: Town | None,
) -> np.ndarray:
    """Noise, dropout and intensity for one cast scan: KITTI points `[N, 4]` float32."""
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    hit = (ids != _core.RAYCAST_MISS) & (rng_range >= sensor.min_range)
    r = rng_range[hit].astype(np.float64)
    idx = ids[hit]
    d = dirs[hit].astype(np.float64)
    cos_i = cosi[hit].astype(np.float64)
    refl = np.empty(len(r))
    drop = np.zeros(len(r))
    obj = idx >= 0
    refl[obj] = world.reflectivity[idx[obj]]
    drop[obj] = world.dropout[idx[obj]]
    ground = ~obj
    if ground.any():
        if town is None:
            refl[ground] = 0.15
        else:
            local = d[ground] * r[ground, None]
            xy = local @ pose[:2, :3].T + pose[:2, 3]
            refl[ground] = town.ground_reflectivity(xy)
    # Texture: real surfaces are not uniform.
    refl = np.clip(refl * rng.lognormal(0.0, 0.2, len(r)), 0.0, 1.0)
    # Lost returns: a base rate, the material's own, grazing angles, dark far targets.
    rel = r / sensor.max_range
    p_lost = sensor.dropout + drop + 0.3 * np.clip(0.08 - cos_i, 0, None) / 0.08
    p_lost += 0.6 * rel**3 * (1.0 - refl)
    keep = rng.random(len(r)) >= p_lost
    noisy = r + rng.normal(0.0, sensor.range_noise, len(r)) * (1.0 + rel)
    intensity = refl * (0.55 + 0.45 * cos_i) * (1.0 - 0.3 * rel) + rng.normal(0, 0.01, len(r))
    points = np.empty((int(keep.sum()), 4), np.float32)
    points[:, :3] = d[keep] * noisy[keep, None]
    points[:, 3] = np.clip(intensity[keep], 0.0, 1.0)
    return points


def scan(
    world: SessionWorld,
    pose: np.ndarray,
    sensor: Sensor | str = "hdl32",
    seed: int = 0,
    town: Town | None = None,
    t: float | None = None,
) -> np.ndarray:
    """One simulated scan from sensor pose `pose` (4 x 4, sensor -> world): `[N, 4]` float32.

    With `t`, cars and people are where they are at that time; without, none move.
    """
    sensor = get_sensor(sensor) if isinstance(sensor, str) else sensor
    pose = np.asarray(pose, float)
    if t is not None:
        world = world.at(t, pose[:2, 3])
    ranges, ids, cosi = cast(world, pose, sensor, np.array([seed], np.uint64))
    rng = np.random.default_rng([seed, 11])
    return finish_scan(
        rng, sensor, sensor.directions(), pose, ranges[0], ids[0], cosi[0], world, town
    )


def plan_sessions(
    town: Town,
    sensor: Sensor,
    sessions: int,
    frames: int,
    step_m: float,
    seed: int,
    robot: RobotParams | None = None,
    wobble_deg: float = 0.0,
) -> list[SimulatedSession]:
    """Routes and sensor poses of every session (no ray casting yet).

    Session 00 drives a closed loop a little shorter than the session (so its last
    scans revisit its first ones); the others revisit part of that loop, odd ones in
    the opposite direction, then drive on into other streets. With `robot`, the later
    sessions' robots differ from session 00's (sensor, mount, offset). `wobble_deg`:
    every session's platform rolls and pitches per scan (`wobble`).
    """
    graph = RoadGraph(town)
    target = frames * step_m
    rng = np.random.default_rng([seed, 6])
    base = loop_route(graph, rng, target - max(3 * step_m, 0.1 * target))
    plans = []
    offset0 = 0.0
    for k in range(sessions):
        srng = np.random.default_rng([seed, 8, k])
        offset = float(srng.uniform(0.3, 1.5))
        spec, height, roll, pitch = sensor, sensor.mount_height, 0.0, 0.0
        if k == 0:
            offset0 = offset
        elif robot is not None:
            spec, height, roll, pitch, own = draw_robot(
                robot, seed, k, sensor, offset0, bool(k % 2)
            )
            offset = offset if own is None else own
        if k == 0:
            route, closed = base, True
            line, s = lane_path(town.nodes, route, offset, closed)
            stations, lateral = loop_stations(srng, frames, step_m, float(s[-1]))
        else:
            # Longer than needed: the smoothed line is a little shorter than the route.
            route = revisit_route(graph, srng, base, target * 1.2 + 60, reverse=bool(k % 2))
            closed = False
            line, s = lane_path(town.nodes, route, offset, closed)
            phase = float(srng.uniform(0.2, 0.8)) * step_m + 10.0
            stations, lateral = open_stations(srng, frames, step_m, phase)
            centre = -offset0 if k % 2 else offset0  # session 00's line, seen from here
            stations, lateral = jitter_stations(robot, seed, k, stations, lateral, centre)
        poses = sensor_poses(town, line, s, closed, stations, lateral, height, srng)
        if roll or pitch:  # the mount's tilt, in the car's frame
            from scipy.spatial.transform import Rotation  # deferred: as in sweep_poses

            tilt = Rotation.from_euler("YX", [pitch, roll], degrees=True).as_matrix()
            poses[:, :3, :3] = poses[:, :3, :3] @ tilt
        if wobble_deg:
            poses[:, :3, :3] = poses[:, :3, :3] @ wobble(frames, wobble_deg, [seed, 31, k])
        times = np.arange(frames) / spec.rate_hz
        mount = None if robot is None else (float(height), roll, pitch)
        plans.append(SimulatedSession(f"{k:02d}", poses, times, route, closed, offset, spec, mount))
    return plans


def wobble(frames: int, deg: float, seed: list[int]) -> np.ndarray:
    """[frames, 3, 3]: a wobbling platform's per-scan tilt (roll and pitch, in the car's
    frame), as NCLT's Segway pitches on every start, stop and kerb.

    Roll and pitch each follow a smooth random walk (an AR(1) process, correlation 0.6
    from one scan to the next) scaled so that about 95 % of scans lie within +-deg; they
    are clipped there. Independent draws per scan would make every revisit differ the
    same; a real platform leans the same way for a few scans in a row.
    """
    from scipy.spatial.transform import Rotation  # deferred: as in sweep_poses

    rng = np.random.default_rng(seed)
    rho = 0.6
    angles = np.empty((frames, 2))
    angles[0] = rng.standard_normal(2)
    for i in range(1, frames):
        angles[i] = rho * angles[i - 1] + np.sqrt(1 - rho**2) * rng.standard_normal(2)
    angles = np.clip(angles * (deg / 2.0), -deg, deg)
    return Rotation.from_euler("YX", angles[:, ::-1], degrees=True).as_matrix()


def simulate(
    out: str | Path,
    sessions: int = 2,
    frames: int | None = None,
    length_m: float | None = None,
    step_m: float = 1.0,
    sensor: str = "hdl32",
    seed: int = 0,
    threads: int = 0,
    azimuth_step_deg: float | None = None,
    motion_distortion: bool = False,
    params: TownParams | None = None,
    on_scan: Callable[[int, int], None] | None = None,
    robot: RobotParams | None = None,
    wobble_deg: float = 0.0,
) -> dict:
    """Write `sessions` KITTI-style sessions of one town under `out`; returns world.json's dict.

    Session length: `frames` scans, or `length_m` metres (default 400 m), `step_m` apart.
    `motion_distortion`: scans as a raw sensor gives them, each ray measured from where
    the sensor was when it fired (the pose is that of the forward ray); otherwise every
    ray leaves from the scan's pose, as after deskewing. `on_scan(done, total)` reports
    progress. `params` sets the town (its style, terrain and change model); `robot`, how
    the robots of later sessions differ from session 00's; `wobble_deg`, how far every
    session's platform rolls and pitches from scan to scan (`wobble`).
    """
    if sessions < 1:
        raise DiscoError("--sessions must be at least 1")
    if step_m <= 0:
        raise DiscoError("--step-m must be positive")
    if frames is not None and length_m is not None:
        raise DiscoError("give --frames or --length-m, not both")
    if frames is None:
        frames = int((length_m if length_m is not None else 400.0) / step_m)
    if frames < 1:
        raise DiscoError("a session needs at least one frame")
    if params is not None:
        params.check()
    if robot is not None:
        robot.check()
    if not 0.0 <= wobble_deg <= 10.0:
        raise DiscoError("--wobble must be within 0..10 degrees")
    spec = get_sensor(sensor)
    if azimuth_step_deg is not None:
        if not 0.01 <= azimuth_step_deg <= 5.0:
            raise DiscoError("--azimuth-step must be within 0.01..5 degrees")
        spec = replace(spec, azimuth_step_deg=float(azimuth_step_deg))
    town = Town(seed, params)
    plans = plan_sessions(town, spec, sessions, frames, step_m, seed, robot, wobble_deg)
    for plan in plans:  # every session's sensor, with the azimuth step asked for
        if plan.sensor is None or plan.sensor is spec:
            plan.sensor = spec
        elif azimuth_step_deg is not None:
            plan.sensor = replace(plan.sensor, azimuth_step_deg=float(azimuth_step_deg))

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    total, done = sessions * frames, 0
    workers = threads if threads > 0 else (os.cpu_count() or 1)
    town.ground_reflectivity(np.zeros((1, 2)))  # paint the ground before the workers start
    # Each scan sees the movers at its own time, so each gets its own world (cheap to
    # build); scans are cast in worker threads (C++, GIL released) ahead of NumPy
    # finishing them here, in order.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for k, plan in enumerate(plans):
            world = town.session_world(k)
            psensor = plan.sensor
            dirs = psensor.directions()
            folder = out / plan.name
            (folder / "velodyne").mkdir(parents=True, exist_ok=True)
            fraction = min(1.0, MAX_SWEEP_SPEED / psensor.rate_hz / step_m)
            starts, ends = (
                sweep_poses(plan.poses, fraction) if motion_distortion else (plan.poses, None)
            )

            def submit(
                i: int,
                world: SessionWorld = world,
                k: int = k,
                plan: SimulatedSession = plan,
                starts: np.ndarray = starts,
                ends: np.ndarray | None = ends,
                psensor: Sensor = psensor,
            ) -> tuple[SessionWorld, Future]:
                w = world.at(float(plan.times[i]), plan.poses[i, :2, 3])
                seeds = np.array([_scan_seed(seed, k, i)], np.uint64)
                end = None if ends is None else ends[i]
                return w, pool.submit(cast, w, starts[i], psensor, seeds, 1, end)

            queue = deque(submit(i) for i in range(min(2 * workers, frames)))
            for i in range(frames):
                w, future = queue.popleft()
                if i + len(queue) + 1 < frames:
                    queue.append(submit(i + len(queue) + 1))
                ranges, ids, cosi = future.result()
                rng = np.random.default_rng([seed, 9, k, i])
                pts = finish_scan(
                    rng, psensor, dirs, plan.poses[i], ranges[0], ids[0], cosi[0], w, town
                )
                pts.tofile(folder / "velodyne" / f"{i:06d}.bin")
                done += 1
                if on_scan is not None:
                    on_scan(done, total)
            write_kitti_poses(folder / "poses.txt", plan.poses)
            write_times(folder / "times.txt", plan.times)

    meta = {
        "format": FORMAT,
        "command": _command(
            sessions,
            frames,
            step_m,
            sensor,
            seed,
            azimuth_step_deg,
            motion_distortion,
            params,
            robot,
            wobble_deg,
        ),
        "seed": int(seed),
        "sessions": [_session_meta(p, frames) for p in plans],
        "step_m": step_m,
        "motion_distortion": bool(motion_distortion),
        "rate_hz": spec.rate_hz,
        "sensor": spec.to_dict(),
        "town": town.describe(),
    }
    if robot is not None:
        meta["robot"] = robot.to_dict()
    if wobble_deg:
        meta["wobble_deg"] = float(wobble_deg)
    (out / "world.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def _command(
    sessions: int,
    frames: int,
    step_m: float,
    sensor: str,
    seed: int,
    azimuth_step_deg: float | None,
    motion_distortion: bool,
    params: TownParams | None,
    robot: RobotParams | None,
    wobble_deg: float = 0.0,
) -> str:
    cmd = (
        f"disco simulate OUT --sessions {sessions} --frames {frames} --step-m {step_m:g} "
        f"--sensor {sensor} --seed {seed}"
    )
    if azimuth_step_deg is not None:
        cmd += f" --azimuth-step {azimuth_step_deg:g}"
    params = params or TownParams()
    change = params.change
    plain = replace(params, style="grid", terrain="flat", change=None) == TownParams()
    if plain and (change is None or change == ChangeParams(fraction=change.fraction)):
        if params.style != "grid":
            cmd += f" --style {params.style}"
        if params.terrain != "flat":
            cmd += f" --terrain {params.terrain}"
        if change is not None:
            cmd += f" --change {change.fraction:g}"
    else:  # the town's parameters are in this very file
        cmd += " --town OUT/world.json"
    if robot is not None:
        if robot.height_m is not None:
            cmd += f" --robot-height {robot.height_m[0]:g},{robot.height_m[1]:g}"
        if robot.tilt_deg:
            cmd += f" --robot-tilt {robot.tilt_deg:g}"
        if robot.offset_m is not None:
            cmd += f" --robot-offset {robot.offset_m:g}"
        if robot.sensor is not None:
            cmd += f" --robot-sensor {robot.sensor}"
        if robot.jitter_m:
            cmd += f" --robot-jitter {robot.jitter_m:g}"
        if robot.side_m is not None:
            cmd += f" --robot-side {robot.side_m[0]:g},{robot.side_m[1]:g}"
    if wobble_deg:
        cmd += f" --wobble {wobble_deg:g}"
    return cmd + (" --motion-distortion" if motion_distortion else "")


def _session_meta(plan: SimulatedSession, frames: int) -> dict:
    out = {
        "name": plan.name,
        "frames": frames,
        "closed_loop": plan.closed,
        "offset_right_m": round(plan.offset_m, 4),
        "route_junctions": [int(n) for n in plan.route],
    }
    if plan.mount is not None:  # a robot of its own
        out["sensor"] = plan.sensor.to_dict() if plan.sensor is not None else None
        out["mount_height_m"] = round(plan.mount[0], 4)
        out["mount_roll_deg"] = round(plan.mount[1], 4)
        out["mount_pitch_deg"] = round(plan.mount[2], 4)
    return out
