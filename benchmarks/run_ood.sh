#!/usr/bin/env bash
# The out-of-distribution validation suite of issue 12 (benchmarks/ood_suite.py): held-out
# town styles and generator settings at scene-change levels 0, 0.15, 0.30 and 0.45, with
# 16, 32 and 64 beams, a hard set (16 beams, tilted queries), a stress set (everything
# changed), and real KITTI scans made hard.
# Recall@1, Recall@5, Recall@1% and yaw error for each model, by change level and by the
# distance to the nearest map scan; tables in $OUT/{quick,full}/tables.md.
#
#   benchmarks/run_ood.sh --quick                       # a few minutes: one style, 32 beams
#   benchmarks/run_ood.sh                               # every world (85; hdl64 costs most)
#   benchmarks/run_ood.sh --quick --models default spectral run/candidate.pt
#   benchmarks/run_ood.sh --update-docs                 # tables into docs/research/ood-suite.md
#   benchmarks/run_ood.sh --only blv --no-real          # issue 24's boulevard worlds only
#
# Its seeds (7101-7301) are used by nothing else (docs/research/model-history.md#seeds). Runs at low priority
# on 2 threads; worlds and per-query rows are cached under $OUT (default out/ood).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
OUT=${OUT:-out/ood}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
exec nice -n 10 "$PY" benchmarks/ood_suite.py --out "$OUT" "$@"
