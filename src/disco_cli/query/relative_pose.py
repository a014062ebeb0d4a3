"""Full relative pose between a query scan and its place match, and loop verification.

The place-recognition step gives the yaw (the heading of the query sensor in the
match's frame, at the model's ~3 degree resolution). Here:

1. the translation (dx, dy) comes from phase correlation of the two scans'
   Cartesian bird's-eye height images, the query's turned by the yaw first;
2. point-to-plane ICP in the compiled core refines (yaw, dx, dy) into the full
   T_match<-query in SE(3) and scores it (fitness: inlier ratio, rmse);
3. yaw and yaw + 180 degrees (the classic ambiguity of corridors and of streets
   that look alike both ways) each get step 1 and a short coarse ICP stage; the
   one with the better fitness goes on to the fine stages;
4. the loop is accepted when fitness and rmse pass the `PoseConfig` thresholds.

See docs/relative_pose.md for the method, the thresholds and how they were chosen.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io.poses.geometry import wrap_deg


class PoseError(DiscoError):
    """Points or settings given to the relative-pose estimator are unusable."""


@dataclass
class PoseConfig:
    """Settings of the relative-pose estimator and the loop-verification thresholds."""

    # Phase correlation of Cartesian height images (seeds the translation).
    bev_cell: float = 0.4  # m per cell
    bev_extent: float = 40.0  # half width of the image (m)
    max_translation: float = 15.0  # ignore correlation peaks farther than this (m)
    try_flipped_yaw: bool = True  # also try yaw + 180 degrees
    # ICP (point-to-plane, coarse to fine).
    source_voxel: float = 1.0  # query downsampling (m)
    target_voxel: float = 0.5  # match downsampling (m)
    max_range: float = 60.0  # points farther from the sensor are left out (m)
    normal_radius: float = 1.0  # cell edge for the match's normals (m)
    stages: tuple[float, ...] = (2.0, 1.0, 0.5)  # correspondence distance per stage (m)
    max_iterations: int = 15  # per stage
    hypothesis_iterations: int = 8  # coarse-stage iterations to judge each yaw hypothesis
    inlier_distance: float = 0.5  # a query point within this of the match is an inlier (m)
    # Verification.
    min_fitness: float = 0.35  # inlier ratio over non-ground query points
    max_rmse: float = 0.3  # m, point-to-plane, over the inliers
    min_points: int = 100  # fewer downsampled points than this: rejected
    # Reject without the fine stages when the best coarse fitness is below this: a
    # wrong place never gets there, and refining it would cost most of the time.
    early_reject_fitness: float = 0.15

    def __post_init__(self) -> None:
        positive = (
            "bev_cell",
            "bev_extent",
            "max_translation",
            "source_voxel",
            "target_voxel",
            "normal_radius",
            "inlier_distance",
            "max_rmse",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise PoseError(f"pose config: {name} must be a positive number, not {value!r}")
        self.stages = tuple(float(s) for s in self.stages)
        if not self.stages or any(not (math.isfinite(s) and s > 0) for s in self.stages):
            raise PoseError(f"pose config: stages must be positive distances, not {self.stages}")
        if min(self.max_iterations, self.hypothesis_iterations, self.min_points) < 1:
            raise PoseError(
                "pose config: max_iterations, hypothesis_iterations and min_points must be >= 1"
            )
        for name in ("min_fitness", "early_reject_fitness"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise PoseError(f"pose config: {name} must lie in [0, 1], not {value}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["stages"] = list(self.stages)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PoseConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise PoseError(f"pose config: unknown key(s) {', '.join(unknown)}")
        return cls(**d)


@dataclass(frozen=True, eq=False)  # eq would compare the arrays ambiguously
class RelativePose:
    """T_match<-query and its verification. `yaw_deg` is the yaw of T, in (-180, 180]."""

    T: np.ndarray = field(repr=False)  # 4 x 4 float64
    dx: float
    dy: float
    dz: float
    yaw_deg: float
    fitness: float  # inlier ratio over the query points not on ground-like surfaces
    rmse: float  # m, point-to-plane, over the inliers
    accepted: bool
    reason: str  # why rejected; "" when accepted


def _as_points(points: Any, what: str) -> np.ndarray:
    """A float32 N x C (C >= 3) view of the points, copied only when it must be."""
    try:
        arr = np.asarray(points, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise PoseError(f"{what} points: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise PoseError(f"{what} points: expected an N x 3 or N x 4 array, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise PoseError(f"{what} points: the scan is empty")
    if any(s < 0 or s % arr.itemsize for s in arr.strides):
        arr = np.ascontiguousarray(arr)
    return arr


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@functools.lru_cache(maxsize=4)
def _hann(n: int) -> np.ndarray:
    """The 2D Hann window (float32 values, as float64), made once per size."""
    w = 0.5 - 0.5 * np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n)
    out = np.outer(w, w).astype(np.float32).astype(np.float64)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=8)
def _reach(n: int, cell: float, max_shift: float) -> np.ndarray:
    """[n, n]: the correlation cells within `max_shift` (indices wrap: k and k - n are
    the same shift)."""
    k = np.fft.fftfreq(n, d=1.0 / n)
    near = np.abs(k) * cell <= max_shift
    out = near[:, None] & near[None, :]
    out.flags.writeable = False
    return out


def _peak_offset(c: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Sub-cell peak position from a parabola through the peak and its neighbours."""
    n0, n1 = c.shape

    def vertex(lo: float, mid: float, hi: float) -> float:
        den = lo - 2.0 * mid + hi
        return 0.0 if den >= 0 else float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5))

    di = vertex(c[(i - 1) % n0, j], c[i, j], c[(i + 1) % n0, j])
    dj = vertex(c[i, (j - 1) % n1], c[i, j], c[i, (j + 1) % n1])
    return i + di, j + dj


