#!/usr/bin/env bash
# The Switch-NeRF family's standing on city-7, a city no default was tuned on
# (docs/results/switch-nerf-city-7.json): LeCO and S+Prop, 8 minutes each, seed 0.
# 2 runs of 8 training minutes, plus validation (a two-run city-7 bench took 21-24 minutes).
# Usage: bench/recipes/switch-nerf-city-7.sh OUT   (from the repository root; OUT: a new folder)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-city-7.sh OUT}"
source bench/recipes/scenes.sh
city=$(scene city-7)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 8 --methods leco,prop --seeds 0 \
    --out "$out"
