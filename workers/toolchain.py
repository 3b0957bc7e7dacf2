"""What a worker's machine has for the job setting `compile`: inductor builds its CPU kernels with a
C++ compiler at run time. Free of torch, so the API can ask it before it accepts a job that the
service's own local workers would run."""

from __future__ import annotations

import shutil
import sysconfig

COMPILERS = ("g++", "c++", "clang++", "gcc")


def cpp_compiler() -> str | None:
    """The path of a C++ compiler on this machine (Python's own CXX first), or None."""
    configured = (sysconfig.get_config_var("CXX") or "").split()[:1]
    for name in (*configured, *COMPILERS):
        found = shutil.which(name)
        if found:
            return found
    return None
