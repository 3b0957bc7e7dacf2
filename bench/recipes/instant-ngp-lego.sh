#!/usr/bin/env bash
# The Instant-NGP family's standing on lego (docs/results/instant-ngp-lego.json): NGP and NGP+LeCO,
# 5 minutes each, seeds 0 and 1, NGP before NGP+LeCO on each seed. Measured as one command per
# method and seed, NGP+LeCO's sampler as --set flags that are its defaults now.
# 4 runs of 5 training minutes, plus validation (five such runs took 40 minutes).
# Usage: bench/recipes/instant-ngp-lego.sh OUT   (from the repository root; LEGO= the dataset)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-lego.sh OUT}"
source bench/recipes/scenes.sh
lego=$(scene lego)
.venv/bin/leco bench --scene "$lego" --profile cpu --budget-min 5 --methods ngp,ngp-leco \
    --seeds 0,1 --out "$out"
