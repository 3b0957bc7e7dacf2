"""Stateful fuzzing of the API, on SQLite and on PostgreSQL: schemathesis's state machine chains
calls along the OpenAPI links the routes declare (service/api/links.py), so later requests use the
ids earlier answers created: upload a scene -> submit a job on it -> cancel it (twice), delete it,
its metrics and artifacts, an artifact's download -> delete the scene while a job uses it, the same
Idempotency-Key again with the same or another body, anything on a deleted scene or job. Whatever
the order and the values, no answer is a 5xx or carries a stack trace or a server path, and no new
scene or job gets an id given out before. Also: every link in the document names an existing
operation, parameter and response field."""

import re
import shutil
from collections import Counter

import pytest
import schemathesis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, seed
from hypothesis import settings as hypothesis_settings
from sqlalchemy import func, select

from service import queue
from service.api.app import create_app
from service.api.poll_cache import PollCache
from service.db import reading, transaction, upgrade
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.store import ArtifactStore
from service.tables import Base, Job
from tests.helpers import tar_of

TOKEN = "fuzz-token"
UPLOAD, SUBMIT = "POST /v1/scenes/upload", "POST /v1/jobs"
WAIT_STEPS = 15  # requests a submitted job waits before it runs (see Workflow.dispatch)
# Seeds of the rounds of 50 scenarios (test_chained_requests_never_get_a_server_error...), in the
# order tried. Alone, on SQLite: seeds 0 and 4 missed a rare chain, 2 followed each 8 times or more.
ROUND_SEEDS = (2, 1, 3, 0, 4)
READS_RUN = {"GET /v1/jobs/{job_id}/metrics", "GET /v1/jobs/{job_id}/artifacts"}
# Links (by name, from whichever answer) that each run must have followed with an earlier answer's
# value in place, to the status named: a stateful fuzz that never chains cannot fail. See
# service/api/links.py.
MUST_CHAIN = [
    ({"SubmitJob"}, 201),  # a new scene's id trains a job
    ({"GetJob", "GetArtifactJob"}, 200),  # a job's id shows it
    ({"CancelJob"}, 200),  # a waiting job cancelled (or asked again)
    ({"DeleteJobScene"}, 409),  # its scene, while it exists
    ({"DeleteJob"}, 204),
    (
        {
            "GetDeletedJob",
            "CancelDeletedJob",
            "DeleteDeletedJob",
            "GetDeletedJobMetrics",
            "ListDeletedJobArtifacts",
        },
        404,
    ),
    ({"GetJobMetrics"}, 200),
    ({"ListJobArtifacts"}, 200),
    ({"GetArtifact", "DownloadArtifact"}, 200),  # an artifact's id from its job's list
    ({"DeleteScene", "DeleteJobScene"}, 204),
    ({"GetDeletedScene", "SubmitJobOnDeletedScene"}, 404),
]


@pytest.fixture(scope="module")
def tiny_archive(tiny_scene) -> bytes:
    return tar_of(tiny_scene.root)


class Findings:
    """What the machine did (per link followed with an earlier answer's value in place: the statuses
    it got; how often an Idempotency-Key came back with another body) and what went wrong, each
    problem with the requests of its scenario up to it. Nothing is raised inside the machine:
    Hypothesis's report of a failing scenario cannot name the steps whose answers feed no link
    (schemathesis keeps only those), and on a scenario that opens with one it fails with a
    FlakyStrategyDefinition instead of the error."""

    def __init__(self):
        self.followed: dict[str, Counter] = {}
        self.key_reused_with_another_body = 0
        self.problems: list[str] = []

    def record(self, link: str, status: int) -> None:
        self.followed.setdefault(link, Counter())[status] += 1

    def reached(self, names: set[str], status: int) -> bool:
        return any(
            link.split("] ", 1)[1].split(" ->")[0] in names and statuses[status]
            for link, statuses in self.followed.items()
        )

    def chains(self) -> str:
        return "\n".join(
            f"{link}: {dict(statuses)}" for link, statuses in sorted(self.followed.items())
        )


