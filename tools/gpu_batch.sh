#!/usr/bin/env bash
# `nanogs-warp batch` on a machine with several GPUs: the shared scenes at three budgets, then four
# tiled 6M-splat scenes on one GPU and on all of them, with GPU utilisation sampled every 100 ms.
# Usage: bash tools/gpu_batch.sh SCENES_DIR LOG_DIR WORK_DIR
#   SCENES_DIR: a folder of .ply scenes with playbot.ply among them (docs/scenes.md); LOG_DIR: where
#   logs go; WORK_DIR: scratch space for the tiled scenes and the batch outputs (about 6 GB).
set -uo pipefail
if [ $# -lt 3 ]; then sed -n '2,7p' "$0"; exit 2; fi
scenes=$1; log=$2; work=$3
mkdir -p "$log" "$work/big"
export PYTHONUNBUFFERED=1
nvidia-smi -L | tee "$log/gpus.txt"
nvidia-smi --query-gpu=timestamp,index,utilization.gpu,memory.used --format=csv,noheader -lms 100 > "$log/util.csv" &
sampler=$!
run() { local name=$1; shift; local t0=$(date +%s.%N); python3 -m nanogs_warp batch "$@" --json > "$log/$name.json" 2> "$log/$name.err"; local rc=$?;
        echo "$name: exit $rc, $(python3 -c "print(f'{$(date +%s.%N) - $t0:.2f}')") s wall" | tee -a "$log/summary.txt"; }
run shared_all "$scenes" -o "$work/out_shared" --ratio 0.1,0.01,0.001 --devices all
run shared_again "$scenes" -o "$work/out_shared" --ratio 0.1,0.01,0.001 --devices all
for i in 0 1 2 3; do python3 tools/tile_scene.py "$scenes/playbot.ply" "$work/big/playbot6m_$i.ply" --count $((6000000 + i)); done
run big_one_gpu "$work/big" -o "$work/out_big1" --ratio 0.1,0.01,0.001 --devices cuda:0
run big_all_gpus "$work/big" -o "$work/out_big2" --ratio 0.1,0.01,0.001 --devices all
kill $sampler
python3 - "$log" <<'PY'
import csv, json, sys
from collections import defaultdict
log = sys.argv[1]
busy = defaultdict(int); total = defaultdict(int)
for row in csv.reader(open(f"{log}/util.csv")):
    if len(row) < 4: continue
    gpu, util = row[1].strip(), int(row[2].strip().split()[0])
    total[gpu] += 1; busy[gpu] += util > 0
for gpu in sorted(total): print(f"GPU {gpu}: {busy[gpu]} of {total[gpu]} samples busy")
for name in ("shared_all", "shared_again", "big_one_gpu", "big_all_gpus"):
    try: d = json.load(open(f"{log}/{name}.json"))
    except Exception as e: print(name, "no json", e); continue
    scenes = d.get("scenes", d) if isinstance(d, dict) else d
    print(name, json.dumps({k: v for k, v in d.items() if k != "scenes"}) if isinstance(d, dict) else "")
    for s in scenes if isinstance(scenes, list) else []:
        print("  ", s.get("input"), s.get("status"), s.get("device"), s.get("seconds"), [o["count"] for o in s.get("outputs") or []])
PY
cmp "$work/out_big1/playbot6m_0_0.1.ply" "$work/out_big2/playbot6m_0_0.1.ply" && echo "one-GPU and all-GPU outputs identical"
