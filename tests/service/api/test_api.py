"""The HTTP API on SQLite and PostgreSQL (FastAPI's TestClient, no training): scenes, bad input,
jobs, idempotency, listing, cancel, metrics downsampling, artifact download (ETag, Range,
integrity), auth, health."""

import io
import tarfile
import threading
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient

from service import queue
from service.api.jobs import KEY_TTL, stored_key
from service.db import transaction
from service.jobs.kinds import TRAIN
from service.jobs.submit import submit
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import IdempotencyKey, Job, Scene, utcnow
from tests.helpers import api_client, synthetic_scene, tar_of
from tests.model.scenes.test_bad_input import png_claiming
from workers.config import TrainConfig

TOKEN = "test-token-123"


@pytest.fixture
def api(service_settings):
    settings = Settings(**{**service_settings.model_dump(), "api_tokens": (TOKEN,)})
    with api_client(settings, TOKEN) as client:
        yield client


def test_scenes_register_upload_list_show_delete(api, tiny_scene, tmp_path):
    synthetic = synthetic_scene(api)
    assert (
        synthetic["name"] == "tiny-0"
        and synthetic["format"] == "meganerf"
        and synthetic["cameras"] > 0
    )
    assert synthetic["generator"] == {"preset": "tiny", "seed": 0} and synthetic["bounds"]
    # same name
    assert api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).status_code == 409
    upload = api.post(
        "/v1/scenes/upload", params={"name": "tiny-upload"}, content=tar_of(tiny_scene.root)
    )
    assert upload.status_code == 201, upload.text
    uploaded = upload.json()
    assert uploaded["format"] == "meganerf" and uploaded["cameras"] == synthetic["cameras"]
    assert [s["name"] for s in api.get("/v1/scenes").json()] == ["tiny-0", "tiny-upload"]
    assert api.get("/v1/scenes/tiny-upload").json()["id"] == uploaded["id"]
    job = api.post(
        "/v1/jobs", json={"scene": "tiny-upload", "method": "switch", "profile": "smoke"}
    ).json()
    conflict = api.delete("/v1/scenes/tiny-upload")
    assert conflict.status_code == 409 and "used by 1 job" in conflict.json()["detail"]
    api.post(f"/v1/jobs/{job['id']}/cancel")
    assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert api.delete("/v1/scenes/tiny-upload").status_code == 204
    assert api.get("/v1/scenes/tiny-upload").status_code == 404
    assert not (api.settings.scenes_dir / f"scene-{uploaded['id']}").exists()


@pytest.mark.parametrize(
    "archive, status, message",
    [
        ("traversal", 422, "path leaves the archive"),
        ("symlink", 422, "links are not allowed"),
        ("noise", 422, "not a tar or zip archive"),
        ("broken-scene", 422, "unknown scene format"),
        ("empty", 422, "empty upload"),
        ("huge", 413, "limit"),
        ("deep", 422, "folders deep; the limit is 32"),
        ("trailing-bomb", 422, "looks like a zip bomb"),
    ],
)
def test_bad_uploads_are_refused_and_nothing_is_stored(api, archive, status, message, tmp_path):
    buffer = io.BytesIO()
    if archive in ("traversal", "symlink", "broken-scene"):
        with tarfile.open(fileobj=buffer, mode="w") as tf:
            info = tarfile.TarInfo(
                "scene/notes.txt" if archive == "broken-scene" else "scene/../../evil.txt"
            )
            if archive == "symlink":
                info = tarfile.TarInfo("scene/link")
                info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
                tf.addfile(info)
            else:
                info.size = 4
                tf.addfile(info, io.BytesIO(b"evil"))
        body = buffer.getvalue()
    elif archive == "deep":
        with tarfile.open(fileobj=buffer, mode="w") as tf:
            info = tarfile.TarInfo("scene/" + "d/" * 1300 + "f.txt")
            info.size = 1
            tf.addfile(info, io.BytesIO(b"x"))
        body = buffer.getvalue()
    elif archive == "trailing-bomb":
        import bz2

        with tarfile.open(fileobj=buffer, mode="w") as tf:
            info = tarfile.TarInfo("scene/a.txt")
            info.size = 1
            tf.addfile(info, io.BytesIO(b"x"))
        # 64 MiB of zeros after the end marker
        body = bz2.compress(buffer.getvalue() + bytes(64 * 2**20))
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


def spoil_file_path(root, target):
    import json

    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"][1]["file_path"] = target
    path.write_text(json.dumps(data))


def spoil_translation(root):
    import json

    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    # finite, rigid, and an overflow in any bound
    data["frames"][1]["transform_matrix"][0][3] = 1e308
    path.write_text(json.dumps(data))


def flat_giants(root):
    """Every image a real, valid 4000 x 4000 PNG of one colour: about 50 KB each, 16 million
    pixels."""
    from PIL import Image

    for path in root.rglob("*.png"):
        Image.new("RGB", (4000, 4000), (200, 30, 30)).save(path)


