#!/usr/bin/env bash
# The GPU check, for a machine with one CUDA device and a Python whose torch sees it (the project's other
# dependencies installed, or at least pydantic on PYTHONPATH: the training stack needs nothing else).
#   bench/gpu-check.sh [OUT]     (default OUT: gpu-check/)
# 0. step costs (`leco bench-step --gpu`, GPU_STEP_TIMEOUT seconds in all, default 180): for each of
#    GPU_STEP_METHODS (default ngp-prop,ngp-leco,ngp,prop,leco) the step at GPU_STEP_RAYS rays (default
#    256 4096 16384: the rays/s curve), eager, with CUDA kernels and syncs per step; then at 256 and
#    4096 rays compiled (--compile) for GPU_COMPILE_METHODS (default ngp-prop,ngp-leco) and for
#    ngp-prop with prop.static_shapes=true (no sync, fixed shapes). One JSON line per measurement in
#    OUT/steps.jsonl. GPU_STEPS=0 skips it.
# 1. tests/workers/train/test_cuda.py: every method trains on the GPU and its model scores the
#    same on the CPU.
# 2. GPU_PAIR_METHODS (default leco,prop: LeCO against proposal networks) on the synthetic city at the `cpu`
#    profile, equal wall-clock budgets on the GPU (GPU_PAIR_MIN minutes each, default 2).
# 3. GPU_PAPER_METHODS (default: every method) at the `paper` profile for GPU_PAPER_MIN minutes (default
#    0.25): rays/s and peak memory at the paper's sizes (too short to compare quality).
# GPU_TESTS=0 skips step 1; step 3 runs only with GPU_PAPER=1; GPU_PAIR_SET="key=value ..." passes each as --set to step 2
# (GPU_PAIR_SEEDS, default 0, its seeds),
# whose runs go to gpu-bench/GPU_PAIR_NAME (default city-pair; give another name for another setting).
# Each step has its own time limit (GPU_PAIR_TIMEOUT, GPU_PAPER_TIMEOUT seconds) and leaves its logs and reports in OUT as soon as it ends, so a step that
# runs out of time still leaves the ones before it. At most 11 minutes by the limits (steps 3, tests 2.5, pair 5.5),
# GPU_PAPER=1 adds up to 4. docs/BENCHMARKS.md "GPU" has the results.
set -u
OUT=${1:-gpu-check}
PY=${PYTHON:-python3}
PAIR_MIN=${GPU_PAIR_MIN:-2}
PAPER_MIN=${GPU_PAPER_MIN:-0.25}
PAIR_METHODS=${GPU_PAIR_METHODS:-leco,prop}
PAIR_NAME=${GPU_PAIR_NAME:-city-pair}
PAIR_SET=()
for kv in ${GPU_PAIR_SET:-}; do PAIR_SET+=(--set "$kv"); done
PAPER_METHODS=()
[ -n "${GPU_PAPER_METHODS:-}" ] && PAPER_METHODS=(--methods "$GPU_PAPER_METHODS")
export PYTHONUNBUFFERED=1
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)

# `leco bench` without the service's command line (whose imports need the database libraries)
BENCH=("$PY" -c 'import argparse, sys
from bench.cli import add_commands
parser = argparse.ArgumentParser(prog="leco")
add_commands(parser.add_subparsers())
args = parser.parse_args(sys.argv[1:])
sys.exit(args.func(args))' bench)

{
    date -u
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
    "$PY" -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda, torch.cuda.get_device_name(0))'
    nproc
} >"$OUT/env.txt" 2>&1

# `leco bench-step` the same way
STEP=("$PY" -c 'import argparse, sys
from bench.step_profile import add_commands
parser = argparse.ArgumentParser(prog="leco")
add_commands(parser.add_subparsers())
args = parser.parse_args(sys.argv[1:])
sys.exit(args.func(args))' bench-step)

step_costs() {
    local m r
    for m in ${GPU_STEP_METHODS:-ngp-prop ngp-leco ngp prop leco}; do
        for r in ${GPU_STEP_RAYS:-256 4096 16384}; do
            "${STEP[@]}" --method "$m" --gpu --rays "$r" --steps 10 --json | tr -d '\n' >>"$OUT/steps.jsonl"
            echo >>"$OUT/steps.jsonl"
        done
    done
    for m in ${GPU_COMPILE_METHODS:-ngp-prop ngp-leco}; do
        for r in 256 4096; do
            "${STEP[@]}" --method "$m" --gpu --rays "$r" --steps 10 --warmup 8 --compile --json | tr -d '\n' >>"$OUT/steps.jsonl"
            echo >>"$OUT/steps.jsonl"
        done
    done
    for r in 256 4096; do
        "${STEP[@]}" --method ngp-prop --gpu --rays "$r" --steps 10 --set prop.static_shapes=true --json | tr -d '\n' >>"$OUT/steps.jsonl"
        echo >>"$OUT/steps.jsonl"
    done
}

if [ "${GPU_STEPS:-1}" != 0 ]; then
    timeout "${GPU_STEP_TIMEOUT:-180}" bash -c "$(declare -p STEP OUT PY); $(declare -f step_costs); step_costs" >"$OUT/steps.log" 2>&1
    echo "steps rc=$?" >>"$OUT/env.txt"
fi

if [ "${GPU_TESTS:-1}" != 0 ]; then
    timeout 150 "$PY" -m pytest -q -s -p no:cacheprovider tests/workers/train/test_cuda.py >"$OUT/test_cuda.log" 2>&1
    echo "test_cuda rc=$?" >>"$OUT/env.txt"
fi

[ -d scenes/city-0 ] || "$PY" -c 'from model.scenes.synthetic import generate; generate("city", 0, "scenes/city-0")'

timeout "${GPU_PAIR_TIMEOUT:-330}" "${BENCH[@]}" --scene scenes/city-0 --profile cpu --gpu --budget-min "$PAIR_MIN" --methods "$PAIR_METHODS" \
    --seeds "${GPU_PAIR_SEEDS:-0}" "${PAIR_SET[@]}" --out "gpu-bench/$PAIR_NAME" >"$OUT/$PAIR_NAME.log" 2>&1
echo "$PAIR_NAME rc=$?" >>"$OUT/env.txt"
cp "gpu-bench/$PAIR_NAME/report.md" "$OUT/$PAIR_NAME-report.md" 2>/dev/null

if [ "${GPU_PAPER:-0}" != 0 ]; then
    timeout "${GPU_PAPER_TIMEOUT:-240}" "${BENCH[@]}" --scene scenes/city-0 --profile paper --gpu --budget-min "$PAPER_MIN" \
        --seeds 0 "${PAPER_METHODS[@]}" --eval-views 1 --out gpu-bench/city-paper >"$OUT/paper.log" 2>&1
    echo "paper rc=$?" >>"$OUT/env.txt"
    cp gpu-bench/city-paper/report.md "$OUT/paper-report.md" 2>/dev/null
fi
# every run's summary and metrics, also of a step cut by its time limit (no checkpoints: paper-size ones are large)
(cd gpu-bench && find . \( -name '*.json' -o -name '*.jsonl' -o -name '*.md' \) -print0 |
    tar -czf "$OUT/gpu-bench.tgz" --null -T -) 2>>"$OUT/env.txt"
cat "$OUT/env.txt"
