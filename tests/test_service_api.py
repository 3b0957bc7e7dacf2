"""The HTTP API on SQLite and PostgreSQL (FastAPI's TestClient, no training): scenes, bad input, jobs,
idempotency, listing, cancel, metrics downsampling, artifact download (ETag, Range, integrity), auth, health."""

import io
import tarfile
import time

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.db import transaction
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import IdempotencyKey, utcnow
from tests.test_bad_input import png_claiming

TOKEN = "test-token-123"


@pytest.fixture
def api(service_settings):
    settings = Settings(**{**service_settings.model_dump(), "api_tokens": (TOKEN,)})
    with TestClient(create_app(settings), headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        client.settings = settings
        yield client


def ready_scene(api) -> dict:
    scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
    deadline = time.monotonic() + 60
    while scene["state"] == "generating" and time.monotonic() < deadline:
        time.sleep(0.2)
        scene = api.get(f"/v1/scenes/{scene['id']}").json()
    assert scene["state"] == "ready", scene
    return scene


def tar_of(folder, top="scene") -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
        tf.add(folder, arcname=top)
    return buffer.getvalue()


def test_scenes_register_upload_list_show_delete(api, tiny_scene, tmp_path):
    synthetic = ready_scene(api)
    assert synthetic["name"] == "tiny-0" and synthetic["format"] == "meganerf" and synthetic["cameras"] > 0
    assert synthetic["generator"] == {"preset": "tiny", "seed": 0} and synthetic["bounds"]
    assert api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).status_code == 409  # same name
    upload = api.post("/v1/scenes/upload", params={"name": "tiny-upload"}, content=tar_of(tiny_scene.root))
    assert upload.status_code == 201, upload.text
    uploaded = upload.json()
    assert uploaded["format"] == "meganerf" and uploaded["cameras"] == synthetic["cameras"]
    assert [s["name"] for s in api.get("/v1/scenes").json()] == ["tiny-0", "tiny-upload"]
    assert api.get("/v1/scenes/tiny-upload").json()["id"] == uploaded["id"]
    job = api.post("/v1/jobs", json={"scene": "tiny-upload", "method": "switch", "profile": "smoke"}).json()
    conflict = api.delete("/v1/scenes/tiny-upload")
    assert conflict.status_code == 409 and "used by 1 job" in conflict.json()["detail"]
    api.post(f"/v1/jobs/{job['id']}/cancel")
    assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert api.delete("/v1/scenes/tiny-upload").status_code == 204
    assert api.get("/v1/scenes/tiny-upload").status_code == 404
    assert not (api.settings.scenes_dir / f"scene-{uploaded['id']}").exists()


@pytest.mark.parametrize("archive, status, message", [
    ("traversal", 422, "path leaves the archive"),
    ("symlink", 422, "links are not allowed"),
    ("noise", 422, "not a tar or zip archive"),
    ("broken-scene", 422, "unknown scene format"),
    ("empty", 422, "empty upload"),
    ("huge", 413, "limit"),
])
def test_bad_uploads_are_refused_and_nothing_is_stored(api, archive, status, message, tmp_path):
    buffer = io.BytesIO()
    if archive in ("traversal", "symlink", "broken-scene"):
        with tarfile.open(fileobj=buffer, mode="w") as tf:
            info = tarfile.TarInfo("scene/notes.txt" if archive == "broken-scene" else "scene/../../evil.txt")
            if archive == "symlink":
                info = tarfile.TarInfo("scene/link")
                info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
                tf.addfile(info)
            else:
                info.size = 4
                tf.addfile(info, io.BytesIO(b"evil"))
        body = buffer.getvalue()
    elif archive == "noise":
        body = bytes(range(256)) * 10
    elif archive == "empty":
        body = b""
    else:
        body = b"\0" * 2048
        api.app.state.settings = Settings(**{**api.settings.model_dump(), "max_upload_bytes": 1024})
    answer = api.post("/v1/scenes/upload", params={"name": "bad"}, content=body)
    assert answer.status_code == status and message in str(answer.json()["detail"]), answer.text
    assert api.get("/v1/scenes").json() == []
    scenes_dir = api.settings.scenes_dir
    assert not scenes_dir.exists() or list(scenes_dir.iterdir()) == []
    assert not (tmp_path / "evil.txt").exists()


