"""Benchmark: the DiSCO network, signatures and yaw on the CPU.

Times, in one process, with medians over repeats:
  * signatures per scan, batched (BEV -> U-Net -> |FFT2| crop), for the shipped model, for
    randomly initialized U-Nets of several widths (the paper's is 64), and for `spectral`
    (no network) as the floor;
  * one scan end to end: read the file, voxelize, embed (the latency of a single query);
  * yaw for 10 candidates by phase correlation, against the exhaustive search it replaces
    (every one of the 120 circular shifts scored by a dot product, in NumPy).
The scan is KITTI frame 0 from ../shared/realdata when present, else a sample scan.

`--accuracy` instead measures yaw on the real scans of ../shared/realdata for `spectral`
and the shipped model: each KITTI scan against copies of itself rotated by random yaws over
the whole circle, and KITTI frame i against frame i + 1 (the query rotated by a random yaw,
truth from the poses), plus the hdl32 pair against rotated copies of itself.
Run: `.venv/bin/python benchmarks/bench_model.py [--widths 8 16 64] [--threads N] [--accuracy]`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _common import median_wall_cpu_ms as median_ms
from _common import print_header

from disco_cli.io.readers import list_scans, read_scan
from disco_cli.model import DEFAULT_WEIGHTS, load_model
from disco_cli.model.bev import BEVConfig, polar_bev, polar_bev_batch
from disco_cli.model.disco import DiscoModel, build_net, default_model_config

REPO = Path(__file__).resolve().parent.parent
KITTI = REPO.parent / "shared" / "realdata" / "kitti00" / "velodyne" / "000000.bin"
SAMPLES = REPO / "data" / "samples" / "00"


def exhaustive_yaw(query: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """The baseline: score all S circular shifts of each candidate by a dot product."""
    s = query.shape[-1]
    best = np.empty(len(matches))
    for k, m in enumerate(matches):
        scores = [float(np.sum(query * np.roll(m, d, axis=-1))) for d in range(s)]
        best[k] = np.argmax(scores)
    return -best * 360.0 / s


def rotate(points: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def yaw_accuracy(names: list[str] | None = None, spins: int = 8) -> None:
    from disco_cli.io.poses import read_kitti_poses, relative_yaw_deg, wrap_deg

    real = REPO.parent / "shared" / "realdata"
    seq = real / "kitti00"
    if not seq.is_dir():
        print("no ../shared/realdata: nothing to measure")
        return
    poses = read_kitti_poses(seq / "poses.txt", seq / "calib.txt")
    frames = sorted(list_scans(seq / "velodyne"))
    if not names:
        names = ["spectral"] + (["default"] if DEFAULT_WEIGHTS.is_file() else [])
    print(
        "\n| model | KITTI scan vs rotated self: mean / max error (deg) "
        "| KITTI i vs i+1: mean / max "
        "| hdl32 scan vs rotated self: mean / max |"
    )
    print("| --- | ---: | ---: | ---: |")
    for name in names:
        model = load_model(name)
        rng = np.random.default_rng(0)
        self_err, next_err, hdl_err = [], [], []
        for path in frames:
            pts = read_scan(path)
            angles = rng.uniform(-180.0, 180.0, spins)
            bevs = polar_bev_batch([pts] + [rotate(pts, a) for a in angles], model.bev_config)
            _, f = model.embed(bevs)
            est = np.array([model.yaw(q, f[:1])[0] for q in f[1:]])
            self_err += list(np.abs(wrap_deg(est + angles)))
        for i in range(10):
            spin = float(rng.uniform(-180.0, 180.0))
            m_pts = read_scan(seq / "velodyne" / f"{i:06d}.bin")
            q_pts = rotate(read_scan(seq / "velodyne" / f"{i + 1:06d}.bin"), spin)
            _, f = model.embed(polar_bev_batch([q_pts, m_pts], model.bev_config))
            truth = wrap_deg(relative_yaw_deg(poses[i], poses[i + 1]) - spin)
            next_err.append(abs(wrap_deg(model.yaw(f[0], f[1:])[0] - truth)))
        for path in sorted((real / "hdl32_pair").glob("*.bin")):
            pts = read_scan(path)
            angles = rng.uniform(-180.0, 180.0, spins)
            _, f = model.embed(
                polar_bev_batch([pts] + [rotate(pts, a) for a in angles], model.bev_config)
            )
            est = np.array([model.yaw(q, f[:1])[0] for q in f[1:]])
            hdl_err += list(np.abs(wrap_deg(est + angles)))
        cells = [
            f"{np.mean(e):.2f} / {np.max(e):.2f}" if e else "-"
            for e in (self_err, next_err, hdl_err)
        ]
        print(f"| {name} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--widths", type=int, nargs="*", default=[8, 16, 64])
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument(
        "--accuracy", action="store_true", help="yaw accuracy on the real scans instead"
    )
    ap.add_argument(
        "--models", nargs="*", help="--accuracy: model names or checkpoints (spectral, default)"
    )
    args = ap.parse_args()
    print_header("bench_model")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.accuracy:
        yaw_accuracy(args.models)
        return
    scan_path = KITTI if KITTI.is_file() else list_scans(SAMPLES)[0]
    points = read_scan(scan_path)
    config = BEVConfig()
    bev = polar_bev(points, config)
    rng = np.random.default_rng(0)
    bevs = np.stack([np.roll(bev, int(k), axis=-1) for k in rng.integers(0, 120, args.batch)])
    print(f"# torch {torch.__version__} on {torch.get_num_threads()} threads")
    print(
        f"# scan {scan_path.name}: {len(points)} points; batch {args.batch}; "
        f"medians of {args.repeat}"
    )

    models = {"spectral": load_model("spectral")}
    if DEFAULT_WEIGHTS.is_file():
        models["default"] = load_model("default")
    for w in args.widths:
        torch.manual_seed(0)
        cfg = default_model_config(config.heights, w)
        models[f"unet-w{w} (random)"] = DiscoModel(build_net(cfg), config, cfg, name=f"w{w}")

    print(
        "\n| model | signature per scan, batched: wall / CPU (ms) "
        "| single scan, read + BEV + embed: wall / CPU (ms) |"
    )
    print("| --- | ---: | ---: |")
    for name, model in models.items():
        bw, bc = median_ms(lambda m=model: m.embed(bevs), args.repeat)

        def single(m=model) -> None:
            m.embed(polar_bev_batch([read_scan(scan_path)], config))

        sw, sc = median_ms(single, args.repeat)
        print(f"| {name} | {bw / args.batch:.2f} / {bc / args.batch:.2f} | {sw:.2f} / {sc:.2f} |")

    model = models.get("default", models["spectral"])
    _, feats = model.embed(bevs[:11])
    q, cands = feats[0], feats[1:]
    fast = median_ms(lambda: model.yaw(q, cands), max(args.repeat, 20))[0]
    # The baseline works on G, F_cnn's output (channel 0 of the two-image features).
    g_q, g_c = (q[0], cands[:, 0]) if q.ndim == 3 else (q, cands)
    slow = median_ms(lambda: exhaustive_yaw(g_q, g_c), 3, warmup=1)[0]
    print(
        f"\nyaw, 10 candidates ({next(k for k, v in models.items() if v is model)} features): "
        f"phase correlation {fast:.3f} ms, exhaustive shift search {slow:.1f} ms "
        f"({slow / fast:.0f}x)"
    )
    if model.abilities.rerank:
        rerank = median_ms(lambda: model.rerank_distances(q, cands), max(args.repeat, 20))[0]
        print(f"re-ranking 10 candidates, yaw included: {rerank:.3f} ms")


if __name__ == "__main__":
    main()
