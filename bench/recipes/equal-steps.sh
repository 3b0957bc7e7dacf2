#!/usr/bin/env bash
# Each method trained for 1,000 main steps on city-0 (`cpu` profile, seed 0, no budget; LeCO's phase
# 1 at its profile's steps), from the checkout in the working directory: the validation PSNR and
# SSIM to every digit, the main steps and the main phase's rays/s. A change that must keep what a
# step computes (docs/BENCHMARKS.md, "A step's cost") is run from a `git archive` copy of each
# commit, one after the other, on a quiet machine. Time: about 10 minutes for the four.
# Usage: bench/recipes/equal-steps.sh OUT   (leco, prop, ngp-leco and ngp-prop)
#   METHODS="prop leco" bench/recipes/equal-steps.sh OUT   those methods only
#   SCENE=DIR bench/recipes/equal-steps.sh OUT   trains on that scene folder instead
#   COMPILE=1 bench/recipes/equal-steps.sh OUT   with the job setting compile (`leco train --compile`)
set -euo pipefail
out="${1:?usage: bench/recipes/equal-steps.sh OUT}"
source bench/recipes/scenes.sh
scene_dir="${SCENE:-$(scene city-0)}"
mkdir -p "$out"
compile=()
[ -n "${COMPILE:-}" ] && compile=(--compile)
for method in leco prop ngp-leco ngp-prop; do
  case " ${METHODS:-$method} " in *" $method "*) ;; *) continue ;; esac
  rm -rf "$out/$method"
  PYTHONPATH="$PWD" .venv/bin/python -m cli train --scene "$scene_dir" --method "$method" \
    --profile cpu --backend local --seed 0 --set main_steps=1000 --out "$out/$method" \
    "${compile[@]}" \
    >"$out/$method.log" 2>&1
  .venv/bin/python - "$out/$method/summary.json" "$method" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
val = s["val"]
steps = s.get("steps", {})
print(f"{sys.argv[2]:9s} psnr {val['psnr']!r} ssim {val['ssim']!r} steps {steps} "
      f"rays/s {s.get('rays_per_s', float('nan')):,.0f}")
PY
done
