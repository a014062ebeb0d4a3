"""Issue 24's second-robot fine-tune: its worlds, its BEVs as compact arrays, and
`disco train`'s loop run on those arrays (on a GPU machine without disco's compiled core).

    .venv/bin/python docs/research/probes/train_second_robot.py worlds DIR  # training + selection
    .venv/bin/python docs/research/probes/train_second_robot.py export DIR/tr.npz DIR/tr/*
    python3 docs/research/probes/train_second_robot.py train DIR/tr.npz --val DIR/val.npz \
        --init default.pt --out run/ --epochs 12 --every 3 --device cuda --d-pos 8 --d-neg 15

`export` voxelizes exactly as `disco train` loads (`load_training_data`, --spacing 1,
--variants 1, --seed 7) and bit-packs the occupancy BEVs (9,422 BEVs: 13 MB); `train`
resumes a copy of `--init` (the shipped weights) with `training.loop.train`, the loop of
`disco train`, writing a snapshot every `--every` epochs. Seeds: training 4101-4108
(4190-4199 in tests), selection 5111-5115; the suite's boulevards are 7107, 7207, 7401
(docs/research/model-history.md#seeds).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]  # the repository, from docs/research/probes
sys.path.insert(0, str(ROOT / "src"))

# name: seed, sensor, change, sessions, length m, step m, robot options
SELECTION = {
    "sel/rv5111": (5111, "hdl32", 0.25, 2, 600, 4, ["--robot-side", "4,8"]),
    "sel/hd5112": (5112, "vlp16", 0.25, 2, 600, 4, ["--robot-jitter", "3", "--robot-tilt", "3"]),
    "sel/rv5113": (5113, "hdl32", 0.30, 2, 600, 4, ["--robot-side", "4,8"]),
    "sel/bv5114": (5114, "hdl32", 0.25, 2, 600, 4, ["--robot-jitter", "1.5"]),
    "sel/hd5115": (5115, "vlp16", 0.30, 2, 600, 4, ["--robot-jitter", "3", "--robot-tilt", "3"]),
}
TRAINING = {
    "tr/rv4101": (4101, "hdl32", 0.25, 3, 400, 2, ["--robot-side", "3,8"]),
    "tr/hd4102": (4102, "vlp16", 0.30, 3, 400, 2, ["--robot-jitter", "3", "--robot-tilt", "3"]),
    "tr/rv4103": (4103, "vlp16", 0.30, 3, 400, 2, ["--robot-side", "3,8", "--robot-tilt", "3"]),
    "tr/bv4104": (4104, "hdl32", 0.25, 3, 400, 2, ["--robot-jitter", "1.5"]),
    "tr/rv4105": (4105, "hdl32", 0.30, 3, 400, 2, ["--robot-side", "3,8"]),
    "tr/hd4106": (4106, "vlp16", 0.25, 3, 400, 2, ["--robot-jitter", "3", "--robot-tilt", "3"]),
}
# Two towns of the default `grid` style (the suite holds the other styles out).
GRID = {
    "tr/gr4107": (4107, "vlp16"),
    "tr/gr4108": (4108, "hdl32"),
}


def _town_toml(path: Path, change: float, wide: bool) -> Path:
    """The suite's boulevard town (ood_suite._simulate_boulevard), wider for side revisits."""
    from disco_cli.simulator.styles import boulevard_toml

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(boulevard_toml(change, wide))
    return path