def test_a_small_upload_may_declare_only_so_many_pixels(api, lego_dir):
    from service.scenes import MAX_PIXELS_PER_UPLOAD_BYTE

    body = lego_upload(lego_dir, flat_giants)
    assert len(body) < 1 << 20 and 3 * 16_000_000 > MAX_PIXELS_PER_UPLOAD_BYTE * len(body)
    answer = api.post("/v1/scenes/upload", params={"name": "giants"}, content=body)
    assert answer.status_code == 422, answer.text
    assert (
        f"{MAX_PIXELS_PER_UPLOAD_BYTE} pixels per byte of the {len(body):,}-byte upload"
        in answer.text
    )
    ok = api.post(
        "/v1/scenes/upload",
        params={"name": "lego"},
        content=lego_upload(lego_dir, lambda root: None),
    )
    assert ok.status_code == 201, ok.text  # real renders hold about one pixel per byte


def test_error_details_are_bounded_and_never_a_dump(api):
    from service.api.app import MAX_DETAIL_CHARS, bounded

    assert bounded("x" * 10_000) == "x" * MAX_DETAIL_CHARS + "... (9,000 more characters)"
    assert bounded("short") == "short" and bounded(["a"]) == ["a"]
    cameras = [{"c2w": "not a matrix"}] * 500  # one error each, and more for their missing fields
    answer = api.post("/v1/jobs/1/renders", json={"path": {"kind": "cameras", "cameras": cameras}})
    assert answer.status_code == 422
    detail = answer.json()["detail"]
    assert len(detail) == 21 and detail[-1]["type"] == "too_many_errors", detail[-1]
    assert len(answer.content) < 8_000 and "not a matrix" not in answer.text


def test_a_scene_name_of_digits_alone_is_refused_so_it_never_reads_as_another_scene_s_id(
    api, tiny_scene
):
    for answer in (
        api.post("/v1/scenes/synthetic", json={"name": "46", "preset": "tiny"}),
        api.post("/v1/scenes/upload", params={"name": "0"}, content=tar_of(tiny_scene.root)),
    ):
        assert answer.status_code == 422 and "reads as a scene id" in answer.text, answer.text
    assert api.get("/v1/scenes").json() == []  # nothing stored, nothing half-written
    ok = api.post("/v1/scenes/synthetic", json={"name": "46a", "preset": "tiny"})
    assert ok.status_code == 202 and ok.json()["name"] == "46a"


@pytest.mark.parametrize(
    "spoil, message",
    [
        (spoil_pose, "camera pose (frame 1) has non-finite values"),
        (
            lambda root: (root / "train" / "r_1.png").write_bytes(png_claiming(60_000, 60_000)),
            "image claims more pixels than the 100 megapixel limit",
        ),
        (
            lambda root: (root / "train" / "r_1.png").write_bytes(
                (root / "train" / "r_1.png").read_bytes()[:300]
            ),
            "image is unreadable",
        ),
        (
            lambda root: spoil_file_path(root, "/proc/self/environ"),
            "file_path (frame 1) '/proc/self/environ' points outside the scene folder",
        ),
        (
            lambda root: spoil_file_path(root, "../../../../../../etc/hostname"),
            "file_path (frame 1) '../../../../../../etc/hostname' points outside the scene folder",
        ),
        (lambda root: spoil_file_path(root, 5), "file_path (frame 1) must be a string"),
        (spoil_translation, "camera position (frame 1) is beyond +-1e+09 source units"),
        (flat_giants, "exceed the budget of"),
    ],
    ids=[
        "nan-pose",
        "huge-image-header",
        "truncated-image",
        "absolute-file-path",
        "climbing-file-path",
        "file-path-a-number",
        "translation-1e308",
        "flat-16-megapixel-pngs",
    ],
)
def test_hostile_scene_contents_are_refused_with_the_file_named(api, lego_dir, spoil, message):
    answer = api.post(
        "/v1/scenes/upload", params={"name": "hostile"}, content=lego_upload(lego_dir, spoil)
    )
    assert answer.status_code == 422 and message in answer.json()["detail"], answer.text
    assert "Traceback" not in answer.text and "/tmp/" not in answer.text  # no server paths leak
    assert api.get("/v1/scenes").json() == []
    scenes_dir = api.settings.scenes_dir
    assert not scenes_dir.exists() or list(scenes_dir.iterdir()) == []


def test_a_downscale_an_llff_scene_cannot_serve_is_refused_at_submit(api, fern_dir):
    upload = api.post("/v1/scenes/upload", params={"name": "fern"}, content=tar_of(fern_dir))
    assert upload.status_code == 201, upload.text
    fern = upload.json()  # it has images_8 only
    refused = api.post("/v1/jobs", json={"scene": fern["id"], "method": "leco", "downscale": 4})
    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"][0]["loc"] == ["body", "downscale"]
    assert "LLFF capture with images_8: downscale 4 must be a multiple of 8" in refused.text
    assert api.get("/v1/jobs").json()["total"] == 0  # nothing stored
    accepted = api.post("/v1/jobs", json={"scene": fern["id"], "method": "leco", "downscale": 16})
    assert accepted.status_code == 201, accepted.text


