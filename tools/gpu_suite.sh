#!/usr/bin/env bash
# Everything we measure on a GPU machine, in one go (figures in docs/performance.md):
#   tests on cuda:0, the CLI on every scene at three budgets, per-stage benchmarks of the real scenes
#   and of tiled scenes, and agreement with CPU outputs made beforehand.
# Usage: bash tools/gpu_suite.sh SCENES_DIR CPU_OUTPUTS_DIR LOG_DIR WORK_DIR [real|tiled|all]
#   SCENES_DIR: a folder of .ply scenes (docs/scenes.md); CPU_OUTPUTS_DIR: the same scenes simplified
#   on the CPU beforehand (<scene>_<ratio>.ply); LOG_DIR: where logs go; WORK_DIR: scratch space for
#   GPU outputs and a 6M-splat tiled scene (about 1 GB).
set -uo pipefail
if [ $# -lt 4 ]; then sed -n '2,9p' "$0"; exit 2; fi
scenes=$1; cpu_out=$2; log=$3; work=$4; part=${5:-all}
gpu_out="$work/gpu_out"
mkdir -p "$log" "$gpu_out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$log/gpu.txt"

if [ "$part" != tiled ]; then
echo "== tests on cuda:0"
python3 -m pytest -q -p no:cacheprovider --continue-on-collection-errors -k "cuda" tests 2>&1 | tail -n 25 | tee "$log/pytest_cuda.txt"

echo "== CLI, every scene, ratios 0.1,0.01,0.001 (PLY read and write included)"
for f in "$scenes"/*.ply; do
  s=$(basename "$f" .ply)
  # the first run also compiles the CUDA kernels (kept in Warp's cache); the second is the one reported
  python3 -m nanogs_warp simplify "$f" -o "$gpu_out/$s.ply" --ratio 0.1,0.01,0.001 --device cuda:0 -w --json > "$log/cli_${s}_first.json" 2>&1 || echo "FAILED $s"
  python3 -m nanogs_warp simplify "$f" -o "$gpu_out/$s.ply" --ratio 0.1,0.01,0.001 --device cuda:0 -w --json > "$log/cli_$s.json" 2>&1
  python3 - "$log/cli_$s.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(f"{d['input']:>40} {d['input_count']:>9,} passes={d['passes']:>2} total={d['seconds']['total']:.3f}s read={d['seconds']['read']:.3f}s",
      " ".join(f"{o['budget']}:{o['count']}@{o['seconds']:.3f}s" for o in d["outputs"]))
PY
done | tee "$log/cli_summary.txt"

echo "== CPU vs CUDA agreement"
python3 tools/compare_outputs.py "$cpu_out" "$gpu_out" 2>&1 | tee "$log/agreement.txt"

echo "== per-stage benchmarks, real scenes"
python3 tools/bench.py "$scenes"/*.ply --device cuda:0 --ratio 0.1,0.01,0.001 --repeat 3 --log "$log/bench.jsonl" 2>&1 | tee "$log/bench_real.txt"
fi
if [ "$part" != real ]; then
echo "== tiled scenes"
for n in 1000000 6000000 20000000 50000000; do
  python3 tools/bench.py "$scenes"/playbot.ply --tile $n --device cuda:0 --ratio 0.1 --repeat 3 --log "$log/bench.jsonl" 2>&1 | tail -n 3
done | tee "$log/bench_tiled.txt"
python3 tools/bench.py "$scenes"/playbot.ply --tile 6000000 --device cuda:0 --ratio 0.001 --repeat 3 --log "$log/bench.jsonl" 2>&1 | tail -n 3 | tee -a "$log/bench_tiled.txt"
# k = 24 (the default at these sizes is 16): time and memory of the wider graph
for n in 6000000 50000000; do
  python3 tools/bench.py "$scenes"/playbot.ply --tile $n --device cuda:0 --ratio 0.1 --repeat 3 --k 24 --log "$log/bench.jsonl" 2>&1 | tail -n 3
done | tee -a "$log/bench_tiled.txt"
echo "== CLI end to end, 6M splats to 0.1 (PLY read and write included)"
python3 tools/tile_scene.py "$scenes"/playbot.ply "$work/playbot6m.ply" --count 6000000
ls -la "$work/playbot6m.ply"
for run in first second; do
  /usr/bin/time -f "$run: %e s wall, %M KB peak host" python3 -m nanogs_warp simplify "$work/playbot6m.ply" -o "$work/playbot6m_small.ply" --ratio 0.1 --device cuda:0 -w --json > "$log/cli_6m_$run.json"
done 2>&1 | tee "$log/cli_6m.txt"
python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print('6M CLI:', d['seconds'], d['passes'], 'passes', d['outputs'][0]['count'], 'splats')" "$log/cli_6m_second.json" | tee -a "$log/cli_6m.txt"
fi
