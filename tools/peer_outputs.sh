#!/usr/bin/env bash
# Other simplifiers' outputs beside a quality sweep's (needs Node; not a test): PlayCanvas
# splat-transform 2.7.1 (`-F N`, config st27), 3.7.0 (`-d N`, st37d) and 3.7.0
# `--decimate-adaptive N` (st37a), on the CPU (`-g cpu`), to exactly ceil(rho x N) splats, written
# as SWEEP_DIR/ply/<scene>_<config>_<ratio>.ply: the names `tools/quality_sweep.py --keep-ply` gives
# its own outputs, so that `tools/unseen_cameras.py SCENES/ SWEEP_DIR/ --configs default,st37a`
# compares them, and `nanogs-warp eval` scores them on the orbit. A file already there is kept.
# Usage: bash tools/peer_outputs.sh SCENES_DIR SWEEP_DIR [RATIOS]   (RATIOS default 0.1,0.01,0.001)
# ST27 and ST37 override the two commands (default: npx -y @playcanvas/splat-transform@VERSION).
set -euo pipefail
scenes=$1; out=$2/ply; ratios=${3:-0.1,0.01,0.001}
st27=${ST27:-npx -y @playcanvas/splat-transform@2.7.1}
st37=${ST37:-npx -y @playcanvas/splat-transform@3.7.0}
python=${PYTHON:-python3}
mkdir -p "$out"
run() {  # config, command, decimation option; the scene, its name, the ratio and the count from the loops below
  local file="$out/${name}_$1_$ratio.ply"
  [ -f "$file" ] && return
  $2 -g cpu -q "$scene" "$file.part.ply" $3 "$count" && mv "$file.part.ply" "$file" || echo "$1 failed on $name at $ratio" >&2
}
for scene in "$scenes"/*.ply; do
  name=$(basename "$scene" .ply)
  # the counts nanogs-warp keeps for these ratios (exact ceils of ratio x N), the scene read once
  counts=($($python -c "import sys
from nanogs_warp.config import target_count
from nanogs_warp.io import read_splat_arrays
n = read_splat_arrays(sys.argv[1]).count
print(*(target_count(n, r) for r in sys.argv[2].split(',')))" "$scene" "$ratios"))
  k=0
  for ratio in ${ratios//,/ }; do
    count=${counts[$k]}; k=$((k + 1))
    run st27 "$st27" -F
    run st37d "$st37" -d
    run st37a "$st37" --decimate-adaptive
    echo "$name $ratio: $count splats"
  done
done
