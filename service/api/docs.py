"""The API docs page (/docs): Swagger UI on /openapi.json with every file served from this origin,
from the swagger-ui-bundle package and our own initialiser, so the page loads no third-party script
and runs under the same Content-Security-Policy as the dashboard (service/api/headers.py). FastAPI's
own /docs and /redoc load their scripts from a CDN: they are off (create_app)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse
from swagger_ui_bundle import swagger_ui_path

OURS = Path(__file__).resolve().parent / "docs_page"
ASSETS = {
    "swagger-ui-bundle.js": (Path(str(swagger_ui_path)), "text/javascript"),
    "swagger-ui.css": (Path(str(swagger_ui_path)), "text/css"),
    "favicon-32x32.png": (Path(str(swagger_ui_path)), "image/png"),
    "docs.js": (OURS, "text/javascript"),
}

router = APIRouter(include_in_schema=False)


@router.get("/docs")
def page() -> FileResponse:
    return FileResponse(OURS / "index.html", media_type="text/html")


@router.get("/docs/assets/{name}")
def asset(name: str) -> FileResponse:
    if name not in ASSETS:
        raise HTTPException(404, f"no docs file {name!r}")
    folder, media_type = ASSETS[name]
    return FileResponse(folder / name, media_type=media_type)
