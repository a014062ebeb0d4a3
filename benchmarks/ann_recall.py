"""Recall@1 of the whole query (re-ranking, the wider pass, the snap) with the exact index
and with the approximate one forced onto small maps: does the approximate search lose
places that the re-ranking would have found?

    PYTHONPATH=src:SITE .venv/bin/python benchmarks/ann_recall.py WORLD... [--model default]
        [--nlist 16] [--nprobe 1 4 16]

Each WORLD is a folder of `disco simulate` (sessions 00 and 01: the suite's worlds,
benchmarks/ood_suite.py); the protocol is the suite's (a match is true within 5 m,
Recall@1 over the queries with a map scan that near). A suite map holds 200-300 scans,
where `--index auto` would take the exact search; the approximate index is forced with
`nlist` clusters of which `nprobe` are scanned (1 of 16 is the share of the map a
million-scan map's default scans: 256 of 4,096), a PCA to 64 dimensions and 8-bit codes,
so that it is as approximate as at a million scans, or more.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from _common import print_header

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ood_suite as S  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("worlds", nargs="+", type=Path)
    ap.add_argument("--model", default="default")
    ap.add_argument("--nlist", type=int, default=16)
    ap.add_argument("--nprobe", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--pca", type=int, default=64)
    args = ap.parse_args()
    print_header("ann_recall")

    import torch

    from disco_cli.io.poses import xy_yaw
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch
    from disco_cli.maps.index.ann import AnnIndex, AnnParams
    from disco_cli.query.search import SignatureIndex, match_queries

    torch.set_num_threads(2)
    model = S.load_suite_model(args.model)
    settings = ["exact"] + [f"ann nprobe {p}/{args.nlist}" for p in args.nprobe]
    hits: dict[str, list[bool]] = {s: [] for s in settings}
    for world in args.worlds:
        e = S.embed_world(model, world, threads=2)
        mx, my, myaw = xy_yaw(e.map_poses)
        qx, qy, _ = xy_yaw(e.queries.poses)
        pose4 = np.c_[mx, my, e.map_poses[:, 2, 3], myaw]
        near = np.hypot(mx[None] - qx[:, None], my[None] - qy[:, None])
        has = near.min(axis=1) <= S.RADIUS
        line = [world.name]
        with tempfile.TemporaryDirectory() as tmp:
            paths = [str(p) for p in e.map_paths]
            batch = ScanBatch(paths, e.map_signatures, e.map_features, pose4)
            with Database.create(Path(tmp) / "map.db", ModelInfo.of(model), batch) as db:
                ids, _ = db.signatures()
                for s in settings:
                    if s == "exact":
                        index = SignatureIndex(e.map_signatures)
                    else:
                        nprobe = int(s.split()[2].split("/")[0])
                        params = AnnParams(args.nlist, nprobe, args.pca, 10)
                        index = AnnIndex.build(e.map_signatures, params)
                    found = match_queries(
                        index, ids, db, model, e.query_signatures, e.query_features, 1
                    )
                    got = [bool(f) and near[i, f[0].row] <= S.RADIUS for i, f in enumerate(found)]
                    got = [g for g, h in zip(got, has) if h]
                    hits[s] += got
                    line.append(f"{s}: {np.mean(got):.4f} ({len(got) - sum(got)} missed)")
        print("  ".join(line), flush=True)
    total = [
        f"{s}: {np.mean(h):.4f} ({len(h) - sum(h)} of {len(h)} missed)" for s, h in hits.items()
    ]
    print("all  " + "  ".join(total), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
