"""A short seeded training run on issue 24's boulevard worlds (alike on both sides, query
scans moved up to 3 m along and across, a quarter to half of the cars, hedges and walls
gone) must find more places than the untrained network it starts from."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")


def test_short_training_on_a_boulevard_beats_the_untrained_network(tmp_path):
    from disco_cli.bev import BEVConfig
    from disco_cli.model import load_model
    from disco_cli.model.disco import DiscoModel, build_net, default_model_config
    from disco_cli.simulator import ChangeParams, RobotParams, TownParams, simulate
    from disco_cli.simulator.styles import BOULEVARD_TOWN, boulevard_change
    from disco_cli.training.data import load_training_data
    from disco_cli.training.evaluate import retrieval_metrics
    from disco_cli.training.loop import TrainOptions, train

    # Shorter blocks than the suite's, so that a 300 m session closes a loop and the
    # second one drives part of it again (in reverse).
    town = {**BOULEVARD_TOWN, "block_min_m": 60.0, "block_max_m": 80.0}
    params = TownParams(**town, change=ChangeParams(**boulevard_change(0.25)))
    world = tmp_path / "blv"
    robot = RobotParams(offset_m=0.0, jitter_m=3.0)
    simulate(
        world,
        2,
        length_m=300.0,
        step_m=4.0,
        sensor="vlp16",
        seed=5104,
        params=params,
        robot=robot,
        threads=2,
    )
    data = load_training_data([world], BEVConfig())
    before_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        opts = TrainOptions(
            epochs=2,
            steps=10,
            batch=4,
            negatives=2,
            width=4,
            lr=3e-3,
            residual=False,
            hard_after=1,
            d_pos=3.0,
            d_neg=10.0,
            seed=0,
            val_queries=40,
        )
        torch.manual_seed(opts.seed)
        config = {**default_model_config(20, 4), "residual": False}
        untrained = DiscoModel(build_net(config), BEVConfig(), config)
        before = retrieval_metrics(untrained, data, 5.0, max_queries=40, seed=0)
        out = tmp_path / "m.pt"
        history = train(data, BEVConfig(), opts, out, command="test", log=lambda s: None)
        after = retrieval_metrics(load_model(str(out)), data, 5.0, max_queries=40, seed=0)
    finally:
        torch.set_num_threads(before_threads)
    assert before["queries"] >= 30
    assert history[-1]["loss"] < history[0]["loss"]
    assert after["recall_at_1"] >= before["recall_at_1"] + 0.15, (before, after)
