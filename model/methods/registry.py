"""Every method the service trains, by name: the CLI, the job schema, the API, the benchmark, the dashboard and
the docs read this table. Adding a method is a file in this package and one line here."""

from __future__ import annotations

from model.methods.base import Method
from model.methods.grid import GridMethod
from model.methods.leco import LeCOMethod
from model.methods.prop import ProposalMethod
from model.methods.switch import SwitchNeRFMethod

METHODS: dict[str, type[Method]] = {}


def register(method: type[Method]) -> type[Method]:
    """Adds a method (also usable as a class decorator); a name already taken by another class is refused."""
    known = METHODS.get(method.name)
    if known is not None and known is not method:
        raise ValueError(f"method name {method.name!r} is already registered by {known.__qualname__}")
    METHODS[method.name] = method
    return method


def get_method(name: str) -> type[Method]:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}: choose one of {', '.join(METHODS)}")
    return METHODS[name]


def with_role(role: str) -> str | None:
    """The name of the registered method with this role ("ours", "reference"), if any."""
    return next((name for name, m in METHODS.items() if m.role == role), None)


for _method in (LeCOMethod, SwitchNeRFMethod, GridMethod, ProposalMethod):
    register(_method)
