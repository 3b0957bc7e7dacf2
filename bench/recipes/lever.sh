#!/usr/bin/env bash
# One lever of docs/EXPERIMENTS.md: METHODS on SCENE at SEEDS with each KEY=VALUE as a --set, at
# the budget the ledger's rows used for that scene (city-N 8 minutes; lego, fern and rooftop 5;
# village-N 4; tiny-N 2; BUDGET=M overrides it). Fern runs validate one tracked view every 60 s, as its rows did.
# Run it once without a KEY=VALUE for the defaults beside it: the ledger compares runs made one
# after another on one machine.
# Time: the budget times the runs (methods x seeds), plus validation.
# Usage: bench/recipes/lever.sh OUT SCENE METHODS SEEDS [KEY=VALUE ...]
#   e.g. bench/recipes/lever.sh out/dilate2 city-0 leco 0,1 guided.dilate=2
set -euo pipefail
out="${1:?usage: bench/recipes/lever.sh OUT SCENE METHODS SEEDS [KEY=VALUE ...]}"
name="${2:?scene}"
methods="${3:?methods}"
seeds="${4:?seeds}"
shift 4
source bench/recipes/scenes.sh
dir=$(scene "$name")
case "$name" in
    city-*) budget=8 ;;
    tiny-*) budget=2 ;;
    village-*) budget=4 ;;
    *) budget=5 ;;
esac
extra=()
[ "$name" = fern ] && extra=(--eval-every-s 60 --eval-views 1)
sets=()
for kv in "$@"; do sets+=(--set "$kv"); done
.venv/bin/leco bench --scene "$dir" --profile cpu --budget-min "${BUDGET:-$budget}" \
    --methods "$methods" --seeds "$seeds" "${extra[@]}" "${sets[@]}" --out "$out"
