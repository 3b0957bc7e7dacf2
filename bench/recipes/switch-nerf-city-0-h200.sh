#!/usr/bin/env bash
# LeCO against S+Prop on one GPU (docs/results/switch-nerf-city-0-h200.json): city-0, `cpu` profile,
# 2 minutes each, seed 0: the pair step of bench/gpu-check.sh alone (no CUDA tests, no paper step).
# 2 runs of 2 training minutes (the whole gpu-check.sh took about 8.5 minutes on an H200).
# Usage: bench/recipes/switch-nerf-city-0-h200.sh OUT   (repository root, on the GPU machine)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-city-0-h200.sh OUT}"
GPU_TESTS=0 GPU_PAPER=0 GPU_PAIR_METHODS=leco,prop GPU_PAIR_MIN=2 bash bench/gpu-check.sh "$out"
