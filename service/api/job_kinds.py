"""GET /v1/job-kinds: the job-kind registry (service/jobs/kinds.py) as clients and the dashboard see
it, so neither types out kind names: each kind's name, whether it trains networks, and where it is
submitted."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from service.jobs.kinds import KINDS

router = APIRouter(prefix="/job-kinds", tags=["jobs"])


class JobKindOut(BaseModel):
    name: str
    trains: bool = Field(
        description="its finished jobs hold networks that renders, exports and views are made of"
    )
    submit: str = Field(description="where a job of this kind is submitted")


class JobKindList(BaseModel):
    items: list[JobKindOut]


def submitted_at(route: str | None) -> str:
    return "POST /v1/jobs" if route is None else f"POST /v1/jobs/{{id}}/{route}"


@router.get("", response_model=JobKindList, operation_id="listJobKinds")
def list_job_kinds() -> JobKindList:
    return JobKindList(
        items=[
            JobKindOut(name=k.name, trains=k.trains, submit=k.submitted_at or submitted_at(k.route))
            for k in KINDS.values()
        ]
    )
