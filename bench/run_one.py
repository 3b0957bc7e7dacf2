"""One benchmark run in its own process (`python -m bench.run_one SPEC_JSON`), so that each method's
peak memory is its own and no method inherits another's warmed-up allocator or threads."""

from __future__ import annotations

import json
import sys

from workers.config import TrainConfig
from workers.train.run import run_training


def main() -> int:
    spec = json.loads(sys.argv[1])
    cfg = TrainConfig.model_validate(spec["config"])
    run_training(cfg, spec["scene"], spec["run_dir"], backend=spec["backend"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
