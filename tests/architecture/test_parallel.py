"""tests/parallel.py: under `pytest -n 2` the tests that start Ray run one after another on one
worker, and a test outside that group which starts Ray fails, naming the table to add it to."""

import json
import os
import subprocess
import sys

import pytest

from tests.helpers import ROOT
from tests.parallel import unit_of


def test_a_test_runs_in_its_group_or_in_its_module():
    assert unit_of("tests/service/test_topology.py::test_x[sqlite]") == "ray"
    assert unit_of("tests/bench/test_bench.py::test_loadtest_polls[postgresql]") == "ray"
    assert unit_of("tests/bench/test_bench.py::test_bench_smoke") == "tests/bench/test_bench.py"
    assert unit_of("tests/workers/render/test_export.py::test_y") == "city"
    assert unit_of("tests/service/api/test_api.py::test_z") == "tests/service/api/test_api.py"


RECORD = """
import json, os

def record(name):
    with open(os.environ["RECORD"], "a") as f:
        f.write(json.dumps([name, os.environ["PYTEST_XDIST_WORKER"]]) + "\\n")
"""


def pytest_run(root, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "RECORD": str(root / "record.jsonl"), "PYTHONPATH": str(ROOT)}
    env.pop("PYTEST_XDIST_WORKER", None)
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    command += ["-p", "tests.parallel", "--rootdir", str(root), "--import-mode=importlib", *args]
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_the_ray_group_runs_whole_on_one_worker_while_modules_share_the_other(tmp_path):
    """A toy tree laid out as ours: three tests of the topology module and two of another Ray
    module, and four modules of one test each. The five Ray tests run on one worker."""
    (tmp_path / "record.py").write_text(RECORD)
    layout = {
        "tests/service/test_topology.py": 3,
        "tests/service/test_fencing.py": 2,
        **{f"tests/model/test_m{i}.py": 1 for i in range(4)},
    }
    for path, count in layout.items():
        file = tmp_path / path
        file.parent.mkdir(parents=True, exist_ok=True)
        body = "import sys, time\nsys.path.insert(0, %r)\nfrom record import record\n" % str(
            tmp_path
        )
        for i in range(count):
            body += f"\ndef test_{i}():\n    time.sleep(0.3)\n    record({f'{path}::{i}'!r})\n"
        file.write_text(body)
    done = pytest_run(tmp_path, "-n", "2", str(tmp_path / "tests"))
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    ran = [json.loads(line) for line in (tmp_path / "record.jsonl").read_text().splitlines()]
    assert len(ran) == 9
    ray_workers = {worker for name, worker in ran if name.startswith("tests/service/")}
    assert len(ray_workers) == 1, ran
    assert {worker for _, worker in ran} == {"gw0", "gw1"}, ran  # the modules went to both


@pytest.mark.slow
def test_a_test_outside_the_group_that_starts_ray_fails_naming_the_table(tmp_path):
    test = tmp_path / "tests" / "model" / "test_starts_ray.py"
    test.parent.mkdir(parents=True)
    test.write_text(
        "import os\n\ndef test_starts_ray():\n    import ray\n\n"
        '    os.environ.setdefault("RAY_AUTH_MODE", "disabled")\n'
        "    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)\n"
    )
    done = pytest_run(tmp_path, str(test))
    assert done.returncode == 1, done.stdout[-2000:]
    assert "tests/model/test_starts_ray.py::test_starts_ray started Ray" in done.stdout
    assert "add it to RAY in tests/parallel.py" in done.stdout
