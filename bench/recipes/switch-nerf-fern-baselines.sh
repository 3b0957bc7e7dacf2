#!/usr/bin/env bash
# Vanilla Switch-NeRF and the occupancy grid on fern (docs/results/switch-nerf-fern-baselines.json),
# 5 minutes each, seed 0, one tracked validation view. The command measured also trained NGP+LeCO
# last; it is left out here.
# 2 runs of 5 training minutes: vanilla's validation renders make it the slow one.
# Usage: bench/recipes/switch-nerf-fern-baselines.sh OUT   (from the repository root)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-fern-baselines.sh OUT}"
source bench/recipes/scenes.sh
fern=$(scene fern)
.venv/bin/leco bench --scene "$fern" --profile cpu --budget-min 5 --eval-every-s 60 --eval-views 1 \
    --methods switch,grid --seeds 0 --out "$out"
