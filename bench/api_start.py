"""What the API process costs to start: `python -m bench.api_start [--repeat 3]` imports the app and
makes it on a fresh, migrated SQLite database in a new interpreter each time, and prints the wall
time, the peak RSS, the number of modules loaded and which of the training stack's libraries came
with them (docs/ARCHITECTURE.md)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROBE = """
import json, resource, sys, time
started = time.perf_counter()
from service.api.app import create_app
from service.settings import Settings
create_app(Settings(data_dir=sys.argv[1]))
seconds = time.perf_counter() - started
heavy = sorted(m for m in ("torch", "ray", "av", "numpy", "PIL") if m in sys.modules)
rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
result = {"seconds": round(seconds, 3), "rss_mb": round(rss_mb, 1)}
print(json.dumps({**result, "modules": len(sys.modules), "heavy": heavy}))
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    from service.db import upgrade
    from service.settings import Settings

    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as data:
            upgrade(Settings(data_dir=Path(data)).db_url)
            done = subprocess.run(
                [sys.executable, "-c", PROBE, data],
                cwd=ROOT,
                capture_output=True,
                text=True,
                check=True,
            )
            print(json.dumps(json.loads(done.stdout.strip().splitlines()[-1])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
