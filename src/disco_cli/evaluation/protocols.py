"""The DiSCO paper's evaluation protocols on NCLT, MulRan and Oxford, as presets.

Xu et al., "DiSCO: Differentiable Scan Context with Orientation", RA-L 2021, section
"Dataset and Experimental Settings" and its appendix, name for each dataset the map
(database) session, the query sessions, the radius within which a retrieved scan is a
true match, the top-k depth, and the training session with its positive and negative
distances. `PROTOCOLS` holds them; `run_protocol` reads the sessions from a dataset
folder laid out as docs/datasets.md says, embeds them with a model and returns, per
query session, the paper's figures (Recall@1, Recall@1%, AUC) computed exactly as
`disco eval` computes them (`disco_cli.evaluation.metrics.retrieval_evaluation`).

Choices the paper leaves open are disco's and are marked as such in `Protocol.notes`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.evaluation.metrics import one_percent_n
from disco_cli.evaluation.runs import score_retrieval
from disco_cli.io.poses import poses_for_scans, xy_yaw
from disco_cli.io.poses.geometry import keep_by_spacing
from disco_cli.io.poses.interpolate import EXACT_S
from disco_cli.io.readers import list_scans, oxford, read_scan
from disco_cli.maps.database import MatchRows
from disco_cli.model.bev import polar_bev
from disco_cli.query.search import SignatureIndex, match_queries
from disco_cli.training.data import PosedScans

__all__ = [
    "PROTOCOLS",
    "Protocol",
    "Session",
    "SessionResult",
    "evaluate_sessions",
    "find_session",
    "load_session",
    "run_protocol",
    "table_rows",
]


@dataclass(frozen=True)
class Protocol:
    """One dataset's protocol. Distances in metres; spacings are metres of travel between
    kept scans (0: every scan with a pose)."""

    name: str
    dataset: str
    map_sessions: tuple[str, ...]
    query_sessions: tuple[str, ...]
    train_sessions: tuple[str, ...]
    radius: float  # a retrieved scan within this distance of the query is a true match
    topk: int  # Recall@1..topk
    d_pos: float  # training: positives within
    d_neg: float  # training: negatives beyond
    map_spacing: float
    query_spacing: float
    train_spacing: float
    every_pair: bool = False  # Oxford: every run is the map for every other run
    # The paper's rows: approach -> (Recall@1, Recall@1 %, AUC), in percent.
    paper: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


# Oxford's PointNetVLAD test split: the runs at these positions of the sorted run folders,
# and the four 150 m squares (northing, easting) whose submaps are queries (Uy and Lee,
# CVPR 2018, generate_test_sets.py, as the PointNetVLAD benchmark defines them).
OXFORD_TEST_RUNS = (5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 22, 24, 31, 32, 33,
                    38, 39, 43, 44)  # fmt: skip
OXFORD_TEST_CENTRES = (
    (5735712.768124, 620084.402381),
    (5735611.299219, 620540.270327),
    (5735237.358209, 620543.094379),
    (5734749.303802, 619932.693364),
)
OXFORD_TEST_HALF_WIDTH = 150.0

PROTOCOLS: dict[str, Protocol] = {
    "nclt": Protocol(
        name="nclt",
        dataset="NCLT",
        map_sessions=("2012-02-04",),
        query_sessions=(
            "2012-03-17",
            "2012-05-26",
            "2012-06-15",
            "2012-08-20",
            "2012-09-28",
            "2012-10-28",
        ),  # fmt: skip
        train_sessions=("2012-02-04",),
        radius=1.5,
        topk=10,
        d_pos=1.5,
        d_neg=2.0,
        map_spacing=0.0,
        query_spacing=0.0,
        train_spacing=0.0,
        paper={
            "DiSCO-occupied": (89.08, 99.14, 92.91),
            "DiSCO-density": (86.71, 97.87, 90.76),
            "Scan Context": (63.58, 92.35, 71.39),
        },
        notes=(
            "disco: every scan with a ground-truth pose is used (the paper follows OREOS "
            "without stating a sampling)",
        ),
    ),
    "mulran": Protocol(
        name="mulran",
        dataset="MulRan",
        map_sessions=("DCC01",),
        query_sessions=("DCC02", "DCC03"),
        train_sessions=("DCC01",),
        radius=3.0,
        topk=10,
        d_pos=3.0,
        d_neg=3.0,
        map_spacing=5.0,
        query_spacing=5.0,
        train_spacing=1.0,
        paper={
            "DiSCO-occupied": (55.28, 93.34, 69.32),
            "DiSCO-density": (56.58, 93.53, 70.74),
            "Scan Context": (52.63, 92.06, 63.76),
        },
        notes=(
            "paper: places sampled every 5 m for evaluation, 1 m for training",
            "disco: the whole DCC runs are used (the paper's evaluation area is only drawn "
            "in a figure), and DCC01 is the map",
        ),
    ),
    "oxford": Protocol(
        name="oxford",
        dataset="Oxford",
        map_sessions=(),  # every test run, in turn
        query_sessions=(),  # every other test run: the submaps inside the test squares
        train_sessions=(),  # every run but the last: oxford_training_sessions
        radius=25.0,
        topk=25,
        d_pos=10.0,
        d_neg=50.0,
        map_spacing=0.0,
        query_spacing=0.0,
        train_spacing=0.0,
        every_pair=True,
        paper={
            "DiSCO-occupied": (75.01, 88.44, 78.81),
            "DiSCO-density": (75.52, 88.62, 79.25),
            "Scan Context": (64.59, 81.88, 69.30),
        },
        notes=(
            "PointNetVLAD's test split: 23 runs, each the map for the queries of the 22 "
            "others; figures are the mean over map runs",
            "the submaps are normalized to [-1, 1] with a scale of their own that is not "
            "stored; disco reads them at --oxford-scale metres per unit (default 20: "
            "docs/formats.md)",
            "training: PointNetVLAD's split (the 10 m-interval submaps of every run but the "
            "last, outside the test squares); the locations have no heading, so the yaw loss "
            "is off (disco)",
        ),
    ),
}


@dataclass
class Session:
    """The scans of one session that have a pose, and their LiDAR poses [N, 4, 4]."""

    name: str
    scans: list[Path]
    poses: np.ndarray
    signatures: np.ndarray | None = None
    features: np.ndarray | None = None


@dataclass(frozen=True)
class SessionResult:
    """The figures of one query session against one map session (metrics of
    `retrieval_evaluation`: recall@1, recall@1%, auc in [0, 1], ...)."""

    map: str
    query: str
    metrics: dict[str, Any]


def _protocol(name: str) -> Protocol:
    try:
        return PROTOCOLS[name.lower()]
    except KeyError:
        raise DiscoError(f"unknown protocol {name!r} (known: {', '.join(PROTOCOLS)})") from None


def find_session(protocol: Protocol | str, root: str | Path, name: str) -> tuple[Path, Path]:
    """(scan folder, pose file) of a session under the dataset folder `root`
    (docs/datasets.md): `DiscoError` naming what is missing."""
    p = _protocol(protocol) if isinstance(protocol, str) else protocol
    root = Path(root)
    folder = root / name
    if p.name == "nclt":
        candidates = [folder / "velodyne_sync"]
        poses = [
            folder / f"groundtruth_{name}.csv",
            root / "ground_truth" / f"groundtruth_{name}.csv",
        ]
    elif p.name == "mulran":
        candidates = [folder / "sensor_data" / "Ouster", folder / "Ouster"]
        poses = [folder / "global_pose.csv"]
    else:
        candidates = [folder / "pointcloud_20m"]
        poses = [folder / "pointcloud_locations_20m.csv"]
    scans = next((c for c in candidates if c.is_dir()), None)
    pose_file = next((c for c in poses if c.is_file()), None)
    if scans is None:
        raise DiscoError(f"{root}: session {name}: no scan folder ({candidates[0]})")
    if pose_file is None:
        raise DiscoError(f"{root}: session {name}: no pose file ({poses[0]})")
    return scans, pose_file


def load_session(
    protocol: Protocol | str,
    root: str | Path,
    name: str,
    spacing: float = 0.0,
    warn: Callable[[str], None] | None = None,
) -> Session:
    """A session's scans with a pose (poses by `disco_cli.io.poses.poses_for_scans`, with the
    dataset's published extrinsic), kept every `spacing` metres of travel."""
    p = _protocol(protocol) if isinstance(protocol, str) else protocol
    folder, pose_file = find_session(p, root, name)
    scans = list_scans(folder, "oxford" if p.name == "oxford" else None)
    T, report = poses_for_scans(scans, pose_file)
    if report.warning() and warn is not None:
        warn(report.warning())
    has = np.isfinite(T[:, 0, 3])
    if not has.any():
        raise DiscoError(f"{pose_file}: none of the {len(scans)} scans of {name} has a pose")
    scans, T = [s for s, h in zip(scans, has) if h], T[has]
    keep = keep_by_spacing(T[:, :2, 3], spacing)
    return Session(name, [scans[i] for i in keep], T[keep])


