#!/usr/bin/env bash
# The Switch-NeRF family's standing on lego (docs/results/switch-nerf-lego.json): LeCO and S+Prop,
# 5 minutes each, seeds 0 and 1, in one command.
# 4 runs of 5 training minutes, plus validation (a four-run lego bench took 37 minutes).
# Usage: bench/recipes/switch-nerf-lego.sh OUT   (from the repository root; LEGO= the dataset)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-lego.sh OUT}"
source bench/recipes/scenes.sh
lego=$(scene lego)
.venv/bin/leco bench --scene "$lego" --profile cpu --budget-min 5 --seeds 0,1 --methods leco,prop \
    --out "$out"
