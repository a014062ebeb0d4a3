"""Which distance the query's rows show (issue 32): Recall@1, recall at 100 % precision,
F1max, AUC, yaw error and how many queries print their top 10 out of distance order.

    .venv/bin/python docs/research/probes/ranking_score_eval.py MAP.db:QUERY_DIR:RADIUS ... \\
        [--shown shifted raw own]

Each argument is a map built by `disco build-db` (with poses), a folder of query scans
with their poses.txt, and the radius (m) within which a match is true. The queries are
embedded once (cached beside the map as MAP.db.queries.npz) and searched as `disco eval`
searches them (`search.match_queries`, the model's policy, exact index, 25 deep or 1 %
of the map), once for each way of showing the distance; the rows' order is the same in
all three (the ranking score, `search.ranking_score`, with the snap as its tie-break):

- `shifted` (shipped): the score, shifted so that the first row shows the query's own
  re-rank distance to it (`search.shown_distances`);
- `raw`: the score itself (re-rank distance less 0.3 over the signature distance);
- `own`: each row's own re-rank distance, as before issue 32 (rows then out of order).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]

SHOWN = {
    "shifted": None,  # the shipped search.shown_distances
    "raw": lambda score, own, first: np.asarray(score, np.float64),
    "own": lambda score, own, first: np.asarray(own, np.float64),
}


def evaluate(db_path: str, query_dir: Path, radius: float) -> dict:
    import disco_cli.query.search as search
    from disco_cli.embedding.batches import embed_paths
    from disco_cli.evaluation.metrics import one_percent_n
    from disco_cli.evaluation.runs import score_retrieval
    from disco_cli.io.poses import read_kitti_poses
    from disco_cli.io.readers import list_scans
    from disco_cli.maps.facade import Map
    from disco_cli.maps.index import index_for_database

    out = {}
    with Map.open(db_path) as m:
        db, model = m.database, m.model
        cache = Path(f"{db_path}.queries.npz")
        if cache.is_file():
            z = np.load(cache)
            sigs, feats = z["signatures"], z["features"]
        else:
            paths = [str(p) for p in list_scans(query_dir)]
            sigs, feats = embed_paths(paths, model, None)
            np.savez(cache, signatures=sigs, features=feats)
        query_poses = read_kitti_poses(query_dir / "poses.txt")
        ids, index = index_for_database(db, "exact")
        depth = max(25, one_percent_n(len(ids)))
        map_rows, _ = db.poses()
        shipped = search.shown_distances
        for name, shown in SHOWN.items():
            search.shown_distances = shipped if shown is None else shown
            try:
                found = search.match_queries(index, ids, db, model, sigs, feats, depth)
            finally:
                search.shown_distances = shipped
            metrics = score_retrieval(found, depth, 25, query_poses, map_rows, radius).metrics
            unsorted = sum(
                any(a.distance > b.distance for a, b in zip(f[:10], f[1:10])) for f in found
            )
            out[name] = {**metrics, "unsorted": unsorted, "queries": len(found)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", nargs="+", help="MAP.db:QUERY_DIR:RADIUS")
    ap.add_argument("--shown", nargs="+", default=list(SHOWN), choices=list(SHOWN))
    args = ap.parse_args()
    from _common import print_header

    print_header("ranking_score_eval")
    print(
        "| data | shown | Recall@1 | R@100%P | F1max | AUC | yaw err mean (deg) | top 10 unsorted |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for spec in args.worlds:
        db, query_dir, radius = spec.rsplit(":", 2)
        got = evaluate(db, Path(query_dir), float(radius))
        for name in args.shown:
            m = got[name]
            print(
                f"| {Path(db).stem} | {name} | {100 * m['recall@1']:.1f} "
                f"| {100 * m['recall@100%precision']:.1f} | {100 * m['f1_max']:.1f} "
                f"| {100 * m['auc']:.1f} | {m['yaw_err_mean_deg']:.2f} "
                f"| {m['unsorted']} of {m['queries']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
