"""What the API accepts can start: a step's batch within the scene's training pixels at the job's
downscale (exact from the images of each size; a generating synthetic scene's from its preset), one
worker a job on the local backend and GPU workers within the backend's GPUs
(service/api/feasibility.py), and a render's, an export's or a view's frames and points within the
memory a job gets (service/jobs/kinds.py)."""

import pytest
from fastapi import HTTPException

from model.memory_estimate import FRAME_BYTES_PER_PIXEL, POINT_BYTES
from model.scenes.synthetic.presets import PRESETS
from service.api.feasibility import check_feasible, training_pixels_at_most
from service.db import reading, transaction
from service.jobs.kinds import TRAIN, Parent, export_memory, render_memory, view_memory
from service.jobs.submit import submit
from service.settings import Settings
from service.tables import Scene
from service.workpool import WorkPool
from tests.helpers import api_client, synthetic_scene
from workers.config import TrainConfig
from workers.render.schemas import ExportConfig, RenderConfig, ViewRequest

INFO = {"downscale": 1, "splits": {"train": {"images": 10, "image_sizes": ["100x50", "80x60"]}}}


def test_the_training_pixels_are_bounded_from_the_recorded_sizes_at_any_downscale():
    assert training_pixels_at_most(INFO, None) == 10 * 100 * 50
    assert training_pixels_at_most(INFO, 2) == 10 * 50 * 25
    assert training_pixels_at_most(INFO, 64) == 10 * 1 * 1  # a side never falls under one pixel
    # sizes recorded at the scene's own downscale 4 (LLFF's images_4): the full images are bigger
    assert training_pixels_at_most({**INFO, "downscale": 4}, 4) == 10 * 100 * 50
    assert training_pixels_at_most({}, 2) is None  # a row without sizes (still generating)


# one 100x50 image and nine of 80x60: 48,200 pixels, where the largest size x 10 is 50,000
MIXED = {
    "downscale": 1,
    "format": "nerfstudio",
    "splits": {
        "train": {
            "images": 10,
            "image_sizes": ["80x60", "100x50"],
            "images_by_size": {"80x60": 9, "100x50": 1},
        }
    },
}


