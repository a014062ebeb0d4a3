"""A pose graph of odometry and loop closures, optimized with GTSAM behind a robust kernel.

    from disco_cli.graph.pose_graph import PoseGraph
    graph = PoseGraph(odometry)                   # [N, 4, 4] T_world<-sensor, one per scan
    graph.add_loops(loops)                        # `Loop`s with T (T_match<-query), fitness, rmse
    result = graph.optimize()
    result.poses                                  # [N, 4, 4], in the odometry's frame
    [lp for lp in result.loops if lp.down_weighted]

Frames and units, once: a pose is `T_world<-sensor` (4 x 4, metres); the first pose is
held where the odometry put it, so the corrected trajectory stays in the odometry's
frame. An odometry edge joins scans i and i + 1 with the odometry's own relative
motion `inv(O_i) @ O_i+1`; a loop edge joins the match j to the query i with
`T_match<-query`. GTSAM orders a pose's 6 errors rotation first (radians, about x, y,
z), then translation (metres): information matrices here use that order.

Pose3, not Pose2: the odometry, the loops' ICP poses and the user's output format are
all 6-DoF. A planar graph would drop the loops' z, roll and pitch, and would have to
put the odometry's own back on afterwards; on a slope (KITTI's hills, the simulator's
`--terrain varied`) that mixes two trajectories. A 1,000-pose Pose3 graph takes well
under a second, so the planar graph's speed buys nothing.

Robustness: every loop edge sits behind a Cauchy kernel (default), so a loop that
disagrees with the odometry and the other loops by many of its sigmas pulls with a
weight of about (k / residual)^2 instead of being followed. `kernel="gnc"` uses
graduated non-convexity (GTSAM's GNC with truncated least squares), which starts from
the plain least-squares solution and drops the loops that stay outside the inlier
threshold; odometry edges are known inliers. The result reports each loop's residual
(whitened: in its own sigmas) and weight at the solution.

`gtsam` is the `[graph]` extra: it is imported when a graph is optimized, and
`GraphExtraMissing` (a `DiscoError`) names `pip install 'disco-cli[graph]'` when absent.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.graph.odometry_bias import fit_yaw_rate, turn_steps

__all__ = [
    "Correction",
    "GraphExtraMissing",
    "LoopResidual",
    "OdometryNoise",
    "PoseGraph",
    "correct",
    "import_gtsam",
    "loop_information",
]

INSTALL_HINT = "pip install 'disco-cli[graph]'"
KERNELS = ("cauchy", "huber", "gnc", "none")
# Width of the Cauchy and Huber kernels in a loop's own sigmas: a loop that fits within
# about 3 sigma keeps at least half its weight (1 / (1 + (3/3)^2)).
KERNEL_WIDTH = 3.0
# A loop whose weight at the solution is below this was down-weighted.
DOWN_WEIGHTED = 0.5


class GraphExtraMissing(DiscoError):
    """gtsam, the `[graph]` extra, is not installed."""


def import_gtsam() -> Any:
    """The gtsam module, or `GraphExtraMissing` with the line to install it."""
    try:
        # deferred: gtsam is the optional [graph] extra (34 MB); only a graph needs it
        import gtsam
    except ImportError:
        raise GraphExtraMissing(f"the pose graph needs gtsam: {INSTALL_HINT}") from None
    return gtsam


@dataclass(frozen=True)
class OdometryNoise:
    """How far each odometry step is trusted: standard deviations of a step's
    translation (`translation_m` plus `translation_share` of the distance driven, per
    axis) and rotation (`rotation_deg` plus `rotation_share` of the angle turned, and
    `yaw_per_m_deg` for each metre driven: a drifting heading). The defaults fit an
    odometry good to a few percent (KISS-ICP's, a wheel odometry's)."""

    translation_m: float = 0.02
    translation_share: float = 0.03
    rotation_deg: float = 0.05
    rotation_share: float = 0.0
    yaw_per_m_deg: float = 0.05

    def sigmas(self, step: np.ndarray) -> np.ndarray:
        """The 6 standard deviations (rotation first, GTSAM's order) of one step."""
        dist = float(np.linalg.norm(step[:3, 3]))
        angle = math.degrees(_angle(step[:3, :3]))
        rot = math.radians(
            self.rotation_deg + self.rotation_share * angle + self.yaw_per_m_deg * dist
        )
        trans = self.translation_m + self.translation_share * dist
        return np.array([rot] * 3 + [trans] * 3)


def _angle(R: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0)))


