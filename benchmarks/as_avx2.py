"""Run a benchmark as an AVX2-only CPU would run it, on a CPU that also has AVX-512.

    .venv/bin/python benchmarks/as_avx2.py benchmarks/bench_query.py --model default

Most robot computers and cloud VMs have AVX2 but not AVX-512, and every library on the
query path picks its kernels by the CPU at run time. This launcher turns the AVX-512
ones off before any of them loads, then runs the script in this process:

- NumPy's dispatched loops: `NPY_DISABLE_CPU_FEATURES` (its AVX-512 feature groups);
- OpenBLAS: `OPENBLAS_CORETYPE=Haswell` (its AVX2 kernels);
- torch: `ATEN_CPU_CAPABILITY=avx2`;
- faiss (the approximate index's sidecar), where installed: `SIMDConfig.set_level(AVX2)`;
- disco's C++ core: its kernel level capped at 2 (AVX2 + FMA), as tests force it.

What it cannot change: the core's clock, caches and memory, and the width of its FMA
units; so the figures say what the AVX2 code paths cost on this core, not what an
AVX2-only CPU measures. Fresh processes a script starts inherit the variables but not
the core's cap (they pick the best kernel this CPU has).
"""

from __future__ import annotations

import os
import runpy
import sys

AVX2_ENVIRONMENT = {
    # NumPy's names for its AVX-512 groups (numpy._core._multiarray_umath.__cpu_features__).
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR "
    "AVX512F AVX512CD AVX512VL AVX512BW AVX512DQ",
    "OPENBLAS_CORETYPE": "Haswell",
    "ATEN_CPU_CAPABILITY": "avx2",
}
AVX2_KERNEL_LEVEL = 2  # the C++ core's levels: 3 AVX-512, 2 AVX2 + FMA, 1 SSE2, 0 plain
_MARK = "DISCO_BENCH_AS_AVX2"


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit("usage: as_avx2.py SCRIPT [ARGS...]")
    if os.environ.get(_MARK) != "1":
        # The libraries read their variables when they load: start again with them set.
        env = os.environ | AVX2_ENVIRONMENT | {_MARK: "1"}
        os.execve(sys.executable, [sys.executable, *sys.argv], env)
    from disco_cli import _core

    _core._set_bev_kernel_level(AVX2_KERNEL_LEVEL)
    try:
        import faiss  # deferred: optional (the `ann` extra); its level is set per process
    except ImportError:
        pass
    else:
        faiss.SIMDConfig.set_level(faiss.SIMDLevel_AVX2)
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    sys.path.insert(0, os.path.dirname(os.path.abspath(script)))
    print(
        f"# as_avx2: AVX-512 off in NumPy, OpenBLAS, torch and faiss; C++ kernels capped at "
        f"{_core._bev_kernel_name()}",
        flush=True,
    )
    runpy.run_path(script, run_name="__main__")


if __name__ == "__main__":
    main()
