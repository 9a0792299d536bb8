"""Shared test helpers: paths of the bundled scenes and models, and short ways to load and run them.

Tests import from here (`from helpers import run, scene`); conftest.py keeps only fixtures."""

import zipfile
from pathlib import Path

import numpy as np
import pinocchio as pin

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
MODELS = ROOT / "models"
BUNDLED = sorted(p.stem for p in SCENES.glob("*.toml"))
# The bundled scenes the event integrators (event-driven, adaptive) refuse, and what they say (everything else runs)
REFUSED: dict = {"solo12_stand": (ms.SceneError, "does not take joint torques"),
                 "a1_drop_recover": (ms.SceneError, "does not take joint torques"),
                 "panda_tapping": (ms.SceneError, "does not take joint torques"),
                 "vibrating_paddle": (ms.SceneError, "does not take a moving static"),
                 "driven_paddle": (ms.SceneError, "does not take a driven joint")}


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


def random_problem(seed, nv=6, m=3):
    """(M, W, u): a random SPD mass matrix, m random rows and a velocity approaching every contact."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((nv, nv))
    M = A @ A.T + nv * np.eye(nv)
    W = rng.standard_normal((nv, m))
    u = rng.standard_normal(nv)
    u -= W @ np.linalg.lstsq(W, u, rcond=None)[0] * 0  # keep u generic
    u -= 2.0 * np.linalg.solve(M, W @ np.ones(m))  # make the contacts approach
    return M, W, u


# A scene of free boxes (format with g, e, T and the bodies' TOML), for contact and row tests.
FREE_BOX = """
[scene]
name = "fd"
[simulation]
gravity = [0, 0, {g}]
restitution = {e}
dt = 1e-3
duration = {T}
{bodies}
"""


def box_body(name, urdf="box.urdf", position=(0, 0, 0), rpy=(0, 0, 0)):
    return (f'[[bodies]]\nname = "{name}"\nurdf = "{{models}}/{urdf}"\nroot_joint = "free"\n'
            f"position = {list(position)}\nrpy = {list(rpy)}\n")


GROUND = '[[statics]]\nname = "ground"\nshape = "halfspace"\n'


def lowest_corner_height(rpy, half=(0.1, 0.1, 0.2)):
    R = pin.rpy.rpyToMatrix(*rpy)
    c = np.array([[sx * half[0], sy * half[1], sz * half[2]] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return -(c @ R.T)[:, 2].min()


def damage_member(path: Path, member: str = "q.npy") -> None:
    """Flip one byte inside the compressed data of one array of an NPZ. (A byte picked at a fixed
    offset of the file can land in a zip local header, whose fields a reader does not use: the
    arrays then read back intact and nothing is damaged.)"""
    raw = bytearray(path.read_bytes())
    info = zipfile.ZipFile(path).getinfo(member)
    start = info.header_offset + 30 + int.from_bytes(raw[info.header_offset + 26:info.header_offset + 28], "little") \
        + int.from_bytes(raw[info.header_offset + 28:info.header_offset + 30], "little")
    raw[start + info.compress_size // 2] ^= 0xFF
    path.write_bytes(bytes(raw))


def slow_cases(values, slow, ids=None) -> list:
    """values for pytest.mark.parametrize, those whose id (ids[k], else the value) is in `slow` marked slow (the
    README's test command leaves them to the slow job: the suite's time, docs in README.md)."""
    import pytest

    ids = list(values) if ids is None else ids
    assert set(slow) <= set(ids), set(slow) - set(ids)
    return [pytest.param(v, marks=pytest.mark.slow, id=str(i)) if i in slow else pytest.param(v, id=str(i))
            for v, i in zip(values, ids)]


def pile_projection(seed, bodies, m):
    """A pile-like projection: `bodies` free bodies (6 velocities each, M block diagonal), m contact rows each on
    two bodies (one on a body alone: against the ground), several rows per pair (a face's corners: dependent rows),
    free velocities pressing the rows."""
    rng = np.random.default_rng(seed)
    nv = 6 * bodies
    M = np.zeros((nv, nv))
    for k in range(bodies):
        A = rng.standard_normal((6, 6))
        M[6 * k:6 * k + 6, 6 * k:6 * k + 6] = A @ A.T + 6.0 * np.eye(6)
    W = np.zeros((nv, m), order="F")
    j = 0
    while j < m:
        a = int(rng.integers(bodies))
        b = min(bodies - 1, a + int(rng.integers(1, 4)))
        w = rng.standard_normal(12)
        for _ in range(min(m - j, int(rng.integers(1, 5)))):  # up to four corners of one face pair
            W[6 * a:6 * a + 6, j] = w[:6] + 0.1 * rng.standard_normal(6)
            if b != a:
                W[6 * b:6 * b + 6, j] = -w[6:]
            j += 1
    Minv = np.zeros_like(M)
    for k in range(bodies):
        Minv[6 * k:6 * k + 6, 6 * k:6 * k + 6] = np.linalg.inv(M[6 * k:6 * k + 6, 6 * k:6 * k + 6])
    v0 = -W @ np.abs(rng.standard_normal(m)) * 0.1
    return M, W, v0, np.zeros(m), Minv
