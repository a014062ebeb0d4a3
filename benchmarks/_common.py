"""Helpers shared by every benchmark: the machine header each prints first, timing
medians, and the synthetic scans and stand-in model that several use.

Benchmarks run as scripts (`.venv/bin/python benchmarks/bench_x.py`), so this
module is imported as `_common` from the script's own folder. It imports only the
standard library and NumPy at the top; disco_cli's C++ core is loaded when the
header is printed.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
REALDATA = REPO.parent / "shared" / "realdata"


def cpu_model() -> str:
    """The CPU's model name: /proc/cpuinfo on Linux (x86 'model name'; on ARM the
    'Model' or 'Hardware' line, or the implementer and part numbers), else what
    platform knows."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                key, sep, value = line.partition(":")
                if sep and key.strip() not in fields:
                    fields[key.strip()] = value.strip()
    except OSError:
        pass
    for key in ("model name", "Model", "Hardware", "cpu model"):
        if fields.get(key):
            return fields[key]
    if "CPU implementer" in fields:
        return f"ARM implementer {fields['CPU implementer']} part {fields.get('CPU part', '?')}"
    return platform.processor() or platform.machine() or "unknown CPU"


def bev_kernel() -> str:
    """The polar BEV kernel in use, and the best this CPU has (e.g. 'avx512')."""
    from disco_cli import _core

    return _core._bev_kernel_name()


def machine_line() -> str:
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    # NumPy's own SIMD loops (arctan2, sqrt) follow the CPU too; this variable turns
    # some off, e.g. "X86_V4 AVX512_ICL" to time NumPy as a CPU without AVX-512 runs it.
    disabled = os.environ.get("NPY_DISABLE_CPU_FEATURES")
    numpy_note = f" (NPY_DISABLE_CPU_FEATURES={disabled})" if disabled else ""
    return (
        f"machine: {cpu_model()} ({platform.machine()}), {os.cpu_count()} cores, "
        f"load average {load}; BEV kernel: {bev_kernel()}; Python "
        f"{sys.version.split()[0]}, NumPy {np.__version__}{numpy_note}"
    )


def print_header(name: str) -> None:
    """The first line of every benchmark's output: which machine the figures are from."""
    print(f"# {name} on {machine_line()}", flush=True)


def _status_mib(field: str) -> float:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in MiB; NaN where it is absent."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def rss_mib() -> float:
    """This process's resident memory (VmRSS) in MiB; NaN where /proc does not say."""
    return _status_mib("VmRSS")


def peak_rss_mib() -> float:
    """This process's peak resident memory (VmHWM) in MiB; NaN where /proc does not say."""
    return _status_mib("VmHWM")


def median_ms(fn: Callable[[], object], repeats: int, warmup: int = 2) -> float:
    """Median wall-clock milliseconds of fn() over `repeats` calls, after `warmup`."""
    return median_wall_cpu_ms(fn, repeats, warmup)[0]


def median_wall_cpu_ms(
    fn: Callable[[], object], repeats: int, warmup: int = 2
) -> tuple[float, float]:
    """Median wall and median process CPU (all threads) milliseconds of fn(); the CPU
    time shows the work done apart from waiting for a busy machine."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        c0 = time.process_time_ns()
        t0 = time.perf_counter_ns()
        fn()
        wall.append(time.perf_counter_ns() - t0)
        cpu.append(time.process_time_ns() - c0)
    return statistics.median(wall) / 1e6, statistics.median(cpu) / 1e6


def interleaved_medians_ms(
    fns: dict[str, Callable[[], object]], rounds: int, block: int = 10, warmup: int = 2
) -> dict[str, float]:
    """Median wall-clock milliseconds of each fn over rounds x block calls. Each round
    calls every fn `block` times in a row (warm caches after the first), one fn after
    the other: on a shared machine they then all see the same spells of load, so
    their ratios hold even when the absolute times drift."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times: dict[str, list[int]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(block):
                t0 = time.perf_counter_ns()
                fn()
                times[name].append(time.perf_counter_ns() - t0)
    return {name: statistics.median(t) / 1e6 for name, t in times.items()}


def median_of_ms(seconds: list[float]) -> float:
    """Median of durations measured in seconds, in milliseconds."""
    return float(np.median(seconds)) * 1e3


def synthetic_scan(seed: int, n: int = 30000) -> np.ndarray:
    """Points on random boxes and a ground ring around the sensor (float32 N x 4)."""
    rng = np.random.default_rng(seed)
    boxes = 60
    r = rng.uniform(4.0, 60.0, boxes)
    a = rng.uniform(0.0, 2 * np.pi, boxes)
    centre = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    size = rng.uniform(0.5, 6.0, (boxes, 2))
    height = rng.uniform(0.5, 8.0, boxes)
    k = rng.integers(0, boxes, n)
    xy = centre[k] + (rng.random((n, 2)) - 0.5) * size[k]
    z = rng.random(n) * height[k] - 1.7
    return np.column_stack([xy, z, rng.random(n)]).astype(np.float32)


def disco_command() -> list[str]:
    """How to run the `disco` command with this interpreter: its console script beside
    the interpreter, else `python -m disco_cli.cli`."""
    exe = Path(sys.executable).parent / "disco"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "disco_cli.cli"]


def model_arg(name: str, tmp: Path) -> tuple[str, str]:
    """The --model argument to use, and what it is: `default` without shipped
    weights becomes the same architecture, untrained (the same cost), saved in tmp."""
    from disco_cli.model import DEFAULT_WEIGHTS

    if name != "default" or DEFAULT_WEIGHTS.is_file():
        return name, name
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.checkpoint import save_checkpoint
    from disco_cli.model.disco import build_net, default_model_config

    bev = BEVConfig()
    cfg = default_model_config(bev.heights)
    path = tmp / "untrained-default.pt"
    save_checkpoint(
        path,
        {
            "state_dict": build_net(cfg).state_dict(),
            "bev_config": bev.to_dict(),
            "model_config": cfg,
            "command": "bench_build_db",
        },
    )
    return str(path), "default architecture, untrained weights (no shipped weights yet)"