def phase_correlation_shift(
    match_image: np.ndarray, query_image: np.ndarray, cell: float, max_shift: float
) -> tuple[float, float]:
    """Translation (x, y) in m that moves the query image onto the match image.

    Normalised cross-power spectrum with a Hann window; the peak is searched within
    `max_shift` and refined to sub-cell precision.
    """
    fm, fq = _spectrum(match_image), _spectrum(query_image)
    x, y, _ = _peak(fm, fq, match_image.shape, cell, max_shift)
    return x, y


def _spectrum(image: np.ndarray) -> np.ndarray:
    """The windowed image's real 2D spectrum."""
    return np.fft.rfft2(image * _hann(image.shape[0]))


def _peak(
    fm: np.ndarray, fq: np.ndarray, shape: tuple[int, ...], cell: float, max_shift: float
) -> tuple[float, float, float]:
    """`phase_correlation_shift`'s (x, y) from two spectra (`_spectrum`), and the
    peak's height: the phase-only correlation at the shift, near 1 where one image is
    the other moved, near 0 (the noise floor of a few hundredths) where they share no
    structure."""
    n = shape[0]
    cross = fm * np.conj(fq)
    mag = np.abs(cross)
    if not mag.max() > 0.0:
        return 0.0, 0.0, 0.0  # an image without structure: nothing to correlate
    # Whiten, but do not blow up the frequencies where either image has no energy.
    cross /= np.maximum(mag, 1e-6 * mag.max())
    corr = np.fft.irfft2(cross, s=shape)
    # Keep shifts within max_shift.
    masked = np.where(_reach(n, float(cell), float(max_shift)), corr, -np.inf)
    i, j = np.unravel_index(int(np.argmax(masked)), masked.shape)
    fi, fj = _peak_offset(corr, int(i), int(j))
    si = fi - n if fi > n / 2 else fi
    sj = fj - n if fj > n / 2 else fj
    return si * cell, sj * cell, float(masked[i, j])


