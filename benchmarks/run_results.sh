#!/usr/bin/env bash
# Regenerates every number in docs/results.md: held-out simulated worlds and rotated real
# KITTI scans, evaluated with each model by `disco eval`. Outputs go under $OUT (default
# out/results, ignored by git): worlds, databases, one report folder per (data, model), and
# results.md with the table; with PLOTS=1 also the combined plots into docs/images/.
#
#   benchmarks/run_results.sh               # all models that are available
#   MODELS="spectral scancontext" benchmarks/run_results.sh
#
# Seeds >= 1000 are never used for training. Takes about 7 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
DISCO=${DISCO:-.venv/bin/disco}
PY=${PY:-.venv/bin/python}
OUT=${OUT:-out/results}
REALDATA=${REALDATA:-../shared/realdata}
if [[ -z "${MODELS:-}" ]]; then
  MODELS="spectral scancontext"
  # The shipped network, once its weights exist.
  if "$PY" -c "from disco_cli.model import load_model; load_model('default')" 2>/dev/null; then
    MODELS="default $MODELS"
  fi
fi
mkdir -p "$OUT/reports"

# name:sensor:seed. sim-vlp16-s1000 is the town of sim-hdl32 (same seed, same routes) seen
# by a 16-beam sensor: its session 01 queried against sim-hdl32's map is the cross-sensor test.
# The 400 m towns (seeds 1002, 1003) are larger, and their revisits run 2-3 m from the map.
WORLDS="sim-hdl32:hdl32:1000:300 sim-vlp16:vlp16:1001:300 sim-vlp16-s1000:vlp16:1000:300"
WORLDS="$WORLDS sim400-hdl32:hdl32:1002:400 sim400-vlp16:vlp16:1003:400"

for spec in $WORLDS; do
  IFS=: read -r name sensor seed length <<<"$spec"
  if [[ ! -f "$OUT/$name/world.json" ]]; then
    "$DISCO" simulate "$OUT/$name" --sessions 2 --length-m "$length" --sensor "$sensor" --seed "$seed"
  fi
done

# Real scans, rotated: KITTI 00 frames 0, 2, .., 10 form the map; frames 1, 3, .., 9 and 15,
# each turned by a random yaw (seed 1000), are the queries (frame 15 is 4.3 m from the map's
# last frame: a place with no true match at 3 m). "self": all 12 frames rotated vs themselves.
if [[ -d "$REALDATA/kitti00" && ! -f "$OUT/kitti00-rot/query/poses.txt" ]]; then
  "$PY" - "$REALDATA/kitti00" "$OUT" <<'PYEOF'
import sys
from pathlib import Path

import numpy as np

from disco_cli.io.poses import read_kitti_poses, write_kitti_poses
from disco_cli.io.readers import read_scan

src, out = Path(sys.argv[1]), Path(sys.argv[2])
frames = [int(p.stem) for p in sorted((src / "velodyne").glob("*.bin"))]
T_all = read_kitti_poses(src / "poses.txt", src / "calib.txt")
rng = np.random.default_rng(1000)