def loop_information(fitness: float | None = None, rmse: float | None = None) -> np.ndarray:
    """6 x 6 information of a loop edge (rotation first, GTSAM's order) from its ICP
    fit: standard deviations of `max(rmse, 0.05)` m in translation and 1 degree in
    rotation for a perfect fit, both divided by sqrt(fitness) (the share of points that
    found a partner: half the points, 1.4 times the sigma). Without a fit: 0.1 m, 1 deg."""
    f = 1.0 if fitness is None or not math.isfinite(fitness) else min(max(fitness, 0.05), 1.0)
    r = 0.1 if rmse is None or not math.isfinite(rmse) else max(rmse, 0.05)
    sig_t = r / math.sqrt(f)
    sig_r = math.radians(1.0) / math.sqrt(f)
    return np.diag([1.0 / sig_r**2] * 3 + [1.0 / sig_t**2] * 3)


@dataclass(frozen=True)
class LoopEdge:
    """A loop edge: scan `query` seen from scan `match` as `T` (T_match<-query)."""

    match: int
    query: int
    T: np.ndarray = field(repr=False)
    information: np.ndarray = field(repr=False)
    label: str = ""


@dataclass(frozen=True)
class LoopResidual:
    """One loop at the solution: its `residual` (whitened error, in its own sigmas),
    `translation_m` and `rotation_deg` (how far the corrected poses are from what the
    loop says), and `weight` (what the robust kernel left of it, 1 = followed fully);
    `down_weighted` when the weight is below 0.5."""

    match: int
    query: int
    residual: float
    translation_m: float
    rotation_deg: float
    weight: float
    label: str = ""

    @property
    def down_weighted(self) -> bool:
        return self.weight < DOWN_WEIGHTED


@dataclass(frozen=True)
class Correction:
    """The optimized trajectory: `poses` `[N, 4, 4]` (T_world<-sensor, the odometry's
    frame), `moved_m` `[N]` how far each pose moved from the odometry, `loops` one
    `LoopResidual` per loop edge, `kernel`, `iterations` and the graph's error before
    and after (GTSAM's, robust)."""

    poses: np.ndarray = field(repr=False)
    moved_m: np.ndarray = field(repr=False)
    loops: tuple[LoopResidual, ...]
    kernel: str
    iterations: int
    error_before: float
    error_after: float
    # The odometry's heading drift the loops showed, taken out before the graph
    # (degrees per metre driven; odometry_bias.py); 0 without loops or with drift=False.
    yaw_drift_deg_per_m: float = 0.0

    @property
    def down_weighted(self) -> list[LoopResidual]:
        return [lp for lp in self.loops if lp.down_weighted]


