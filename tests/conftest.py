"""Shared fixtures: the real scenes in ../shared/datasets (tests skip, saying why, when it is absent)."""

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"


def shared_dataset(name: str) -> Path:
    path = SHARED / name
    if not path.is_dir():
        pytest.skip(f"shared dataset {name} not found at {path} (it ships beside the checkout in ../shared)")
    return path


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    return shared_dataset("nerf_synthetic_lego_200")


@pytest.fixture(scope="session")
def fern_dir() -> Path:
    return shared_dataset("nerf_llff_fern")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The tiny synthetic city (seed 0), generated once per session: exact depth maps and occupancy."""
    from model.scenes import load_scene
    from model.scenes.synthetic import generate

    out = tmp_path_factory.mktemp("tiny-scene") / "tiny-0"
    generate("tiny", 0, out)
    return load_scene(out)
