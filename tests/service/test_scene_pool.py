"""Scene registration is bounded work in the API process, on SQLite and PostgreSQL. A full scene
pool answers 429 with Retry-After before an upload's body is read; a scene over the pixel budget is
refused with nothing stored; /cameras answers from the layout kept at registration, without
decoding."""

import shutil
import time

import pytest

from service.scenes import layout_path
from service.settings import Settings
from service.workpool import Busy, WorkerLost, WorkPool
from tests.helpers import api_client, synthetic_scene, tar_of
from tests.service.api.test_api import TOKEN


@pytest.fixture
def api(service_settings, request):
    extra = getattr(request, "param", {})
    settings = Settings(
        **{
            **service_settings.model_dump(),
            "api_tokens": (TOKEN,),
            "scene_workers": 1,
            "scene_queue": 0,
            **extra,
        }
    )
    with api_client(settings, TOKEN) as client:
        yield client


def stored(settings: Settings) -> list[str]:
    return (
        sorted(p.name for p in settings.scenes_dir.iterdir())
        if settings.scenes_dir.exists()
        else []
    )


def test_the_pool_runs_and_queues_at_most_what_it_was_given():
    pool = WorkPool(workers=1, queue=1, what="jobs")
    pool.admit()
    pool.admit()
    with pytest.raises(Busy, match="1 jobs are running and 1 waiting"):
        pool.admit()
    pool.release()
    with pool.admitted(), pool.running():
        pass
    pool.release()


def test_a_full_pool_answers_429_before_reading_the_upload_and_stores_nothing(api, tiny_scene):
    pool = api.app.state.scene_pool
    pool.admit()  # another registration holds the only place
    try:
        upload = api.post(
            "/v1/scenes/upload", params={"name": "flood"}, content=tar_of(tiny_scene.root)
        )
        synthetic = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0})
    finally:
        pool.release()
    for answer in (upload, synthetic):
        assert answer.status_code == 429 and answer.headers["retry-after"] == "10", answer.text
        assert "1 scene registrations are running and 0 waiting" in answer.json()["detail"]
    assert api.get("/v1/scenes").json() == [] and stored(api.settings) == []
    assert (
        api.post(
            "/v1/scenes/upload", params={"name": "calm"}, content=tar_of(tiny_scene.root)
        ).status_code
        == 201
    )


@pytest.mark.parametrize("api", [{"max_scene_pixels": 10_000}], indirect=True)
def test_a_scene_over_the_pixel_budget_is_refused_and_nothing_is_stored(api, tiny_scene):
    answer = api.post("/v1/scenes/upload", params={"name": "big"}, content=tar_of(tiny_scene.root))
    assert answer.status_code == 422
    assert (
        "budget of 10,000 decoded pixels for one scene (LECO_MAX_SCENE_PIXELS)"
        in answer.json()["detail"]
    )
    assert api.get("/v1/scenes").json() == [] and stored(api.settings) == []


def test_cameras_come_from_the_layout_kept_at_registration(api, tiny_scene):
    scene = api.post(
        "/v1/scenes/upload", params={"name": "cams"}, content=tar_of(tiny_scene.root)
    ).json()
    first = api.get(f"/v1/scenes/{scene['id']}/cameras").json()
    assert len(first["cameras"]) == scene["cameras"] and len(first["aabb"]) == 2
    folder = api.settings.scenes_dir / f"scene-{scene['id']}"
    # nothing left to decode: the answer cannot come from the images
    shutil.rmtree(folder / "train" / "rgbs")
    assert api.get(f"/v1/scenes/{scene['id']}/cameras").json() == first
    assert api.delete(f"/v1/scenes/{scene['id']}").status_code == 204
    assert not layout_path(api.settings, scene["id"]).exists() and stored(api.settings) == []


def admit_when_free(pool: WorkPool, within_s: float = 10.0) -> None:
    deadline = time.monotonic() + within_s
    while True:
        try:
            return pool.admit()
        except Busy:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_a_scene_without_a_kept_layout_is_loaded_once_through_the_pool(api):
    # synthetic: its generation frees its place in the pool when it is done
    scene = synthetic_scene(api)
    layout = layout_path(api.settings, scene["id"])
    expected = api.get(f"/v1/scenes/{scene['id']}/cameras").json()
    layout.unlink()  # as a scene registered before layouts were kept
    pool = api.app.state.scene_pool
    admit_when_free(pool)
    try:
        busy = api.get(f"/v1/scenes/{scene['id']}/cameras")
    finally:
        pool.release()
    assert busy.status_code == 429 and not layout.exists()
    assert api.get(f"/v1/scenes/{scene['id']}/cameras").json() == expected and layout.exists()


def test_the_work_runs_in_the_pools_own_processes_and_a_killed_one_is_replaced():
    import os

    pool = WorkPool(workers=1, queue=0, what="scene registrations")
    try:
        with pool.admitted(), pool.running():
            first = pool.call(os.getpid)
            # not this process: decoding never holds the API's interpreter lock
            assert first != os.getpid()
            with pytest.raises(WorkerLost, match="stopped before it finished"):
                pool.call(os._exit, 1)  # as the kernel's OOM killer would
            # a fresh process takes the next call
            assert pool.call(os.getpid) not in (first, os.getpid())
    finally:
        pool.close()
