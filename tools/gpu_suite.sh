#!/usr/bin/env bash
# Everything we measure on a GPU machine, in one go (see README "GPU checks"):
#   tests on cuda:0, the CLI on every scene at three budgets, per-stage benchmarks of the real scenes
#   and of tiled scenes, and agreement with CPU outputs made beforehand.
# Usage: bash tools/gpu_suite.sh SCENES_DIR CPU_OUTPUTS_DIR LOG_DIR [real|tiled|all]
set -uo pipefail
scenes=$1; cpu_out=$2; log=$3; part=${4:-all}
mkdir -p "$log" /tmp/gpu_out
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$log/gpu.txt"

if [ "$part" != tiled ]; then
echo "== tests on cuda:0"
python3 -m pytest -q -p no:cacheprovider --continue-on-collection-errors -k "cuda" tests 2>&1 | tail -n 25 | tee "$log/pytest_cuda.txt"

echo "== CLI, every scene, ratios 0.1,0.01,0.001 (PLY read and write included)"
for f in "$scenes"/*.ply; do
  s=$(basename "$f" .ply)
  # the first run also compiles the CUDA kernels (kept in Warp's cache); the second is the one reported
  python3 -m nanogs_warp simplify "$f" -o /tmp/gpu_out/$s.ply --ratio 0.1,0.01,0.001 --device cuda:0 --json > "$log/cli_${s}_first.json" 2>&1 || echo "FAILED $s"
  python3 -m nanogs_warp simplify "$f" -o /tmp/gpu_out/$s.ply --ratio 0.1,0.01,0.001 --device cuda:0 --json > "$log/cli_$s.json" 2>&1
  python3 - "$log/cli_$s.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(f"{d['input']:>40} {d['input_count']:>9,} passes={d['passes']:>2} total={d['seconds']['total']:.3f}s read={d['seconds']['read']:.3f}s",
      " ".join(f"{o['budget']}:{o['count']}@{o['seconds']:.3f}s" for o in d["outputs"]))
PY
done | tee "$log/cli_summary.txt"

echo "== CPU vs CUDA agreement"
python3 tools/compare_outputs.py "$cpu_out" /tmp/gpu_out 2>&1 | tee "$log/agreement.txt"

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
python3 tools/tile_scene.py "$scenes"/playbot.ply /tmp/playbot6m.ply --count 6000000
ls -la /tmp/playbot6m.ply
for run in first second; do
  /usr/bin/time -f "$run: %e s wall, %M KB peak host" python3 -m nanogs_warp simplify /tmp/playbot6m.ply -o /tmp/playbot6m_small.ply --ratio 0.1 --device cuda:0 --json > "$log/cli_6m_$run.json"
done 2>&1 | tee "$log/cli_6m.txt"
python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print('6M CLI:', d['seconds'], d['passes'], 'passes', d['outputs'][0]['count'], 'splats')" "$log/cli_6m_second.json" | tee -a "$log/cli_6m.txt"
fi
