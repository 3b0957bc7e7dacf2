"""Integers at the API boundary are integers: every integer field of every JSON request body in the
OpenAPI document (ids, counts, seeds, sizes, nested ones included) refuses a boolean, a numeric
string and a float, and null unless the field is optional. Lax parsing read `{"scene": true}` as
scene 1 and `true` as one worker. A job's `overrides` (a free-form map in the OpenAPI document) are
held to the same rule, setting by setting, against the profile's own schema."""

import pytest
from fastapi.testclient import TestClient

from model.profiles import PROFILES, Profile, settings
from service.api.app import create_app
from service.settings import Settings
from workers.config import TrainConfig, parse_overrides

TOKEN = "strict-token"
BAD = {"a boolean": True, "a numeric string": "2", "a float": 2.0, "null": None}


def resolve(schema: dict, node: dict) -> dict:
    while "$ref" in node:
        node = schema["components"]["schemas"][node["$ref"].rsplit("/", 1)[-1]]
    return node


def integer_fields(schema: dict, node: dict, body: dict, path: tuple = ()):
    """(path of names, a body placing the field there, the probes it may take: null if optional,
    a numeric string if it takes any string) for every integer field under NODE; a discriminated
    union is entered once per member, with its tag set."""
    node = resolve(schema, node)
    for name, prop in node.get("properties", {}).items():
        options = [resolve(schema, o) for o in prop.get("anyOf", prop.get("oneOf", [prop]))]
        if any(o.get("type") == "integer" for o in options):
            skip = {None} if any(o.get("type") == "null" for o in options) else set()
            if any(o.get("type") == "string" and not {"const", "enum"} & set(o) for o in options):
                skip.add("2")  # a field that takes any string too (a scene's name) takes "2"
            yield (*path, name), body, skip
        for member in options:
            if "properties" in member:
                tag = {
                    k: v["const"] for k, v in member["properties"].items() if "const" in v
                }  # the discriminator, so the member is the one validated
                yield from integer_fields(schema, member, tag, (*path, name))


def placed(path: tuple, tags: dict, value) -> dict:
    """{"a": {"b": value}} for path (a, b), with the member's tag beside the innermost field."""
    inner = {**tags, path[-1]: value}
    for name in reversed(path[:-1]):
        inner = {name: inner}
    return inner


@pytest.fixture
def client(service_settings):
    settings = Settings(**{**service_settings.model_dump(), "api_tokens": (TOKEN,)})
    with TestClient(create_app(settings)) as c:
        c.headers["Authorization"] = f"Bearer {TOKEN}"
        yield c


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_every_integer_field_of_every_request_body_takes_integers_only(client):
    schema = client.get("/openapi.json").json()
    checked = []
    for route, operations in schema["paths"].items():
        for verb, operation in operations.items():
            content = operation.get("requestBody", {}).get("content", {})
            if "application/json" not in content:
                continue
            url = route.replace("{job_id}", "1").replace("{scene_id}", "1")
            for path, tags, allowed in integer_fields(
                schema, content["application/json"]["schema"], {}
            ):
                for what, value in BAD.items():
                    if value in allowed:
                        continue
                    answer = client.request(verb, url, json=placed(path, tags, value))
                    where = f"{verb.upper()} {route} {'.'.join(path)} = {what}"
                    assert answer.status_code == 422, f"{where}: {answer.status_code}"
                    locs = [e["loc"][1:] for e in answer.json()["detail"]]
                    # the error names the field (a union adds its member's name to the location)
                    assert any([x for x in loc if x in path] == list(path) for loc in locs), (
                        f"{where}: no error names it ({locs})"
                    )
                checked.append(f"{route} {'.'.join(path)}")
    # the job's counts and seed, the scene it names, the synthetic scene's seed, render, view and
    # export sizes, and the nested camera paths' sizes
    assert {
        "/v1/jobs workers",
        "/v1/jobs seed",
        "/v1/jobs scene",
        "/v1/jobs downscale",
        "/v1/scenes/synthetic seed",
        "/v1/jobs/{job_id}/renders frames",
        "/v1/jobs/{job_id}/renders appearance",
        "/v1/jobs/{job_id}/renders path.width",
        "/v1/jobs/{job_id}/renders path.render_width",
        "/v1/jobs/{job_id}/view width",
        "/v1/jobs/{job_id}/exports resolution",
    } <= set(checked)
    assert len(checked) >= 25


