#!/usr/bin/env bash
# The Switch-NeRF family's standing on fern (docs/results/switch-nerf-fern.json): S+Prop and LeCO,
# 5 minutes each, seed 0. The command measured also trained NGP+LeCO first; it is left out here.
# 2 runs of 5 training minutes; each took 7-18 minutes of wall time with its validations.
# Usage: bench/recipes/switch-nerf-fern.sh OUT   (from the repository root; FERN= the dataset)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-fern.sh OUT}"
source bench/recipes/scenes.sh
fern=$(scene fern)
.venv/bin/leco bench --scene "$fern" --profile cpu --budget-min 5 --methods prop,leco --seeds 0 \
    --out "$out"
