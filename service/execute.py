"""`python -m service.execute --job-id N --attempt A`: one claimed attempt of a job, as a Ray job on
a cluster runs it (settings from the environment). With `--settings -` the settings come as JSON on
standard input: the embedded dispatcher's child process on the local backend
(service/jobs/process.py)."""

from __future__ import annotations

import argparse
import logging
import sys

from service.jobs.attempt import execute
from service.jobs.process import OUTCOME, become_child, read_settings
from service.settings import Settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="run one claimed attempt of a LeCO service job")
    parser.add_argument("--job-id", type=int, required=True)
    parser.add_argument("--attempt", type=int, required=True)
    parser.add_argument("--settings", choices=["-"], help="read the settings as JSON from stdin")
    parser.add_argument("--parent-pid", type=int, help="die with this process (Linux)")
    args = parser.parse_args(argv)
    if args.parent_pid is not None:
        become_child(args.parent_pid)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    settings = read_settings(sys.stdin.read()) if args.settings else Settings.from_env()
    state = execute(settings, args.job_id, args.attempt)
    print(f"job {args.job_id} attempt {args.attempt}: {state}")
    print(f"{OUTCOME} {state}", flush=True)
    return 0 if state in ("succeeded", "cancelled", "lost") else 1


if __name__ == "__main__":
    sys.exit(main())
