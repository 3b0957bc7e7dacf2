#!/usr/bin/env bash
# The Instant-NGP family's standing on fern (docs/results/instant-ngp-fern.json): NGP then NGP+LeCO,
# 5 minutes each, seed 0, one tracked validation view every 60 s. Measured as one command per
# method, NGP+LeCO's sampler as --set flags that are its defaults now.
# 2 runs of 5 training minutes; NGP's validations are the slow part (its grid keeps most of the
# frustum: one NGP fern run took 33 minutes of wall time).
# Usage: bench/recipes/instant-ngp-fern.sh OUT   (from the repository root; FERN= the dataset)
set -euo pipefail
out="${1:?usage: bench/recipes/instant-ngp-fern.sh OUT}"
source bench/recipes/scenes.sh
fern=$(scene fern)
.venv/bin/leco bench --scene "$fern" --profile cpu --budget-min 5 --eval-every-s 60 --eval-views 1 \
    --methods ngp,ngp-leco --seeds 0 --out "$out"
