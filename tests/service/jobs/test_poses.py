"""A poses job through the API, on SQLite and PostgreSQL: an archive of photos becomes a scene
'posing', its job runs the pipeline stage by stage (each stage a phase in percent) and the scene
becomes ready in east-north-up metres; a cancel fails the scene and leaves no scene folder; a
dispatcher killed mid-job hands it back and the next attempt goes on from the finished stages;
what cannot be posed is refused at upload or fails naming why."""

import io
import os
import signal
import sys
import tarfile
import threading

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from service.dispatcher import Dispatcher  # noqa: E402
from tests.helpers import (  # noqa: E402
    ON_POSTGRESQL,
    ON_SQLITE,
    api_client,
    dispatch_process,
    wait_for,
)
from workers.poses.exif import write_jpeg  # noqa: E402

pytestmark = pytest.mark.slow
ENDED = ("succeeded", "failed", "cancelled")


def photos_tar(folder) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(folder, arcname="photos")
    return buffer.getvalue()


@pytest.fixture
def settings(service_settings):
    return service_settings.model_copy(update={"backend": "local"})


@pytest.fixture
def dispatcher(settings):
    running = Dispatcher(settings, poll_s=0.2)
    threading.Thread(target=running.run_forever, daemon=True).start()
    yield running
    running.stop(wait=True)


def upload(api, folder, name="flight", **params):
    return api.post(
        "/v1/scenes/photos",
        params={"name": name, "max_image_size": 320, **params},
        content=photos_tar(folder),
        headers={"content-type": "application/octet-stream"},
    )


def test_photos_become_a_scene_in_metres(settings, dispatcher, flight, capsys):
    """Through `leco submit --photos`'s own client (cli/submit.py) on the API in process."""
    from argparse import Namespace

    from cli.submit import Api, ensure_scene, wait_ready

    with api_client(settings) as api:
        client = Api("http://testserver", None)
        client.http = api  # a TestClient is an httpx.Client on the app
        args = Namespace(
            photos=str(flight / "photos"),
            name="flight",
            poses_set=["max_image_size=320"],
            upload=None,
            synthetic=None,
            scene=None,
        )
        scene = ensure_scene(client, args)
        assert (scene["state"], scene["source"], scene["format"]) == ("posing", "photos", None)
        job_id = scene["poses_job"]
        job = api.get(f"/v1/jobs/{job_id}").json()
        assert (job["kind"], job["method"], job["profile"]) == ("poses", "colmap", "incremental")
        assert job["config"]["max_image_size"] == 320
        assert [p["name"] for p in job["phases"]] == [
            "features",
            "matching",
            "mapping",
            "alignment",
            "export",
        ]
        # a training job waits for the poses: refused while the scene is posing
        refused = api.post("/v1/jobs", json={"scene": scene["id"], "method": "switch"})
        assert refused.status_code == 409 and "posing" in refused.text
        ready = wait_ready(client, scene, sys.stderr)  # follows the poses job to its end
        assert (ready["state"], ready["format"], ready["cameras"]) == ("ready", "colmap", 30)
        assert f"job {job_id} succeeded" in capsys.readouterr().err
        job = api.get(f"/v1/jobs/{job_id}").json()
        assert job["percent"] == 100.0
        assert all(p["step"] == 100 for p in job["phases"]), job["phases"]
        cameras = api.get(f"/v1/scenes/{scene['id']}/cameras").json()
        assert len(cameras["cameras"]) == 30
    assert not (settings.scenes_dir / f"scene-{scene['id']}.photos").exists()
    assert (settings.scenes_dir / f"scene-{scene['id']}" / "georeference.json").is_file()


@ON_SQLITE
def test_a_cancelled_poses_job_fails_its_scene_and_leaves_no_scene_folder(
    settings, dispatcher, flight
):
    with api_client(settings) as api:
        scene = upload(api, flight / "photos").json()
        job_id = scene["poses_job"]
        wait_for(api, job_id, lambda j: j["phase"] == "matching" or j["state"] in ENDED, 300)
        assert api.post(f"/v1/jobs/{job_id}/cancel").status_code in (200, 202)
        job = wait_for(api, job_id, lambda j: j["state"] in ENDED, 120)
        assert job["state"] == "cancelled", job
        after = api.get(f"/v1/scenes/{scene['id']}").json()
        assert after["state"] == "failed" and "cancelled" in after["error"]
        assert not (settings.scenes_dir / f"scene-{scene['id']}").exists()
        # the scene is deleted with its job, with what posing left beside it
        assert api.delete(f"/v1/jobs/{job_id}").status_code == 204
        assert api.delete(f"/v1/scenes/{scene['id']}").status_code == 204
    assert sorted(p.name for p in settings.scenes_dir.iterdir() if "scene-" in p.name) == []


@ON_POSTGRESQL
def test_a_dispatcher_killed_mid_poses_hands_it_back_and_the_next_attempt_resumes(settings, flight):
    with api_client(settings) as api:
        scene = upload(api, flight / "photos").json()
        job_id = scene["poses_job"]
        with dispatch_process(settings, LECO_BACKEND="local") as first:
            wait_for(api, job_id, lambda j: j["phase"] == "matching" or j["state"] in ENDED, 300)
            os.kill(first.pid, signal.SIGKILL)
            first.wait(10)
        work = settings.scenes_dir / f".scene-{scene['id']}.poses" / "state.json"
        assert '"features"' in work.read_text()
        second = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=second.run_forever, daemon=True).start()
        try:
            job = wait_for(api, job_id, lambda j: j["state"] in ENDED, 300)
        finally:
            second.stop(wait=True)
        assert job["state"] == "succeeded" and job["attempts"] == 2, job
        assert api.get(f"/v1/scenes/{scene['id']}").json()["state"] == "ready"


def test_what_cannot_be_posed_is_refused_at_upload(settings, tmp_path):
    few = tmp_path / "few"
    few.mkdir()
    for i in range(3):
        write_jpeg(few / f"{i}.jpg", np.zeros((30, 40, 3), np.uint8), focal_px=30.0)
    with api_client(settings) as api:
        refused = upload(api, few)
        assert refused.status_code == 422 and "holds 3 photos" in refused.text
        bad = upload(api, few, min_photos=2, matcher="nearest")
        assert bad.status_code == 422
        assert bad.json()["detail"][0]["loc"] == ["query", "matcher"]
        unknown = upload(api, few, min_photos=2, colour="blue")
        assert unknown.status_code == 422 and "unknown setting 'colour'" in unknown.text
        assert api.get("/v1/scenes").json() == []
    assert [p for p in settings.scenes_dir.iterdir() if not p.name.startswith(".")] == []


@ON_SQLITE
def test_a_truncated_photo_fails_the_job_and_the_scene_naming_it(
    settings, dispatcher, flight, tmp_path
):
    import shutil

    folder = tmp_path / "photos"
    shutil.copytree(flight / "photos", folder)
    whole = (folder / "DJI_0005.JPG").read_bytes()
    (folder / "DJI_0005.JPG").write_bytes(whole[: len(whole) // 3])
    with api_client(settings) as api:
        scene = upload(api, folder).json()
        job = wait_for(api, scene["poses_job"], lambda j: j["state"] in ENDED, 120)
        assert job["state"] == "failed" and "DJI_0005.JPG" in job["error"], job
        after = api.get(f"/v1/scenes/{scene['id']}").json()
        assert after["state"] == "failed" and "truncated or damaged" in after["error"]
    assert not (settings.scenes_dir / f"scene-{scene['id']}").exists()
