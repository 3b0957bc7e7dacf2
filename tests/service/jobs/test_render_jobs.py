"""Render, export and view of a finished job through the API, on SQLite and PostgreSQL: bad input is
refused naming the field and queues nothing; a render job runs on a dispatcher like training,
survives a dispatcher stopping mid-render (the next attempt renders again and replaces, never
duplicates, the video); exports and views come from the stored final networks."""

import threading
import time

import pytest
from sqlalchemy import select

from service.db import reading
from service.dispatcher import Dispatcher
from service.settings import Settings
from service.tables import Artifact
from service.workpool import WorkPool
from tests.helpers import ON_SQLITE, api_client, wait_for
from workers.render.export import read_ply_points
from workers.render.video import probe

pytestmark = pytest.mark.slow
# looking down -z from 3 units above the box centre
ROTATION = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0]]


@pytest.fixture
def settings(database_url, tmp_path):
    from service.db import upgrade

    upgrade(database_url)
    return Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        local_cpus=2,
        lease_s=6.0,
        backend="local",
    )


def start(settings):
    dispatcher = Dispatcher(settings, poll_s=0.2)
    thread = threading.Thread(target=dispatcher.run_forever, daemon=True)
    thread.start()
    return dispatcher


def ended(job):
    return job["state"] in ("succeeded", "failed", "cancelled")


def refused(answer, *field):
    assert answer.status_code == 422, answer.text
    locs = [tuple(d["loc"]) for d in answer.json()["detail"]]
    assert any(loc[: len(field)] == field for loc in locs), locs
    return answer.json()["detail"]


