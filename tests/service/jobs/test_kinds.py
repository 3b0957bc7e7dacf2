"""Job kinds have one home (service/jobs/kinds.py): a toy kind added here, a function and a registry
line, is submitted through the API, run by a dispatcher through the one attempt runner and stored,
on SQLite and PostgreSQL; and no module outside the kinds compares a kind's name."""

import ast
import json
import threading
import time

import pytest
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select

from service.db import reading, transaction
from service.dispatcher import Dispatcher
from service.jobs.context import Attempt
from service.jobs.kinds import KINDS, TRAIN, JobKind, Parent, Refused, register
from service.jobs.paths import run_dir_for
from service.jobs.submit import submit
from service.tables import Artifact, Job, Scene
from tests.helpers import ROOT, api_client
from workers.config import TrainConfig


class InventoryConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    note: str = Field("", max_length=40)


def inventory(attempt: Attempt) -> None:
    """The toy's work: a JSON list of the training job's stored files, stored as the job's one
    artifact."""
    with reading(attempt.settings.db_url) as session:
        names = sorted(
            session.scalars(select(Artifact.name).where(Artifact.job_id == attempt.job.parent_id))
        )
    folder = run_dir_for(attempt.settings, attempt.job.id, attempt.number)
    folder.mkdir(parents=True, exist_ok=True)
    cfg = InventoryConfig.model_validate(attempt.job.config)
    (folder / "inventory.json").write_text(
        json.dumps({"parent": attempt.job.parent_id, "files": names, "note": cfg.note})
    )
    attempt.store.phase_started("inventory")
    attempt.store.artifact(
        "report", folder / "inventory.json", name="inventory.json", phase="inventory", step=1
    )


def no_shouting(cfg, parent: Parent) -> None:
    if cfg.note.isupper():
        raise Refused("note", f"a note on job {parent.job_id} in capitals")


TOY = JobKind(
    "inventory",
    InventoryConfig,
    inventory,
    lambda cfg, parent: [("inventory", 1)],
    route="inventories",
    check=no_shouting,
    description="The files a finished training job stored, listed.",
)


@pytest.fixture
def toy():
    register(TOY)
    yield TOY
    KINDS.pop(TOY.name)


def a_finished_training_job(settings) -> int:
    """A training job marked succeeded on a registered scene (the toy reads no networks, so none are
    trained)."""
    with transaction(settings.db_url) as session:
        scene = Scene(name="s", source="synthetic", state="ready", path=str(settings.data_dir))
        session.add(scene)
        session.flush()
        job = submit(session, TRAIN, scene.id, TrainConfig(method="switch", profile="smoke"))
        job.state = "succeeded"
        return job.id


def test_a_registered_toy_kind_runs_through_the_api_and_a_dispatcher(toy, service_settings):
    # registered in this process only: run in the dispatcher's thread, not a child process
    settings = service_settings.model_copy(update={"backend": "local", "local_in_child": False})
    parent = a_finished_training_job(settings)
    with api_client(settings) as api:
        kinds = {k["name"]: k for k in api.get("/v1/job-kinds").json()["items"]}
        assert kinds["inventory"] == {
            "name": "inventory",
            "trains": False,
            "submit": "POST /v1/jobs/{id}/inventories",
        }
        refused = api.post(f"/v1/jobs/{parent}/inventories", json={"note": "LOUD"})
        assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["body", "note"]
        assert api.post(f"/v1/jobs/{parent}/inventories", json={"nope": 1}).status_code == 422
        made = api.post(f"/v1/jobs/{parent}/inventories", json={"note": "quiet"})
        assert made.status_code == 201, made.text
        job = made.json()
        assert (job["kind"], job["trains"], job["parent_id"], job["total_steps"]) == (
            "inventory",
            False,
            parent,
            1,
        )
        # not made of a toy job
        assert api.post(f"/v1/jobs/{job['id']}/inventories", json={}).status_code == 422
        dispatcher = Dispatcher(settings, poll_s=0.1)
        threading.Thread(target=dispatcher.run_forever, daemon=True).start()
        try:
            deadline = time.monotonic() + 60
            while (state := api.get(f"/v1/jobs/{job['id']}").json())["state"] not in (
                "succeeded",
                "failed",
            ):
                assert time.monotonic() < deadline, state
                time.sleep(0.1)
        finally:
            dispatcher.stop(wait=True)
        assert state["state"] == "succeeded", state["error"]
        listed = api.get(f"/v1/jobs/{parent}/inventories").json()
        assert [j["id"] for j in listed["items"]] == [job["id"]]
        assert api.get("/v1/jobs", params={"kind": "inventory"}).json()["total"] == 1
        assert api.get("/v1/jobs", params={"trains": True}).json()["total"] == 1
        stored = next(
            a
            for a in api.get(f"/v1/jobs/{job['id']}/artifacts").json()
            if a["name"] == "inventory.json"
        )
        body = json.loads(api.get(stored["url"]).content)
        assert body == {"parent": parent, "files": [], "note": "quiet"}
    with reading(settings.db_url) as session:
        assert session.get(Job, job["id"]).kind == "inventory"


def test_the_registry_refuses_a_second_owner_of_a_name_and_a_name_the_table_cannot_hold():
    with pytest.raises(ValueError, match="'train' is already registered"):
        register(JobKind("train", InventoryConfig, inventory, lambda cfg, parent: [("x", 1)]))
    with pytest.raises(ValueError, match="1-16 lowercase"):
        register(JobKind("Inventory", InventoryConfig, inventory, lambda cfg, parent: [("x", 1)]))
    assert list(KINDS) == ["train", "render", "export", "poses"]


def test_an_unknown_kind_filter_is_refused_naming_the_kinds(service_settings):
    with api_client(service_settings) as api:
        refused = api.get("/v1/jobs", params={"kind": "nope"})
    assert refused.status_code == 422
    assert "choose one of train, render, export, poses" in refused.text


# Modules that queue, run, list and serve every kind: none may compare a job's kind with a kind's
# name.
GENERIC = [
    "service/queue.py",
    "service/dispatcher.py",
    "service/jobs/attempt.py",
    "service/jobs/submit.py",
    *[str(p.relative_to(ROOT)) for p in (ROOT / "service" / "api").glob("*.py")],
]


@pytest.mark.parametrize("path", GENERIC)
def test_generic_modules_compare_no_kind_name(path):
    tree = ast.parse((ROOT / path).read_text())
    compared = [
        (node.lineno, c.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Compare)
        for c in [node.left, *node.comparators]
        if isinstance(c, ast.Constant) and c.value in KINDS
    ]
    assert compared == [], f"{path} compares kind names: {compared}"
