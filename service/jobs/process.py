"""One attempt in a child process (`python -m service.execute --settings -`), as the embedded
dispatcher runs a job on the local backend: the training's memory is the child's, so an allocation
the machine cannot give, or the kernel's out-of-memory killer, ends the job and not the API that
started it. The child reads its settings from standard input (they may not all come from the
environment: tests and `leco serve` build them), prints its outcome as its last line, and dies
with its parent (a killed dispatcher leaves no training behind it)."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

from service.jobs.attempt import finish
from service.settings import Settings

log = logging.getLogger("leco.execute")

OUTCOME = "outcome:"  # the child's last line: "outcome: <state>"
STATES = ("succeeded", "failed", "cancelled", "lost")
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def command(job_id: int, attempt: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "service.execute",
        "--job-id",
        str(job_id),
        "--attempt",
        str(attempt),
        "--settings",
        "-",
        "--parent-pid",
        str(os.getpid()),
    ]


def settings_json(settings: Settings) -> str:
    # the child serves no request: it needs no bearer token
    return settings.model_copy(update={"api_tokens": ()}).model_dump_json()


def run_in_child(settings: Settings, job_id: int, attempt: int) -> str:
    """Runs the attempt in a child process and returns the state it left the job in. A child that
    ends without saying (killed, crashed) fails the job with the reason, if this attempt still
    holds it."""
    child = subprocess.Popen(
        command(job_id, attempt),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    out, _ = child.communicate(settings_json(settings))
    said = [line for line in out.splitlines() if line.startswith(OUTCOME)]
    state = said[-1][len(OUTCOME) :].strip() if said else ""
    if state in STATES:
        return state
    reason = ended_without_outcome(child.returncode)
    log.error("job %s attempt %s: %s", job_id, attempt, reason)
    return "failed" if finish(settings, job_id, attempt, "failed", reason) else "lost"


def ended_without_outcome(returncode: int) -> str:
    if returncode < 0:
        name = signal.Signals(-returncode).name
        cause = (
            "most likely the machine ran out of memory (the kernel's out-of-memory killer); "
            "give the job fewer rays a step or a smaller model, or LECO_SLOT_MEMORY_MB the "
            "memory a job may really use"
            if -returncode == signal.SIGKILL
            else "stopped from outside the service"
        )
        return f"the job's process was killed by {name}: {cause}"
    return (
        f"the job's process exited with code {returncode} without an outcome (its traceback is "
        "in the service's log)"
    )


def become_child(parent_pid: int) -> None:
    """Set up in the child before anything else: die with the dispatcher's thread that started it
    (Linux), be the first the out-of-memory killer picks (before the API), and leave Ctrl-C to the
    dispatcher (it hands the job back; the run stops at its next step boundary)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != parent_pid:  # it died before the line above took effect
            sys.exit(f"the dispatcher (pid {parent_pid}) that started this attempt is gone")
        try:
            Path("/proc/self/oom_score_adj").write_text("1000")
        except OSError:  # a locked-down container: the kernel's own choice stands
            pass


def read_settings(text: str) -> Settings:
    return Settings.model_validate_json(text)
