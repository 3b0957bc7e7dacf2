"""OpenAPI links: which answer's ids feed which next request (a scene's id into a job, a job's id
into its metrics, cancel and artifacts, an artifact's id into its download). They document the API's
workflows for client authors, and the stateful fuzz (tests/service/api/test_stateful.py) follows
them to build chains of calls; a test there checks that every link names an existing operation,
parameter and response field.

A link's parameter is written `<location>.<name>` and its value is an OpenAPI runtime expression:
`$response.body#/<pointer>` reads the answer, `$request.path.<name>` the request that got it (the
only thing left of a resource after a 204)."""

from __future__ import annotations


def _link(
    operation_id: str,
    description: str,
    parameters: dict | None = None,
    body: dict | str | None = None,
) -> dict:
    link: dict[str, str | dict] = {"operationId": operation_id, "description": description}
    if parameters:
        link["parameters"] = parameters
    if body is not None:
        link["requestBody"] = body
    return link


def scene_links(pointer: str = "") -> dict:
    """From an answer holding a scene (SceneOut) at `pointer`: what can be done with that scene."""
    scene = f"$response.body#{pointer}/id"
    return {
        "GetScene": _link("getScene", "the scene", {"path.scene": scene}),
        "GetSceneCameras": _link(
            "getSceneCameras", "its cameras and foreground box", {"path.scene": scene}
        ),
        "DeleteScene": _link(
            "deleteScene", "delete it (409 while a job uses it)", {"path.scene": scene}
        ),
        "SubmitJob": _link("submitJob", "train it (`scene` is its id)", body={"scene": scene}),
        "ListJobsOfScene": _link("listJobs", "the jobs that train it", {"query.scene": scene}),
    }


def deleted_scene_links() -> dict:
    """After DELETE /v1/scenes/{scene} (204, no body): the scene is gone for every route."""
    scene = "$request.path.scene"
    return {
        "GetDeletedScene": _link("getScene", "404 from now on", {"path.scene": scene}),
        "SubmitJobOnDeletedScene": _link("submitJob", "404: no such scene", body={"scene": scene}),
    }


def job_links(pointer: str = "") -> dict:
    """From an answer holding a job (JobOut) at `pointer`: the job's routes, and its scene's."""
    job, scene = f"$response.body#{pointer}/id", f"$response.body#{pointer}/scene_id"
    return {
        "GetJob": _link("getJob", "the job's state and progress", {"path.job_id": job}),
        "CancelJob": _link(
            "cancelJob", "cancel it (again: the same answer; ended: 409)", {"path.job_id": job}
        ),
        "DeleteJob": _link(
            "deleteJob", "delete it once it has ended (409 before)", {"path.job_id": job}
        ),
        "GetJobMetrics": _link("getJobMetrics", "its metric series", {"path.job_id": job}),
        "ListJobArtifacts": _link("listJobArtifacts", "what it stored", {"path.job_id": job}),
        "GetJobScene": _link("getScene", "the scene it trains", {"path.scene": scene}),
        "DeleteJobScene": _link("deleteScene", "409 while this job exists", {"path.scene": scene}),
    }


def submitted_job_links() -> dict:
    """From a new job (POST /v1/jobs, 201): the job's routes, and the same Idempotency-Key sent
    again."""
    key = "$request.header.idempotency-key"
    return {
        **job_links(),
        "ReplaySubmission": _link(
            "submitJob",
            "the same key and body: the stored answer again",
            {"header.idempotency-key": key},
            body="$request.body",
        ),
        "ReuseIdempotencyKey": _link(
            "submitJob", "the same key with another body: 422", {"header.idempotency-key": key}
        ),
    }


def cancelled_job_links() -> dict:
    """From POST /v1/jobs/{job_id}/cancel (200): cancel again, follow it, delete it once it has
    stopped."""
    return {
        name: link
        for name, link in job_links().items()
        if name in ("GetJob", "CancelJob", "DeleteJob")
    }


def deleted_job_links() -> dict:
    """After DELETE /v1/jobs/{job_id} (204, no body): the job is gone for every route."""
    job = {"path.job_id": "$request.path.job_id"}
    return {
        "GetDeletedJob": _link("getJob", "404 from now on", job),
        "CancelDeletedJob": _link("cancelJob", "404", job),
        "DeleteDeletedJob": _link("deleteJob", "404", job),
        "GetDeletedJobMetrics": _link("getJobMetrics", "404", job),
        "ListDeletedJobArtifacts": _link("listJobArtifacts", "404", job),
    }


def artifact_links(pointer: str = "") -> dict:
    """From an answer holding an artifact (ArtifactOut) at `pointer`."""
    artifact = f"$response.body#{pointer}/id"
    return {
        "GetArtifact": _link(
            "getArtifact", "the artifact's description", {"path.artifact_id": artifact}
        ),
        "DownloadArtifact": _link("downloadArtifact", "its bytes", {"path.artifact_id": artifact}),
        "GetArtifactJob": _link(
            "getJob", "the job that stored it", {"path.job_id": f"$response.body#{pointer}/job_id"}
        ),
    }


def links(status: int, described: dict) -> dict:
    """The `responses` entry of a route decorator: FastAPI merges it into the route's own answer."""
    return {status: {"links": described}}
