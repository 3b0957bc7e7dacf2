#!/usr/bin/env bash
# Speed against error on city-0 (docs/EXPERIMENTS.md): LeCO, vanilla and the grid at their default
# sampling budget and at a leaner and a richer one (bench/variants.py sweep), 4 minutes each,
# seed 0.
# 10 runs of 4 training minutes, plus validation.
# Usage: bench/recipes/sweep.sh OUT   (from the repository root)
set -euo pipefail
out="${1:?usage: bench/recipes/sweep.sh OUT}"
source bench/recipes/scenes.sh
city=$(scene city-0)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 4 --methods leco,switch,grid \
    --sweep --seeds 0 --eval-every-s 40 --out "$out"