# Override probes, each with the JSON kinds of setting that take it: an integer is a number too.
PROBES = {
    "a boolean": (True, {"boolean"}),
    "a numeric string": ("2", {"string"}),
    "a float": (2.0, {"number"}),
    "an integer": (1, {"integer", "number"}),
    "null": (None, {"null"}),
}
# what the refusal says a setting of each kind takes
EXPECTED = {
    "integer": "expected an integer",
    "number": "expected a number",
    "boolean": "expected true or false",
    "string": "expected one of",
    "array": "expected a list of integers",
}


def setting_kinds(schema: dict, key: str) -> set[str]:
    """The JSON kinds the profile's schema gives the setting at a dotted key (null if optional)."""
    node = schema
    for part in key.split("."):
        node = node["properties"][part]
        while "$ref" in node:
            node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
    return {option["type"] for option in node.get("anyOf", [node])}


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_every_override_takes_its_settings_type_only(client):
    """Every setting `leco settings` lists, sent as an override a boolean, a numeric string, a
    float, an integer or null where its type does not take one: 422 naming the key and what it
    takes. Lax parsing read `{"rays_per_device": true}` as 1 ray and `"2"` as 2."""
    schema = Profile.model_json_schema()
    sent = 0
    for key, _, _ in settings(PROFILES["smoke"]):
        kinds = setting_kinds(schema, key)
        for what, (value, takers) in PROBES.items():
            if kinds & takers:
                continue
            body = {"scene": 1, "method": "leco", "profile": "smoke", "overrides": {key: value}}
            answer = client.post("/v1/jobs", json=body)
            assert answer.status_code == 422, f"{key} = {what}: {answer.status_code}"
            [problem] = answer.json()["detail"]
            named = [EXPECTED[k] for k in kinds - {"null"}]
            assert f"override {key!r}" in problem["msg"] and named[0] in problem["msg"], (
                f"{key} = {what}: {problem['msg']}"
            )
            sent += 1
    assert sent > 3 * 200  # 211 settings when this was written, each refusing three or more


def test_overrides_of_the_right_type_still_resolve():
    """What the strict check must keep taking: an integer for a number, null for an optional
    setting, a Literal's string, a JSON list for a tuple, and the CLI's --set values (JSON)."""
    cfg = TrainConfig(
        method="leco",
        profile="smoke",
        overrides={
            "lr": 1,
            "network.capacity_factor": None,
            "guided.placement": True,
            "guided.placement_within": "volume",
            "prop.samples": [16, 8],
            **parse_overrides(["occupancy.steps=200", "guided.empty_threshold=0.5"]),
        },
    )
    profile = cfg.resolved_profile()
    assert (profile.lr, profile.network.capacity_factor, profile.guided.placement) == (
        1.0,
        None,
        True,
    )
    assert profile.guided.placement_within == "volume" and profile.prop.samples == (16, 8)
    assert profile.occupancy.steps == 200 and profile.guided.empty_threshold == 0.5


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_a_job_stored_with_a_lax_override_is_still_shown(client):
    """A job taken before overrides were strict may hold `"rays_per_device": "64"`: it is listed
    and shown (without an ETA), not a 500 for every job list."""
    from service.db import transaction
    from service.jobs.kinds import TRAIN
    from service.jobs.submit import submit
    from service.tables import Scene

    settings = client.app.state.settings
    with transaction(settings.db_url) as session:
        scene = Scene(name="stored", source="synthetic", state="ready", path="/nowhere")
        session.add(scene)
        session.flush()
        job = submit(session, TRAIN, scene.id, TrainConfig(method="leco", profile="smoke"))
        job.config = {**job.config, "overrides": {"rays_per_device": "64"}}
        session.flush()
        job_id = job.id
    shown = client.get(f"/v1/jobs/{job_id}")
    assert shown.status_code == 200 and shown.json()["eta_s"] is None, shown.text
    assert client.get("/v1/jobs").json()["total"] == 1