def embed_session(
    session: Session, model: Any, protocol: Protocol, batch: int = 32, threads: int = 0
) -> None:
    """Signatures and features of a session's scans, in order (set on the session)."""
    fmt = "oxford" if protocol.name == "oxford" else None
    sigs, feats = [], []
    for start in range(0, len(session.scans), batch):
        bevs = []
        for path in session.scans[start : start + batch]:
            pts = read_scan(path, fmt)
            bev = polar_bev(pts, model.bev_config)
            if not np.any(bev):
                raise ScanReadError(path, f"no points in range ({len(pts)} points)")
            bevs.append(bev)
        s, f = model.embed(np.stack(bevs).astype(np.float32, copy=False))
        sigs.append(np.asarray(s, np.float32))
        feats.append(np.asarray(f, np.float32))
    session.signatures = np.concatenate(sigs)
    session.features = np.concatenate(feats)


def evaluate_sessions(
    map_session: Session,
    query_session: Session,
    model: Any,
    radius: float,
    topk: int,
    query_mask: np.ndarray | None = None,
    policy: Any = None,
) -> dict[str, Any]:
    """`disco eval`'s figures for one query session against one map session: the same
    search (`match_queries` under `policy`, None: the model's), ground truth within
    `radius` metres in x, y, and `retrieval_evaluation`. `query_mask` picks the queries."""
    mx, my, myaw = xy_yaw(map_session.poses)
    map_rows = np.c_[mx, my, map_session.poses[:, 2, 3], myaw]
    m_feats = map_session.features
    m_paths = [str(p) for p in map_session.scans]

    class _Memory:
        """The map session in memory, standing in for a database in `match_queries`."""

        def rows(self, ids: np.ndarray) -> MatchRows:
            ids = np.asarray(ids, np.int64)
            return MatchRows(ids, [m_paths[i] for i in ids], map_rows[ids], m_feats[ids])

    sel = np.arange(len(query_session.scans))
    if query_mask is not None:
        sel = sel[np.asarray(query_mask, bool)]
    q_sigs = query_session.signatures[sel]
    q_feats = query_session.features[sel]
    n_map = len(map_rows)
    depth = max(topk, one_percent_n(n_map))
    ids = np.arange(n_map)
    matches = match_queries(
        SignatureIndex(map_session.signatures),
        ids,
        _Memory(),
        model,
        q_sigs,
        q_feats,
        depth,
        policy,
    )
    ev = score_retrieval(matches, depth, topk, query_session.poses[sel], map_rows, radius)
    return ev.metrics


