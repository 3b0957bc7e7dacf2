#!/usr/bin/env bash
# The table of docs/BENCHMARKS.md "A step's cost": `leco bench-step` for every method on the tiny
# city (generated under scenes/ when absent), `cpu` profile, 256 rays, 20 timed and 20 profiled
# steps after 3 warm-up steps, one method after another; then the markdown table. Run it on a quiet
# machine (nothing else running): the op and sync counts do not depend on the load, the times do.
# Time: about 2 minutes.
# Usage: bench/recipes/step-cost.sh OUT
set -euo pipefail
out="${1:?usage: bench/recipes/step-cost.sh OUT}"
mkdir -p "$out"
for method in leco switch grid prop leco-prop ngp ngp-leco ngp-prop ngp-leco-prop; do
  .venv/bin/leco bench-step --method "$method" --profile cpu --rays 256 --steps 20 --warmup 3 \
    --json > "$out/$method.json"
done
.venv/bin/python - "$out" <<'PY'
import json, sys
from pathlib import Path

rows = [json.loads(p.read_text()) for p in sorted(Path(sys.argv[1]).glob("*.json"))]
stages = ["ray_batch", "sampler", "field", "background", "losses", "backward", "optimizer", "other"]
print("| method | step ms | rays/s | device ops | host syncs | " + " | ".join(stages) + " |")
print("|---|---:|---:|---:|---:|" + "---:|" * len(stages))
for r in rows:
    share = [f"{100 * r['stages'].get(s, {}).get('share', 0):.0f}%" for s in stages]
    print(
        f"| {r['method']} | {r['step_ms']['median']:.1f} | {r['rays_per_s']:,.0f} | "
        f"{r['ops_per_step']:,.0f} | {r['host_syncs_per_step']:.0f} | " + " | ".join(share) + " |"
    )
PY
