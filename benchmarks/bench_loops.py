"""Online loop closure per scan: what `LoopDetector` adds to each scan after its embedding.

    .venv/bin/python benchmarks/bench_loops.py [--length-m 400] [--seed 0]

Simulates one drive through a town (`disco simulate`'s library call, hdl32), embeds every
scan once, then feeds the embeddings to two detectors in the same process, scan by scan
and alternating which goes first: the model as shipped, and the same model without the
wider re-ranking pass (`rerank_wider = 0`, the baseline). Per scan that searches (past the
50-frame exclusion window): median and 90th percentile of `add_embedded` (search,
re-ranking, yaw of the best match; no pose), and how many scans re-ranked wider. The
embedding itself (3-5 ms a scan) is `bench_model.py`'s. Both detectors leave out the
geometric check of the best candidates (`check_candidates = 0`): it reads each scan's
points, which this benchmark does not keep (`bench_query.py` times the check).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


class _Counting:
    """Wraps a model's re-ranking (with the query's views, as DiSCO re-ranks) to count
    its calls: a scan's second is the wider pass."""

    def __init__(self, model):
        self.calls, self._rerank = 0, model.rerank_distances_views
        model.rerank_distances_views = self

    def __call__(self, query_features, features, views):
        self.calls += 1
        return self._rerank(query_features, features, views)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--length-m", type=float, default=400.0, help="length of the drive (m)")
    ap.add_argument("--seed", type=int, default=0, help="the town's seed")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    import ood_suite as suite
    import torch
    from _common import median_of_ms, print_header

    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.query.loop_detector import LoopDetector
    from disco_cli.simulator import simulate

    torch.set_num_threads(args.threads)
    print_header("bench_loops")
    with tempfile.TemporaryDirectory() as tmp:
        simulate(tmp, sessions=1, length_m=args.length_m, seed=args.seed, threads=0)
        paths, _ = suite.load_session(Path(tmp) / "00")
        shipped, baseline = load_model("default"), load_model("default")
        sigs, feats = suite.embed(shipped, lambda i: read_scan(paths[i]), len(paths), args.threads)
    counter, wider = _Counting(shipped), 0
    unchecked = replace(shipped.query_policy, check_candidates=0)
    detectors = {
        "shipped": LoopDetector(shipped, verify=False, policy=unchecked),
        "without the wider pass": LoopDetector(
            baseline, verify=False, policy=replace(unchecked, rerank_wider=0)
        ),
    }
    times: dict[str, list[float]] = {k: [] for k in detectors}
    for i in range(len(paths)):
        counter.calls = 0
        order = list(detectors) if i % 2 == 0 else list(detectors)[::-1]
        for name in order:
            t = time.perf_counter()
            detectors[name].add_embedded(sigs[i], feats[i])
            if i >= detectors[name].exclude_frames:
                times[name].append(time.perf_counter() - t)
        wider += counter.calls > 1
    n = len(times["shipped"])
    print(f"{len(paths)} scans of a {args.length_m:g} m drive (seed {args.seed}); {n} search")
    for name, ts in times.items():
        print(
            f"  {name}: median {median_of_ms(ts):.2f} ms per scan, 90th percentile "
            f"{np.percentile(ts, 90) * 1e3:.2f} ms"
        )
    ratio = np.median(times["shipped"]) / np.median(times["without the wider pass"])
    print(f"  ratio of the medians: {ratio:.2f}; scans that re-ranked wider: {wider}")


if __name__ == "__main__":
    main()
