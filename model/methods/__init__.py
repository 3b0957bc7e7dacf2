"""Methods: each in its own file behind one interface (base.py), listed in one registry (registry.py)."""

from model.methods.base import Method, Networks, PhaseMemory, SweepPoint
from model.methods.registry import METHODS, get_method, register, with_role

__all__ = ["METHODS", "Method", "Networks", "PhaseMemory", "SweepPoint", "get_method", "register", "with_role"]
