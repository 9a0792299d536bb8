"""Peer simulators (MuJoCo, PyBullet, Siconos) on moreau-sim's impact scenes.

Uniform entry point:

    from scripts.peers import run, available
    res = run("mujoco", "bouncing_ball", e=0.8, h=1e-3, T=3.0)
    res = run("pybullet", "newton_cradle_5", e=1.0, h=1e-3, T=0.5, gap=1e-3, config="tuned")
    res = run("siconos", "box_drop", e=0.5, h=1e-3, T=1.5)

`run` returns a dict with "peer", "scene", "e", "h", "T", "settings" (every setting used),
"t" and the state series as numpy arrays, "cpu_seconds" (process CPU time of the stepping
loop only, model building excluded) and "version":

- bouncing_ball:   t, z, vz                     (centre height / vertical velocity)
- newton_cradle_5: t, x (N x 5), vx (N x 5), vx_final (5)
- box_drop:        t, pos (N x 3), quat (N x 4, w x y z), vel (N x 3), min_corner_z (N)

Peers: "mujoco", "pybullet" (param config="default" | "tuned"), "siconos" (runs in Debian's
/usr/bin/python3 as a subprocess that prints JSON; override with $SICONOS_PYTHON).
MuJoCo/PyBullet run in-process when importable, else in a subprocess of $PEERS_PYTHON
(e.g. /work/peersenv/bin/python) if set. Any failure raises PeerError naming peer and scene.
`available()` -> {peer: None if usable else the reason}.
"""
from __future__ import annotations

import importlib
import importlib.util
import json
import os
import subprocess
import sys

from . import _common
from ._common import (PeerError, SCENES, apexes, ball_reference, cradle_reference,  # noqa: F401
                      cradle_sequential_reference, first_crossing, to_jsonable)

PEERS = ("mujoco", "pybullet", "siconos")
_HERE = os.path.dirname(os.path.abspath(__file__))
_MODULES = {"mujoco": "mujoco_runner", "pybullet": "pybullet_runner",
            "siconos": "siconos_runner"}
_IMPORT = {"mujoco": "mujoco", "pybullet": "pybullet"}
_INSTALL = {
    "mujoco": "pip install mujoco",
    "pybullet": "pip install pybullet",
    "siconos": "apt-get install -y python3-siconos (Debian; used from /usr/bin/python3)",
}


def _siconos_python() -> str:
    return os.environ.get("SICONOS_PYTHON", "/usr/bin/python3")


def _subprocess_python(peer: str) -> str | None:
    """Interpreter to run `peer` in a subprocess, or None to run it in-process."""
    if peer == "siconos":
        return _siconos_python()
    if importlib.util.find_spec(_IMPORT[peer]) is not None:
        return None
    return os.environ.get("PEERS_PYTHON") or None


def _probe(python: str, module: str) -> str | None:
    try:
        cp = subprocess.run([python, "-c", f"import {module}"], capture_output=True,
                            text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot run {python}: {exc}"
    if cp.returncode != 0:
        last = (cp.stderr.strip().splitlines() or ["?"])[-1]
        return f"`import {module}` fails in {python}: {last}"
    return None


def available() -> dict:
    """{peer: None if it can run here, else a message saying why not and how to install}."""
    out = {}
    for peer in PEERS:
        if peer == "siconos":
            py = _siconos_python()
            if not os.path.exists(py):
                out[peer] = f"{py} not found; {_INSTALL[peer]}"
                continue
            msg = _probe(py, "siconos.kernel")
            out[peer] = None if msg is None else f"{msg}; {_INSTALL[peer]}"
            continue
        if importlib.util.find_spec(_IMPORT[peer]) is not None:
            out[peer] = None
            continue
        py = os.environ.get("PEERS_PYTHON")
        if py:
            msg = _probe(py, _IMPORT[peer])
            out[peer] = None if msg is None else f"{msg}; {_INSTALL[peer]}"
        else:
            out[peer] = (f"`{_IMPORT[peer]}` not importable in {sys.executable} and "
                         f"$PEERS_PYTHON unset; {_INSTALL[peer]}")
    return out


def _run_subprocess(python: str, peer: str, scene: str, e, h, T, params) -> dict:
    script = os.path.join(_HERE, _MODULES[peer] + ".py")
    cmd = [python, script, scene, "--e", repr(float(e)), "--h", repr(float(h)),
           "--T", repr(float(T)), "--params", json.dumps(to_jsonable(params))]
    try:
        cp = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        raise PeerError(f"{peer}/{scene}: cannot start {python}: {exc}") from exc
    if cp.returncode != 0:
        lines = cp.stderr.strip().splitlines()
        msg = next((ln for ln in reversed(lines) if ln.startswith("PEER-ERROR")), None)
        tail = "\n".join(lines[-15:])
        raise PeerError(f"{peer}/{scene} failed (exit {cp.returncode}): "
                        f"{msg or 'no message'}\n--- stderr tail ---\n{tail}")
    try:
        res = json.loads(cp.stdout)
    except json.JSONDecodeError as exc:
        raise PeerError(f"{peer}/{scene}: output is not JSON ({exc}); "
                        f"stdout starts {cp.stdout[:200]!r}") from exc
    return _common.from_jsonable(res)


def run(peer: str, scene: str, *, e: float, h: float, T: float, **params) -> dict:
    """Simulate `scene` in `peer` with restitution e, step h, duration T (see module doc)."""
    if peer not in PEERS:
        raise PeerError(f"{peer}/{scene}: unknown peer; expected one of {PEERS}")
    if scene not in SCENES:
        raise PeerError(f"{peer}/{scene}: unknown scene; expected one of {SCENES}")
    py = _subprocess_python(peer)
    if py is not None:
        return _run_subprocess(py, peer, scene, e, h, T, params)
    if importlib.util.find_spec(_IMPORT[peer]) is None:
        raise PeerError(f"{peer}/{scene}: not available: {available()[peer]}")
    mod = importlib.import_module(f".{_MODULES[peer]}", __name__)
    try:
        return mod.run(scene, e=e, h=h, T=T, **params)
    except Exception as exc:  # noqa: BLE001
        raise PeerError(f"{peer}/{scene} failed: {type(exc).__name__}: {exc}") from exc
