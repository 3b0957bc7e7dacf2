#!/usr/bin/env bash
# NGP and NGP+Prop on city-0 (docs/results/instant-ngp-city-0-with-prop.json), 8 minutes each,
# seed 0; measured as one command per method, NGP first.
# 2 runs of 8 training minutes, plus validation (five such runs took 50 minutes).
# Usage: bench/recipes/instant-ngp-city-0-with-prop.sh OUT   (from the repository root)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-city-0-with-prop.sh OUT}"
source bench/recipes/scenes.sh
city=$(scene city-0)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 8 --methods ngp,ngp-prop --seeds 0 \
    --out "$out"
