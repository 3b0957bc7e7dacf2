"""tests/crash_report.py: a test that kills pytest is named in the output even after Ray ran in
the same process (Ray's handler for SIGABRT otherwise swallows faulthandler's report)."""

import subprocess
import sys

import pytest

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
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    args += ["-p", "tests.crash_report"] if plugin else []
    done = subprocess.run(
        [*args, str(tmp_path / "test_crash.py")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode != 0
    named = "in test_that_kills_the_process" in done.stderr
    assert named == plugin, done.stderr[-2000:]