class Server:
    """The app as uvicorn serves it: an exception in a route reaches the client as the 500 that
    Starlette's ServerErrorMiddleware sent before re-raising it for the server's log, not as an
    exception in the client."""

    def __init__(self, app: FastAPI):
        self.app = app

    async def __call__(self, scope, receive, send):
        try:
            await self.app(scope, receive, send)
        except Exception:
            if scope["type"] != "http":
                raise


def start_empty(settings: Settings, app: FastAPI) -> None:
    """Every scenario starts on an empty service: Hypothesis replays and extends earlier scenarios'
    choices and requires them to behave the same (a name an earlier scenario took would not), and an
    empty poll cache holds no answer from an earlier scenario."""
    with transaction(settings.db_url) as session:
        for table in reversed(Base.metadata.sorted_tables):  # children first
            session.execute(table.delete())
    for folder in (settings.scenes_dir, settings.artifacts, settings.runs_dir):
        shutil.rmtree(folder, ignore_errors=True)
    app.state.poll_cache = PollCache(settings.poll_cache_s)


# What a run stores, one of each kind (docs/SERVICE.md, "What a job stores"), with a few bytes each.
STORED = [
    ("checkpoint", "checkpoint-step0000005.pt"),
    ("render", "renders/final_000.png"),
    ("occupancy_model", "final/occupancy.pt"),
    ("pointcloud", "occupancy.ply"),
    ("report", "summary.json"),
]


def run_some_training(settings: Settings) -> int:
    """What a dispatcher and a run write, without the training: the oldest queued job is claimed,
    gets a few metric steps and its artifacts through the run's own stores, and succeeds. Returns
    its id."""
    job_id, attempt = queue.claim(settings.db_url, "stateful-fuzz", settings.lease_s)
    store = DatabaseRunStore(
        settings.db_url, str(settings.artifacts), job_id, attempt, settings.retry_s
    )
    for step in range(1, 6):
        store.write(
            step,
            {"phase": "main", "loss": 1.0 / step, "psnr": 10.0 + step, "wall_time_s": 0.1 * step},
        )
    artifacts = ArtifactStore(settings.db_url, settings.artifacts)
    for kind, name in STORED:
        artifacts.put(
            job_id, kind, name, f"{job_id} {name}".encode(), phase="main", step=5, attempt=attempt
        )
    queue.finish(settings.db_url, job_id, attempt, "succeeded")
    return job_id


def train_up_to(settings: Settings, last: int) -> list[int]:
    """Every job queued up to `last` runs to the end (claims take the oldest first)."""
    with reading(settings.db_url) as session:
        waiting = session.scalar(
            select(func.count()).select_from(Job).where(Job.state == "queued", Job.id <= last)
        )
    return [run_some_training(settings) for _ in range(waiting)]


def created_id(case, response) -> tuple[str, int] | None:
    """("scene" | "job", id) when the answer made a new resource (an idempotent replay makes
    none)."""
    if case.operation.label == UPLOAD and response.status_code == 201:
        return "scene", response.json()["id"]
    if (
        case.operation.label == SUBMIT
        and response.status_code == 201
        and "idempotent-replayed" not in response.headers
    ):
        return "job", response.json()["id"]
    return None


def wrong_answers(case, response, ids: dict[str, set]) -> list[str]:
    """What is wrong with this answer (the routes followed here do not include /readyz, whose 503 is
    documented); adds the id of a scene or job it made to `ids`, this scenario's ids so far."""
    where = f"{case.method} {case.formatted_path}"
    found = []
    if response.status_code >= 500:
        found.append(f"{where}: {response.status_code} {response.text[:500]}")
    if "Traceback" in response.text or 'File "/' in response.text:
        found.append(f"{where}: a stack trace or a server path in {response.text[:500]}")
    made = created_id(case, response)
    # an id a client may still hold (a deleted job's, say) must never name another
    if made is not None:
        kind, ident = made
        if ident in ids[kind]:
            found.append(f"{where}: the new {kind} got id {ident}, which an earlier {kind} had")
        ids[kind].add(ident)
    return found