@ON_SQLITE
def test_render_export_and_view_of_a_finished_job_and_a_render_across_a_dispatcher_restart(
    settings,
):
    with api_client(settings) as api:
        scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
        while scene["state"] == "generating":
            time.sleep(0.2)
            scene = api.get(f"/v1/scenes/{scene['id']}").json()
        train = api.post(
            "/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "smoke"}
        ).json()
        # an unfinished job: 422 naming it, nothing queued
        detail = refused(api.post(f"/v1/jobs/{train['id']}/renders", json={}), "path", "job_id")
        assert "queued" in detail[0]["msg"]
        dispatcher = start(settings)
        try:
            assert wait_for(api, train["id"], ended)["state"] == "succeeded"
            jid = train["id"]
            bad = [
                ({"path": {"kind": "helix"}}, ("body", "path")),
                (
                    {
                        "path": {
                            "kind": "cameras",
                            "cameras": [{"c2w": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}],
                        }
                    },
                    ("body", "path", "cameras", "cameras", 0, "c2w"),
                ),
                ({"frames": 100_000}, ("body", "frames")),
                ({"frames": 1000, "width": 1920, "height": 1080}, ("body", "frames")),
                ({"width": 99}, ("body", "width")),
                ({"appearance": 999}, ("body", "appearance")),
            ]
            for body, field in bad:
                refused(api.post(f"/v1/jobs/{jid}/renders", json=body), *field)
            refused(
                api.post(
                    f"/v1/jobs/{jid}/view",
                    json={"camera": {"c2w": ROTATION}, "width": 640, "height": 640},
                ),
                "body",
                "height",
            )
            refused(api.post(f"/v1/jobs/{jid}/exports", json={"what": "mesh"}), "body", "what")
            assert api.post("/v1/jobs/999999/renders", json={}).status_code == 404
            assert api.get("/v1/jobs").json()["total"] == 1  # nothing was queued

            # a render job: progress, artifacts, a playable H.264 MP4
            render = api.post(
                f"/v1/jobs/{jid}/renders",
                json={
                    "frames": 6,
                    "width": 64,
                    "height": 48,
                    "fps": 12,
                    "depth_video": True,
                    "path": {"kind": "orbit", "pitch_deg": 40},
                },
            )
            assert render.status_code == 201, render.text
            render = render.json()
            assert (
                render["kind"] == "render"
                and render["parent_id"] == jid
                and render["total_steps"] == 6
            )
            render = wait_for(api, render["id"], ended)
            assert render["state"] == "succeeded", render["error"]
            assert (
                render["step"] == 6 and render["latest_metrics"]["render"]["seconds_per_frame"] > 0
            )
            artifacts = {a["name"]: a for a in api.get(f"/v1/jobs/{render['id']}/artifacts").json()}
            assert set(artifacts) == {
                "video.mp4",
                "video.poster.png",
                "video.depth.mp4",
                "video.camera_path.json",
                "video.render.json",
            }
            assert artifacts["video.mp4"]["content_type"] == "video/mp4"
            video = settings.data_dir / "check.mp4"
            video.write_bytes(api.get(artifacts["video.mp4"]["url"]).content)
            assert probe(video) == {
                "codec": "h264",
                "width": 64,
                "height": 48,
                "frames": 6,
                "fps": 12.0,
                "pix_fmt": "yuv420p",
            }
            listed = api.get(f"/v1/jobs/{jid}/renders").json()
            assert [j["id"] for j in listed["items"]] == [render["id"]]
            assert [
                j["id"] for j in api.get("/v1/jobs", params={"kind": "train"}).json()["items"]
            ] == [jid]

            # exports: a coloured point cloud and the occupancy, with the transform beside them
            cloud = api.post(
                f"/v1/jobs/{jid}/exports",
                json={"what": "pointcloud", "stride": 2, "min_opacity": 0.01},
            ).json()
            cloud = wait_for(api, cloud["id"], ended)
            assert cloud["state"] == "succeeded", cloud["error"]
            names = {a["name"]: a for a in api.get(f"/v1/jobs/{cloud['id']}/artifacts").json()}
            assert set(names) == {"pointcloud.ply", "transform.json", "export.json"}
            ply = settings.data_dir / "cloud.ply"
            ply.write_bytes(api.get(names["pointcloud.ply"]["url"]).content)
            assert len(read_ply_points(ply)) > 0
            assert api.get(names["transform.json"]["url"]).json()["units"] == "metres"
            refused(
                api.post(f"/v1/jobs/{render['id']}/exports", json={"what": "cameras"}),
                "path",
                "job_id",
            )

            # a view: a PNG of the asked size, the same request answered from the cache
            body = {"camera": {"c2w": ROTATION, "fov_deg": 60}, "width": 80, "height": 60}
            first = api.post(f"/v1/jobs/{jid}/view", json=body)
            assert first.status_code == 200 and first.headers["content-type"] == "image/png"
            from io import BytesIO

            from PIL import Image

            assert Image.open(BytesIO(first.content)).size == (80, 60)
            again = api.post(f"/v1/jobs/{jid}/view", json=body)
            assert (
                again.content == first.content
                and again.headers["x-render-seconds"] == first.headers["x-render-seconds"]
            )
            api.app.state.view_pool = busy = WorkPool(1, 0, "view renders")
            busy.admit()  # the one renderer is taken: a new camera is refused at once
            answer = api.post(f"/v1/jobs/{jid}/view", json={**body, "width": 40, "height": 30})
            assert answer.status_code == 429 and answer.headers["retry-after"] == "1"
            busy.release()

            # a render across a dispatcher restart: handed back, rendered again by attempt 2, one
            # video
            long = api.post(
                f"/v1/jobs/{jid}/renders", json={"frames": 60, "width": 160, "height": 120}
            ).json()
            wait_for(api, long["id"], lambda j: j["step"] >= 2)
            dispatcher.shutdown()
            # handed back at once (the job view may be up to LECO_POLL_CACHE_S old, hence the short
            # wait)
            wait_for(api, long["id"], lambda j: j["state"] == "queued", timeout=5)
        finally:
            dispatcher.shutdown()
        dispatcher = start(settings)
        try:
            long = wait_for(api, long["id"], ended, timeout=300)
            # a render cancelled mid-way stops between frames and stores nothing
            stopped = api.post(
                f"/v1/jobs/{jid}/renders", json={"frames": 200, "width": 160, "height": 120}
            ).json()
            wait_for(api, stopped["id"], lambda j: j["step"] >= 2)
            assert api.post(f"/v1/jobs/{stopped['id']}/cancel").json()["cancel_requested"]
            stopped = wait_for(api, stopped["id"], ended, timeout=60)
            assert stopped["state"] == "cancelled" and stopped["step"] < 200
            assert api.get(f"/v1/jobs/{stopped['id']}/artifacts").json() == []
        finally:
            dispatcher.shutdown()
        assert long["state"] == "succeeded" and long["attempts"] == 2, long
        videos = [
            a
            for a in api.get(f"/v1/jobs/{long['id']}/artifacts").json()
            if a["name"] == "video.mp4"
        ]
        with reading(settings.db_url) as session:
            rows = session.execute(
                select(Artifact.attempt).where(
                    Artifact.job_id == long["id"], Artifact.name == "video.mp4"
                )
            ).all()
        assert len(videos) == 1 and rows == [(2,)]  # stored once, by the attempt that finished
        video.write_bytes(api.get(videos[0]["url"]).content)
        assert probe(video)["frames"] == 60

        # the training job goes with its renders and exports
        assert api.delete(f"/v1/jobs/{jid}").status_code == 204
        assert api.get(f"/v1/jobs/{render['id']}").status_code == 404
        assert api.get("/v1/jobs").json()["total"] == 0
