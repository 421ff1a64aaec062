"""Shared fixtures: paths of the repository and of the paper's gantry config."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def gantry_yaml(repo) -> Path:
    return repo / "configs" / "gantry.yaml"