def _oxford_runs(root: Path) -> list[str]:
    runs = sorted(d.name for d in root.iterdir() if (d / "pointcloud_locations_20m.csv").is_file())
    if len(runs) <= max(OXFORD_TEST_RUNS):
        raise DiscoError(
            f"{root}: PointNetVLAD's Oxford test split needs its 45 run folders "
            f"(run {max(OXFORD_TEST_RUNS)} in sorted order); found {len(runs)}"
        )
    return [runs[i] for i in OXFORD_TEST_RUNS]


def oxford_in_test_squares(northing: np.ndarray, easting: np.ndarray) -> np.ndarray:
    """Which Oxford positions lie in PointNetVLAD's test squares (150 m half-width)."""
    inside = np.zeros(len(northing), dtype=bool)
    w = OXFORD_TEST_HALF_WIDTH
    for n0, e0 in OXFORD_TEST_CENTRES:
        inside |= (np.abs(northing - n0) < w) & (np.abs(easting - e0) < w)
    return inside


def run_protocol(
    name: str,
    root: str | Path,
    model: Any,
    warn: Callable[[str], None] | None = None,
    progress: Callable[[str], None] | None = None,
    oxford_scale: float | None = None,
    policy: Any = None,
) -> tuple[Protocol, list[SessionResult]]:
    """Evaluate `model` on a dataset folder by the paper's protocol: one result per
    (map session, query session) pair. `oxford_scale`: metres per unit of PointNetVLAD's
    normalized submaps (None: `disco_cli.io.readers.oxford.DEFAULT_SCALE`). `policy`: the
    query stage's `QueryPolicy` (None: the model's)."""
    with oxford.scale(oxford_scale):
        return _run_protocol(name, root, model, warn, progress, policy)


