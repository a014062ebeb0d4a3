"""The training loop: quadruplets of precomputed BEVs, random rotations, joint loss, Adam.

Every step draws `batch` quadruplets (query, positive, k negatives, one other negative),
rolls each BEV by a random number of sectors (the paper's N-way rotation augmentation,
exact on a polar grid), drops a random share of its cells (sparser sensors), and
minimizes L_quad + lambda * L_rot. After `hard_after` epochs
half of the negatives are the query's nearest signatures among its true negatives.

Augmentation beyond the paper's: with `augment_p > 0` each sampled scan is replaced, with
that probability, by one of its augmented copies (`data.load_training_data(variants=N)`:
fewer beams, fewer points, tilted, shifted in z); with `occlude_p > 0` a BEV loses a
random wedge of 30-90 degrees (every height and ring of those sectors), as when a truck
or a wall beside the car hides part of the view.

A checkpoint is written after every epoch; `resume=True` continues from it. Every epoch's
random numbers derive from (seed, epoch), so a resumed run draws what the uninterrupted
run would have drawn.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from disco_cli.errors import ModelError
from disco_cli.model.checkpoint import read_checkpoint, save_checkpoint
from disco_cli.model.disco import DiscoModel, build_net, default_model_config
from disco_cli.model.signature import signatures_torch
from disco_cli.model.verify import aligned_correlation_torch
from disco_cli.model.yaw import correlation_curves_torch, expected_shift_torch
from disco_cli.training.data import TrainData
from disco_cli.training.evaluate import retrieval_metrics
from disco_cli.training.losses import quadruplet_loss, verify_loss, yaw_loss
from disco_cli.training.mining import PairMiner


@dataclass
class TrainOptions:
    epochs: int = 10
    steps: int = 0  # steps per epoch; 0: one pass over the queries
    batch: int = 8
    negatives: int = 4
    lr: float = 1e-3
    lambda_yaw: float = 0.1
    margin1: float = 0.5
    margin2: float = 0.2
    d_pos: float = 3.0
    d_neg: float = 10.0
    width: int = 8
    residual: bool = True
    bev_dropout: float = 0.1
    hard_after: int = 2
    self_supervised: bool = False
    time_gap: int = 50
    seed: int = 0
    device: str = "cpu"
    val_queries: int = 300
    # Re-ranking loss (this project's addition, 0 = the paper's loss only): each query's
    # U image against `verify_candidates` scans of another pass within `verify_radius` m.
    lambda_verify: float = 0.0
    verify_candidates: int = 6
    verify_radius: float = 10.0
    # Augmentation (0 = off): augmented copies made at load time, and wedge occlusion.
    variants: int = 0
    augment_p: float = 0.0
    occlude_p: float = 0.0


StepCallback = Callable[[int, int, int, dict[str, float]], None]


def _roll_batch(bevs: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """Each BEV [H, R, S] rolled along sectors by its own amount."""
    s = bevs.shape[-1]
    cols = (np.arange(s)[None, :] - rolls[:, None]) % s
    return np.take_along_axis(bevs, cols[:, None, None, :], axis=-1)


def _occlude(bevs: np.ndarray, p: float, rng: np.random.Generator) -> np.ndarray:
    """Each BEV [H, R, S], with probability p, loses a wedge of 30-90 degrees of sectors."""
    s = bevs.shape[-1]
    hit = np.flatnonzero(rng.random(len(bevs)) < p)
    for b in hit:
        width = int(round(rng.uniform(30.0, 90.0) * s / 360.0))
        cols = (int(rng.integers(0, s)) + np.arange(width)) % s
        bevs[b][..., cols] = 0
    return bevs


def _pool_signatures(
    net: Any, data: TrainData, rows: np.ndarray, device: str, crop: tuple[int, int]
) -> np.ndarray:
    out = []
    net.eval()
    with torch.no_grad():
        for s in range(0, len(rows), 64):
            x = torch.from_numpy(data.float_bevs(rows[s : s + 64])).to(device)
            out.append(signatures_torch(net(x), crop).cpu().numpy())
    return np.concatenate(out)


def _model_config(heights: int, opts: TrainOptions) -> dict[str, Any]:
    model_config = default_model_config(heights, opts.width)
    model_config["residual"] = bool(opts.residual)
    return model_config


def resumable_checkpoint(
    out_path: str | Path, heights: int, opts: TrainOptions
) -> dict[str, Any] | None:
    """The checkpoint at `out_path` that `--resume` continues (None: there is none yet,
    training starts); `ModelError` when it is unreadable or of another model
    configuration. `disco train` calls it before loading any data."""
    out_path = Path(out_path)
    if not out_path.is_file():
        return None
    ckpt = read_checkpoint(out_path)
    if dict(ckpt.get("model_config", {})) != _model_config(heights, opts):
        raise ModelError(f"{out_path}: was trained with another model configuration; cannot resume")
    return ckpt


def train(
    data: TrainData,
    bev_config: Any,
    opts: TrainOptions,
    out_path: str | Path,
    command: str = "",
    resume: bool = False,
    val: TrainData | None = None,
    on_step: StepCallback | None = None,
    log: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Train and write checkpoints to out_path; the per-epoch history is returned."""
    out_path = Path(out_path)
    device = opts.device
    model_config = _model_config(data.bevs.shape[1], opts)
    crop = tuple(model_config["crop"])
    torch.manual_seed(opts.seed)
    net = build_net(model_config).to(device)
    optim = torch.optim.Adam(net.parameters(), lr=opts.lr)
    start_epoch, history = 0, []
    ckpt = resumable_checkpoint(out_path, data.bevs.shape[1], opts) if resume else None
    if ckpt is not None:
        net.load_state_dict(ckpt["state_dict"])
        state = ckpt.get("train_state", {})
        if "optimizer" in state:
            optim.load_state_dict(state["optimizer"])
        start_epoch = int(state.get("epoch", -1)) + 1
        history = list(ckpt.get("metrics", {}).get("history", []))
        # Keep the whole provenance: every command that trained these weights, in order.
        previous = str(ckpt.get("command", ""))
        if previous and command and previous.split(" ; ")[-1] != command:
            command = f"{previous} ; {command}"
        elif previous:
            command = previous
        log(f"resuming {out_path} after epoch {start_epoch}")

    miner = PairMiner(data, opts.d_pos, opts.d_neg, opts.self_supervised, opts.time_gap)
    steps = opts.steps or max(1, len(miner.queries) // opts.batch)
    k = opts.negatives
    per = 3 + k
    sectors = data.sectors
    variants = data.variant_table() if opts.augment_p > 0 else None
    if variants is not None and variants.shape[1] == 0:
        variants = None
    for epoch in range(start_epoch, opts.epochs):
        rng = np.random.default_rng([opts.seed, epoch])
        torch.manual_seed(opts.seed * 100_003 + epoch)
        if epoch >= opts.hard_after and len(miner.pool) > per:
            miner.update_hard(_pool_signatures(net, data, miner.pool, device, crop))
        net.train()
        t0 = time.monotonic()
        sums = {"loss": 0.0, "quad": 0.0, "yaw": 0.0, "yaw_deg": 0.0}
        if opts.lambda_verify > 0:
            sums["verify"] = 0.0
        for step in range(steps):
            qs = rng.choice(miner.queries, size=opts.batch)
            rows = np.empty((opts.batch, per), dtype=np.int64)
            for b, q in enumerate(qs):
                negs = miner.negatives(int(q), k, rng)
                rows[b, 0] = q
                rows[b, 1] = miner.positive(int(q), rng)
                rows[b, 2 : 2 + k] = negs
                rows[b, -1] = miner.other_negative(int(q), negs, rng)
            flat = rows.ravel()
            vsets = []
            if opts.lambda_verify > 0 and not opts.self_supervised:
                for b, q in enumerate(qs):
                    found = miner.verify_set(
                        int(q), opts.verify_candidates, opts.verify_radius, rng
                    )
                    if found is not None:
                        vsets.append((b, *found))
                if vsets:
                    flat = np.concatenate([flat, *[v[1] for v in vsets]])
            rolls = rng.integers(0, sectors, size=len(flat))
            shown = flat
            if variants is not None:
                # Some scans are shown as one of their augmented copies (same pose).
                pick = variants[flat, rng.integers(0, variants.shape[1], size=len(flat))]
                swap = (rng.random(len(flat)) < opts.augment_p) & (pick >= 0)
                shown = np.where(swap, pick, flat)
            bevs = _roll_batch(data.float_bevs(shown), rolls)
            if opts.occlude_p > 0:
                bevs = _occlude(bevs, opts.occlude_p, rng)
            x = torch.from_numpy(bevs).to(device)
            if opts.bev_dropout > 0:
                # Domain randomization: drop occupied cells, as a sparser sensor would.
                x = x * (torch.rand(x.shape, device=device) >= opts.bev_dropout)
            feats = net(x)
            verify_feats = None
            if vsets:
                # The image that re-ranking compares: the U-Net's own part (DiscoModel._u).
                u = feats - x.sum(dim=1) if opts.residual else feats
                n_main = opts.batch * per
                verify_feats = u[n_main:].view(len(vsets), opts.verify_candidates, *u.shape[1:])
                verify_query = u[:n_main].view(opts.batch, per, *u.shape[1:])[
                    [v[0] for v in vsets], 0
                ]
                feats = feats[:n_main]
            sig = signatures_torch(feats, crop).view(opts.batch, per, -1)
            l_quad = quadruplet_loss(
                sig[:, 0], sig[:, 1], sig[:, 2 : 2 + k], sig[:, -1], opts.margin1, opts.margin2
            )
            f = feats.view(opts.batch, per, *feats.shape[1:])
            log_p = net.corr2soft(correlation_curves_torch(f[:, 0], f[:, 1]))
            # q ~ roll(p, delta): delta from the headings, plus the two augmentation rolls.
            r = rolls[: opts.batch * per].reshape(opts.batch, per)
            head = (data.heading_deg[rows[:, 1]] - data.heading_deg[rows[:, 0]]) * sectors / 360.0
            shift = torch.as_tensor(head + r[:, 0] - r[:, 1], device=device)
            l_yaw = yaw_loss(log_p, shift)
            loss = l_quad + opts.lambda_yaw * l_yaw
            if verify_feats is not None:
                scores = aligned_correlation_torch(verify_query, verify_feats)
                dists = torch.as_tensor(np.stack([v[2] for v in vsets]), device=device)
                l_verify = verify_loss(scores, dists.float())
                loss = loss + opts.lambda_verify * l_verify
                sums["verify"] += float(l_verify.detach())
            with torch.no_grad():
                # The paper's estimate, the expectation of p(delta), as a readable error.
                diff = expected_shift_torch(log_p.exp()) - shift + sectors / 2
                off = torch.remainder(diff, sectors)
                yaw_deg = ((off - sectors / 2).abs() * 360.0 / sectors).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
            for key, v in (("loss", loss), ("quad", l_quad), ("yaw", l_yaw), ("yaw_deg", yaw_deg)):
                sums[key] += float(v.detach())
            if on_step:
                on_step(epoch, step + 1, steps, {key: v / (step + 1) for key, v in sums.items()})
        entry: dict[str, Any] = {"epoch": epoch, "seconds": round(time.monotonic() - t0, 1)}
        entry.update({key: round(v / steps, 5) for key, v in sums.items()})
        model = DiscoModel(net, bev_config, model_config, name="training", device=device)
        check = val if val is not None else data
        metrics = retrieval_metrics(
            model,
            check,
            opts.d_pos,
            opts.self_supervised and val is None,
            max_queries=opts.val_queries,
            seed=opts.seed,
            time_gap=opts.time_gap,
        )
        prefix = "val" if val is not None else "train"
        entry.update({f"{prefix}_{key}": v for key, v in metrics.items()})
        history.append(entry)
        # Numbered from 1 as the progress bar numbers it ("epoch 1/2"); the history keeps
        # the 0-based index that `resume` reads.
        log(
            f"epoch {epoch + 1}/{opts.epochs} "
            + " ".join(
                f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                for k, v in entry.items()
                if k != "epoch"
            )
        )
        save_checkpoint(
            out_path,
            {
                "state_dict": net.state_dict(),
                "bev_config": bev_config.to_dict(),
                "model_config": model_config,
                "command": command,
                "train_state": {
                    "epoch": epoch,
                    "optimizer": optim.state_dict(),
                    "options": {key: v for key, v in asdict(opts).items()},
                },
                "metrics": {"history": history},
            },
        )
    return history
