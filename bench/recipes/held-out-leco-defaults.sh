#!/usr/bin/env bash
# LeCO's defaults against the defaults of 2026-11-25 and S+Prop on the held-out suite
# (docs/EXPERIMENTS.md, "Held-out checks"): 3 methods x 5 scenes, one seed, from a frozen copy.
# Time: 15 runs of 4 minutes (the rooftop's 5) plus validation; seed 0 took 104 minutes of wall
# time on 2 CPU cores (2026-11-28).
# Usage: ROOFTOP_MIRROR=... bench/recipes/held-out-leco-defaults.sh OUT [SEEDS]   (from the
# repository root; OUT a new folder)
set -euo pipefail
out="${1:?usage: bench/recipes/held-out-leco-defaults.sh OUT [SEEDS]}"
.venv/bin/leco bench --suite held-out --methods leco,leco-2026-11-25,prop --seeds "${2:-0}" \
    --out "$out"