def _run_protocol(
    name: str,
    root: str | Path,
    model: Any,
    warn: Callable[[str], None] | None,
    progress: Callable[[str], None] | None,
    policy: Any = None,
) -> tuple[Protocol, list[SessionResult]]:
    p = _protocol(name)
    root = Path(root)
    if not root.is_dir():
        raise DiscoError(f"{root}: no such folder")
    say = progress or (lambda _msg: None)
    results: list[SessionResult] = []
    if p.every_pair:
        if (root / "oxford").is_dir():
            root = root / "oxford"
        runs = _oxford_runs(root)
        sessions = {}
        for run in runs:
            say(f"embedding {run}")
            s = load_session(p, root, run, p.map_spacing, warn)
            embed_session(s, model, p)
            sessions[run] = s
        for m in runs:
            for q in runs:
                if q == m:
                    continue
                qs = sessions[q]
                mask = oxford_in_test_squares(qs.poses[:, 0, 3], qs.poses[:, 1, 3])
                if not mask.any():
                    continue
                met = evaluate_sessions(sessions[m], qs, model, p.radius, p.topk, mask, policy)
                results.append(SessionResult(m, q, met))
        return p, results
    for m in p.map_sessions:
        say(f"embedding the map {m}")
        ms = load_session(p, root, m, p.map_spacing, warn)
        embed_session(ms, model, p)
        for q in p.query_sessions:
            try:
                find_session(p, root, q)
            except DiscoError as exc:
                # A partial download still evaluates the sessions it has.
                if warn is not None:
                    warn(f"{exc}: skipped")
                continue
            say(f"embedding the queries {q}")
            qs = load_session(p, root, q, p.query_spacing, warn)
            embed_session(qs, model, p)
            met = evaluate_sessions(ms, qs, model, p.radius, p.topk, policy=policy)
            results.append(SessionResult(m, q, met))
    if not results:
        raise DiscoError(f"{root}: none of the query sessions {', '.join(p.query_sessions)}")
    return p, results


def _pct(v: Any) -> float | None:
    return None if v is None or not np.isfinite(v) else round(100.0 * float(v), 2)


def table_rows(protocol: Protocol, results: list[SessionResult], approach: str) -> list[dict]:
    """Rows in the layout of the paper's table (percent): one per query session (Oxford:
    averaged over the map runs), their mean, and the paper's own rows beside them."""
    by_query: dict[str, list[dict]] = {}
    for r in results:
        by_query.setdefault(r.query, []).append(r.metrics)
    rows = []
    keys = (("recall@1", "recall@1"), ("recall@1%", "recall@1%"), ("auc", "auc"))
    means: dict[str, list[float]] = {k: [] for k, _ in keys}
    for query, mets in by_query.items():
        row = {"dataset": protocol.dataset, "approach": approach, "session": query}
        for col, key in keys:
            vals = [m[key] for m in mets if m.get(key) is not None]
            row[col] = _pct(np.mean(vals)) if vals else None
            if vals:
                means[col].append(float(np.mean(vals)))
        row["queries"] = int(sum(m["num_queries"] for m in mets))
        rows.append(row)
    mean_row = {"dataset": protocol.dataset, "approach": approach, "session": "mean"}
    for col, _ in keys:
        mean_row[col] = _pct(np.mean(means[col])) if means[col] else None
    mean_row["queries"] = sum(r["queries"] for r in rows)
    rows.append(mean_row)
    for paper_approach, (r1, r1p, auc) in protocol.paper.items():
        rows.append(
            {
                "dataset": protocol.dataset,
                "approach": f"{paper_approach} (paper)",
                "session": "mean",
                "recall@1": r1,
                "recall@1%": r1p,
                "auc": auc,
                "queries": None,
            }
        )
    return rows