def test_job_requests_are_validated_field_by_field(api):
    scene = synthetic_scene(api)
    cases = [
        ({"scene": scene["id"], "method": "leco", "colour": "red"}, "colour"),
        ({"scene": scene["id"], "method": "nerf"}, "method"),
        ({"scene": scene["id"], "method": "leco", "workers": 9}, "workers"),
        ({"scene": scene["id"], "method": "leco", "workers": 4}, "local Ray has 2 CPUs"),
        ({"scene": scene["id"], "method": "leco", "budget_min": -1}, "budget_min"),
        ({"scene": scene["id"], "method": "leco", "downscale": 0}, "downscale"),
        ({"scene": scene["id"], "method": "leco", "downscale": 1.5}, "downscale"),
        ({"scene": scene["id"], "method": "leco", "downscale": 65}, "downscale"),
        (
            {"scene": scene["id"], "method": "leco", "overrides": {"occupancy.stepz": 5}},
            "'occupancy.stepz': no such setting",
        ),
        ({"scene": scene["id"], "method": "leco", "profile": "huge"}, "unknown profile 'huge'"),
        ({"method": "leco"}, "scene"),
    ]
    for body, named in cases:
        answer = api.post("/v1/jobs", json=body)
        assert answer.status_code == 422 and named in str(answer.json()["detail"]), (
            body,
            answer.text,
        )
    missing = api.post("/v1/jobs", json={"scene": "no-such-scene", "method": "leco"})
    assert missing.status_code == 404 and "no-such-scene" in missing.json()["detail"]
    assert api.get("/v1/jobs/12345").status_code == 404
    assert api.get("/v1/jobs").json()["total"] == 0


def test_idempotency_key_replays_refuses_and_waits(api):
    scene = synthetic_scene(api)
    body = {"scene": scene["id"], "method": "leco", "profile": "smoke"}
    first = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    assert first.status_code == again.status_code == 201
    assert again.json() == first.json() and again.headers["idempotent-replayed"] == "true"
    other = api.post("/v1/jobs", json={**body, "method": "grid"}, headers={"Idempotency-Key": "k1"})
    assert other.status_code == 422 and "different request body" in str(other.json()["detail"])
    # A refused request keeps no key (rows would grow with the rate of refusals, for a day): sent
    # again, it is checked again and answered the same; its key is free for a request that runs.
    missing = {"scene": 999, "method": "leco"}
    refused = [
        api.post("/v1/jobs", json=missing, headers={"Idempotency-Key": f"r{i}"}) for i in range(20)
    ]
    assert {answer.status_code for answer in refused} == {404}
    assert stored_keys(api.settings) == 1  # k1's, which made a job
    again = api.post("/v1/jobs", json=missing, headers={"Idempotency-Key": "r0"})
    assert again.status_code == 404 and again.json() == refused[0].json()
    assert "idempotent-replayed" not in again.headers
    made = api.post("/v1/jobs", json={**body, "seed": 1}, headers={"Idempotency-Key": "r0"})
    assert made.status_code == 201 and stored_keys(api.settings) == 2
    with transaction(api.settings.db_url) as session:  # a first request still in flight
        session.add(
            IdempotencyKey(
                key=stored_key(f"Bearer {TOKEN}", "k3"),
                request_hash=_digest(body),
                state="in_flight",
                created_at=utcnow(),
            )
        )
    busy = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k3"})
    assert busy.status_code == 409 and "still in flight" in busy.json()["detail"]
    assert api.get("/v1/jobs").json()["total"] == 2  # k1's and r0's, for all of that


def stored_keys(settings) -> int:
    from sqlalchemy import func, select

    with transaction(settings.db_url) as session:
        return session.scalar(select(func.count()).select_from(IdempotencyKey))


