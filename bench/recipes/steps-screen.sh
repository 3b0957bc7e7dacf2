#!/usr/bin/env bash
# LeCO at equal steps on city-0 (docs/EXPERIMENTS.md): the `cpu` profile's 1,500 phase-1 and 1,500
# main steps, no budget, seed 0, each KEY=VALUE as a --set: PSNR compared at equal steps, the cost
# read in samples per ray. Run it once without a KEY=VALUE for the defaults.
# Usage: bench/recipes/steps-screen.sh OUT [KEY=VALUE ...]
set -euo pipefail
out="${1:?usage: bench/recipes/steps-screen.sh OUT [KEY=VALUE ...]}"
shift
source bench/recipes/scenes.sh
city=$(scene city-0)
sets=()
for kv in "$@"; do sets+=(--set "$kv"); done
.venv/bin/leco train --scene "$city" --method leco --profile cpu --backend local --seed 0 \
    "${sets[@]}" --out "$out"