@dataclass(frozen=True)
class LayoutCheck:
    """The cheap geometric check of a candidate: the query's and the match's Cartesian
    height images (the query turned by the yaw, or the yaw + 180 degrees where that
    correlates better) phase-correlated. `peak`: the phase-only correlation's peak;
    `shift_m`: how far the query sensor stands from the match's by it."""

    peak: float
    shift_m: float
    flipped: bool


def layout_check(
    query_points: Any, match_points: Any, yaw_deg: float, config: PoseConfig | None = None
) -> LayoutCheck:
    """Phase correlation of the two scans' height images at the recognised yaw (and the
    yaw + 180 degrees with `try_flipped_yaw`): a few milliseconds, against tens for the
    ICP of `estimate_relative_pose`."""
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    config = config or PoseConfig()
    query = _as_points(query_points, "query")
    match = _as_points(match_points, "match")
    match_image = _core.height_image(match, 0.0, config.bev_cell, config.bev_extent)
    fm = _spectrum(match_image)
    yaw = math.radians(float(yaw_deg))
    fq = _spectrum(_core.height_image(query, yaw, config.bev_cell, config.bev_extent))
    best = None
    for flipped in (False, True) if config.try_flipped_yaw else (False,):
        # The image a half turn on is this one turned about its centre (the grid is
        # symmetric about the sensor, and so is the window), so its spectrum follows
        # from this one's: a third of the check's cost saved.
        spectrum = _turned_spectrum(fq, match_image.shape) if flipped else fq
        x, y, peak = _peak(fm, spectrum, match_image.shape, config.bev_cell, config.max_translation)
        if best is None or peak > best.peak:
            best = LayoutCheck(peak, math.hypot(x, y), flipped)
    assert best is not None
    return best


