"""What the API accepts can start: a step's batch within the scene's training pixels at the job's
downscale, one worker a job on the local backend (service/api/feasibility.py), and a render's or an
export's frames and points within the memory a job gets (service/jobs/kinds.py)."""

import pytest
from fastapi import HTTPException

from model.memory_estimate import FRAME_BYTES_PER_PIXEL, POINT_BYTES
from service.api.feasibility import check_feasible, training_pixels_at_most
from service.db import transaction
from service.jobs.kinds import TRAIN, Parent, export_memory, render_memory
from service.jobs.submit import submit
from service.settings import Settings
from service.tables import Scene
from tests.helpers import api_client, synthetic_scene
from workers.config import TrainConfig
from workers.render.schemas import ExportConfig, RenderConfig

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


# ----- renders and exports: their frames and points within the memory a job gets
# -------------------------------------------------------------------------------------------------
VIEWS = {
    "downscale": 1,
    "splits": {
        "train": {"images": 100, "image_sizes": ["2000x1500"]},
        "val": {"images": 10, "image_sizes": ["2000x1500", "1000x750"]},
    },
}


def parent(config: TrainConfig | None = None) -> Parent:
    cfg = config or TrainConfig(method="leco", profile="cpu")
    return Parent(1, cfg.method, 100, 110, cfg, 2000 * 1500)


def test_a_point_clouds_memory_follows_its_views_pixels_and_keeps_at_most_max_points():
    def parts(**body) -> dict:
        memory = export_memory(ExportConfig(what="pointcloud", **body), parent())
        assert memory is not None and memory.field == "stride"
        return memory.estimate["parts"]

    full, strided = parts(stride=1, max_points=20_000_000), parts(stride=4, max_points=20_000_000)
    assert full["frame"] == 16 * strided["frame"] == 2000 * 1500 * FRAME_BYTES_PER_PIXEL
    assert full["points"] == 20_000_000 * POINT_BYTES  # 110 views x 3M pixels, capped
    assert strided["points"] == 20_000_000 * POINT_BYTES
    few = parts(stride=64, max_points=20_000_000)  # at most 733 pixels a view (31 x 23 taken)
    assert few["points"] == 110 * 733 * POINT_BYTES
    cameras = export_memory(ExportConfig(what="cameras"), parent())
    assert cameras is not None and cameras.estimate["parts"]["frame"] == 0
    assert export_memory(ExportConfig(what="pointcloud"), Parent(1, "leco", 1, 1)) is None


def a_finished_training_job_on(settings, info: dict) -> int:
    with transaction(settings.db_url) as session:
        scene = Scene(name="big", source="upload", state="ready", path="/nowhere", info=info)
        session.add(scene)
        session.flush()
        job = submit(session, TRAIN, scene.id, TrainConfig(method="leco", profile="cpu"))
        job.state = "succeeded"
        return job.id


def test_a_render_or_export_over_the_jobs_memory_is_refused_naming_its_field(service_settings):
    small = render_memory(RenderConfig(width=320, height=240), parent())
    large = render_memory(RenderConfig(width=1920, height=1080), parent())
    assert small is not None and large is not None
    slot_mb = (small.estimate["total"] + large.estimate["total"]) // 2 // 2**20
    settings = service_settings.model_copy(update={"slot_memory_mb": slot_mb})
    job = a_finished_training_job_on(settings, VIEWS)
    with api_client(settings) as api:
        body = {"width": 1920, "height": 1080, "frames": 10}
        refused = api.post(f"/v1/jobs/{job}/renders", json=body)
        assert refused.status_code == 422, refused.text
        [problem] = refused.json()["detail"]
        assert problem["loc"] == ["body", "width"]
        assert f"a job here gets {slot_mb:,} MiB" in problem["msg"] and "frame" in problem["msg"]
        fits = api.post(f"/v1/jobs/{job}/renders", json={**body, "width": 320, "height": 240})
        assert fits.status_code == 201, fits.text
        dense = api.post(f"/v1/jobs/{job}/exports", json={"what": "pointcloud", "stride": 1})
        assert dense.status_code == 422 and dense.json()["detail"][0]["loc"] == ["body", "stride"]
        sparse = api.post(f"/v1/jobs/{job}/exports", json={"what": "pointcloud", "stride": 16})
        assert sparse.status_code == 201, sparse.text
        assert api.get("/v1/jobs", params={"kind": "render"}).json()["total"] == 1