TABLE_COLUMNS = ["dataset", "approach", "session", "recall@1", "recall@1%", "auc", "queries"]


@dataclass(frozen=True)
class TrainingSetup:
    """What `disco train --protocol` trains on: session folders (or, for Oxford, explicit
    `disco_cli.training.data.PosedScans`) and the paper's distances. `lambda_yaw`: the yaw
    loss weight the protocol imposes (None: the command's)."""

    sessions: list[Any]
    d_pos: float
    d_neg: float
    spacing: float
    lambda_yaw: float | None = None


# PointNetVLAD's training split: every run but the last in sorted order (44 of 45), its
# 10 m-interval submaps (generate_training_tuples_baseline.py).
OXFORD_TRAIN_SCANS = "pointcloud_20m_10overlap"
OXFORD_TRAIN_LOCATIONS = "pointcloud_locations_20m_10overlap.csv"


def oxford_training_sessions(
    root: str | Path, warn: Callable[[str], None] | None = None
) -> list[Any]:
    """PointNetVLAD's Oxford training split under `root` (benchmark_datasets/ or its
    oxford/): for every run but the last of the sorted run folders, its
    pointcloud_20m_10overlap submaps that have a row in its locations CSV and lie outside
    the four test squares, as `PosedScans` of one world (UTM: pooled across runs).
    Runs without the training split are named in one warning and skipped."""
    root = Path(root)
    if (root / "oxford").is_dir():
        root = root / "oxford"
    if not root.is_dir():
        raise DiscoError(f"{root}: no such folder")
    csvs = ("pointcloud_locations_20m.csv", OXFORD_TRAIN_LOCATIONS)
    runs = sorted(d for d in root.iterdir() if any((d / c).is_file() for c in csvs))
    if len(runs) <= max(OXFORD_TEST_RUNS):
        raise DiscoError(
            f"{root}: PointNetVLAD's Oxford training split is every run but the last of its "
            f"45 run folders; found {len(runs)}"
        )
    sessions, missing = [], []
    for run in runs[:-1]:
        folder, csv = run / OXFORD_TRAIN_SCANS, run / OXFORD_TRAIN_LOCATIONS
        if not folder.is_dir() or not csv.is_file():
            missing.append(run.name)
            continue
        scans = list_scans(folder, "oxford")
        # The CSV is the split's index: a submap is used at its own row's location only.
        T, _ = poses_for_scans(scans, csv, "oxford", max_time_gap=EXACT_S)
        keep = np.isfinite(T[:, 0, 3])
        keep[keep] = ~oxford_in_test_squares(T[keep, 0, 3], T[keep, 1, 3])
        if keep.any():
            scans = [s for s, k in zip(scans, keep) if k]
            sessions.append(PosedScans(run.name, scans, T[keep], str(root), "oxford"))
    if missing and warn is not None:
        warn(
            f"{root}: {len(missing)} of {len(runs) - 1} training runs have no "
            f"{OXFORD_TRAIN_SCANS}/ and {OXFORD_TRAIN_LOCATIONS} (e.g. {missing[0]}): skipped"
        )
    if not sessions:
        raise DiscoError(
            f"{root}: no {OXFORD_TRAIN_SCANS} submap outside the test squares in the "
            f"{len(runs) - 1} training runs"
        )
    return sessions


def training_setup(
    name: str, root: str | Path, warn: Callable[[str], None] | None = None
) -> TrainingSetup:
    """The paper's training sessions under `root` with its positive/negative distances.

    Oxford's locations are 2D and its submaps carry no heading, so there is no yaw to
    supervise: its setup turns the yaw (KL) loss off (`lambda_yaw` 0), and the network
    learns from the quadruplet loss alone, rotation invariance still coming from the
    random sector rolls of every training BEV."""
    p = _protocol(name)
    if p.every_pair:
        sessions = oxford_training_sessions(root, warn)
        return TrainingSetup(sessions, p.d_pos, p.d_neg, p.train_spacing, lambda_yaw=0.0)
    sessions = []
    for s in p.train_sessions:
        find_session(p, root, s)  # one clear line when it is missing
        sessions.append(Path(root) / s)
    return TrainingSetup(sessions, p.d_pos, p.d_neg, p.train_spacing)
