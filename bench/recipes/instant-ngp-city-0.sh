#!/usr/bin/env bash
# The Instant-NGP family's standing on city-0 (docs/results/instant-ngp-city-0.json, seed 1; with
# SEEDS=0, docs/results/instant-ngp-city-0-seed-0.json): NGP then NGP+LeCO, 8 minutes each. Measured
# as two commands with NGP+LeCO's sampler as --set flags that are its defaults now; one command runs
# them in the same order.
# 2 runs of 8 training minutes per seed (two seeds of this pair took 40 minutes of wall time).
# Usage: bench/recipes/instant-ngp-city-0.sh OUT [SEEDS]   (default SEEDS: 1)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-city-0.sh OUT [SEEDS]}"
seeds="${2:-1}"
source bench/recipes/scenes.sh
city=$(scene city-0)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 8 --methods ngp,ngp-leco \
    --seeds "$seeds" --out "$out"
