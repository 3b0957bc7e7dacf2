"""GET /v1/methods: the registry (model/methods) as clients and the dashboard see it, so neither
types out method names: each method's name, benchmark label, role, phases and whether it learns an
occupancy."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel

from model.methods import METHODS

router = APIRouter(prefix="/methods", tags=["methods"])


class MethodOut(BaseModel):
    name: str
    label: str
    # "ours" (speed-ups are LeCO's), "reference" (the unguided method they are measured against),
    # "baseline"
    role: str
    phases: list[str]
    has_occupancy: bool


class MethodList(BaseModel):
    items: list[MethodOut]


def method_out(name: str) -> MethodOut:
    m = METHODS[name]
    return MethodOut(
        name=name, label=m.label, role=m.role, phases=list(m.phases), has_occupancy=m.has_occupancy
    )


@router.get("", response_model=MethodList, operation_id="listMethods")
def list_methods() -> MethodList:
    return MethodList(items=[method_out(name) for name in METHODS])


def check_method_filter(method: str | None) -> None:
    """A `?method=` filter must name a registered method: 422 naming the choices otherwise."""
    if method is not None and method not in METHODS:
        raise HTTPException(
            422,
            [
                {
                    "loc": ["query", "method"],
                    "type": "value_error",
                    "msg": f"unknown method {method!r}: choose one of {', '.join(METHODS)}",
                }
            ],
        )
