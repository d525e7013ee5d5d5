#!/usr/bin/env bash
# Interoperability with PlayCanvas splat-transform (needs Node; not a test): converts a scene to
# every format with nanogs-warp and has splat-transform read each one back to PLY, then has
# splat-transform write every format and reads each with nanogs-warp; prints counts and attribute
# errors against the input (tools/compare_formats.py), and runs the PLY -> SPZ -> PLY -> simplify
# round trip through splat-transform.
# Usage: bash tools/interop.sh SCENE.ply WORK_DIR
# SPLAT_TRANSFORM overrides the command (default: npx -y @playcanvas/splat-transform).
set -uo pipefail
scene=$1; work=$2
st=${SPLAT_TRANSFORM:-npx -y @playcanvas/splat-transform}
nanogs=${NANOGS:-nanogs-warp}
python=${PYTHON:-python3}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$work/ours" "$work/theirs" "$work/back"
$st --version || { echo "splat-transform does not run" >&2; exit 1; }

echo "== nanogs-warp writes, splat-transform reads"
for ext in compressed.ply spz sog splat; do
  $nanogs simplify "$scene" -o "$work/ours/scene.$ext" --ratio 1 --device cpu -q || echo "nanogs-warp could not write .$ext"
  $st -q -w "$work/ours/scene.$ext" "$work/back/from_ours_$ext.ply" || echo "splat-transform could not read our .$ext"
done
mkdir -p "$work/ours/lod"
$nanogs simplify "$scene" -o "$work/ours/lod/lod-meta.json" --ratio 1,0.1 --device cpu -q || echo "nanogs-warp could not write lod-meta.json"
# splat-transform takes a lod-meta.json as output only: it reads our set's levels, one SOG each
$st -q -w "$work/ours/lod/0_0/meta.json" "$work/back/from_ours_lod_level0.ply" || echo "splat-transform could not read our LOD level 0"
$python "$here/compare_formats.py" "$scene" "$work"/back/from_ours_*.ply

echo "== splat-transform writes, nanogs-warp reads"
$st -q -w "$scene" "$work/theirs/scene.compressed.ply"
$st -q -w "$scene" --spz-version 3 "$work/theirs/scene.spz"
$st -q -w -g cpu "$scene" "$work/theirs/scene.sog" || rm -f "$work/theirs/scene.sog"
mkdir -p "$work/theirs/meta" && $st -q -w -g cpu "$scene" "$work/theirs/meta/meta.json"
mkdir -p "$work/theirs/lod" && $st -q -w -g cpu "$scene" -l 0 "$work/ours/lod/1_0/meta.json" -l 1 "$work/theirs/lod/lod-meta.json"
$python "$here/compare_formats.py" "$scene" "$work/theirs/scene.compressed.ply" "$work/theirs/scene.spz" \
  "$work/theirs/scene.sog" "$work/theirs/meta/meta.json" "$work/theirs/lod/lod-meta.json"
$nanogs info "$work/theirs/lod/lod-meta.json" | head -2

echo "== PLY -> SPZ -> PLY (splat-transform) -> simplify"
$st -q -w "$work/theirs/scene.spz" "$work/theirs/spz_back.ply"
$nanogs info "$work/theirs/spz_back.ply" | grep -E "splats|NaN|opacity"
$nanogs simplify "$work/theirs/spz_back.ply" -o "$work/theirs/spz_back_small.ply" --ratio 0.1 --device cpu --json \
  | $python -c "import json, sys; s = json.load(sys.stdin); print('input', s['input_count'], 'after prune', s['after_prune_count'], 'output', s['outputs'][0]['count'], 'notes', s['notes'])"