def test_idempotency_keys_are_checked_scoped_to_their_token_answer_the_job_now_and_expire(
    service_settings,
):
    settings = Settings(**{**service_settings.model_dump(), "api_tokens": (TOKEN, "token-two")})
    with api_client(settings, TOKEN) as api, api_client(settings, "token-two") as two:
        scene = synthetic_scene(api)
        body = {"scene": scene["id"], "method": "grid", "profile": "smoke"}
        for bad in ("", "a key", "k\xe9".encode("latin-1"), "k" * 256):
            refused = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": bad})
            assert refused.status_code == 422, bad
            assert refused.json()["detail"][0]["loc"] == ["header", "idempotency-key"]
        assert api.get("/v1/jobs").json()["total"] == 0
        first = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"}).json()
        # another token's k1 is its own key: a job of its own, and no view of the first answer
        other = two.post(
            "/v1/jobs", json={**body, "method": "switch"}, headers={"Idempotency-Key": "k1"}
        )
        assert other.status_code == 201 and other.json()["id"] != first["id"]
        # a replay answers the job as it is now: cancelled, then deleted
        api.post(f"/v1/jobs/{first['id']}/cancel")
        again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
        assert again.status_code == 201 and again.headers["idempotent-replayed"] == "true"
        assert again.json()["id"] == first["id"] and again.json()["state"] == "cancelled"
        assert api.delete(f"/v1/jobs/{first['id']}").status_code == 204
        gone = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
        assert gone.status_code == 410 and "was deleted" in gone.json()["detail"]
        # a day later the key is forgotten: the same request creates a job again
        with transaction(settings.db_url) as session:
            row = session.get(IdempotencyKey, stored_key(f"Bearer {TOKEN}", "k1"))
            row.created_at = utcnow() - KEY_TTL - timedelta(minutes=1)
        fresh = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
        assert fresh.status_code == 201 and "idempotent-replayed" not in fresh.headers
        assert fresh.json()["id"] not in (first["id"], other.json()["id"])


def _digest(body):
    import hashlib
    import json

    from service.api.schemas import JobRequest

    return hashlib.sha256(
        json.dumps(JobRequest(**body).model_dump(mode="json"), sort_keys=True).encode()
    ).hexdigest()


def test_list_filters_pagination_show_and_cancel(api):
    scene = synthetic_scene(api)
    ids = [
        api.post("/v1/jobs", json={"scene": scene["id"], "method": m, "profile": "smoke"}).json()[
            "id"
        ]
        for m in ("leco", "switch", "grid", "leco", "switch")
    ]
    page = api.get("/v1/jobs", params={"limit": 2}).json()
    assert (
        [j["id"] for j in page["items"]] == ids[::-1][:2]
        and page["total"] == 5
        and page["next_offset"] == 2
    )
    last = api.get("/v1/jobs", params={"limit": 2, "offset": 4}).json()
    assert [j["id"] for j in last["items"]] == [ids[0]] and last["next_offset"] is None
    assert api.get("/v1/jobs", params={"method": "leco"}).json()["total"] == 2
    assert api.get("/v1/jobs", params={"scene": "tiny-0", "state": "queued"}).json()["total"] == 5
    assert api.get("/v1/jobs", params={"state": "sleeping"}).status_code == 422
    job = api.get(f"/v1/jobs/{ids[0]}").json()
    assert job["state"] == "queued" and [p["name"] for p in job["phases"]] == ["occupancy", "main"]
    assert job["total_steps"] == 40 and job["percent"] == 0 and job["eta_s"] is None
    cancelled = api.post(f"/v1/jobs/{ids[0]}/cancel").json()
    assert cancelled["state"] == "cancelled" and {p["state"] for p in cancelled["phases"]} == {
        "cancelled"
    }
    assert api.get("/v1/jobs", params={"state": "cancelled"}).json()["total"] == 1
    assert api.delete(f"/v1/jobs/{ids[1]}").status_code == 409  # still queued


def test_metrics_filters_polling_and_downsampling(api):
    scene = synthetic_scene(api)
    job = api.post(
        "/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "smoke"}
    ).json()

    assert queue.claim(api.settings.db_url, "test", 60) == (job["id"], 1)
    store = DatabaseRunStore(
        api.settings.db_url, str(api.settings.artifacts), job["id"], 1, api.settings.retry_s
    )
    for step in range(1, 21):
        store.write(
            step,
            {
                "phase": "occupancy",
                "loss": 1.0 / step,
                "psnr": 10.0 + step,
                "phase_step": step,
                "rays_per_s": 1000.0,
                "wall_time_s": 0.1 * step,
                "note": "text is skipped",
                "bad": float("nan"),
            },
        )
    # a replayed step
    store.write(20, {"phase": "occupancy", "loss": 0.5, "phase_step": 20, "wall_time_s": 2.0})
    all_series = api.get(f"/v1/jobs/{job['id']}/metrics").json()["series"]
    assert {s["name"] for s in all_series} == {
        "loss",
        "psnr",
        "phase_step",
        "rays_per_s",
        "wall_time_s",
    }
    loss = api.get(
        f"/v1/jobs/{job['id']}/metrics", params={"name": "loss", "phase": "occupancy"}
    ).json()["series"][0]
    assert [p["step"] for p in loss["points"]] == list(range(1, 21)) and loss["points"][-1][
        "value"
    ] == 0.5
    polled = api.get(
        f"/v1/jobs/{job['id']}/metrics", params={"name": "loss", "after_step": 17}
    ).json()["series"][0]
    assert [p["step"] for p in polled["points"]] == [18, 19, 20]
    thin = api.get(
        f"/v1/jobs/{job['id']}/metrics", params={"name": "psnr", "max_points": 4}
    ).json()["series"][0]
    # in SQL
    assert [p["step"] for p in thin["points"]] == [1, 8, 14, 20] and thin["total_points"] == 20
    # exactly min(m, n) points, the first and the last among them, no repeats
    for m in (2, 3, 7, 19, 20, 25):
        steps = [
            p["step"]
            for p in api.get(
                f"/v1/jobs/{job['id']}/metrics", params={"name": "psnr", "max_points": m}
            ).json()["series"][0]["points"]
        ]
        assert len(steps) == len(set(steps)) == min(m, 20) and steps[0] == 1 and steps[-1] == 20, (
            m,
            steps,
        )
    one = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "psnr", "max_points": 1}).json()[
        "series"
    ][0]
    assert [p["step"] for p in one["points"]] == [20]
    shown = api.get(f"/v1/jobs/{job['id']}").json()
    assert shown["phase"] == "occupancy" and shown["step"] == 20 and shown["percent"] == 50.0
    assert shown["latest_metrics"]["occupancy"]["loss"] == 0.5
    # 20 steps left x smoke batch 64 / 1000 rays/s
    assert shown["eta_s"] == pytest.approx(20 * 64 / 1000.0)
    store.resume(10)  # a restarted attempt continues from its step-10 checkpoint
    loss = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "loss"}).json()["series"][0]
    assert loss["points"][-1]["step"] == 10


