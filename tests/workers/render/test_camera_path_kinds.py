"""Camera-path kinds have one home (workers/camera_paths): a toy kind added here, one class and a
registry line, is a render's `path` in the schema and the OpenAPI document, is listed by GET
/v1/camera-paths, is a `leco render --path`, and builds its cameras on a real scene."""

import argparse
import ast
from typing import Literal

import pytest
import torch
from pydantic import Field, ValidationError

from cli.render import path_spec
from model.scenes.camera_paths import CameraPath, box_centre_and_radius, intrinsics_for_fov, look_at
from model.scenes.cameras import rotation_error
from tests.helpers import ROOT, api_client
from workers.render.camera_paths.base import PathKind
from workers.render.camera_paths.registry import PATH_KINDS, register_path, unregister_path
from workers.render.job import build_path
from workers.render.schemas import RenderConfig


class DollyPath(PathKind):
    """dolly: straight down at the box's centre, from `start` to `end` box radii above it."""

    kind: Literal["dolly"] = "dolly"
    generated = True
    start: float = Field(3.0, gt=0, le=100)
    end: float = Field(1.5, gt=0, le=100)

    def build(self, scene, width, height, frames) -> CameraPath:
        centre, radius = box_centre_and_radius(scene.bounds.aabb.double())
        heights = torch.linspace(self.start, self.end, frames, dtype=torch.float64) * radius
        poses = [
            look_at(centre + torch.tensor([0.0, 1e-3, 1.0], dtype=torch.float64) * h, centre)
            for h in heights
        ]
        k = intrinsics_for_fov(50.0, width, height)
        return CameraPath(torch.stack(poses), k.expand(frames, 4).clone(), width, height)


@pytest.fixture
def dolly():
    register_path(DollyPath)
    yield DollyPath
    unregister_path("dolly")


def test_a_registered_toy_path_kind_renders_from_the_schema_the_cli_and_the_api(
    dolly, tiny_scene, service_settings
):
    cfg = RenderConfig(width=32, height=24, frames=5, path={"kind": "dolly", "end": 2.0})
    assert isinstance(cfg.path, DollyPath) and cfg.frame_count == 5
    path = build_path(cfg, tiny_scene)
    assert len(path) == 5 and rotation_error(path.c2w).max() < 1e-9
    heights = path.c2w[:, 2, 3]
    assert (heights.diff() < 0).all()  # moving down towards the box
    with pytest.raises(ValidationError, match="path.dolly.start"):
        RenderConfig(path={"kind": "dolly", "start": -1})
    args = argparse.Namespace(path="dolly", pitch=10.0, altitude=None, turns=None, fov=None)
    assert path_spec(args) == {"kind": "dolly"}  # the flags it has none of are not passed
    with api_client(service_settings) as api:
        listed = {k["kind"]: k for k in api.get("/v1/camera-paths").json()["items"]}
        assert listed["dolly"]["generated"] and "straight down" in listed["dolly"]["description"]
        assert set(listed["dolly"]["schema"]["properties"]) == {"kind", "start", "end"}
        assert "DollyPath" in api.get("/openapi.json").json()["components"]["schemas"]


def test_the_registry_lists_the_built_in_kinds_and_refuses_a_second_owner():
    assert list(PATH_KINDS) == ["orbit", "flyover", "spiral", "cameras", "nerfstudio"]

    class Impostor(PathKind):
        kind: Literal["orbit"] = "orbit"

    with pytest.raises(ValueError, match="'orbit' is already registered"):
        register_path(Impostor)
    with pytest.raises(ValidationError):
        RenderConfig(path={"kind": "dolly"})  # not registered


OUTSIDE = [
    p
    for layer in ("model", "workers", "service", "cli", "bench")
    for p in (ROOT / layer).rglob("*.py")
    if "camera_paths" not in p.parts
]


def test_no_module_outside_the_kinds_compares_a_path_kind():
    compared = []
    for path in OUTSIDE:
        for node in ast.walk(ast.parse(path.read_text())):
            operands = [node.left, *node.comparators] if isinstance(node, ast.Compare) else []
            tags = [c for c in operands if isinstance(c, ast.Constant) and c.value in PATH_KINDS]
            # A path's kind against a tag (`path.kind == "orbit"`); "cameras" is also an export and
            # a JSON key.
            if tags and any(
                "kind" in ast.unparse(c) or "path" in ast.unparse(c)
                for c in operands
                if c not in tags
            ):
                compared.append((str(path.relative_to(ROOT)), node.lineno))
    assert compared == []
    script = (ROOT / "service" / "dashboard" / "app.js").read_text()
    assert not [k for k in PATH_KINDS if f'kind === "{k}"' in script or f'kind !== "{k}"' in script]
