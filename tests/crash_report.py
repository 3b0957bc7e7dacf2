"""A crash names its test, even after Ray ran in this process.

pytest's faulthandler prints the Python stack of a test that kills the process (SIGABRT, SIGSEGV).
`ray.init` puts Ray's own handler for those signals in front of it, and Ray's handler writes to
the file descriptor pytest captures, so a crash in any later test printed nothing: the run just
stopped after its last dot. Before each test, once Ray was imported, faulthandler is put back in
front, writing where pytest's own faulthandler writes. It must be disabled first: `enable()` on an
enabled faulthandler changes its file and installs nothing."""

import faulthandler
import sys

import pytest
from _pytest.faulthandler import fault_handler_stderr_fd_key


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    if "ray" not in sys.modules or fault_handler_stderr_fd_key not in item.config.stash:
        return
    faulthandler.disable()
    faulthandler.enable(file=item.config.stash[fault_handler_stderr_fd_key], all_threads=True)