def test_artifact_download_etag_range_and_integrity(api):
    scene = synthetic_scene(api)
    job = api.post(
        "/v1/jobs", json={"scene": scene["id"], "method": "grid", "profile": "smoke"}
    ).json()
    from service.store import ArtifactStore

    store = ArtifactStore(api.settings.db_url, api.settings.artifacts)
    data = bytes(range(256)) * 40
    meta = store.put(
        job["id"], "checkpoint", "checkpoint-step0000010.pt", data, phase="main", step=10
    )
    listed = api.get(f"/v1/jobs/{job['id']}/artifacts").json()
    assert [(a["kind"], a["name"], a["size"], a["sha256"]) for a in listed] == [
        ("checkpoint", "checkpoint-step0000010.pt", len(data), meta["sha256"])
    ]
    assert api.get(f"/v1/jobs/{job['id']}/artifacts", params={"kind": "render"}).json() == []
    assert api.get(f"/v1/jobs/{job['id']}/artifacts", params={"kind": "nope"}).status_code == 422
    url = listed[0]["url"]
    full = api.get(url)
    assert full.status_code == 200 and full.content == data
    assert full.headers["etag"] == f'"{meta["sha256"]}"' and full.headers["content-length"] == str(
        len(data)
    )
    assert full.headers["content-type"] == "application/octet-stream"
    for header in (
        full.headers["etag"],
        "*",
        f"W/{full.headers['etag']}",
        f'"x", {full.headers["etag"]}',
    ):
        assert api.get(url, headers={"If-None-Match": header}).status_code == 304, header
    assert api.head(url, headers={"If-None-Match": "*"}).status_code == 304
    assert api.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
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
    routes = [
        (m.upper(), path) for path, ops in paths.items() for m in ops if path.startswith("/v1")
    ]
    assert len(routes) >= 12
    for method, path in routes:
        concrete = (
            path.replace("{scene}", "1").replace("{job_id}", "1").replace("{artifact_id}", "1")
        )
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"}):
            answer = anonymous.request(method, concrete, headers=headers)
            assert answer.status_code == 401, (method, path, headers)
        assert TOKEN not in answer.text
    assert anonymous.get("/healthz").json() == {"status": "ok"}
    ready = anonymous.get("/readyz").json()["checks"]
    # no URL, no path
    assert ready["database"] == "up" and api.settings.db_url.split("://")[-1] not in str(ready)
    metrics = anonymous.get("/metrics").text
    assert 'leco_jobs{state="queued"} 0' in metrics and "leco_http_requests_total" in metrics
    # a flood of invented method names and paths adds no series: they fold into one label each
    for i in range(50):
        anonymous.request(f"M{i:03d}{'X' * 2000}", f"/nowhere/{i}")
    before = anonymous.get("/metrics").text.count("leco_http_requests_total{")
    for i in range(50, 100):
        anonymous.request(f"M{i:03d}{'X' * 2000}", f"/nowhere/{i}")
    after = anonymous.get("/metrics").text
    assert after.count("leco_http_requests_total{") == before and "XXXX" not in after
    assert 'method="other",route="unmatched"' in after
    openapi = anonymous.get("/openapi.json").json()
    assert "/v1/jobs/{job_id}/metrics" in openapi["paths"]


