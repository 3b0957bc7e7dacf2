#!/usr/bin/env bash
# The Instant-NGP family on one GPU (docs/results/instant-ngp-city-0-h200.json): NGP, NGP+LeCO and
# NGP+Prop on city-0, `cpu` profile, 1 minute each, seed 0: the pair step of bench/gpu-check.sh
# alone.
# NGP+LeCO's row there predates its current defaults; this recipe measures it with them.
# 3 runs of 1 training minute, plus validation and the scene's generation.
# Usage: bench/recipes/instant-ngp-city-0-h200.sh OUT   (repository root, on the GPU machine)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-city-0-h200.sh OUT}"
GPU_TESTS=0 GPU_PAPER=0 GPU_PAIR_METHODS=ngp,ngp-leco,ngp-prop GPU_PAIR_MIN=1 \
    bash bench/gpu-check.sh "$out"