def rz(deg):
    a = np.deg2rad(deg)
    R = np.eye(4)
    R[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return R


def write(folder, chosen, rotate):
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    poses = []
    for i, f in enumerate(chosen):
        pts = read_scan(src / "velodyne" / f"{f:06d}.bin").copy()
        a = float(rng.uniform(-180, 180)) if rotate else 0.0
        pts[:, :3] = pts[:, :3] @ rz(a)[:3, :3].T  # points R(a) p: the sensor turned by -a
        pts.astype(np.float32).tofile(folder / "velodyne" / f"{i:06d}.bin")
        poses.append(T_all[f] @ rz(-a))
    write_kitti_poses(folder / "poses.txt", np.stack(poses))


write(out / "kitti00-rot" / "map", [f for f in frames if f % 2 == 0 and f <= 10], False)
write(out / "kitti00-rot" / "query", [f for f in frames if f % 2 == 1 or f == 15], True)
write(out / "kitti00-self" / "map", frames, False)
write(out / "kitti00-self" / "query", frames, True)
PYEOF
fi

# name:map:queries
DATA="sim-hdl32:$OUT/sim-hdl32/00:$OUT/sim-hdl32/01"
DATA="$DATA sim-vlp16:$OUT/sim-vlp16/00:$OUT/sim-vlp16/01"
DATA="$DATA sim-hdl32-map-vlp16-queries:$OUT/sim-hdl32/00:$OUT/sim-vlp16-s1000/01"
DATA="$DATA sim400-hdl32:$OUT/sim400-hdl32/00:$OUT/sim400-hdl32/01"
DATA="$DATA sim400-vlp16:$OUT/sim400-vlp16/00:$OUT/sim400-vlp16/01"
for name in kitti00-rot kitti00-self; do
  [[ -d "$OUT/$name" ]] && DATA="$DATA $name:$OUT/$name/map:$OUT/$name/query"
done

for spec in $DATA; do
  IFS=: read -r name map query <<<"$spec"
  for model in $MODELS; do
    db="$OUT/$name-$model.db"
    rm -f "$db" "$db-wal" "$db-shm"
    "$DISCO" build-db "$map" -o "$db" --model "$model"
    "$DISCO" eval "$query" --db "$db" --radius 3 --topk 25 --format tsv \
      --report "$OUT/reports/$name-$model" >/dev/null
  done
done

# Single-sequence loop closure: session 00 of each world drives a closed loop, so its last
# scans revisit its first; each scan searches the scans at least 100 frames (100 m) before it.
LOOPS="sim-hdl32 sim-vlp16 sim400-hdl32 sim400-vlp16"
for name in $LOOPS; do
  for model in $MODELS; do
    "$DISCO" eval-loops "$OUT/$name/00" --model "$model" --radius 3 --exclude-frames 100 \
      --format tsv --report "$OUT/reports/loops-$name-$model" >/dev/null
  done
done

# Scan Context's first stage: how often the true place is among the 10 candidates of the
# ring-key search, with the paper's occupancy ring key and with our default mean-height one.
"$PY" - "$OUT" $DATA <<'PYEOF' >"$OUT/ringkey.md"
import sys
from pathlib import Path

import numpy as np

from disco_cli.model.bev import polar_bev_batch
from disco_cli.io.poses import read_kitti_poses
from disco_cli.io.readers import list_scans, read_scan
from disco_cli.model.scancontext import ScanContextModel, ring_keys

model = ScanContextModel()
print("| data | revisits: median distance to the nearest map scan | true place among the 10 nearest ring keys: occupancy (paper) | mean height (ours) |")
print("| --- | ---: | ---: | ---: |")
for spec in sys.argv[2:]:
    name, map_dir, query_dir = spec.split(":")
    if name.startswith("kitti"):
        continue
    feats, xy = [], []
    for folder in (Path(map_dir), Path(query_dir)):
        clouds = [read_scan(p) for p in list_scans(folder)]
        feats.append(model.embed(polar_bev_batch(clouds, model.bev_config))[1])
        xy.append(read_kitti_poses(folder / "poses.txt")[:, :2, 3])
    dist = np.linalg.norm(xy[1][:, None] - xy[0][None], axis=-1)
    near = dist <= 3.0
    has = near.any(axis=1)
    cells = []
    for kind in ("occupancy", "mean"):
        km, kq = ring_keys(feats[0], kind), ring_keys(feats[1], kind)
        d = np.linalg.norm(kq[:, None] - km[None], axis=-1)
        top = np.argsort(d, axis=1, kind="stable")[:, :10]
        hit = np.take_along_axis(near, top, axis=1).any(axis=1)
        cells.append(f"{100 * hit[has].mean():.1f} %")
    gap = np.median(dist.min(axis=1)[near.any(axis=1)])
    print(f"| {name} | {gap:.2f} m | {cells[0]} | {cells[1]} |")
PYEOF

# The tables (and, with PLOTS=1, the combined plots for docs/images/).
"$PY" - "$OUT" "${PLOTS:-0}" $DATA <<'PYEOF'
import json
import sys
from pathlib import Path

out, plots = Path(sys.argv[1]), sys.argv[2] == "1"
names = [spec.split(":")[0] for spec in sys.argv[3:]]
order = ["default", "spectral", "scancontext"]


def pct(v):
    return "n/a" if v is None else f"{100 * v:.1f}"


def deg(v):
    return "n/a" if v is None else f"{v:.2f}"


lines = [
    "| data | model | Recall@1 | Recall@1% | AUC | F1max | R@100%P | yaw err mean / median (deg) | queries (with match) / map |",
    "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
]
for name in names:
    for model in order:
        f = out / "reports" / f"{name}-{model}" / "metrics.json"
        if not f.is_file():
            continue
        m = json.loads(f.read_text())
        lines.append(
            f"| {name} | {model} | {pct(m['recall@1'])} | {pct(m['recall@1%'])} | {pct(m['auc'])} "
            f"| {pct(m['f1_max'])} | {pct(m['recall@100%precision'])} "
            f"| {deg(m['yaw_err_mean_deg'])} / {deg(m['yaw_err_median_deg'])} "
            f"| {m['num_queries']} ({m['num_queries_with_match']}) / {m['num_database']} |"
        )
lines += [
    "",
    "| sequence (loop closure) | model | F1max | R@100%P | AUC | Recall@1 | yaw err mean / median (deg) | queries (with loop) |",
    "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
]
runs = []
for f in (out / "reports").glob("loops-*/metrics.json"):
    name = f.parent.name[len("loops-"):]
    model = next((o for o in order if name.endswith("-" + o)), None)
    if model is not None:
        runs.append((name[: -len(model) - 1], order.index(model), model, f))
for seq, _, model, f in sorted(runs):
    m = json.loads(f.read_text())
    name = f"{seq}-{model}"
    lines.append(
        f"| {name[: -len(model) - 1]}/00 | {model} | {pct(m['f1_max'])} | {pct(m['recall@100%precision'])} "
        f"| {pct(m['auc'])} | {pct(m['recall@1'])} "
        f"| {deg(m['yaw_err_mean_deg'])} / {deg(m['yaw_err_median_deg'])} "
        f"| {m['num_queries']} ({m['num_queries_with_match']}) |"
    )
if (out / "ringkey.md").is_file():
    lines += ["", (out / "ringkey.md").read_text().strip()]
(out / "results.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))

if plots:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    images = Path("docs/images")
    images.mkdir(parents=True, exist_ok=True)
    for name in names:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
        for model in order:
            d = out / "reports" / f"{name}-{model}"
            if not (d / "curves.json").is_file():
                continue
            c = json.loads((d / "curves.json").read_text())
            m = json.loads((d / "metrics.json").read_text())
            pr = c["pr"]
            ax1.plot(pr["recall"], pr["precision"], drawstyle="steps-post",
                     label=f"{model} (AUC {m['auc']:.3f})")
            err = np.sort(np.array(c["yaw_errors_deg"], dtype=float))
            if err.size:
                ax2.plot(err, np.arange(1, err.size + 1) / err.size, label=model)
        ax1.set(xlabel="Recall", ylabel="Precision", xlim=(0, 1.01), ylim=(0, 1.01),
                title=f"{name}: precision-recall")
        ax2.set(xlabel="|yaw error| (deg)", ylabel="fraction of correct top-1", xscale="log",
                title=f"{name}: yaw error CDF")
        for ax in (ax1, ax2):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(images / f"results-{name}.png", dpi=80)
        plt.close(fig)
        print(f"wrote {images / f'results-{name}.png'}")
PYEOF

# With UPDATE_DOCS=1, put the tables into docs/results.md between its markers.
if [[ "${UPDATE_DOCS:-0}" == 1 ]]; then
  "$PY" - "$OUT/results.md" docs/results.md <<'PYEOF'
import re
import sys
from pathlib import Path

table, doc = Path(sys.argv[1]).read_text().strip(), Path(sys.argv[2])
text = doc.read_text()
begin, end = "<!-- results:begin -->", "<!-- results:end -->"
new = re.sub(f"{begin}.*?{end}", lambda _: f"{begin}\n{table}\n{end}", text, flags=re.S)
doc.write_text(new)
print(f"updated {doc}")
PYEOF
fi
