#!/usr/bin/env bash
# Every method's smoke run on the tiny city (seed 0), one local worker: prints each method's validation
# PSNR to every digit. A refactor that moves code must leave this output unchanged; run it before and after.
# Usage: bench/recipes/smoke-psnr.sh [WORK_DIR]   (from the repository root, after `make install`)
#   METHODS="prop leco-prop" bench/recipes/smoke-psnr.sh   prints those methods' only
set -euo pipefail
work="${1:-$(mktemp -d)}"
leco=".venv/bin/python -m cli"   # the checkout in the working directory, not the editable install
[ -d "$work/tiny-0" ] || $leco scene synth --preset tiny --seed 0 --out "$work/tiny-0" >/dev/null
for method in leco switch grid prop leco-prop ngp ngp-leco ngp-prop ngp-leco-prop; do
  case " ${METHODS:-$method} " in *" $method "*) ;; *) continue ;; esac
  rm -rf "$work/run-$method"
  $leco train --scene "$work/tiny-0" --method "$method" --profile smoke --backend local \
    --out "$work/run-$method" >/dev/null 2>&1
  .venv/bin/python - "$work/run-$method/summary.json" "$method" <<'PY'
import json, sys
val = json.load(open(sys.argv[1]))["val"]
print(f"{sys.argv[2]:9s} psnr {val['psnr']!r} ssim {val['ssim']!r}")
PY
done
