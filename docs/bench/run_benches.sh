#!/usr/bin/env bash
# Reproduces docs/bench/<scene>_d<D>/bench.{csv,md,svg}: a path reference per scene and depth
# (time-budgeted), then `cvfarm bench` of the CV estimator against `path`.
#
#   cargo build --release -p cli && docs/bench/run_benches.sh
#
# Environment: REF_SECONDS (reference render budget, default 45), MAX_SECONDS (per-estimator
# bench budget, default 30), SPP_SERIES (default 32,64,…,512), SCENES (default: colour-lamp many-lights veach-mis envmap cornell-box; empty for none),
# DEPTHS (default: 2 5), ESTIMATORS (default: path,cms), SEEDS (renders per point, default 3:
# the error is then the seed-to-seed variance of one render, free of the reference's own noise;
# the reference only normalises), OUT (default docs/bench: where the <scene>_d<D> directories go),
# SAMPLER (sobol or independent, default sobol: the sampler of every bench render; references
# are always Sobol `path` renders).
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${BIN:-target/release/cvfarm}
REF_SECONDS=${REF_SECONDS:-45}
MAX_SECONDS=${MAX_SECONDS:-30}
# cms trains on its first 16 spp: start the series where the CV is applied.
SPP_SERIES=${SPP_SERIES:-32,64,128,256,512}
SCENES=${SCENES-"colour-lamp many-lights veach-mis envmap cornell-box"}
DEPTHS=${DEPTHS:-"2 5"}
ESTIMATORS=${ESTIMATORS:-path,cms}
SEEDS=${SEEDS:-3}
OUT=${OUT:-docs/bench}
SAMPLER=${SAMPLER:-sobol}
mkdir -p out/bench-ref
for scene in $SCENES; do
  for d in $DEPTHS; do
    ref=out/bench-ref/${scene}_d${d}.exr
    if [ ! -f "$ref" ]; then
      "$BIN" render "scenes/$scene/scene.json" --max-depth "$d" --seed 1000 \
        --time-budget "$REF_SECONDS" -o "$ref" --stats "${ref%.exr}.json"
    fi
    "$BIN" bench "scenes/$scene/scene.json" --estimators "$ESTIMATORS" --max-depth "$d" \
      --reference "$ref" --max-seconds "$MAX_SECONDS" --spp-series "$SPP_SERIES" --seeds "$SEEDS" \
      --sampler "$SAMPLER" --out "$OUT/${scene}_d${d}"
  done
done
# The shared Mitsuba scenes (MITSUBA_SCENES, default below; empty to skip) at their native
# 128×128 against the shared references (depth 5 only), into $OUT/mitsuba-<name>_d5.
SHARED=${SHARED:-../shared/scenes-mitsuba}
MITSUBA_SCENES=${MITSUBA_SCENES-"cbox manylights-4 bsdf-spheres/roughplastic-ggx bsdf-spheres/roughconductor-ggx"}
for s in $MITSUBA_SCENES; do
  name=$(basename "$s")
  "$BIN" bench "$SHARED/$s/scene.xml" --estimators "$ESTIMATORS" --max-depth 5 \
    --reference "$SHARED/refs/${name}_d5.exr" --max-seconds 60 --spp-series 128,256,512 \
    --seeds "$SEEDS" --sampler "$SAMPLER" --out "$OUT/mitsuba-${name}_d5"
done