def state_machine(schema, settings: Settings, archive: bytes, findings: Findings):
    app = schema.app
    server = Server(app)

    class Workflow(schema.as_state_machine()):
        def setup(self):
            start_empty(settings, app)
            self.ids = {"scene": set(), "job": set()}
            # (step, job id) of each job this scenario submitted
            self.submitted: list[tuple[int, int]] = []
            # this scenario's requests so far, for the report of a problem
            self.steps: list[str] = []
            # (Idempotency-Key, body) of each keyed submit that made a job
            self.keyed: list[tuple[str, dict]] = []

        def step(self, input):
            output = super().step(input)
            # a value from an earlier answer
            if input.transition is not None and input.applied_parameters:
                findings.record(input.transition.id, output.response.status_code)
            return output

        def before_call(self, case):
            # Random bytes are refused (the stateless fuzz sends those): a real archive makes the
            # scene that the chains after it use.
            if case.operation.label == UPLOAD:
                case.body = archive
            self.dispatch(case)

        def dispatch(self, case):
            """A dispatcher runs each job WAIT_STEPS requests after it was submitted, or before the
            first request that reads what the run writes: until then the job waits (to be cancelled,
            twice; deleting it is 409), afterwards it has ended (cancel is 409) with metrics and
            artifacts. Counted in requests, not seconds, so that a scenario replays the same."""
            read = (
                (case.path_parameters or {}).get("job_id")
                if case.operation.label in READS_RUN
                else None
            )
            due = [
                job
                for step, job in self.submitted
                if step + WAIT_STEPS <= len(self.steps) or job == read
            ]
            for trained in train_up_to(settings, max(due)) if due else []:
                # Shown at once, not after the poll cache's 0.5 s: the clock would make replays
                # differ.
                app.state.poll_cache.forget(trained)

        def get_call_kwargs(self, case):
            return {"headers": {"Authorization": f"Bearer {TOKEN}"}, "app": server}

        def after_call(self, response, case):
            super().after_call(response, case)
            if case.operation.label == SUBMIT and response.status_code == 201:
                self.submitted.append((len(self.steps), response.json()["id"]))
                if "Idempotency-Key" in (case.headers or {}):
                    self.keyed.append((case.headers["Idempotency-Key"], case.body))

        def teardown(self):
            """Each key of a submit that made a job, sent again with another seed: refused (422) and
            named. Generated keys (printable ASCII, up to 255 characters) almost never repeat by
            chance, so the scenario sends these itself, after its chain (which stays as generated).
            """
            for key, body in self.keyed:
                other = {**body, "seed": (body.get("seed", 0) + 1) % 2**31}
                headers = {"Authorization": f"Bearer {TOKEN}", "Idempotency-Key": key}
                answer = TestClient(server).post("/v1/jobs", json=other, headers=headers)
                if answer.status_code == 422 and "with a different request body" in answer.text:
                    findings.key_reused_with_another_body += 1
                else:
                    findings.problems.append(
                        f"POST /v1/jobs again with its key and another body: {answer.status_code} "
                        f"{answer.text[:300]}\n  after:\n    " + "\n    ".join(self.steps)
                    )

        def validate_response(self, response, case, **kwargs):
            self.steps.append(
                f"{case.method} {case.formatted_path} {case.query or ''} -> {response.status_code}"
            )
            for problem in wrong_answers(case, response, self.ids):
                findings.problems.append(f"{problem}\n  after:\n    " + "\n    ".join(self.steps))

    return Workflow