def test_the_training_pixels_are_exact_where_the_row_records_the_images_of_each_size():
    assert training_pixels_at_most(MIXED, None) == 9 * 80 * 60 + 100 * 50 == 48_200
    # each side floored as model/scenes/images.py downscaled_size does: 80x60 -> 26x20, 100x50 ->
    # 33x16 at 3; at least a pixel a side
    assert training_pixels_at_most(MIXED, 3) == 9 * 26 * 20 + 33 * 16
    assert training_pixels_at_most(MIXED, 64) == 10
    # LLFF recorded from images_4 (its smallest factor): a downscale read from images_4 is exact,
    # one read from images_8 (files of their own sizes) keeps the upper bound
    llff = {**MIXED, "format": "llff", "downscale": 4, "image_folder_factors": [4, 8]}
    assert training_pixels_at_most(llff, 12) == 9 * 26 * 20 + 33 * 16  # images_4, resized by 3
    assert training_pixels_at_most(llff, 8) == 10 * ((101 * 4 - 1) // 8) * ((51 * 4 - 1) // 8)
    # a row recorded before the counts keeps the upper bound
    assert training_pixels_at_most(INFO, None) == 50_000


def test_a_batch_over_the_exact_pixels_of_mixed_sizes_is_refused():
    """49,152 rays a step fit the upper bound (50,000) but not the split's 48,200 pixels: the
    training code would fail with "batch_size 49152 exceeds the 48200 pixels of the split"."""
    cfg = TrainConfig(method="leco", overrides={"rays_per_device": 49_152})
    with pytest.raises(HTTPException) as error:
        check_feasible(cfg, Settings(database_url="sqlite://"), "mixed", MIXED)
    [problem] = error.value.detail
    assert problem["loc"] == ["body", "overrides"]
    assert "scene 'mixed' has 48200 training pixels at its own scale" in problem["msg"]
    check_feasible(  # 48,128 rays fit
        TrainConfig(method="leco", overrides={"rays_per_device": 48_128}),
        Settings(database_url="sqlite://"),
        "mixed",
        MIXED,
    )


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
    with reading(api.settings.db_url) as session:
        info = session.get(Scene, scene["id"]).info
    # registration records the images of each size; the preset says the same before generation
    splits = {
        name: {key: split[key] for key in ("images", "image_sizes", "images_by_size")}
        for name, split in info["splits"].items()
    }
    assert splits["train"]["images_by_size"] == {"40x30": 10}
    assert splits == PRESETS["tiny"].split_info()["splits"]
    body = {"scene": scene["id"], "method": "grid", "profile": "smoke", "downscale": 64}
    answer = api.post("/v1/jobs", json=body)
    assert answer.status_code == 422
    [problem] = [p for p in answer.json()["detail"] if p["loc"] == ["body", "downscale"]]
    assert "has 10 training pixels at downscale 64" in problem["msg"]
    assert api.get("/v1/jobs").json()["total"] == 0  # nothing queued
    assert api.post("/v1/jobs", json={**body, "downscale": 2}).status_code == 201


def a_scene_row(settings, name: str, **fields) -> int:
    with transaction(settings.db_url) as session:
        scene = Scene(name=name, path="/nowhere", **fields)
        session.add(scene)
        session.flush()
        return scene.id


def test_a_job_on_a_scene_still_generating_is_checked_against_its_presets_sizes(api):
    """The tiny preset's 10 training views of 40x30 (model/scenes/synthetic/presets.py), while the
    row has no info yet (nothing generates these rows: the test made them)."""
    tiny = a_scene_row(
        api.settings,
        "tiny-generating",
        source="synthetic",
        state="generating",
        format="meganerf",
        generator={"preset": "tiny", "seed": 0},
    )
    body = {"scene": tiny, "method": "grid", "profile": "smoke", "downscale": 64}
    answer = api.post("/v1/jobs", json=body)
    assert answer.status_code == 422, answer.text
    [problem] = [p for p in answer.json()["detail"] if p["loc"] == ["body", "downscale"]]
    assert "scene 'tiny-generating' has 10 training pixels at downscale 64" in problem["msg"]
    queued = api.post("/v1/jobs", json={**body, "downscale": 2})  # waits for the scene
    assert queued.status_code == 201 and queued.json()["state"] == "queued", queued.text
    # sizes that cannot be known before the scene is ready: refused, naming its state, as a
    # failed scene is
    unknown = a_scene_row(
        api.settings,
        "unknown-generating",
        source="synthetic",
        state="generating",
        generator={"preset": "no-such-preset", "seed": 0},
    )
    answer = api.post("/v1/jobs", json={**body, "scene": unknown, "downscale": 2})
    assert answer.status_code == 409, answer.text
    assert "is generating and its image sizes are not known yet" in answer.json()["detail"]
    assert api.get("/v1/jobs").json()["total"] == 1


READY = {
    "downscale": 1,
    "format": "nerfstudio",
    "cameras": 10,
    "splits": {
        "train": {"images": 10, "image_sizes": ["100x50"], "images_by_size": {"100x50": 10}}
    },
}


def test_workers_are_checked_against_the_backends_gpus_and_the_local_backend(service_settings):
    """Through the API: GPU workers against the local Ray's GPUs (LECO_LOCAL_GPUS, the hook a
    test sets as LECO_CLUSTER_GPUS for a cluster), and two workers on the local backend."""

    scene = a_scene_row(service_settings, "ready", source="upload", state="ready", info=READY)

    def submit_on(settings: Settings, **body):
        with api_client(settings) as api:
            job = {"scene": scene, "method": "grid", "profile": "smoke", **body}
            return api.post("/v1/jobs", json=job)

    def refusal(answer) -> dict:
        assert answer.status_code == 422, answer.text
        [problem] = answer.json()["detail"]
        return problem

    one_gpu = service_settings.model_copy(update={"local_gpus": 1})
    problem = refusal(submit_on(one_gpu, workers=2, use_gpu=True))
    assert problem["loc"] == ["body", "workers"]
    assert "2 GPU workers asked for" in problem["msg"] and "local Ray has 1 GPU:" in problem["msg"]
    no_gpu = service_settings.model_copy(update={"local_gpus": 0})
    problem = refusal(submit_on(no_gpu, use_gpu=True))
    assert problem["loc"] == ["body", "use_gpu"] and "local Ray has no GPU" in problem["msg"]
    assert submit_on(one_gpu, workers=2).status_code == 201  # no GPU asked: CPUs count
    local = service_settings.model_copy(update={"backend": "local"})
    problem = refusal(submit_on(local, workers=2))
    assert problem["loc"] == ["body", "workers"] and "the local backend" in problem["msg"]
    assert submit_on(local).status_code == 201


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


def test_a_view_over_the_jobs_memory_is_refused_as_a_render_is(service_settings):
    camera = {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0]], "fov_deg": 60}
    small = view_memory(ViewRequest(camera=camera, width=160, height=120), parent())
    large = view_memory(ViewRequest(camera=camera, width=640, height=480), parent())
    assert small is not None and large is not None
    # the same estimate as a render's frame of that size
    render = render_memory(RenderConfig(width=640, height=480), parent())
    assert render is not None and large.estimate == render.estimate
    slot_mb = (small.estimate["total"] + large.estimate["total"]) // 2 // 2**20
    settings = service_settings.model_copy(update={"slot_memory_mb": slot_mb})
    job = a_finished_training_job_on(settings, VIEWS)
    with api_client(settings) as api:
        body = {"camera": camera, "width": 640, "height": 480}
        refused = api.post(f"/v1/jobs/{job}/view", json=body)
        assert refused.status_code == 422, refused.text
        [problem] = refused.json()["detail"]
        assert problem["loc"] == ["body", "width"]
        assert f"a job here gets {slot_mb:,} MiB" in problem["msg"] and "frame" in problem["msg"]
        # the small one passes the check and reaches the view pool (full here: 429, nothing
        # rendered)
        api.app.state.view_pool = busy = WorkPool(1, 0, "view renders")
        busy.admit()
        fits = api.post(f"/v1/jobs/{job}/view", json={**body, "width": 160, "height": 120})
        assert fits.status_code == 429, fits.text
        busy.release()


def test_compile_on_cpu_workers_of_a_machine_without_a_cpp_compiler_is_refused(monkeypatch):
    from service.api import feasibility

    cfg = TrainConfig(method="prop", compile=True)
    monkeypatch.setattr(feasibility, "cpp_compiler", lambda: "/usr/bin/g++")
    check_feasible(cfg, Settings(database_url="sqlite://"), "mixed", MIXED)
    monkeypatch.setattr(feasibility, "cpp_compiler", lambda: None)
    with pytest.raises(HTTPException) as error:
        check_feasible(cfg, Settings(database_url="sqlite://"), "mixed", MIXED)
    [problem] = error.value.detail
    assert problem["loc"] == ["body", "compile"]
    assert "needs a C++ compiler" in problem["msg"] and "compile=false" in problem["msg"]
    check_feasible(  # without compile nothing is asked of the machine
        TrainConfig(method="prop"), Settings(database_url="sqlite://"), "mixed", MIXED
    )
