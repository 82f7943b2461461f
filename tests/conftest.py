"""Shared fixtures."""

import pytest

from hmdrt.scene import Scene, load_scene


@pytest.fixture(scope="session")
def whitted_scene() -> Scene:
    return load_scene("whitted")
