"""What the API accepts can start: a step's batch within the scene's training pixels at the job's
downscale, and one worker a job on the local backend (service/api/feasibility.py)."""

import pytest
from fastapi import HTTPException

from service.api.feasibility import check_feasible, training_pixels_at_most
from service.settings import Settings
from tests.helpers import api_client, synthetic_scene
from workers.config import TrainConfig

INFO = {"downscale": 1, "splits": {"train": {"images": 10, "image_sizes": ["100x50", "80x60"]}}}


def test_the_training_pixels_are_bounded_from_the_recorded_sizes_at_any_downscale():
    assert training_pixels_at_most(INFO, None) == 10 * 100 * 50
    assert training_pixels_at_most(INFO, 2) == 10 * 50 * 25
    assert training_pixels_at_most(INFO, 64) == 10 * 1 * 1  # a side never falls under one pixel
    # sizes recorded at the scene's own downscale 4 (LLFF's images_4): the full images are bigger
    assert training_pixels_at_most({**INFO, "downscale": 4}, 4) == 10 * 100 * 50
    assert training_pixels_at_most({}, 2) is None  # a row without sizes (still generating)


def refused(cfg: TrainConfig, backend: str = "ray") -> list[dict]:
    settings = Settings(database_url="sqlite://", backend=backend)
    with pytest.raises(HTTPException) as error:
        check_feasible(cfg, settings, "toy", INFO)
    assert error.value.status_code == 422
    return error.value.detail


def test_a_batch_over_the_pixels_and_workers_the_backend_cannot_run_are_refused():
    batch = TrainConfig(method="leco", overrides={"rays_per_device": 65536})
    [problem] = refused(batch)
    assert (
        problem["loc"] == ["body", "overrides"]
        and "at most 50000 training pixels" in problem["msg"]
    )
    small = TrainConfig(method="leco", profile="smoke", downscale=64)  # 64 rays, 10 pixels
    [problem] = refused(small)
    assert problem["loc"] == ["body", "downscale"] and "at downscale 64" in problem["msg"]
    two = TrainConfig(method="leco", profile="smoke", workers=2)
    [problem] = refused(two, backend="local")
    assert problem["loc"] == ["body", "workers"] and "local backend" in problem["msg"]
    check_feasible(two, Settings(database_url="sqlite://", backend="ray"), "toy", INFO)
    check_feasible(
        TrainConfig(method="leco", profile="smoke"),
        Settings(database_url="sqlite://", backend="local"),
        "toy",
        INFO,
    )


@pytest.fixture
def api(service_settings):
    with api_client(service_settings, None) as client:
        yield client


def test_the_api_refuses_a_job_whose_batch_exceeds_the_scenes_pixels(api):
    scene = synthetic_scene(api)
    body = {"scene": scene["id"], "method": "grid", "profile": "smoke", "downscale": 64}
    answer = api.post("/v1/jobs", json=body)
    assert answer.status_code == 422
    [problem] = [p for p in answer.json()["detail"] if p["loc"] == ["body", "downscale"]]
    assert "training pixels at downscale 64" in problem["msg"]
    assert api.get("/v1/jobs").json()["total"] == 0  # nothing queued
    assert api.post("/v1/jobs", json={**body, "downscale": 2}).status_code == 201
