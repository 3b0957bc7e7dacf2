"""The OpenAPI links the routes declare (service/api/links.py): every link names an existing operation,
parameter and response field, so the document tells clients how ids flow between calls."""

import re

import pytest

from service.api.app import create_app
from service.db import upgrade
from service.settings import Settings


# ----- the links themselves ---------------------------------------------------------------------------------
@pytest.fixture
def openapi(tmp_path) -> dict:
    url = f"sqlite:///{tmp_path / 'leco.db'}"
    upgrade(url)
    return create_app(Settings(data_dir=tmp_path / "data", database_url=url)).openapi()


def operations(document: dict) -> dict[str, dict]:
    return {op["operationId"]: op for methods in document["paths"].values() for op in methods.values()}


def resolve(document: dict, schema: dict) -> dict:
    while "$ref" in schema:
        schema = document["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return schema


def pointer_resolves(document: dict, schema: dict, pointer: str) -> bool:
    """Whether every answer valid against `schema` can hold a value at the JSON pointer."""
    for token in [t for t in pointer.split("/") if t]:
        schema = resolve(document, schema)
        if token.isdigit() and schema.get("type") == "array":
            schema = schema["items"]
        elif token in schema.get("properties", {}):
            schema = schema["properties"][token]
        else:
            return False
    return True


def expression_problem(document: dict, source: dict, status: str, expression) -> str | None:
    if isinstance(expression, dict):
        return next(filter(None, (expression_problem(document, source, status, e) for e in expression.values())),
                    None)
    if expression == "$request.body":
        return None if "requestBody" in source else "no request body"
    if match := re.fullmatch(r"\$request\.(path|query|header)\.(.+)", expression):
        known = {(p["in"], p["name"]) for p in source.get("parameters", [])}
        return None if match.groups() in known else f"{source['operationId']} has no {match[1]} {match[2]}"
    if match := re.fullmatch(r"\$response\.body#(/.*)", expression):
        content = source["responses"][status].get("content", {}).get("application/json")
        if content and pointer_resolves(document, content["schema"], match[1]):
            return None
        return f"{status} of {source['operationId']} has no {match[1]}"
    return f"unknown expression {expression!r}"


def link_problems(document: dict, source: dict, status: str, link: dict) -> list[str]:
    target = operations(document).get(link["operationId"])
    if target is None:
        return [f"no operation {link['operationId']}"]
    problems = []
    params = {(p["in"], p["name"]) for p in target.get("parameters", [])}
    for name, expression in link.get("parameters", {}).items():
        if tuple(name.split(".", 1)) not in params:
            problems.append(f"{link['operationId']} has no parameter {name}")
        problems.append(expression_problem(document, source, status, expression))
    if "requestBody" in link:
        body = link["requestBody"]
        schema = target.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema")
        if schema is None:
            problems.append(f"{link['operationId']} takes no JSON body")
        elif isinstance(body, dict):
            problems += [f"{link['operationId']}'s body has no {key}" for key in body
                         if key not in resolve(document, schema).get("properties", {})]
        problems.append(expression_problem(document, source, status, body))
    return [p for p in problems if p]


def test_every_link_names_an_operation_parameter_and_field_that_exist(openapi):
    problems, count = [], 0
    for source in operations(openapi).values():
        for status, response in source["responses"].items():
            for name, link in response.get("links", {}).items():
                count += 1
                problems += [f"{source['operationId']} {status} {name}: {p}"
                             for p in link_problems(openapi, source, status, link)]
    assert problems == []
    assert count >= 45  # scenes, jobs, artifacts, deletions, idempotency (service/api/links.py)


def test_the_link_check_finds_a_wrong_operation_parameter_or_field(openapi):
    submit = operations(openapi)["submitJob"]

    def to_job(expression="$response.body#/id", parameter="path.job_id", operation="getJob") -> dict:
        return {"operationId": operation, "parameters": {parameter: expression}}

    broken = [
        (to_job(operation="getJobs"), "no operation getJobs"),
        (to_job(parameter="path.id"), "getJob has no parameter path.id"),
        (to_job("$response.body#/job"), "201 of submitJob has no /job"),
        (to_job("$request.path.job_id"), "submitJob has no path job_id"),
        ({"operationId": "submitJob", "requestBody": {"scene_id": "$response.body#/scene_id"}}, "body has no scene_id"),
    ]
    for link, problem in broken:
        assert any(problem in p for p in link_problems(openapi, submit, "201", link)), (link, problem)
