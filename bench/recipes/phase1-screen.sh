#!/usr/bin/env bash
# LeCO's phase 1 alone on city-0 (docs/EXPERIMENTS.md): the `cpu` profile's 1,500 occupancy steps
# and one main step, seed 0, each KEY=VALUE as a --set; its summary scores O against the exact
# solid.
# Phase 1 took about 90 s on 2 CPU cores. Run it once without a KEY=VALUE for the defaults.
# Usage: bench/recipes/phase1-screen.sh OUT [KEY=VALUE ...]
set -euo pipefail
out="${1:?usage: bench/recipes/phase1-screen.sh OUT [KEY=VALUE ...]}"
shift
source bench/recipes/scenes.sh
city=$(scene city-0)
sets=()
for kv in "$@"; do sets+=(--set "$kv"); done
.venv/bin/leco train --scene "$city" --method leco --profile cpu --backend local --seed 0 \
    --set main_steps=1 "${sets[@]}" --out "$out"