def test_the_token_is_checked_and_the_body_capped_before_the_body_is_read(api):
    """No token -> 401 whatever the body (malformed, huge); a token and a huge JSON body -> 413."""
    from fastapi.testclient import TestClient

    from service.api.gate import MAX_JSON_BODY

    bare = TestClient(api.app)  # no Authorization header
    for body in (b"{not json", b"x" * (8 * 2**20)):
        answer = bare.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
        assert answer.status_code == 401 and answer.headers["www-authenticate"] == "Bearer", (
            answer.text
        )
    answer = bare.post("/v1/scenes/upload", params={"name": "x"}, content=b"x" * 1000)
    assert answer.status_code == 401
    huge = api.post(
        "/v1/jobs",
        content=b"{" + b" " * MAX_JSON_BODY + b"}",
        headers={"content-type": "application/json"},
    )
    assert huge.status_code == 413 and "limit" in huge.json()["detail"]

    def chunks():  # no Content-Length: the size is counted as it arrives
        for _ in range(MAX_JSON_BODY // 1024 + 2):
            yield b" " * 1024

    streamed = api.post("/v1/jobs", content=chunks(), headers={"content-type": "application/json"})
    assert streamed.status_code == 413
    assert (
        api.post(
            "/v1/jobs", content=b"{not json", headers={"content-type": "application/json"}
        ).status_code
        == 422
    )
    assert api.get("/v1/jobs").status_code == 200  # and a proper request still goes through


def test_a_render_body_of_the_documented_maximum_of_cameras_passes_the_body_cap(api):
    import json
    import math

    from service.api.gate import MAX_PATH_BODY, PATH_CAMERAS
    from workers.render.schemas import MAX_FRAMES

    assert PATH_CAMERAS == MAX_FRAMES
    cameras = []
    # full-precision floats, as a client serialising float64 poses sends them
    for i in range(MAX_FRAMES):
        a = 0.1 + i * 1e-3
        c, s = math.cos(a), math.sin(a)
        cameras.append(
            {
                "c2w": [
                    [c, -s, 0.0, 1.0 / 3 + i],
                    [s, c, 0.0, -2.0 / 7],
                    [0.0, 0.0, 1.0, math.pi],
                    [0.0, 0.0, 0.0, 1.0],
                ],
                "intrinsics": [
                    111.11111111111111,
                    111.11111111111111,
                    63.999999999999999,
                    47.123456789012345,
                ],
            }
        )
    body = json.dumps(
        {
            "frames": MAX_FRAMES,
            "width": 64,
            "height": 48,
            "path": {"kind": "cameras", "cameras": cameras},
        }
    ).encode()
    assert len(body) > 300_000
    answer = api.post(
        "/v1/jobs/999999/renders", content=body, headers={"content-type": "application/json"}
    )
    # read and parsed whole: the job is what is missing
    assert answer.status_code == 404, answer.text
    too_big = api.post(
        "/v1/jobs/999999/renders",
        content=b" " * (MAX_PATH_BODY + 1),
        headers={"content-type": "application/json"},
    )
    assert too_big.status_code == 413
    assert (
        api.post("/v1/jobs", content=body, headers={"content-type": "application/json"}).status_code
        == 413
    )


@pytest.mark.parametrize(
    "field, value, named",
    [
        ("overrides", {"network.width": 100000}, "network.width"),
        ("overrides", {"occupancy.samples_per_ray": 1e6}, "occupancy.samples_per_ray"),
        ("overrides", {"rays_per_device": 1e9}, "rays_per_device"),
        ("overrides", {"grid.resolution": 1e5}, "grid.resolution"),
        ("overrides", {"main_steps": 1e20}, "main_steps"),
        ("overrides", {"lr": float("inf")}, "lr"),
        ("overrides", {"occupancy.w_g": float("nan")}, "occupancy.w_g"),
        ("seed", 10**23, "seed"),
        ("val_every", 1, "val_every"),
        ("max_failures", 10**9, "max_failures"),
        ("budget_min", float("inf"), "budget_min"),
        ("scene", "DIGITS", ""),  # 5,000 digits, more than Python parses into an int by default
    ],
)
def test_job_configs_are_bounded_on_both_sides_and_finite(api, field, value, named):
    """Every number has an upper bound and must be finite; 422 names the field, nothing is
    stored."""
    import json

    body = json.dumps({"scene": 1, "method": "leco", "profile": "smoke", field: value}).replace(
        '"DIGITS"', "9" * 5000
    )
    answer = api.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
    # The 5,000-digit id is not even JSON Python will parse: 400, "error parsing the body"; the rest
    # 422.
    assert answer.status_code == (400 if value == "DIGITS" else 422), answer.text
    assert named in answer.text and "Traceback" not in answer.text
    assert api.get("/v1/jobs").json()["items"] == []


def test_a_job_that_cannot_fit_its_slot_is_refused_with_the_estimate(api):
    """The API estimates a job's peak memory (model/memory_estimate.py) and refuses what cannot
    fit."""
    scene = synthetic_scene(api)

    def submit(**body):
        return api.post(
            "/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "cpu", **body}
        )

    huge = submit(
        overrides={"network.width": 2048, "network.num_experts": 64, "network.expert_layers": 16}
    )
    assert huge.status_code == 422, huge.text
    [problem] = huge.json()["detail"]
    assert (
        problem["loc"] == ["body", "overrides"]
        and "network.width" in problem["msg"]
        and "MiB" in problem["msg"]
    )
    # O asked at 16 points of 4,096 bins of 8,192 rays, with gradients: about 20 GiB whatever the
    # main samples (this was accepted while the estimate counted the main samples only)
    asked = submit(
        overrides={
            "rays_per_device": 8192,
            "guided.coarse_samples": 4096,
            "guided.queries_per_bin": 16,
        }
    )
    assert asked.status_code == 422 and "guided.coarse_samples" in asked.text, asked.text
    api.app.state.settings = Settings(**{**api.settings.model_dump(), "slot_memory_mb": 1500})
    assert submit().status_code == 201  # one cpu-profile rank: about 1.1 GiB
    two = submit(workers=2)
    assert two.status_code == 422 and "2 rank(s)" in two.json()["detail"][0]["msg"]
    api.app.state.settings = Settings(
        **{
            **api.settings.model_dump(),
            "ray_address": "http://127.0.0.1:9",
            "cluster_max_workers": 4,
            "cluster_gpus": 2,
        }
    )
    many = submit(workers=6)
    assert many.status_code == 422 and "at most 4" in many.json()["detail"][0]["msg"]
    gpus = submit(workers=3, use_gpu=True)
    assert gpus.status_code == 422 and "this cluster has 2 GPUs" in gpus.text
    assert len(api.get("/v1/jobs").json()["items"]) == 1  # only the job that fits was stored


@pytest.mark.parametrize(
    "path",
    [
        "/v1/jobs?scene=a%00b",
        "/v1/scenes/a%00b",
        "/v1/jobs/1/metrics?phase=m%00",
        "/v1/jobs/1/artifacts/a%00b",
        "/v1/scenes/" + "9" * 5000,
        "/v1/jobs?scene=" + "9" * 5000,
        "/v1/jobs?limit=99999999999",
        "/v1/jobs/1/metrics?after_step=99999999999",
        "/v1/jobs/99999999999",
        "/healthz?x=%00",
    ],
)
def test_nul_bytes_and_huge_numbers_in_paths_and_queries_are_4xx(api, path):
    """These gave 500 on PostgreSQL (NUL in a string literal) or in int() (5,000 digits)."""
    answer = api.get(path)
    assert answer.status_code < 500, (path, answer.status_code, answer.text[:200])
    if "%00" in path:
        assert answer.status_code == 422 and "NUL byte" in answer.json()["detail"]
    elif "scene=" in path:
        assert answer.json()["items"] == []  # a filter that matches nothing
    else:
        assert answer.status_code in (404, 422)


def test_readyz_says_up_or_down_only_and_a_local_backend_needs_no_ray(service_settings):

    local = Settings(**{**service_settings.model_dump(), "backend": "local"})
    with api_client(local) as client:
        answer = client.get("/readyz")
        assert answer.status_code == 200
        assert answer.json() == {
            "ready": True,
            "checks": {"database": "up", "ray": "not used (LECO_BACKEND=local)"},
        }
    down = Settings(**{**service_settings.model_dump(), "ray_address": "http://127.0.0.1:9"})
    with api_client(down) as client:
        answer = client.get("/readyz")
        assert answer.status_code == 503 and answer.json()["checks"] == {
            "database": "up",
            "ray": "down",
        }
        assert "127.0.0.1:9" not in answer.text


def test_no_auth_only_on_loopback_blank_tokens_refused_and_the_token_file_private(
    tmp_path, monkeypatch
):
    import argparse
    import stat

    from cli.serve import loopback, serve, write_private

    assert loopback("127.0.0.1") and loopback("::1") and loopback("localhost")
    assert not loopback("0.0.0.0") and not loopback("10.0.0.5") and not loopback("example.org")
    with pytest.raises(SystemExit, match="--no-auth with --host 0.0.0.0 would open the API"):
        serve(argparse.Namespace(no_auth=True, host="0.0.0.0"))
    monkeypatch.setenv("LECO_API_TOKENS", " , ")
    with pytest.raises(ValueError, match="LECO_API_TOKENS is set but holds no token"):
        Settings.from_env()
    monkeypatch.setenv("LECO_API_TOKENS", "a, b")
    assert Settings.from_env().api_tokens == ("a", "b")
    path = tmp_path / "api-token"
    path.write_text("old")
    path.chmod(0o644)  # a file left readable by an earlier version is replaced, not reused
    write_private(path, "secret")
    assert path.read_text() == "secret" and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["api-token"]


def test_security_headers_and_the_dashboards_content_security_policy(api):
    for path in (
        "/dashboard/",
        "/dashboard/static/app.js",
        "/v1/jobs",
        "/healthz",
        "/v1/jobs?x=%00",
    ):
        headers = api.get(path).headers
        assert (
            headers["x-content-type-options"] == "nosniff" and headers["x-frame-options"] == "DENY"
        ), path
    csp = api.get("/dashboard/").headers["content-security-policy"]
    assert (
        "script-src 'self';" in csp and "frame-ancestors 'none'" in csp and "unsafe-eval" not in csp
    )
    assert "script-src 'self' 'unsafe-inline'" not in csp
    assert "<script>" not in api.get("/dashboard/").text  # every script is a file the policy allows


def test_an_idempotent_job_and_its_recorded_answer_commit_together(api, monkeypatch):
    """A failure between writing the job and recording the key's answer used to leave a job whose
    key a retry would not find, so the retry made a second job. Now both roll back and the retry
    makes one."""
    from fastapi.testclient import TestClient

    from service.api import jobs

    scene = synthetic_scene(api)
    body = {"scene": scene["id"], "method": "grid", "profile": "smoke"}

    def broken(session, key, status, payload):
        raise RuntimeError("the database went away mid-commit")

    monkeypatch.setattr(jobs, "record_answer", broken)
    client = TestClient(
        api.app, raise_server_exceptions=False, headers={"Authorization": f"Bearer {TOKEN}"}
    )
    assert client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"}).status_code == 500
    assert api.get("/v1/jobs").json()["items"] == []  # the job rolled back with the answer
    monkeypatch.undo()
    first = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k1"})
    assert first.status_code == 201 and again.json()["id"] == first.json()["id"]
    assert (
        again.headers["Idempotent-Replayed"] == "true" and api.get("/v1/jobs").json()["total"] == 1
    )


# A delete and a submit on the same training job at the same time: a render or export that was
# accepted (201) is never deleted by the delete that raced it; the delete is refused instead.
def succeeded_training_job(url: str, scene_id: int) -> int:
    with transaction(url) as session:
        job = submit(session, TRAIN, scene_id, TrainConfig(method="switch", profile="smoke"))
        session.flush()
        job.state = "succeeded"
        return job.id


def submit_until_gone(
    api, job: int, body: dict, go: threading.Barrier, accepted: list[int], other: list[int]
) -> None:
    go.wait()
    while len(accepted) < 3:
        answer = api.post(f"/v1/jobs/{job}/renders", json=body)
        if answer.status_code != 201:
            other.append(answer.status_code)
            return
        accepted.append(answer.json()["id"])


def test_a_render_accepted_while_its_training_job_is_deleted_survives(api):
    url = api.settings.db_url
    with transaction(url) as session:
        scene = Scene(
            name="race",
            source="upload",
            state="ready",
            path="/nowhere",
            format="meganerf",
            info={"cameras": 4, "splits": {"train": {"images": 4}}},
        )
        session.add(scene)
        session.flush()
        scene_id = scene.id
    body = {"frames": 2, "width": 16, "height": 16, "path": {"kind": "orbit"}}
    deleted = refused = 0
    for _ in range(12):
        job = succeeded_training_job(url, scene_id)
        accepted: list[int] = []
        # answers other than 201 (asserted here: a thread's failed assert is only a warning)
        other: list[int] = []
        go = threading.Barrier(2)
        submitter = threading.Thread(
            target=submit_until_gone, args=(api, job, body, go, accepted, other)
        )
        submitter.start()
        go.wait()
        answer = api.delete(f"/v1/jobs/{job}")
        submitter.join()
        assert set(other) <= {404}, other  # a submit that lost the race finds no job
        assert answer.status_code in (204, 409), answer.text
        if answer.status_code == 204:
            deleted += 1
            assert not accepted, "a render was accepted and then deleted with its training job"
        else:
            refused += 1
            assert "cancel it" in answer.json()["detail"]
        for render in accepted:  # every accepted render is still there, its parent with it
            assert api.get(f"/v1/jobs/{render}").status_code == 200
            assert api.get(f"/v1/jobs/{job}").status_code == 200
    assert deleted + refused == 12
    with transaction(url) as session:  # nothing orphaned: every render's parent exists
        renders = session.query(Job).filter(Job.kind == "render").all()
        assert all(session.get(Job, r.parent_id) is not None for r in renders)


def test_synthetic_presets_the_api_offers_are_the_generators_but_the_scale_scene():
    """The API's preset choice is spelled out (the API process loads no generator); it must name
    every preset but xl, whose gigabyte of files is generated with `leco scene synth`."""
    from typing import get_args

    from model.scenes.synthetic import PRESETS
    from service.api.schemas import SyntheticSceneRequest

    offered = get_args(SyntheticSceneRequest.model_fields["preset"].annotation)
    assert set(offered) == set(PRESETS) - {"xl"}
