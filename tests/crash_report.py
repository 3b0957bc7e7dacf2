"""A test that kills pytest (SIGABRT, SIGSEGV) is named, with the top of its Python stack, at the
very end of `make test`'s output.

Two things hid such a crash. `ray.init` puts Ray's own handler for those signals in front of
pytest's faulthandler, so after any test that started Ray a crash printed nothing. And with Ray's
threads alive faulthandler's report runs to hundreds of lines whose end, all a CI log shows, is
pytest's own frames. So before each test faulthandler is re-armed (disabled first: `enable()` on an
enabled faulthandler only changes its file) to write into a report file that starts with the test's
id and pytest's memory then (a process that runs out of memory can abort rather than be killed); a
run that ends normally removes it. When pytest dies, `make test` runs this module, which
prints the test, the fatal error and the innermost frames of the thread that died.

    python -m tests.crash_report     # print the report of a run that died, if there is one

The report is `.pytest_cache/crash-report.txt` under the repository, or $LECO_CRASH_REPORT."""

from __future__ import annotations

import faulthandler
import os
import sys
from pathlib import Path
from typing import IO

import pytest

from tests.helpers import ROOT

FRAMES = 12  # innermost frames printed: the test's own call and what it was doing


def report_path() -> Path:
    """The report of this process: with xdist, each worker writes its own (crash-report-gw0.txt)."""
    path = Path(os.environ.get("LECO_CRASH_REPORT") or ROOT / ".pytest_cache" / "crash-report.txt")
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    return path.with_name(f"{path.stem}-{worker}{path.suffix}") if worker else path


_report: IO[str] | None = None


def memory_line() -> str:
    """pytest's resident and virtual memory and the machine's available memory, in MB (Linux's
    /proc; elsewhere a line saying it is unknown)."""
    try:
        status = Path("/proc/self/status").read_text().splitlines()
        meminfo = Path("/proc/meminfo").read_text().splitlines()
    except OSError:
        return "memory at its start: unknown on this platform"

    def mb(lines: list[str], key: str) -> str:
        kb = next((line.split()[1] for line in lines if line.startswith(key + ":")), None)
        return "?" if kb is None else f"{int(kb) // 1024:,}"

    return (
        f"memory at its start: pytest resident {mb(status, 'VmRSS')} MB, virtual "
        f"{mb(status, 'VmSize')} MB; machine available {mb(meminfo, 'MemAvailable')} MB"
    )


def pytest_configure(config: pytest.Config) -> None:
    global _report
    path = report_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    _report = path.open("w")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    if _report is None:
        return
    _report.seek(0)
    _report.truncate()
    _report.write(f"pytest died while running {item.nodeid}\n{memory_line()}\n")
    _report.flush()
    faulthandler.disable()
    faulthandler.enable(file=_report, all_threads=True)


def pytest_unconfigure(config: pytest.Config) -> None:
    global _report
    if _report is None:
        return
    faulthandler.disable()
    _report.close()
    _report = None
    report_path().unlink(missing_ok=True)


def summary(text: str, frames: int = FRAMES) -> str:
    """The test's line, its memory line, faulthandler's 'Fatal Python error' line and the first
    `frames` frames of the thread that crashed (faulthandler marks it 'Current thread'; the others
    come before it)."""
    lines = text.splitlines()
    head = lines[:1] + [
        line
        for line in lines
        if line.startswith("memory at its start") or "Fatal Python error" in line
    ]
    start = next((i for i, line in enumerate(lines) if line.startswith("Current thread")), None)
    if start is None:
        return "\n".join(head + lines[1 : 1 + frames])
    stack = [line for line in lines[start + 1 :] if line.startswith("  File")][:frames]
    return "\n".join([*head, lines[start], *stack])


def main() -> int:
    path = report_path()
    for report in sorted(path.parent.glob(f"{path.stem}*{path.suffix}")):
        if report.read_text().strip():
            print(f"\n--- {report} (innermost frame first)", file=sys.stderr)
            print(summary(report.read_text()), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
