"""One root for every error the project raises on purpose (model/errors.py): each class has a kind,
and the command line and the API report a kind one way everywhere."""

import importlib
import pkgutil

import pytest
from fastapi.testclient import TestClient

from cli.main import EXIT_CODES
from model import errors
from model.errors import KINDS, LecoError
from service.api.app import RETRY_KINDS, STATUSES, create_app
from service.settings import Settings

PACKAGES = ["model", "workers", "service", "cli", "bench"]
SKIP = ("__main__",)  # entry points that run on import


def project_exceptions() -> list[type]:
    found = []
    for package in PACKAGES:
        root = importlib.import_module(package)
        for info in pkgutil.walk_packages(root.__path__, f"{package}."):
            if info.name.endswith(SKIP):
                continue
            module = importlib.import_module(info.name)
            for value in vars(module).values():
                if (
                    isinstance(value, type)
                    and issubclass(value, BaseException)
                    and value.__module__ == module.__name__
                ):
                    found.append(value)
    return found


def test_every_error_class_of_the_project_has_the_one_root_and_a_kind():
    found = project_exceptions()
    assert len(found) >= 20  # the scan sees the project's classes (SceneError, RunError, ...)
    strays = [f"{c.__module__}.{c.__name__}" for c in found if not issubclass(c, LecoError)]
    assert strays == []
    assert {c.kind for c in found} <= set(KINDS)


def test_every_kind_has_an_exit_code_and_an_http_status():
    assert set(EXIT_CODES) == set(KINDS) == set(STATUSES)
    assert STATUSES["invalid"] == 422 and STATUSES["conflict"] == 409
    assert STATUSES["busy"] == 429 and STATUSES["unavailable"] == 503


def test_the_cli_reports_a_project_error_by_its_kind(capsys, tmp_path):
    from cli.main import main

    assert main(["scene", "info", str(tmp_path / "nowhere")]) == EXIT_CODES["invalid"]
    assert "nowhere" in capsys.readouterr().err


@pytest.mark.parametrize(
    "error, status",
    [
        (errors.InvalidInput("the width must be even"), 422),
        (errors.Conflict("a scene called city exists"), 409),
        (errors.Busy("every worker is taken"), 429),
        (errors.Unavailable("the database is away"), 503),
        (errors.Failed("the artifact root is not writable"), 500),
    ],
)
def test_the_api_reports_an_uncaught_project_error_by_its_kind(error, status, tmp_path):
    from service.db import upgrade

    url = f"sqlite:///{tmp_path}/db.sqlite"
    upgrade(url)
    app = create_app(Settings(data_dir=tmp_path, database_url=url))

    @app.get("/toy-error")
    def toy() -> None:
        raise error

    with TestClient(app, raise_server_exceptions=False) as client:
        response = client.get("/toy-error")
    assert response.status_code == status
    assert response.json() == {"detail": str(error)}
    assert ("retry-after" in response.headers) == (error.kind in RETRY_KINDS)