def _turned_spectrum(spectrum: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """`_spectrum` of a real image [N0, N1] turned by a half turn (img[::-1, ::-1]), from
    the image's own (`rfft2` layout): for g[n] = f[N - 1 - n] along an axis,
    G[k] = exp(2 pi i k / N) conj(F[k])."""
    return _half_turn_ramp(*shape) * np.conj(spectrum)


@functools.lru_cache(maxsize=4)
def _half_turn_ramp(n0: int, n1: int) -> np.ndarray:
    """exp(2 pi i (k0 / N0 + k1 / N1)) over an `rfft2` spectrum's [N0, N1 // 2 + 1]."""
    k0 = np.fft.fftfreq(n0, d=1.0 / n0)[:, None]
    k1 = np.arange(n1 // 2 + 1)[None, :]
    out = np.exp(2j * np.pi * (k0 / n0 + k1 / n1))
    out.flags.writeable = False
    return out


def _icp_config(config: PoseConfig) -> Any:
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    c = _core.IcpConfig()
    c.source_voxel = config.source_voxel
    c.target_voxel = config.target_voxel
    c.max_range = config.max_range
    c.normal_radius = config.normal_radius
    c.stages = list(config.stages)
    c.max_iterations = config.max_iterations
    c.inlier_distance = config.inlier_distance
    return c


def estimate_relative_pose(
    query_points: Any, match_points: Any, yaw_deg: float, config: PoseConfig | None = None
) -> RelativePose:
    """T_match<-query for a query scan and its match, seeded by the recognised yaw.

    `query_points`, `match_points`: N x 3 or N x 4 arrays (x, y, z first; float32
    passes without a copy). `yaw_deg`: yaw of T_match<-query from place recognition.
    Non-finite points are ignored. The result says whether the loop is accepted.
    """
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    config = config or PoseConfig()
    query = _as_points(query_points, "query")
    match = _as_points(match_points, "match")
    try:
        yaw0 = float(yaw_deg)
    except (TypeError, ValueError):
        raise PoseError(f"yaw_deg must be a number, not {yaw_deg!r}") from None
    if not math.isfinite(yaw0):
        raise PoseError(f"yaw_deg must be finite, not {yaw_deg!r}")

    icp = _icp_config(config)
    target = _core.PlaneTarget(match, icp)
    source = _core.icp_prepare_source(query, icp)
    if len(source) < config.min_points or len(target.points) < config.min_points:
        T = np.eye(4)
        T[:3, :3] = _rot_z(math.radians(yaw0))
        return _result(T, 0.0, math.nan, config, too_few=(len(source), len(target.points)))

    match_image = _core.height_image(match, 0.0, config.bev_cell, config.bev_extent)
    hypotheses = [yaw0, yaw0 + 180.0] if config.try_flipped_yaw else [yaw0]
    # Each hypothesis gets only a short coarse stage on every other query point; the
    # better one goes on to the fine stages with all points. A wrong seed never
    # converges, so running it to the end would be wasted time.
    sparse_source = np.ascontiguousarray(source[::2])
    best = None
    for yaw in hypotheses:
        yaw_rad = math.radians(yaw)
        query_image = _core.height_image(query, yaw_rad, config.bev_cell, config.bev_extent)
        tx, ty = phase_correlation_shift(
            match_image, query_image, config.bev_cell, config.max_translation
        )
        initial = np.eye(4)
        initial[:3, :3] = _rot_z(yaw_rad)
        initial[:3, 3] = (tx, ty, 0.0)
        coarse = target.align(sparse_source, initial, 0, 1, config.hypothesis_iterations)
        if best is None or coarse.fitness > best.fitness:
            best = coarse
    assert best is not None
    if best.fitness < config.early_reject_fitness:
        return _result(np.array(best.transform), best.fitness, best.rmse, config)
    best = target.align(source, np.array(best.transform), 1 if len(config.stages) > 1 else 0, -1)
    return _result(np.array(best.transform), best.fitness, best.rmse, config)


def _result(
    T: np.ndarray,
    fitness: float,
    rmse: float,
    config: PoseConfig,
    too_few: tuple[int, int] | None = None,
) -> RelativePose:
    reasons = []
    if too_few is not None:
        reasons.append(
            f"too few points after downsampling (query {too_few[0]}, match {too_few[1]}, "
            f"need {config.min_points})"
        )
    else:
        if not fitness >= config.min_fitness:
            reasons.append(f"fitness {fitness:.2f} < {config.min_fitness:.2f}")
        if not rmse <= config.max_rmse:
            reasons.append(f"rmse {rmse:.2f} m > {config.max_rmse:.2f} m")
    yaw = wrap_deg(math.degrees(math.atan2(T[1, 0], T[0, 0])))
    return RelativePose(
        T=T,
        dx=float(T[0, 3]),
        dy=float(T[1, 3]),
        dz=float(T[2, 3]),
        yaw_deg=yaw,
        fitness=float(fitness),
        rmse=float(rmse),
        accepted=not reasons,
        reason="; ".join(reasons),
    )


# Standard deviations of an accepted loop with fitness 1 (the ICP's typical error
# on real scans at these voxel sizes); a lower fitness scales the information down.
_SIGMA_TRANSLATION = 0.1  # m
_SIGMA_ROTATION = math.radians(1.0)  # rad


def information_matrix(result: RelativePose) -> np.ndarray:
    """6 x 6 information (inverse covariance) of a loop edge, for g2o's EDGE_SE3:QUAT.

    Order x, y, z, then the rotation as g2o parameterises it (the quaternion's
    vector part, about half the rotation angle in radians). Diagonal: fitness
    times 1/sigma^2 with sigma 0.1 m and 1 degree; zero for a rejected loop.
    """
    if not result.accepted:
        return np.zeros((6, 6))
    sigma_q = _SIGMA_ROTATION / 2.0  # quaternion vector part ~ angle / 2
    diag = [1.0 / _SIGMA_TRANSLATION**2] * 3 + [1.0 / sigma_q**2] * 3
    return np.diag(np.asarray(diag) * max(result.fitness, 0.0))
