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
