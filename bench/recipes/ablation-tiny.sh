#!/usr/bin/env bash
# The paper's Tables 4, 5, 7 and 9 on the tiny city (docs/EXPERIMENTS.md): LeCO and the grid
# with the ablations (homogeneous MoE, no density loss, Grid-256, the empty-space expert's size),
# 2 minutes each.
# 7 runs of 2 training minutes: 19 minutes of wall time on 2 CPU cores when measured.
# Usage: bench/recipes/ablation-tiny.sh OUT [SEEDS]   (default SEEDS: 0)
set -euo pipefail
out="${1:?usage: bench/recipes/ablation-tiny.sh OUT [SEEDS]}"
seeds="${2:-0}"
source bench/recipes/scenes.sh
tiny=$(scene tiny-0)
.venv/bin/leco bench --scene "$tiny" --profile cpu --budget-min 2 --seeds "$seeds" \
    --methods leco,grid --ablation --out "$out"
