"""`disco serve`: the latency of one request, against the same query in the server's own
process (the floor) and a fresh `disco query` process per scan (what a script that
shells out pays without a server).

    .venv/bin/python benchmarks/bench_serve.py [--map-scans 300] [--queries 60]

A map of 30k-point synthetic scans is built first (`disco build-db`); then a server is
started on a Unix socket and asked about `--queries` scans, one request at a time over
one connection, by file path and with the points inline. Printed: the median and 90th
percentile of each, and the ratio to the in-process query measured in this run. Then
`--fleet` clients (20) connect at the same moment, each asking one scan by path, for
`--fleet-rounds` rounds: the median and the largest time from connecting to the reply,
and how many were answered.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _common import median_of_ms, print_header, synthetic_scan


def percentile_ms(seconds: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(seconds) * 1000.0, q))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map-scans", type=int, default=300)
    ap.add_argument("--queries", type=int, default=60)
    ap.add_argument("--fresh", type=int, default=5, help="fresh `disco query` processes")
    ap.add_argument("--fleet", type=int, default=20, help="clients connecting at once")
    ap.add_argument("--fleet-rounds", type=int, default=3)
    args = ap.parse_args()
    print_header("bench_serve")

    from disco_cli.maps.facade import Map
    from disco_cli.service.client import Client

    exe = Path(sys.executable).parent / "disco"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scans = tmp / "scans"
        scans.mkdir()
        for i in range(args.map_scans):
            synthetic_scan(i).tofile(scans / f"{i:06d}.bin")
        queries = []
        for i in range(args.queries):  # map scans turned and moved a little
            pts = synthetic_scan(i * 3 % args.map_scans).copy()
            a = np.radians(17.0 * i)
            c, s = np.cos(a), np.sin(a)
            pts[:, :2] = pts[:, :2] @ np.array([[c, -s], [s, c]], np.float32).T + 0.3
            path = tmp / f"q{i:04d}.bin"
            pts.tofile(path)
            queries.append(str(path))
        db = tmp / "map.db"
        subprocess.run(
            [str(exe), "build-db", str(scans), "-o", str(db)], check=True, stderr=subprocess.DEVNULL
        )

        # The floor: the same queries in this process, map and model already loaded.
        with Map.open(db) as m:
            list(m.query_files(queries[:3], topk=10))  # warm-up
            floor = []
            for q in queries:
                t = time.perf_counter()
                list(m.query_files([q], topk=10))
                floor.append(time.perf_counter() - t)

        sock = tmp / "disco.sock"
        proc = subprocess.Popen(
            [str(exe), "serve", "--db", str(db), "--socket", str(sock)], stderr=subprocess.PIPE
        )
        try:
            t0 = time.perf_counter()
            while not sock.exists():
                if proc.poll() is not None:
                    raise SystemExit(f"server failed: {proc.stderr.read().decode()}")
                time.sleep(0.02)
            ready = time.perf_counter() - t0
            from disco_cli.io.readers import read_scan

            inline_pts = [read_scan(q) for q in queries]
            with Client(sock) as c:
                for q in queries[:3]:
                    c.query(q)
                by_path, inline = [], []
                for q, pts in zip(queries, inline_pts):
                    t = time.perf_counter()
                    c.query(q)
                    by_path.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    c.query(pts)
                    inline.append(time.perf_counter() - t)
            fleet, answered = fleet_latencies(sock, queries, args.fleet, args.fleet_rounds)
        finally:
            proc.terminate()
            proc.wait(timeout=30)

        fresh = []
        for q in queries[: args.fresh]:
            t = time.perf_counter()
            subprocess.run(
                [str(exe), "query", q, "--db", str(db)],
                check=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            fresh.append(time.perf_counter() - t)

    base = median_of_ms(floor)
    print(
        f"map {args.map_scans} scans, {args.queries} queries of 30k points; "
        f"server ready in {ready:.2f} s"
    )
    print("| request | median ms | p90 ms | x in-process |")
    print("| --- | ---: | ---: | ---: |")
    for label, times in (
        ("in-process Map.query_files (floor)", floor),
        ("disco serve, scan path", by_path),
        ("disco serve, points inline", inline),
        ("fresh `disco query` process", fresh),
    ):
        med = median_of_ms(times)
        print(f"| {label} | {med:.2f} | {percentile_ms(times, 90):.2f} | {med / base:.2f} |")
    total = args.fleet * args.fleet_rounds
    print(
        f"{args.fleet} clients at once, {args.fleet_rounds} rounds: {answered} of {total} "
        f"answered; connect to reply median {median_of_ms(fleet):.1f} ms, "
        f"max {max(fleet) * 1000.0:.1f} ms"
    )


def fleet_latencies(sock: Path, queries: list[str], n: int, rounds: int) -> tuple[list, int]:
    """Seconds from connecting to the reply of `n` clients released together, each
    with its own connection and one query by path; and how many were answered."""
    from disco_cli.service.client import Client, ClientError

    times: list[float] = []
    answered = 0
    lock = threading.Lock()
    for r in range(rounds):
        gate = threading.Barrier(n)

        def one(i: int) -> None:
            nonlocal answered
            gate.wait()
            t = time.perf_counter()
            try:
                with Client(socket=sock) as c:
                    c.query(queries[(r * n + i) % len(queries)])
            except ClientError:
                return
            with lock:
                times.append(time.perf_counter() - t)
                answered += 1

        threads = [threading.Thread(target=one, args=(i,)) for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    return times, answered


if __name__ == "__main__":
    main()
