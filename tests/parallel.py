"""How `make test` shares the suite between two pytest-xdist workers (`-n 2`).

A unit of work is a test module, except for two groups that each run whole on one worker:
- `ray`: every test that starts Ray, in pytest or in a process it starts (a service's job on the Ray
  backend). The topology test's `ray stop --force` ends every Ray on the machine, and its
  `ray start --head` is a cluster another test's `ray.init()` could find: they take turns.
- `city`: the tests that share the session's synthetic city and its LeCO run (tests/conftest.py,
  tests/workers/conftest.py), which cost minutes to make and would be made once per worker.

The groups are decided from test ids in the controller (xdist's own `xdist_group` mark is not read
under pytest 9, whose node ids are no longer a string it can rewrite). A test outside `ray` that
leaves Ray started in its process fails, naming the table to add it to; one that starts Ray only in
a process it spawns is not caught that way. RAY lists every test that a run of the whole suite saw
start Ray (a gcs_server or raylet among its processes' descendants, looked for every 0.3 s).

    .venv/bin/python -m pytest -n 2      # as `make test` runs it
    .venv/bin/python -m pytest           # one process, the same tests
"""

from __future__ import annotations

import sys

import pytest

RAY = (
    "tests/architecture/test_crash_report.py::test_an_abort_after_ray",
    "tests/architecture/test_parallel.py::test_a_test_outside_the_group_that_starts_ray",
    "tests/bench/test_bench.py::test_loadtest",
    "tests/bench/test_load_shutdown.py",
    "tests/service/test_faults.py",
    "tests/service/test_fencing.py",
    "tests/service/test_lifecycle.py",
    "tests/service/test_topology.py",
    "tests/workers/train/test_ray_training.py",
)

CITY = (
    "tests/model/scenes/synthetic/test_city.py",
    "tests/workers/render/test_export.py",
    "tests/workers/train/test_training.py::test_leco_pipeline_on_the_city",
)


def unit_of(nodeid: str) -> str:
    """The work unit a test runs in: a group's name, else its module."""
    if nodeid.startswith(RAY):
        return "ray"
    if nodeid.startswith(CITY):
        return "city"
    return nodeid.split("::", 1)[0]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class Units(LoadScopeScheduling):
        # Units go out most tests first (xdist's --loadscope-reorder): the Ray group, the largest,
        # starts at once on one worker while the other works through the modules.
        def _split_scope(self, nodeid: str) -> str:
            return unit_of(nodeid)

    return Units(config, log)


def ray_running() -> bool:
    ray = sys.modules.get("ray")
    return ray is not None and ray.is_initialized()


@pytest.fixture(autouse=True)
def ray_only_in_its_group(request):
    """A test outside the `ray` group must not start Ray in pytest's process."""
    before = ray_running()
    yield
    if not before and ray_running() and unit_of(request.node.nodeid) != "ray":
        pytest.fail(
            f"{request.node.nodeid} started Ray: add it to RAY in tests/parallel.py so that it "
            "never runs beside the topology test's `ray stop --force`"
        )
