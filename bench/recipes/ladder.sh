#!/usr/bin/env bash
# The ablation ladder on city-0 (docs/EXPERIMENTS.md): LeCO from the paper's formulation to the
# `cpu` defaults one change at a time (bench/variants.py RUNGS), beside S+Prop and vanilla,
# 4 minutes each.
# 19 runs of 4 training minutes: 89 minutes of wall time on 2 CPU cores when measured.
# Usage: bench/recipes/ladder.sh OUT [SEED]   (default SEED: 0)
set -euo pipefail
out="${1:?usage: bench/recipes/ladder.sh OUT [SEED]}"
seed="${2:-0}"
source bench/recipes/scenes.sh
city=$(scene city-0)
.venv/bin/leco bench --scene "$city" --profile cpu --budget-min 4 --methods leco,prop,switch \
    --ladder --seeds "$seed" --eval-every-s 40 --out "$out"
