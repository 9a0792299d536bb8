"""Build a scene from Python instead of a TOML file, the way PyBullet's ``loadURDF`` or MuJoCo's
``MjSpec`` are used; the result is the same validated :class:`~moreau_sim.scene.Scene`.

    import moreau_sim as ms
    b = ms.SceneBuilder("two_balls", restitution=0.8, duration=2.0)
    b.add_body("ball", "models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[1.0])
    b.add_halfspace("ground")
    traj = ms.run(b.build())

The builder writes the scene's TOML (``b.toml()``, ``b.save(path)``) and parses it with
scene.parse_scene, so every key, default and error message is the one of a scene file
(docs/scenes.md) and every output describes itself (its meta holds that TOML). Keys take the
scene-file names; paths are resolved against `folder` (default: the working directory).
"""

from __future__ import annotations

import enum
from pathlib import Path

import tomli_w

from .scene import Scene, parse_scene


class SceneBuilder:
    """A scene assembled call by call: bodies from URDF/MJCF files, static shapes, collision
    pair rules, and the [simulation] options (as keyword arguments with the scene-file names)."""

    def __init__(self, name: str, *, description: str = "", folder: str | Path | None = None, **options):
        self.name, self.description = name, description
        self.folder = Path(folder) if folder is not None else Path.cwd()
        self.options: dict = {}
        self.output: dict = {}
        self.bodies: list[dict] = []
        self.statics: list[dict] = []
        self.collisions: dict[str, list] = {}
        self._resolved: dict[str, str] = {}  # _path's answers: many bodies name one model file
        self.set(**options)

    def set(self, **options) -> SceneBuilder:
        """[simulation] options by their scene-file names (restitution, dt, duration, gravity,
        bias, ...); save_every goes to [output]. Returns the builder."""
        for key, value in options.items():
            (self.output if key == "save_every" else self.options)[key] = _plain(value)
        return self

    def add_body(self, name: str, urdf: str | Path | None = None, *, mjcf: str | Path | None = None,
                 root_joint: str = "free", **keys) -> SceneBuilder:
        """A body from a URDF (or `mjcf=` an MJCF file) attached by `root_joint` (fixed, free,
        planar, prismatic, revolute, translation); other keys as in [[bodies]]: position, rpy,
        axis, axes, q0, u0, meshes, package_dirs."""
        if (urdf is None) == (mjcf is None):
            raise ValueError("add_body: give a urdf path or mjcf=, exactly one")
        body = {"name": name, "mjcf" if mjcf is not None else "urdf": self._path(mjcf if mjcf is not None else urdf),
                "root_joint": root_joint}
        body.update({k: _plain(v) for k, v in keys.items()})
        self.bodies.append(body)
        return self

    def add_halfspace(self, name: str = "ground", *, normal=(0.0, 0.0, 1.0), offset: float = 0.0) -> SceneBuilder:
        """The static half-space {x : normal . x <= offset} (a ground plane by default)."""
        return self._static(name, "halfspace", normal=normal, offset=offset)

    def add_box(self, name: str, size, **keys) -> SceneBuilder:
        """A static box of full side lengths `size` [m]; keys: position, rpy."""
        return self._static(name, "box", size=size, **keys)

    def add_sphere(self, name: str, radius: float, **keys) -> SceneBuilder:
        """A static sphere [m]; keys: position."""
        return self._static(name, "sphere", radius=radius, **keys)

    def add_cylinder(self, name: str, radius: float, length: float, **keys) -> SceneBuilder:
        """A static cylinder along its local z [m]; keys: position, rpy."""
        return self._static(name, "cylinder", radius=radius, length=length, **keys)

    def include(self, a: str, b: str) -> SceneBuilder:
        """Add the collision pairs between `a` and `b` (body, static, link or geometry names)."""
        self.collisions.setdefault("include", []).append([a, b])
        return self

    def exclude(self, a: str, b: str) -> SceneBuilder:
        """Remove the collision pairs between `a` and `b`."""
        self.collisions.setdefault("exclude", []).append([a, b])
        return self

    def toml(self) -> str:
        """The scene as TOML text (a scene file)."""
        doc: dict = {"scene": {"name": self.name, "description": self.description}}
        if self.options:
            doc["simulation"] = self.options
        if self.output:
            doc["output"] = self.output
        if self.collisions:
            doc["collisions"] = self.collisions
        doc["bodies"] = self.bodies
        if self.statics:
            doc["statics"] = self.statics
        return tomli_w.dumps(doc)

    def build(self) -> Scene:
        """The validated Scene (SceneError names the field, as for a file)."""
        return parse_scene(self.toml(), path=self.folder / f"{self.name}.toml")

    def save(self, path: str | Path) -> Path:
        """Write the scene file (paths in it are absolute), making its folder if needed (as
        ``Trajectory.save`` and ``run -o`` do)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.toml(), encoding="utf-8")
        return path

    def _static(self, name: str, shape: str, **keys) -> SceneBuilder:
        self.statics.append({"name": name, "shape": shape, **{k: _plain(v) for k, v in keys.items()}})
        return self

    def _path(self, p: str | Path) -> str:
        text = str(p)
        if text.startswith("package://"):
            return text
        if text not in self._resolved:
            self._resolved[text] = str((self.folder / p).resolve())
        return self._resolved[text]


def _plain(value):
    """TOML-writable form: tuples and arrays as lists, numpy scalars as floats."""
    if isinstance(value, enum.Enum):
        return value.value
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value
