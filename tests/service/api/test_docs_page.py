"""The API docs page loads nothing from another origin: Swagger UI's files come from this server,
under the dashboard's Content-Security-Policy; FastAPI's CDN pages are off."""

import re

import pytest

from tests.helpers import api_client


@pytest.fixture
def api(service_settings):
    with api_client(service_settings) as client:
        yield client


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_the_docs_page_serves_swagger_ui_from_this_origin_under_the_csp(api):
    page = api.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "script-src 'self'" in page.headers["content-security-policy"]
    sources = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert sources and all(s.startswith("/docs/assets/") for s in sources), sources
    assert "<script>" not in page.text  # no inline script for the policy to block
    for source in sources:
        asset = api.get(source)
        assert asset.status_code == 200 and len(asset.content) > 100, source
    assert b"SwaggerUIBundle" in api.get("/docs/assets/swagger-ui-bundle.js").content
    initialiser = api.get("/docs/assets/docs.js").text
    assert "/openapi.json" in initialiser
    # Swagger UI's default validatorUrl is validator.swagger.io, a third-party host
    assert re.search(r"^\s*validatorUrl:\s*null,", initialiser, re.MULTILINE), initialiser
    assert api.get("/docs/assets/../app.py").status_code == 404
    assert api.get("/docs/assets/index.j2").status_code == 404
    assert api.get("/redoc").status_code == 404