def lego_upload(lego_dir, spoil) -> bytes:
    """A two-view lego scene (Blender format) as a tar, after `spoil(root)` damaged it."""
    import json
    import shutil
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "lego"
        for split, names in (("train", ["r_0", "r_1"]), ("val", ["r_0"])):
            (root / split).mkdir(parents=True)
            data = json.loads((lego_dir / f"transforms_{split}.json").read_text())
            data["frames"] = [f for f in data["frames"] if f["file_path"].split("/")[-1] in names]
            for f in data["frames"]:
                shutil.copy(lego_dir / (f["file_path"] + ".png"), root / split)
            (root / f"transforms_{split}.json").write_text(json.dumps(data))
        spoil(root)
        return tar_of(root)


def spoil_pose(root):
    import json

    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"][1]["transform_matrix"][1][3] = float("nan")
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("spoil, message", [
    (spoil_pose, "camera pose (frame 1) has non-finite values"),
    (lambda root: (root / "train" / "r_1.png").write_bytes(png_claiming(60_000, 60_000)),
     "image claims more pixels than the 100 megapixel limit"),
    (lambda root: (root / "train" / "r_1.png").write_bytes((root / "train" / "r_1.png").read_bytes()[:300]),
     "image is unreadable"),
], ids=["nan-pose", "huge-image-header", "truncated-image"])
def test_hostile_scene_contents_are_refused_with_the_file_named(api, lego_dir, spoil, message):
    answer = api.post("/v1/scenes/upload", params={"name": "hostile"}, content=lego_upload(lego_dir, spoil))
    assert answer.status_code == 422 and message in answer.json()["detail"], answer.text
    assert "Traceback" not in answer.text and "/tmp/" not in answer.text  # no server paths leak
    assert api.get("/v1/scenes").json() == []
    scenes_dir = api.settings.scenes_dir
    assert not scenes_dir.exists() or list(scenes_dir.iterdir()) == []


def test_job_requests_are_validated_field_by_field(api):
    scene = ready_scene(api)
    cases = [
        ({"scene": scene["id"], "method": "leco", "colour": "red"}, "colour"),
        ({"scene": scene["id"], "method": "nerf"}, "method"),
        ({"scene": scene["id"], "method": "leco", "workers": 9}, "workers"),
        ({"scene": scene["id"], "method": "leco", "workers": 4}, "local Ray has 2 CPUs"),
        ({"scene": scene["id"], "method": "leco", "budget_min": -1}, "budget_min"),
        ({"scene": scene["id"], "method": "leco", "overrides": {"occupancy.stepz": 5}}, "'occupancy.stepz': no such setting"),
        ({"scene": scene["id"], "method": "leco", "profile": "huge"}, "unknown profile 'huge'"),
        ({"method": "leco"}, "scene"),
    ]
    for body, named in cases:
        answer = api.post("/v1/jobs", json=body)
        assert answer.status_code == 422 and named in str(answer.json()["detail"]), (body, answer.text)
    missing = api.post("/v1/jobs", json={"scene": "no-such-scene", "method": "leco"})
    assert missing.status_code == 404 and "no-such-scene" in missing.json()["detail"]
    assert api.get("/v1/jobs/12345").status_code == 404
    assert api.get("/v1/jobs").json()["total"] == 0