def _check_poses(poses: Any, what: str) -> np.ndarray:
    T = np.asarray(poses, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise DiscoError(f"{what} must be [N, 4, 4] poses, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise DiscoError(f"{what}: poses must be finite")
    return T


def _rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation made exactly orthonormal (text files round to 9 digits)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


class PoseGraph:
    """Odometry edges along `odometry` `[N, 4, 4]`, loop edges added one by one; see the
    module docstring. `kernel`: `cauchy` (default), `huber`, `gnc` or `none`;
    `kernel_width`: in sigmas. `noise`: the odometry's `OdometryNoise`. `drift`: first
    fit the odometry's heading drift (yaw per metre) to the loops and take it out
    (`odometry_bias.py`)."""

    def __init__(
        self,
        odometry: Any,
        *,
        kernel: str = "cauchy",
        kernel_width: float = KERNEL_WIDTH,
        noise: OdometryNoise | None = None,
        drift: bool = True,
    ):
        self.odometry = _check_poses(odometry, "odometry")
        if len(self.odometry) == 0:
            raise DiscoError("odometry: no poses")
        if kernel not in KERNELS:
            raise DiscoError(f"unknown kernel {kernel!r}; use {', '.join(KERNELS)}")
        if not kernel_width > 0:
            raise DiscoError(f"kernel_width must be positive, not {kernel_width!r}")
        self.kernel = kernel
        self.kernel_width = float(kernel_width)
        self.noise = noise or OdometryNoise()
        self.drift = bool(drift)
        self.loops: list[LoopEdge] = []

    def __len__(self) -> int:
        return len(self.odometry)

    def add_loop(
        self,
        match: int,
        query: int,
        T: Any,
        information: Any = None,
        *,
        fitness: float | None = None,
        rmse: float | None = None,
        label: str = "",
    ) -> None:
        """A loop edge: scan `query` seen from scan `match` as `T` (4 x 4,
        T_match<-query); `information` 6 x 6 (rotation first), by default from the
        fit (`loop_information(fitness, rmse)`)."""
        n = len(self)
        if not (0 <= int(match) < n and 0 <= int(query) < n) or int(match) == int(query):
            raise DiscoError(f"loop {match} -> {query}: indices must be two scans of 0..{n - 1}")
        T = _check_poses(np.asarray(T, dtype=np.float64)[None], f"loop {match} -> {query}")[0]
        info = loop_information(fitness, rmse) if information is None else information
        info = np.asarray(info, dtype=np.float64)
        if info.shape != (6, 6) or not np.isfinite(info).all():
            raise DiscoError(f"loop {match} -> {query}: information must be a finite 6 x 6")
        self.loops.append(LoopEdge(int(match), int(query), _rigid(T), info, label))

    def add_loops(self, loops: Iterable[Any]) -> int:
        """Add `Loop`s (`LoopDetector`'s: match_index, query_index, T, fitness, rmse);
        those without a pose are left out. A loop whose ICP fit missed the acceptance
        bar (`accepted` False) still comes in: on a changed campus the bar refused
        nearly every true loop (385 of 417 confident ones on the NCLT-like selection
        worlds), and the fit already weighs it (`loop_information`). A loop's
        `confidence` (in [0, 1], where the detector gives one) scales its information:
        a loop half sure of itself counts half. Returns how many were added."""
        added = 0
        for lp in loops:
            if getattr(lp, "T", None) is None:
                continue
            label = f"{getattr(lp, 'query', '')} -> {getattr(lp, 'match', '')}".strip(" ->")
            info = loop_information(getattr(lp, "fitness", None), getattr(lp, "rmse", None))
            confidence = getattr(lp, "confidence", None)
            if confidence is not None and math.isfinite(confidence):
                info = info * min(max(float(confidence), 0.05), 1.0)
            self.add_loop(lp.match_index, lp.query_index, lp.T, info, label=label)
            added += 1
        return added

    # -- optimizing ----------------------------------------------------------------

    def _loop_model(self, gtsam: Any, info: np.ndarray) -> Any:
        gauss = gtsam.noiseModel.Gaussian.Information(info)
        if self.kernel == "cauchy":
            est = gtsam.noiseModel.mEstimator.Cauchy.Create(self.kernel_width)
        elif self.kernel == "huber":
            est = gtsam.noiseModel.mEstimator.Huber.Create(self.kernel_width)
        else:  # gnc robustifies by itself; none is plain least squares
            return gauss
        return gtsam.noiseModel.Robust.Create(est, gauss)

    def _weight(self, residual: float) -> float:
        k = self.kernel_width
        if self.kernel == "cauchy":
            return 1.0 / (1.0 + (residual / k) ** 2)
        if self.kernel == "huber":
            return 1.0 if residual <= k else k / residual
        return 1.0

    def optimize(self, max_iterations: int = 100) -> Correction:
        """Optimize the graph (Levenberg-Marquardt from the odometry; GNC around it
        with `kernel="gnc"`) and return the `Correction`."""
        gtsam = import_gtsam()
        n = len(self)
        graph = gtsam.NonlinearFactorGraph()
        initial = gtsam.Values()
        rate = 0.0
        if self.drift and self.loops:
            edges = [(lp.match, lp.query, lp.T, lp.information) for lp in self.loops]
            rate = fit_yaw_rate(
                self.odometry, edges, width=self.kernel_width, robust=self.kernel != "none"
            )
        odo = [_rigid(T) for T in turn_steps(self.odometry, rate)]
        for i, T in enumerate(odo):
            initial.insert(i, gtsam.Pose3(T))
        anchor = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(odo[0]), anchor))
        for i in range(n - 1):
            step = np.linalg.inv(odo[i]) @ odo[i + 1]
            model = gtsam.noiseModel.Diagonal.Sigmas(self.noise.sigmas(step))
            graph.add(gtsam.BetweenFactorPose3(i, i + 1, gtsam.Pose3(_rigid(step)), model))
        first_loop = graph.size()
        for lp in self.loops:
            model = self._loop_model(gtsam, lp.information)
            graph.add(gtsam.BetweenFactorPose3(lp.match, lp.query, gtsam.Pose3(lp.T), model))
        before = graph.error(initial)
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        weights = None
        if self.kernel == "gnc" and self.loops:
            params = gtsam.GncLMParams(lm)
            params.setKnownInliers(list(range(first_loop)))
            params.setLossType(gtsam.GncLossType.TLS)
            optimizer = gtsam.GncLMOptimizer(graph, initial, params)
            # Inlier threshold: the chi-square of 6 errors at 0.99 (16.8), as GTSAM's own.
            optimizer.setInlierCostThresholdsAtProbability(0.99)
            result = optimizer.optimize()
            weights = np.asarray(optimizer.getWeights())[first_loop:]
            iterations = -1  # GNC runs several LM solves; it does not report a count
        else:
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm)
            result = optimizer.optimize()
            iterations = int(optimizer.iterations())
        poses = np.stack([result.atPose3(i).matrix() for i in range(n)])
        moved = np.linalg.norm(poses[:, :3, 3] - self.odometry[:, :3, 3], axis=1)
        residuals = []
        for k, lp in enumerate(self.loops):
            predicted = np.linalg.inv(poses[lp.match]) @ poses[lp.query]
            err = np.linalg.inv(lp.T) @ predicted
            e = np.concatenate([_rotvec(err[:3, :3]), err[:3, 3]])
            r = float(math.sqrt(max(e @ lp.information @ e, 0.0)))
            w = float(weights[k]) if weights is not None else self._weight(r)
            residuals.append(
                LoopResidual(
                    lp.match,
                    lp.query,
                    r,
                    float(np.linalg.norm(err[:3, 3])),
                    math.degrees(_angle(err[:3, :3])),
                    w,
                    lp.label,
                )
            )
        return Correction(
            poses,
            moved,
            tuple(residuals),
            self.kernel,
            iterations,
            before,
            graph.error(result),
            math.degrees(rate),
        )


def _rotvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, radians) of a 3 x 3 rotation."""
    angle = _angle(R)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return axis / 2.0
    if math.pi - angle < 1e-6:  # half a turn: the axis from R + I
        col = np.argmax(np.diag(R))
        v = (R[:, col] + np.eye(3)[col]) / math.sqrt(2.0 * (1.0 + R[col, col]))
        return v * angle
    return axis * (angle / (2.0 * math.sin(angle)))


def correct(odometry: Any, loops: Iterable[Any], **options: Any) -> Correction:
    """One call: a `PoseGraph` of `odometry` `[N, 4, 4]` and `loops` (`LoopDetector`'s
    `Loop`s), optimized. `options`: `PoseGraph`'s (kernel, kernel_width, noise, drift)."""
    graph = PoseGraph(odometry, **options)
    graph.add_loops(loops)
    return graph.optimize()
