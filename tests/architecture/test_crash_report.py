"""tests/crash_report.py: a test that kills pytest after Ray ran in the same process is named, with
the frame that died, by `python -m tests.crash_report` (what `make test` runs when pytest dies);
without the plugin Ray's handler swallows faulthandler's report and nothing names it."""

import os
import subprocess
import sys

import pytest

from tests.crash_report import summary
from tests.helpers import ROOT

CRASHING = """
import os

def test_ray_starts_and_stops_here():
    import ray

    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    ray.shutdown()

def test_that_kills_the_process():
    os.abort()
"""


@pytest.mark.slow
@pytest.mark.parametrize("plugin", [True, False])
def test_an_abort_after_ray_names_its_test_only_with_the_plugin(tmp_path, plugin):
    (tmp_path / "test_crash.py").write_text(CRASHING)
    env = {**os.environ, "LECO_CRASH_REPORT": str(tmp_path / "crash-report.txt")}
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    args += ["-p", "tests.crash_report"] if plugin else []
    done = subprocess.run(
        [*args, str(tmp_path / "test_crash.py")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode != 0
    printed = subprocess.run(
        [sys.executable, "-m", "tests.crash_report"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    ).stderr
    named = "in test_that_kills_the_process" in printed + done.stderr
    assert named == plugin, (printed + done.stderr)[-2000:]
    if plugin:
        lines = printed.strip().splitlines()
        assert lines[1] == "pytest died while running test_crash.py::test_that_kills_the_process"
        assert lines[2].startswith("memory at its start: pytest resident ")
        assert " MB, virtual " in lines[2] and "machine available" in lines[2]
        assert "Fatal Python error: Aborted" in lines[3]
        assert len(lines) <= 4 + 1 + 12, printed


MEMORY = (
    "memory at its start: pytest resident 12,000 MB, virtual 18,000 MB; machine available 90 MB"
)


def test_the_summary_keeps_the_thread_that_died_and_drops_the_others():
    report = "\n".join(
        [
            "pytest died while running tests/x.py::test_y",
            MEMORY,
            "Fatal Python error: Segmentation fault",
            "",
            "Thread 0x01 (most recent call first):",
            '  File "ray/worker.py", line 9 in poll',
            "",
            "Current thread 0x02 (most recent call first):",
            *(f'  File "f{i}.py", line {i} in g{i}' for i in range(30)),
            "",
            "Extension modules: torch._C (total: 1)",
        ]
    )
    lines = summary(report, frames=3).splitlines()
    assert lines == [
        "pytest died while running tests/x.py::test_y",
        MEMORY,
        "Fatal Python error: Segmentation fault",
        "Current thread 0x02 (most recent call first):",
        '  File "f0.py", line 0 in g0',
        '  File "f1.py", line 1 in g1',
        '  File "f2.py", line 2 in g2',
    ]