def test_idempotency_key_replays_refuses_and_waits(api):
    scene = ready_scene(api)
    body = {"scene": scene["id"], "method": "leco", "profile": "smoke"}
    first = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    assert first.status_code == again.status_code == 201
    assert again.json() == first.json() and again.headers["idempotent-replayed"] == "true"
    other = api.post("/v1/jobs", json={**body, "method": "grid"}, headers={"Idempotency-Key": "k1"})
    assert other.status_code == 422 and "different request body" in str(other.json()["detail"])
    missing = {"scene": 999, "method": "leco"}
    assert api.post("/v1/jobs", json=missing, headers={"Idempotency-Key": "k2"}).status_code == 404
    assert api.post("/v1/jobs", json=missing, headers={"Idempotency-Key": "k2"}).status_code == 404  # replayed
    with transaction(api.settings.db_url) as session:  # a first request still in flight
        session.add(IdempotencyKey(key="k3", request_hash=_digest(body), state="in_flight", created_at=utcnow()))
    busy = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k3"})
    assert busy.status_code == 409 and "still in flight" in busy.json()["detail"]
    assert api.get("/v1/jobs").json()["total"] == 1  # one job for all of that


def _digest(body):
    import hashlib
    import json

    from service.api.schemas import JobRequest

    return hashlib.sha256(json.dumps(JobRequest(**body).model_dump(mode="json"), sort_keys=True).encode()).hexdigest()


def test_list_filters_pagination_show_and_cancel(api):
    scene = ready_scene(api)
    ids = [api.post("/v1/jobs", json={"scene": scene["id"], "method": m, "profile": "smoke"}).json()["id"]
           for m in ("leco", "switch", "grid", "leco", "switch")]
    page = api.get("/v1/jobs", params={"limit": 2}).json()
    assert [j["id"] for j in page["items"]] == ids[::-1][:2] and page["total"] == 5 and page["next_offset"] == 2
    last = api.get("/v1/jobs", params={"limit": 2, "offset": 4}).json()
    assert [j["id"] for j in last["items"]] == [ids[0]] and last["next_offset"] is None
    assert api.get("/v1/jobs", params={"method": "leco"}).json()["total"] == 2
    assert api.get("/v1/jobs", params={"scene": "tiny-0", "state": "queued"}).json()["total"] == 5
    assert api.get("/v1/jobs", params={"state": "sleeping"}).status_code == 422
    job = api.get(f"/v1/jobs/{ids[0]}").json()
    assert job["state"] == "queued" and [p["name"] for p in job["phases"]] == ["occupancy", "main"]
    assert job["total_steps"] == 40 and job["percent"] == 0 and job["eta_s"] is None
    cancelled = api.post(f"/v1/jobs/{ids[0]}/cancel").json()
    assert cancelled["state"] == "cancelled" and {p["state"] for p in cancelled["phases"]} == {"cancelled"}
    assert api.get("/v1/jobs", params={"state": "cancelled"}).json()["total"] == 1
    assert api.delete(f"/v1/jobs/{ids[1]}").status_code == 409  # still queued


def test_metrics_filters_polling_and_downsampling(api):
    scene = ready_scene(api)
    job = api.post("/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "smoke"}).json()
    from service import queue

    assert queue.claim(api.settings.db_url, "test", 60) == (job["id"], 1)
    store = DatabaseRunStore(api.settings.db_url, str(api.settings.artifacts), job["id"], 1)
    for step in range(1, 21):
        store.write(step, {"phase": "occupancy", "loss": 1.0 / step, "psnr": 10.0 + step, "phase_step": step,
                           "rays_per_s": 1000.0, "wall_time_s": 0.1 * step, "note": "text is skipped",
                           "bad": float("nan")})
    store.write(20, {"phase": "occupancy", "loss": 0.5, "phase_step": 20, "wall_time_s": 2.0})  # a replayed step
    all_series = api.get(f"/v1/jobs/{job['id']}/metrics").json()["series"]
    assert {s["name"] for s in all_series} == {"loss", "psnr", "phase_step", "rays_per_s", "wall_time_s"}
    loss = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "loss", "phase": "occupancy"}).json()["series"][0]
    assert [p["step"] for p in loss["points"]] == list(range(1, 21)) and loss["points"][-1]["value"] == 0.5
    polled = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "loss", "after_step": 17}).json()["series"][0]
    assert [p["step"] for p in polled["points"]] == [18, 19, 20]
    thin = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "psnr", "max_points": 4}).json()["series"][0]
    assert [p["step"] for p in thin["points"]] == [1, 7, 14, 20] and thin["total_points"] == 20
    one = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "psnr", "max_points": 1}).json()["series"][0]
    assert [p["step"] for p in one["points"]] == [20]
    shown = api.get(f"/v1/jobs/{job['id']}").json()
    assert shown["phase"] == "occupancy" and shown["step"] == 20 and shown["percent"] == 50.0
    assert shown["latest_metrics"]["occupancy"]["loss"] == 0.5
    assert shown["eta_s"] == pytest.approx(20 * 64 / 1000.0)  # 20 steps left x smoke batch 64 / 1000 rays/s
    store.resume(10)  # a restarted attempt continues from its step-10 checkpoint
    loss = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "loss"}).json()["series"][0]
    assert loss["points"][-1]["step"] == 10


