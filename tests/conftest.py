"""Fixtures only; shared helpers live in helpers.py."""

import pytest

from helpers import inline_scene


@pytest.fixture
def tmp_scene(tmp_path):
    return lambda toml, name="inline": inline_scene(toml, tmp_path, name)
