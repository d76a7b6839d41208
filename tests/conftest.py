"""Shared fixtures: loopback Zenoh endpoints, shipped defaults, the shared data folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from collabslam.supervisor import free_port
from common.config import Config, load_config

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def cfg() -> Config:
    """The shipped defaults; tests override only what they need."""
    return load_config()


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is not present on this machine")
    return SHARED_DATA


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests that start real processes (marked `e2e`, 20-90 s each) run first, in their
    files' order: with pytest-xdist workers (`make test TEST_WORKERS=2`, work stealing)
    the long ones are spread over both and the short ones fill in behind, instead of
    one long test finishing alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("e2e") is None)
