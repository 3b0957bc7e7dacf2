#!/usr/bin/env bash
# The Switch-NeRF family's standing on the Giza rooftop, a real outdoor capture
# (docs/results/switch-nerf-rooftop.json): S+Prop, LeCO, vanilla and the grid, 5 minutes each,
# seed 0. The command measured also trained NGP+LeCO and NGP first; they are left out here.
# 4 runs of 5 training minutes; the measured command's 6 runs took 71 minutes of wall time.
# Usage: ROOFTOP_MIRROR=... bench/recipes/switch-nerf-rooftop.sh OUT   (from the repository root)
set -euo pipefail
out="${1:?usage: bench/recipes/switch-nerf-rooftop.sh OUT}"
source bench/recipes/scenes.sh
rooftop=$(scene rooftop)
.venv/bin/leco bench --scene "$rooftop" --profile cpu --budget-min 5 \
    --methods prop,leco,switch,grid --seeds 0 --out "$out"
