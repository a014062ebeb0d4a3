"""`disco eval` / `eval-loops` end to end on a tiny generated world, and the report files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.evaluation import metrics as m
from disco_cli.evaluation import plots, report

KEYS = [
    "recall@1",
    "recall@1%",
    "recall@N",
    "auc",
    "f1_max",
    "yaw_err_mean_deg",
    "yaw_err_std_deg",
    "yaw_err_median_deg",
]

# --- a tiny world -----------------------------------------------------------------------------
# Boxes of random size and height on flat ground; a scan is every world point within 50 m of
# the sensor (1.8 m above the ground), in the sensor frame, with 2 cm noise. No occlusion:
# enough for place recognition to have something to find, fast to make.


def world_points(rng: np.random.Generator) -> np.ndarray:
    parts = [np.c_[rng.uniform(-70, 330, 60000), rng.uniform(-70, 70, 60000), np.zeros(60000)]]
    for _ in range(160):
        cx, cy = rng.uniform(-70, 330), rng.uniform(-70, 70)
        w, d, h = rng.uniform(1, 8), rng.uniform(1, 8), rng.uniform(1, 15)
        n = int(40 * (w + d) * h**0.5)
        t = rng.uniform(0, 1, n)
        side = rng.integers(0, 4, n)
        x = np.where(side < 2, cx - w / 2 + t * w, cx + np.where(side == 2, -w / 2, w / 2))
        y = np.where(side < 2, cy + np.where(side == 0, -d / 2, d / 2), cy - d / 2 + t * d)
        parts.append(np.c_[x, y, rng.uniform(0, h, n)])
    return np.vstack(parts)


def scan_at(world: np.ndarray, x: float, y: float, yaw: float, rng) -> np.ndarray:
    rel = world - [x, y, 1.8]
    keep = np.hypot(rel[:, 0], rel[:, 1]) < 50.0
    rel = rel[keep]
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.c_[c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]]
    local += rng.normal(0, 0.02, local.shape)
    return np.c_[local, np.zeros(len(local))].astype(np.float32)


def write_session(folder: Path, world: np.ndarray, poses_xyyaw: list[tuple], rng) -> None:
    (folder / "velodyne").mkdir(parents=True)
    lines, times = [], []
    for i, (x, y, yaw) in enumerate(poses_xyyaw):
        scan_at(world, x, y, yaw, rng).tofile(folder / "velodyne" / f"{i:06d}.bin")
        c, s = np.cos(yaw), np.sin(yaw)
        lines.append(f"{c} {-s} 0 {x} {s} {c} 0 {y} 0 0 1 0")
        times.append(f"{i * 1.0:.1f}")
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    (folder / "times.txt").write_text("\n".join(times) + "\n")


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory) -> Path:
    """Session 00 drives east along y = 0; session 01 drives back west 0.7 m to the side, half
    a step shifted, then three scans far beyond the map (places the map has never seen)."""
    root = tmp_path_factory.mktemp("world")
    rng = np.random.default_rng(7)
    world = world_points(rng)
    a = [(x, 0.0, 0.0) for x in np.arange(0.0, 63.0, 3.0)]
    b = [(x, 0.7, np.pi) for x in np.arange(61.5, 0.0, -3.0)]
    b += [(x, 0.0, 0.3) for x in (230.0, 260.0, 290.0)]
    write_session(root / "00", world, a, rng)
    write_session(root / "01", world, b, rng)
    return root


def run(*args: str):
    from disco_cli.cli import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    return result


@pytest.fixture(scope="module")
def databases(tiny_world, tmp_path_factory) -> dict[str, Path]:
    pytest.importorskip("disco_cli.model.bev")
    out = {}
    for model in ("spectral", "scancontext"):
        db = tmp_path_factory.mktemp("db") / f"{model}.db"
        result = run("build-db", tiny_world / "00", "-o", db, "--model", model)
        assert result.exit_code == 0, result.output
        out[model] = db
    return out


def truth_counts(world: Path, radius: float) -> tuple[int, int]:
    """(queries, queries with a map scan within radius), by a plain loop over the poses."""

    def xy(f: Path):
        rows = [ln.split() for ln in f.read_text().splitlines() if ln]
        return [(float(r[3]), float(r[7])) for r in rows]

    q, d = xy(world / "01" / "poses.txt"), xy(world / "00" / "poses.txt")
    return len(q), sum(any(np.hypot(a - c, b - e) <= radius for c, e in d) for a, b in q)


@pytest.mark.parametrize("model", ["spectral", "scancontext"])
def test_eval_writes_metrics_json(tiny_world, databases, tmp_path, model):
    out = tmp_path / "report"
    result = run(
        "eval",
        tiny_world / "01",
        "--db",
        databases[model],
        "--topk",
        "5",
        "--report",
        out,
        "--format",
        "jsonl",
    )
    assert result.exit_code == 0, result.output
    got = json.loads((out / "metrics.json").read_text())
    for key in KEYS:
        assert key in got
    n_q, n_true = truth_counts(tiny_world, 3.0)
    assert got["num_queries"] == n_q == 24
    assert got["num_queries_with_match"] == n_true == 21
    assert got["num_database"] == 21
    assert len(got["recall@N"]) == 5
    assert all(0.0 <= r <= 1.0 for r in got["recall@N"])
    assert got["recall@N"] == sorted(got["recall@N"])  # recall@N never falls as N grows
    for key in ("recall@1", "recall@1%", "auc", "f1_max"):
        assert 0.0 <= got[key] <= 1.0
    # The printed JSON line is the same figures.
    printed = json.loads(result.stdout.strip().splitlines()[-1])
    assert printed["recall@1"] == got["recall@1"]
    assert (out / "summary.md").is_file()
    assert (out / "precision_recall.png").stat().st_size > 1000
    curves = json.loads((out / "curves.json").read_text())
    assert len(curves["yaw_errors_deg"]) == got["num_yaw_errors"]


def test_scancontext_finds_the_reverse_revisits(tiny_world, databases, tmp_path):
    # The revisits drive the other way: the yaw is 180 deg, and Scan Context's shift search
    # must find it (within a sector) for the places it retrieves.
    out = tmp_path / "r"
    result = run(
        "eval",
        tiny_world / "01",
        "--db",
        databases["scancontext"],
        "--topk",
        "3",
        "--report",
        out,
        "--format",
        "jsonl",
    )
    assert result.exit_code == 0, result.output
    got = json.loads((out / "metrics.json").read_text())
    assert got["recall@1"] >= 0.8
    assert got["yaw_err_median_deg"] <= 6.0


def test_eval_loops_runs(tiny_world, tmp_path):
    pytest.importorskip("disco_cli.model.bev")
    # One sequence: session 00 then 01 again as later frames; frames 21+ revisit frames 0-20.
    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    lines = []
    for s in ("00", "01"):
        for f in sorted((tiny_world / s / "velodyne").glob("*.bin")):
            (seq / "velodyne" / f"{len(lines):06d}.bin").write_bytes(f.read_bytes())
            lines.append(None)
    poses = "".join((tiny_world / s / "poses.txt").read_text() for s in ("00", "01"))
    (seq / "poses.txt").write_text(poses)
    out = tmp_path / "loops"
    result = run(
        "eval-loops",
        seq,
        "--model",
        "scancontext",
        "--exclude-frames",
        "10",
        "--report",
        out,
        "--format",
        "jsonl",
    )
    assert result.exit_code == 0, result.output
    got = json.loads((out / "metrics.json").read_text())
    # Queries: frames 10..44 (35). With a true loop: by a plain loop over the poses, a frame
    # with an earlier one (at least 10 frames back) within 3 m; 16 of the revisits (by hand:
    # revisit k at x = 61.5 - 3k meets frames 20 - k and 21 - k, allowed from k = 5 on).
    xy = [(float(ln.split()[3]), float(ln.split()[7])) for ln in poses.splitlines() if ln]
    want = sum(
        any(np.hypot(xy[i][0] - xy[j][0], xy[i][1] - xy[j][1]) <= 3.0 for j in range(i - 9))
        for i in range(10, len(xy))
    )
    assert got["num_queries"] == 45 - 10
    assert got["num_queries_with_match"] == want == 16
    for key in ("auc", "f1_max", "recall@100%precision"):
        assert 0.0 <= got[key] <= 1.0


def test_eval_without_query_poses_is_one_clear_line(tiny_world, databases, tmp_path):
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "a.bin").write_bytes((tiny_world / "01" / "velodyne" / "000000.bin").read_bytes())
    result = run("eval", lone, "--db", databases["spectral"])
    assert result.exit_code == 1
    assert "query poses" in result.output
    assert "Traceback" not in result.output


def test_eval_pose_count_mismatch(tiny_world, databases, tmp_path):
    bad = tmp_path / "poses.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    result = run("eval", tiny_world / "01", "--db", databases["spectral"], "--poses", bad)
    assert result.exit_code == 1
    assert "1 poses for 24" in result.output


def test_eval_needs_a_database_with_poses(tiny_world, tmp_path):
    pytest.importorskip("disco_cli.model.bev")
    bare = tmp_path / "bare"
    (bare / "velodyne").mkdir(parents=True)
    for f in sorted((tiny_world / "00" / "velodyne").glob("*.bin"))[:3]:
        (bare / "velodyne" / f.name).write_bytes(f.read_bytes())
    db = tmp_path / "bare.db"
    assert run("build-db", bare, "-o", db, "--model", "spectral").exit_code == 0
    result = run("eval", tiny_world / "01", "--db", db)
    assert result.exit_code == 1
    assert "no pose" in result.output and "bare.db" in result.output
    assert "Traceback" not in result.output


def test_eval_unreadable_query_scan_names_the_file(tiny_world, databases, tmp_path):
    q = tmp_path / "q"
    (q / "velodyne").mkdir(parents=True)
    for f in sorted((tiny_world / "01" / "velodyne").glob("*.bin"))[:2]:
        (q / "velodyne" / f.name).write_bytes(f.read_bytes())
    broken = q / "velodyne" / "000001.bin"
    broken.write_bytes(broken.read_bytes()[:-6])  # no longer whole float32 x 4 records
    poses = (tiny_world / "01" / "poses.txt").read_text().splitlines()[:2]
    (q / "poses.txt").write_text("\n".join(poses) + "\n")
    result = run("eval", q, "--db", databases["spectral"])
    assert result.exit_code == 1
    assert "000001.bin" in result.output
    assert "Traceback" not in result.output


def test_eval_loops_bad_exclusion_options(tiny_world, tmp_path):
    seq = tmp_path / "notimes"
    (seq / "velodyne").mkdir(parents=True)
    for f in sorted((tiny_world / "00" / "velodyne").glob("*.bin"))[:3]:
        (seq / "velodyne" / f.name).write_bytes(f.read_bytes())
    poses = (tiny_world / "00" / "poses.txt").read_text().splitlines()[:3]
    (seq / "poses.txt").write_text("\n".join(poses) + "\n")
    # The default exclusion is 30 s, which needs timestamps.
    result = run("eval-loops", seq, "--model", "spectral")
    assert result.exit_code == 1 and "no times" in result.output
    both = run(
        "eval-loops", seq, "--model", "spectral", "--exclude-frames", "2", "--exclude-seconds", "3"
    )
    assert both.exit_code == 1 and "not both" in both.output


# --- the report files, without any model ------------------------------------------------------


def hand_evaluation() -> m.Evaluation:
    truth = np.zeros((3, 150), dtype=bool)
    truth[0, 0] = truth[1, 1] = True
    retrieved = np.array([[0, 2], [2, 1], [5, 6]])
    distances = np.array([[0.1, 0.2], [0.3, 0.4], [0.2, 0.5]])
    yaw_est, yaw_true = np.array([5.0, 0, 0]), np.array([1.0, 0, 0])
    return m.retrieval_evaluation(retrieved, distances, truth, yaw_est, yaw_true)


def test_report_files(tmp_path):
    ev = hand_evaluation()
    written = report.write_report(tmp_path, ev, {"model": "hand", "protocol": "multi-session"})
    names = {p.name for p in written}
    assert {"metrics.json", "curves.json", "summary.md"} <= names
    assert {"recall_at_n.png", "precision_recall.png", "yaw_error.png", "rejection.png"} <= names
    got = json.loads((tmp_path / "metrics.json").read_text())
    # By hand: q0 right at rank 1, q1 at rank 2, q2 has no true match.
    assert got["recall@N"] == [0.5, 1.0]
    assert got["recall@1"] == 0.5
    assert got["yaw_err_mean_deg"] == 4.0
    assert got["run"]["model"] == "hand"
    summary = (tmp_path / "summary.md").read_text()
    assert "| Recall@1 | 50.00 % |" in summary


def test_report_without_matplotlib_still_writes_metrics(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(plots, "_pyplot", lambda: None)
    written = report.write_report(tmp_path, hand_evaluation(), {"model": "hand"})
    assert not any(p.suffix == ".png" for p in written)
    assert json.loads((tmp_path / "metrics.json").read_text())["recall@1"] == 0.5
    assert "pip install 'disco-cli[plot]'" in capsys.readouterr().err


def test_tsv_output(capsys):
    report.print_metrics(hand_evaluation().metrics, report_format("tsv"), title="t")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "metric\tvalue"
    assert "recall@1\t0.5" in lines


def report_format(name: str):
    from disco_cli.runtime.console import OutputFormat

    return OutputFormat(name)


def test_rerank_wider_option_reaches_the_report(tiny_world, tmp_path):
    db = tmp_path / "default.db"
    result = run("build-db", tiny_world / "00", "-o", db, "--model", "default")
    assert result.exit_code == 0, result.output
    # None: the shipped setting; 0 turns the pass off; another depth is recorded as given.
    cases = [(None, {"depth": 40, "above": 0.7}), ("0", None), ("15", {"depth": 15, "above": 0.7})]
    for option, want in cases:
        out = tmp_path / f"report-{option}"
        extra = [] if option is None else ["--rerank-wider", option]
        result = run("eval", tiny_world / "01", "--db", db, "--report", out, *extra)
        assert result.exit_code == 0, result.output
        got = json.loads((out / "metrics.json").read_text())["run"].get("rerank_wider")
        assert got == want, option


def test_rerank_wider_with_a_model_that_has_none(tiny_world, databases):
    result = run("eval", tiny_world / "01", "--db", databases["spectral"], "--rerank-wider", "5")
    assert result.exit_code == 1
    assert "spectral has no wider re-ranking pass" in result.output
    assert len(result.output.strip().splitlines()) == 1
    # 0 asks for no pass, which such a model already does.
    result = run("eval", tiny_world / "01", "--db", databases["spectral"], "--rerank-wider", "0")
    assert result.exit_code == 0, result.output


def test_query_of_an_unseen_place_re_ranks_wider(tiny_world, tmp_path):
    """Query 21 lies 170 m beyond the map: none of its 10 nearest signatures re-ranks
    within 0.7, so the search re-ranks all 21 map scans, unless --rerank-wider 0."""
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    db = tmp_path / "default.db"
    assert run("build-db", tiny_world / "00", "-o", db, "--model", "default").exit_code == 0
    model = load_model("default")
    maps = sorted((tiny_world / "00" / "velodyne").glob("*.bin"))
    query = tiny_world / "01" / "velodyne" / "000021.bin"

    def embed(p: Path):
        return model.embed(polar_bev(read_scan(p), model.bev_config)[None])

    m_sig, m_feat = (np.concatenate(a) for a in zip(*[embed(p) for p in maps]))
    q_sig, q_feat = embed(query)
    # The truth: the rule applied by hand to the signature order and the model's distances.
    order = np.argsort(((m_sig.astype(np.float64) - q_sig[0]) ** 2).sum(1), kind="stable")
    dist, _ = model.rerank(q_feat[0], m_feat[order])
    assert dist[:10].min() > 0.7, "the premise: no good match among the 10 nearest"
    narrow, wide = order[np.argmin(dist[:10])], order[np.argmin(dist)]
    assert narrow != wide, "the premise: a scan beyond the 10th re-ranks best"
    for extra, want in (([], wide), (["--rerank-wider", "0"], narrow)):
        result = run("query", query, "--db", db, "--topk", "1", "--format", "jsonl", *extra)
        assert result.exit_code == 0, result.output
        assert json.loads(result.output.splitlines()[0])["match"] == str(maps[want]), extra
