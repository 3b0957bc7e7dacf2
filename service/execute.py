"""`python -m service.execute --job-id N --attempt A`: one claimed attempt of a job, as a Ray job on
a cluster runs it (the embedded dispatcher calls service.jobs.attempt.execute directly)."""

from __future__ import annotations

import argparse
import logging
import sys

from service.jobs.attempt import execute
from service.settings import Settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="run one claimed attempt of a LeCO service job")
    parser.add_argument("--job-id", type=int, required=True)
    parser.add_argument("--attempt", type=int, required=True)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    state = execute(Settings.from_env(), args.job_id, args.attempt)
    print(f"job {args.job_id} attempt {args.attempt}: {state}")
    return 0 if state in ("succeeded", "cancelled", "lost") else 1


if __name__ == "__main__":
    sys.exit(main())