def worlds(out: Path, disco: str) -> None:
    for name, (seed, sensor, change, sessions, length, step, robot) in {
        **SELECTION,
        **TRAINING,
    }.items():
        folder = out / name
        if (folder / "world.json").is_file():
            continue
        wide = "--robot-side" in robot
        town = _town_toml(out / "towns" / f"{folder.name}.toml", change, wide)
        cmd = [disco, "simulate", str(folder), "--sessions", str(sessions)]
        cmd += ["--length-m", str(length), "--sensor", sensor, "--seed", str(seed)]
        cmd += ["--town", str(town), "--step-m", str(step)]
        cmd += robot if wide else ["--robot-offset", "0", *robot]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    for name, (seed, sensor) in GRID.items():
        folder = out / name
        if (folder / "world.json").is_file():
            continue
        cmd = [disco, "simulate", str(folder), "--sessions", "3", "--length-m", "300"]
        cmd += ["--step-m", "1.5", "--sensor", sensor, "--seed", str(seed), "--change", "0.3"]
        cmd += ["--robot-offset", "3", "--robot-tilt", "3"]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def export(out: Path, folders: list[Path], spacing: float, variants: int, seed: int) -> None:
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data

    d = load_training_data(folders, BEVConfig(), spacing=spacing, seed=seed, variants=variants)
    if d.bevs.dtype != np.uint8 or d.bevs.max() > 1:
        raise SystemExit("export: the BEVs are not occupancy grids; nothing to bit-pack")
    np.savez_compressed(
        out,
        bits=np.packbits(d.bevs, axis=-1),
        shape=np.array(d.bevs.shape),
        xy=d.xy,
        heading_deg=d.heading_deg,
        group=d.group,
        session=d.session,
        frame=d.frame,
        source=d.source,
        anchors=d.anchors,
        sessions=np.array(d.sessions),
    )
    print(out, d.bevs.shape, f"{len(d.anchors)} scans")


def load(path: Path):
    from disco_cli.training.data import TrainData

    z = np.load(path)
    bevs = np.unpackbits(z["bits"], axis=-1, count=int(z["shape"][-1]))
    return TrainData(
        bevs=bevs,
        xy=z["xy"],
        heading_deg=z["heading_deg"],
        group=z["group"],
        session=z["session"],
        frame=z["frame"],
        source=z["source"],
        sessions=[str(s) for s in z["sessions"]],
        anchors=z["anchors"],
    )


def train(a: argparse.Namespace) -> None:
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.loop import TrainOptions
    from disco_cli.training.loop import train as run

    data, val = load(a.data), (load(a.val) if a.val else None)
    a.out.mkdir(parents=True, exist_ok=True)
    ck = a.out / "ft.pt"
    shutil.copy(a.init, ck)
    opts = dict(
        steps=a.steps,
        batch=a.batch,
        negatives=4,
        lr=a.lr,
        lambda_yaw=0.15,
        d_pos=a.d_pos,
        d_neg=a.d_neg,
        hard_after=1,
        lambda_verify=1.0,
        verify_radius=10.0,
        variants=1,
        augment_p=0.5,
        occlude_p=0.2,
        seed=7,
        device=a.device,
    )
    t0 = time.monotonic()
    for e in range(a.every, a.epochs + 1, a.every):
        run(
            data,
            BEVConfig(),
            TrainOptions(epochs=e, **opts),
            ck,
            command=f"{a.command} ; train_second_robot.py train {json.dumps(opts)} epochs {e}",
            resume=True,
            val=val,
            log=lambda s: print(s, flush=True),
        )
        shutil.copy(ck, a.out / f"ft-e{e}.pt")
        print(f"epoch {e}: {time.monotonic() - t0:.0f} s", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    w = sub.add_parser("worlds")
    w.add_argument("out", type=Path)
    w.add_argument("--disco", default=str(ROOT / ".venv" / "bin" / "disco"))
    x = sub.add_parser("export")
    x.add_argument("out", type=Path)
    x.add_argument("folders", nargs="+", type=Path)
    x.add_argument("--spacing", type=float, default=1.0)
    x.add_argument("--variants", type=int, default=1)
    x.add_argument("--seed", type=int, default=7)
    t = sub.add_parser("train")
    t.add_argument("data", type=Path)
    t.add_argument("--val", type=Path)
    t.add_argument("--init", type=Path, required=True, help="checkpoint to start from")
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--epochs", type=int, default=12)
    t.add_argument("--every", type=int, default=3)
    t.add_argument("--steps", type=int, default=150)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--d-pos", type=float, default=8.0)
    t.add_argument("--d-neg", type=float, default=15.0)
    t.add_argument("--device", default="cuda")
    t.add_argument("--command", default="", help="provenance: the command that made --init")
    a = ap.parse_args()
    if a.what == "worlds":
        worlds(a.out, a.disco)
    elif a.what == "export":
        export(a.out, a.folders, a.spacing, a.variants, a.seed)
    else:
        train(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
