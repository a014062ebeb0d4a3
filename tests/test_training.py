"""Training: losses against hand-computed values, pair mining, and a short seeded run on a
tiny synthetic world that must lower the loss and beat the untrained network's recall."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import short_training  # noqa: E402

from disco_cli.errors import DiscoError  # noqa: E402
from disco_cli.training.losses import quadruplet_loss, shift_target, yaw_loss  # noqa: E402

# -- a tiny world: pillars seen from two drives along the same road ----------------------


def _world(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 90
    # Pillars (x, y, radius, height) scattered around a 200 m road along x.
    return np.column_stack(
        [
            rng.uniform(-40, 240, n),
            rng.uniform(-40, 40, n),
            rng.uniform(0.4, 3.0, n),
            rng.uniform(1.0, 12.0, n),
        ]
    )


def _scan(
    pillars: np.ndarray, x: float, y: float, yaw: float, rng: np.random.Generator
) -> np.ndarray:
    pts = []
    for px, py, rad, h in pillars:
        if np.hypot(px - x, py - y) > 45:
            continue
        k = int(60 * rad * h / 4) + 8
        ang = rng.uniform(0, 2 * np.pi, k)
        z = rng.uniform(-1.4, h - 1.5, k)
        pts.append(np.column_stack([px + rad * np.cos(ang), py + rad * np.sin(ang), z]))
    world = np.concatenate(pts)
    world = world[rng.random(len(world)) < 0.8]  # thin: no two visits see the same points
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = world[:, 0] - x, world[:, 1] - y
    local = np.column_stack([c * dx + s * dy, -s * dx + c * dy, world[:, 2]])
    local += rng.normal(0, 0.03, local.shape)
    return np.column_stack([local, np.zeros(len(local))]).astype(np.float32)


def write_world(root: Path, seed: int = 0, scans: int = 40) -> Path:
    """Two sessions (one world folder) of KITTI-style sequences, 5 m apart scans."""
    pillars = _world(seed)
    rng = np.random.default_rng(seed + 1)
    world = root / f"world{seed}"
    for name, lateral, heading in (("a", 0.0, 0.0), ("b", 1.5, np.pi)):
        seq = world / name
        (seq / "velodyne").mkdir(parents=True)
        rows = []
        for i in range(scans):
            x = 5.0 * i + (2.0 if name == "b" else 0.0)
            yaw = heading + rng.normal(0, 0.3)
            _scan(pillars, x, lateral, yaw, rng).tofile(seq / "velodyne" / f"{i:06d}.bin")
            c, s = np.cos(yaw), np.sin(yaw)
            rows.append([c, -s, 0, x, s, c, 0, lateral, 0, 0, 1, 0])
        np.savetxt(seq / "poses.txt", np.array(rows), fmt="%.6f")
    return world


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_world(tmp_path_factory.mktemp("train"))


# -- losses --------------------------------------------------------------------------


def test_quadruplet_loss_by_hand():
    q = torch.tensor([[1.0, 0.0]])
    p = torch.tensor([[0.6, 0.8]])  # |q - p|^2 = 0.16 + 0.64 = 0.8
    negs = torch.tensor([[[0.0, 1.0], [-1.0, 0.0]]])  # |q - n|^2 = 2 and 4
    other = torch.tensor([[0.0, -1.0]])  # |o - n|^2 = 4 and 2
    # first: max(0.5 + 0.8 - 2, 0.5 + 0.8 - 4, 0) = 0;
    # second: max(0.2 + 0.8 - 4, 0.2 + 0.8 - 2, 0) = 0
    assert float(quadruplet_loss(q, p, negs, other)) == pytest.approx(0.0)
    p_far = torch.tensor([[-0.6, 0.8]])  # |q - p|^2 = 2.56 + 0.64 = 3.2
    # first: 0.5 + 3.2 - 2 = 1.7; second: 0.2 + 3.2 - 2 = 1.4
    assert float(quadruplet_loss(q, p_far, negs, other)) == pytest.approx(3.1)


def test_yaw_loss_is_zero_only_for_the_true_shift():
    s = 12
    target = shift_target(torch.tensor([3.0, 4.25]), s)
    np.testing.assert_allclose(target[0].numpy(), np.eye(s)[3])
    assert target[1, 4] == pytest.approx(0.75) and target[1, 5] == pytest.approx(0.25)
    # A prediction equal to the target scores (almost) zero; a wrong one scores log(1/eps).
    good = torch.log(target.clamp_min(1e-9))
    assert float(yaw_loss(good, torch.tensor([3.0, 4.25]))) == pytest.approx(0.0, abs=1e-6)
    uniform = torch.full((1, s), -np.log(s))
    assert float(yaw_loss(uniform, torch.tensor([7.0]))) == pytest.approx(np.log(s), rel=1e-5)
    # Shifts wrap around the circle: -1 is bin s - 1.
    np.testing.assert_allclose(shift_target(torch.tensor([-1.0]), s)[0].numpy(), np.eye(s)[s - 1])


# -- data and mining -----------------------------------------------------------------


def test_loading_and_mining_follow_the_poses(world):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.mining import PairMiner

    data = load_training_data([world], BEVConfig())
    assert len(data) == 80 and data.bevs.dtype == np.uint8
    assert set(data.session) == {0, 1} and set(data.group) == {0}
    miner = PairMiner(data, d_pos=3.0, d_neg=10.0)
    rng = np.random.default_rng(0)
    for q in miner.queries[:20]:
        p = miner.positive(int(q), rng)
        assert np.linalg.norm(data.xy[p] - data.xy[q]) < 3.0 and p != q
        negs = miner.negatives(int(q), 4, rng)
        assert np.all(np.linalg.norm(data.xy[negs] - data.xy[q], axis=1) > 10.0)
        o = miner.other_negative(int(q), negs, rng)
        assert np.all(np.linalg.norm(data.xy[negs] - data.xy[o], axis=1) > 10.0)
    with pytest.raises(DiscoError, match="no positive pairs"):
        PairMiner(data, d_pos=0.1, d_neg=10.0)


def test_hard_negative_search_equals_a_full_sort():
    from disco_cli.training.mining import _nearest_rows

    rng = np.random.default_rng(3)
    x = rng.normal(size=(300, 64)).astype(np.float32)
    d = ((x[:, None, :].astype(np.float64) - x[None]) ** 2).sum(-1)
    want = np.argsort(d, axis=1, kind="stable")[:, :10]
    np.testing.assert_array_equal(_nearest_rows(x, 10, block=64), want)


def test_verify_sets_start_with_the_nearest_scan_of_another_pass(world):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.mining import PairMiner

    data = load_training_data([world], BEVConfig())
    miner = PairMiner(data, d_pos=3.0, d_neg=10.0)
    rng = np.random.default_rng(1)
    found = 0
    for q in miner.queries:
        got = miner.verify_set(int(q), 3, 10.0, rng)
        other = np.flatnonzero(data.session != data.session[q])
        dist = np.linalg.norm(data.xy[other] - data.xy[q], axis=1)
        if got is None:
            assert (dist <= 10.0).sum() < 3 or dist.min() > 3.0
            continue
        rows, d = got
        found += 1
        assert len(set(rows.tolist())) == 3 and np.all(data.session[rows] != data.session[q])
        np.testing.assert_allclose(d, np.linalg.norm(data.xy[rows] - data.xy[q], axis=1))
        assert d[0] == pytest.approx(dist.min()) and np.all(d <= 10.0)
    assert found > 0
    assert miner.verify_set(int(miner.queries[0]), 50, 10.0, rng) is None


def test_training_with_the_verify_loss_records_it_and_reranks(world, tmp_path, one_thread):
    from disco_cli.model import load_model
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.loop import TrainOptions, train

    data = load_training_data([world], BEVConfig())
    opts = TrainOptions(
        epochs=1, steps=4, batch=4, negatives=2, width=4, lambda_verify=1.0,
        verify_candidates=3, seed=0, val_queries=20,
    )  # fmt: skip
    out = tmp_path / "v.pt"
    history = train(data, BEVConfig(), opts, out, command="test", log=lambda s: None)
    assert history[0]["verify"] > 0 and np.isfinite(history[0]["loss"])
    model = load_model(str(out))
    assert model.query_policy.rerank_candidates > 0


def test_training_without_poses_needs_self_supervised(tmp_path):
    from disco_cli.errors import PoseFileError
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data

    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        _scan(_world(3), 2.0 * i, 0.0, 0.0, rng).tofile(seq / "velodyne" / f"{i:06d}.bin")
    with pytest.raises(PoseFileError, match="self-supervised"):
        load_training_data([seq], BEVConfig())
    data = load_training_data([seq], BEVConfig(), self_supervised=True, copies=2)
    assert len(data) == 9 and len(data.anchors) == 3
    assert np.all(data.source[data.anchors] == data.anchors)


# -- a short training run ------------------------------------------------------------


def test_self_supervised_training_runs_and_finds_the_copies(tmp_path, one_thread):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.loop import TrainOptions, train

    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(1)
    pillars = _world(5)
    for i in range(12):
        _scan(pillars, 15.0 * i, 0.0, 0.0, rng).tofile(seq / "velodyne" / f"{i:06d}.bin")
    data = load_training_data([seq], BEVConfig(), self_supervised=True, copies=1)
    opts = TrainOptions(
        epochs=1, steps=3, batch=2, negatives=2, width=2, self_supervised=True, time_gap=3, seed=0
    )
    history = train(data, BEVConfig(), opts, tmp_path / "ss.pt", log=lambda s: None)
    # Each augmented copy (rotated, moved, thinned) must find its own source scan.
    assert history[0]["train_queries"] == 12 and history[0]["train_recall_at_1"] >= 0.9
    assert history[0]["train_yaw_err_median"] < 3.0


def test_short_training_lowers_loss_and_beats_the_untrained_network(world, tmp_path, one_thread):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data
    from disco_cli.training.loop import train

    data = load_training_data([world], BEVConfig())
    out = tmp_path / "m.pt"
    opts, before, history, after = short_training(
        data, data, out, 3.0, 40, steps=10, d_pos=3.0, d_neg=10.0, val_queries=40
    )
    assert len(history) == 2
    assert history[-1]["loss"] < history[0]["loss"]
    assert after["recall_at_1"] >= before["recall_at_1"] + 0.2, (before, after)
    # Resuming a finished run trains no further epochs and keeps the history.
    again = train(data, BEVConfig(), opts, out, command="test", resume=True, log=lambda s: None)
    assert again == history


# -- the command ---------------------------------------------------------------------


def test_train_command_writes_a_loadable_checkpoint_and_resumes(world, tmp_path, one_thread):
    from typer.testing import CliRunner

    from disco_cli.cli import app
    from disco_cli.model import load_model

    out = tmp_path / "cli.pt"
    args = [
        "train",
        str(world),
        "-o",
        str(out),
        "--epochs",
        "1",
        "--steps",
        "2",
        "--batch",
        "2",
        "--negatives",
        "2",
        "--width",
        "2",
        "--seed",
        "3",
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    ckpt = torch.load(out, weights_only=True)
    assert len(ckpt["metrics"]["history"]) == 1
    # The provenance spells out every option, defaults included.
    assert ckpt["command"].startswith(f"disco train {world} -o {out} --epochs 1 --steps 2")
    assert "--lambda-yaw 0.1" in ckpt["command"] and "--residual" in ckpt["command"]
    assert load_model(str(out)).model_config["width"] == 2
    # An existing output is not overwritten by accident: one error line, exit 1.
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 1 and "--resume" in again.output and "Traceback" not in again.output
    # The per-epoch summary numbers epochs as the progress lines do (1 of 1), not from 0.
    summary = [ln for ln in result.stderr.splitlines() if "seconds=" in ln]
    assert len(summary) == 1 and summary[0].startswith("epoch 1/1 "), result.stderr
    assert "epoch=" not in result.stderr
    more = CliRunner().invoke(app, args[:5] + ["2"] + args[6:] + ["--resume"])
    assert more.exit_code == 0, more.output
    summary = [ln for ln in more.stderr.splitlines() if "seconds=" in ln]
    assert len(summary) == 1 and summary[0].startswith("epoch 2/2 "), more.stderr
    assert "after epoch 1" in more.stderr
    assert len(torch.load(out, weights_only=True)["metrics"]["history"]) == 2


def test_verify_loss_is_refused_without_poses(world, tmp_path):
    from typer.testing import CliRunner

    from disco_cli.cli import app

    args = ["train", str(world), "-o", str(tmp_path / "m.pt"), "--self-supervised"]
    res = CliRunner().invoke(app, [*args, "--lambda-verify", "0.5"])
    assert res.exit_code == 1 and "--lambda-verify needs poses" in res.stderr
    assert not (tmp_path / "m.pt").exists()


def test_train_command_reports_missing_poses_in_one_line(tmp_path):
    from typer.testing import CliRunner

    from disco_cli.cli import app

    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    _scan(_world(4), 0.0, 0.0, 0.0, np.random.default_rng(0)).tofile(
        seq / "velodyne" / "000000.bin"
    )
    result = CliRunner().invoke(app, ["train", str(seq), "-o", str(tmp_path / "m.pt")])
    assert result.exit_code == 1
    assert "poses.txt" in result.output and "Traceback" not in result.output
