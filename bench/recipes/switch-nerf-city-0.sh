#!/usr/bin/env bash
# The Switch-NeRF family's standing on city-0 (docs/results/switch-nerf-city-0.json): LeCO, S+Prop,
# vanilla Switch-NeRF and the occupancy grid, 8 minutes each, seeds 0 and 1, in one command.
# 8 runs of 8 training minutes: 83 minutes of wall time on 2 CPU cores when measured.
# Usage: bench/recipes/switch-nerf-city-0.sh OUT   (from the repository root; OUT: a new folder)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-city-0.sh OUT}"
source bench/recipes/scenes.sh
city=$(scene city-0)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 8 --methods leco,prop,switch,grid \
    --seeds 0,1 --out "$out"