def test_artifact_download_etag_range_and_integrity(api):
    scene = ready_scene(api)
    job = api.post("/v1/jobs", json={"scene": scene["id"], "method": "grid", "profile": "smoke"}).json()
    from service.store import ArtifactStore

    store = ArtifactStore(api.settings.db_url, api.settings.artifacts)
    data = bytes(range(256)) * 40
    meta = store.put(job["id"], "checkpoint", "checkpoint-step0000010.pt", data, phase="main", step=10)
    listed = api.get(f"/v1/jobs/{job['id']}/artifacts").json()
    assert [(a["kind"], a["name"], a["size"], a["sha256"]) for a in listed] == [
        ("checkpoint", "checkpoint-step0000010.pt", len(data), meta["sha256"])]
    assert api.get(f"/v1/jobs/{job['id']}/artifacts", params={"kind": "render"}).json() == []
    assert api.get(f"/v1/jobs/{job['id']}/artifacts", params={"kind": "nope"}).status_code == 422
    url = listed[0]["url"]
    full = api.get(url)
    assert full.status_code == 200 and full.content == data
    assert full.headers["etag"] == f'"{meta["sha256"]}"' and full.headers["content-length"] == str(len(data))
    assert full.headers["content-type"] == "application/octet-stream"
    assert api.get(url, headers={"If-None-Match": full.headers["etag"]}).status_code == 304
    part = api.get(url, headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == data[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(data)}"
    assert api.get(url, headers={"Range": "bytes=-10"}).content == data[-10:]
    assert api.get(url, headers={"Range": f"bytes={len(data) + 5}-"}).status_code == 416
    assert api.head(url).headers["content-length"] == str(len(data))
    blob = store.blob_path(meta["sha256"])
    blob.write_bytes(data[:-1] + b"\x00")  # bit rot on disk (the last byte was 0xff)
    broken = api.get(url)
    assert broken.status_code == 500 and "integrity check failed" in broken.json()["detail"]
    assert api.get("/v1/artifacts/999/download").status_code == 404


def test_every_v1_route_needs_the_token_and_health_does_not(api):
    anonymous = TestClient(api.app)
    paths = api.app.openapi()["paths"]
    routes = [(m.upper(), path) for path, ops in paths.items() for m in ops if path.startswith("/v1")]
    assert len(routes) >= 12
    for method, path in routes:
        concrete = path.replace("{scene}", "1").replace("{job_id}", "1").replace("{artifact_id}", "1")
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"}):
            answer = anonymous.request(method, concrete, headers=headers)
            assert answer.status_code == 401, (method, path, headers)
        assert TOKEN not in answer.text
    assert anonymous.get("/healthz").json() == {"status": "ok"}
    ready = anonymous.get("/readyz")
    assert ready.json()["checks"]["database"].startswith("ok")
    metrics = anonymous.get("/metrics").text
    assert 'leco_jobs{state="queued"} 0' in metrics and "leco_http_requests_total" in metrics
    openapi = anonymous.get("/openapi.json").json()
    assert "/v1/jobs/{job_id}/metrics" in openapi["paths"]
