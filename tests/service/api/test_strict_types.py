"""Integers at the API boundary are integers: every integer field of every JSON request body in the
OpenAPI document (ids, counts, seeds, sizes, nested ones included) refuses a boolean, a numeric
string and a float, and null unless the field is optional. Lax parsing read `{"scene": true}` as
scene 1 and `true` as one worker."""

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings

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