@pytest.mark.slow
def test_chained_requests_never_get_a_server_error_or_a_stack_trace(service_settings, tiny_archive):
    # No poll cache: a job list cached for 0.5 s while the dispatcher trains would make what the
    # chains see depend on the machine's speed (tests/service/api/test_poll_cache.py covers it).
    settings = Settings(
        **{**service_settings.model_dump(), "api_tokens": (TOKEN,), "poll_cache_s": 0.0}
    )
    schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(settings))
    # Generating a synthetic city is real work in a background thread: the uploads make the scenes
    # here.
    schema = schema.exclude(path="/v1/scenes/synthetic", method="POST")
    # Only the links the document declares (no inferred ones): what is tested is what clients are
    # told.
    schema.config.phases.stateful.inference.algorithms = []
    findings = Findings()
    machine = state_machine(schema, settings, tiny_archive, findings)
    # Rounds of 50 scenarios from fixed seeds, a further round only while a link below was never
    # followed to its answer: which scenarios 50 draws make varies with what ran before in the
    # process, and the rarer chains (an artifact of a job trained in the scenario) can miss in one
    # round. Every round's answers are checked.
    for round_seed in ROUND_SEEDS:
        seed(round_seed)(machine).run(
            settings=hypothesis_settings(
                max_examples=50,
                stateful_step_count=40,
                deadline=None,
                database=None,
                # nothing fails inside the machine (see Findings): nothing to shrink
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            )
        )
        if all(findings.reached(names, status) for names, status in MUST_CHAIN):
            break
    assert not findings.problems, f"{len(findings.problems)} problems; the first:\n" + "\n".join(
        findings.problems[:3]
    )
    missed = [
        (names, status) for names, status in MUST_CHAIN if not findings.reached(names, status)
    ]
    assert not missed, (
        f"links never followed to that answer: {missed}; followed:\n{findings.chains()}"
    )
    assert findings.key_reused_with_another_body


# ----- the links themselves
# ---------------------------------------------------------------------------------
@pytest.fixture
def openapi(tmp_path) -> dict:
    url = f"sqlite:///{tmp_path / 'leco.db'}"
    upgrade(url)
    return create_app(Settings(data_dir=tmp_path / "data", database_url=url)).openapi()


def operations(document: dict) -> dict[str, dict]:
    return {
        op["operationId"]: op for methods in document["paths"].values() for op in methods.values()
    }


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
        return next(
            filter(
                None, (expression_problem(document, source, status, e) for e in expression.values())
            ),
            None,
        )
    if expression == "$request.body":
        return None if "requestBody" in source else "no request body"
    if match := re.fullmatch(r"\$request\.(path|query|header)\.(.+)", expression):
        known = {(p["in"], p["name"]) for p in source.get("parameters", [])}
        return (
            None
            if match.groups() in known
            else f"{source['operationId']} has no {match[1]} {match[2]}"
        )
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
        schema = (
            target.get("requestBody", {})
            .get("content", {})
            .get("application/json", {})
            .get("schema")
        )
        if schema is None:
            problems.append(f"{link['operationId']} takes no JSON body")
        elif isinstance(body, dict):
            problems += [
                f"{link['operationId']}'s body has no {key}"
                for key in body
                if key not in resolve(document, schema).get("properties", {})
            ]
        problems.append(expression_problem(document, source, status, body))
    return [p for p in problems if p]


def test_every_link_names_an_operation_parameter_and_field_that_exist(openapi):
    problems, count = [], 0
    for source in operations(openapi).values():
        for status, response in source["responses"].items():
            for name, link in response.get("links", {}).items():
                count += 1
                problems += [
                    f"{source['operationId']} {status} {name}: {p}"
                    for p in link_problems(openapi, source, status, link)
                ]
    assert problems == []
    assert count >= 45  # scenes, jobs, artifacts, deletions, idempotency (service/api/links.py)


def test_the_link_check_finds_a_wrong_operation_parameter_or_field(openapi):
    submit = operations(openapi)["submitJob"]

    def to_job(
        expression="$response.body#/id", parameter="path.job_id", operation="getJob"
    ) -> dict:
        return {"operationId": operation, "parameters": {parameter: expression}}

    broken = [
        (to_job(operation="getJobs"), "no operation getJobs"),
        (to_job(parameter="path.id"), "getJob has no parameter path.id"),
        (to_job("$response.body#/job"), "201 of submitJob has no /job"),
        (to_job("$request.path.job_id"), "submitJob has no path job_id"),
        (
            {"operationId": "submitJob", "requestBody": {"scene_id": "$response.body#/scene_id"}},
            "body has no scene_id",
        ),
    ]
    for link, problem in broken:
        assert any(problem in p for p in link_problems(openapi, submit, "201", link)), (
            link,
            problem,
        )
