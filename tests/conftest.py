"""Fixtures only; shared helpers live in helpers.py."""

import pytest

from helpers import inline_scene


@pytest.fixture
def tmp_scene(tmp_path):
    return lambda toml, name="inline": inline_scene(toml, tmp_path, name)


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a test over ~10 s alone (deselect with -m 'not slow')")
