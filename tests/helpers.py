"""Shared test helpers: paths of the bundled scenes and models, and short ways to load and run them.

Tests import from here (`from helpers import run, scene`); conftest.py keeps only fixtures."""

from pathlib import Path

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
MODELS = ROOT / "models"
BUNDLED = sorted(p.stem for p in SCENES.glob("*.toml"))


def scene(name: str, **options) -> ms.Scene:
    """A bundled scene with options overridden."""
    return ms.load_scene(SCENES / f"{name}.toml").with_options(**options)


def run(name: str, **options) -> ms.Trajectory:
    return ms.simulate(ms.build_model(scene(name, **options)), progress=False)


def inline_scene(toml: str, tmp_path: Path, name: str = "inline") -> ms.Scene:
    """A scene written to tmp_path (URDF paths may use {models})."""
    p = tmp_path / f"{name}.toml"
    p.write_text(toml.replace("{models}", str(MODELS)))
    return ms.load_scene(p)
