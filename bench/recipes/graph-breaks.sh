#!/usr/bin/env bash
# torch._dynamo.explain on each method's training step (`Method.step` on one ray batch of the tiny
# city, `cpu` profile, 256 rays, main step 1,000, perturbed as in training): graphs, graph breaks
# and the first reasons, as `leco bench-step --compile` reports them, without compiling or timing.
# Usage: bench/recipes/graph-breaks.sh METHOD[+KEY=VALUE...] ...   (from the repository root)
#   bench/recipes/graph-breaks.sh ngp-prop ngp-prop+prop.static_shapes=true prop
set -euo pipefail
[ "$#" -gt 0 ] || { echo "usage: bench/recipes/graph-breaks.sh METHOD[+KEY=VALUE...] ..." >&2; exit 2; }
PYTHONPATH="$PWD" .venv/bin/python - "$@" <<'PY'
import contextlib
import sys
import tempfile
from pathlib import Path

import torch

from bench import step_profile as sp
from workers.config import parse_overrides

torch.set_num_threads(1)
for spec in sys.argv[1:]:
    method, *sets = spec.split("+")
    with tempfile.TemporaryDirectory(prefix="leco-breaks-") as tmp:
        with contextlib.redirect_stdout(sys.stderr):
            run = sp.make_run(
                method, "cpu", 256, sp.scene_folder(None), Path(tmp), torch.device("cpu"),
                overrides=parse_overrides(sets),
            )
            phase = sp.default_phase(run.method.phases)
            sp.enter_phase(run, phase, 1000)
        fn, args = sp.method_step(run, phase)
        found = sp.graph_breaks(fn, *args)
        print(f"{spec}: {found['graphs']} graphs, {found['graph_breaks']} breaks", flush=True)
        for reason in found["break_reasons"]:
            print(f"    {reason}", flush=True)
PY
