"""Methods: each in its own file behind one interface (base.py), listed in one registry
(registry.py) of torch-free specs (spec.py). `Method`, `Networks` and `method_state` need PyTorch
and load on first use."""

from typing import Any

from model.methods.costs import PhaseMemory, SweepPoint
from model.methods.registry import METHODS, family_of, get_method, register, with_role
from model.methods.spec import MethodSpec

__all__ = [
    "METHODS",
    "Method",
    "MethodSpec",
    "Networks",
    "PhaseMemory",
    "SweepPoint",
    "get_method",
    "register",
    "with_role",
    "family_of",
]


def __getattr__(name: str) -> Any:
    if name in ("Method", "Networks"):
        from model.methods import base

        return getattr(base, name)
    raise AttributeError(f"module 'model.methods' has no attribute {name!r}")
