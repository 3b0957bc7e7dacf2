#!/usr/bin/env bash
# NGP and NGP+Prop on lego (docs/results/instant-ngp-lego-with-prop.json), 5 minutes each, seeds 0
# and 1; measured as NGP's two seeds (beside NGP+LeCO) then one command per NGP+Prop seed.
# 4 runs of 5 training minutes, plus validation (nine such runs took 100 minutes).
# Usage: bench/recipes/instant-ngp-lego-with-prop.sh OUT   (from the repository root)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-lego-with-prop.sh OUT}"
source bench/recipes/scenes.sh
lego=$(scene lego)
.venv/bin/leco bench --scene "$lego" --profile cpu --budget-min 5 --methods ngp,ngp-prop \
    --seeds 0,1 --out "$out"
