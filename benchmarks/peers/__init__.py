"""Peer simulators (MuJoCo, PyBullet, Siconos) on moreau-sim's scenes: one runner per peer, each
reading the neutral spec of benchmarks.spec, with one set of documented defaults per peer
(`DEFAULTS` in benchmarks.peers.mujoco / .pybullet / .siconos).

    from benchmarks.peers import available, run, run_model
    available()                                   # {peer: None if usable, else why not and how to install}
    res = run("mujoco", spec)                     # spec = benchmarks.spec.make_spec(model)
    res = run("pybullet", spec, config="tuned")   # peer parameters as keywords (unknown names: an error)
    t, q, u, res = run_model("siconos", model, e=0.5, h=1e-3, T=1.5)   # the same in model coordinates

Where each peer runs:
- MuJoCo, PyBullet: in this process when importable (`pip install -e '.[peers]'`), else in a
  subprocess of $PEERS_PYTHON (a venv of your own with mujoco / pybullet) if set.
- Siconos: always in a subprocess of SICONOS_PYTHON (Debian's `python3-siconos` is importable only
  from Debian's own interpreter: `apt-get install -y python3-siconos`).
A subprocess gets the spec as JSON on stdin and prints the result as JSON (spec.child_main); it
loads only numpy, spec.py and the peer's module (no Pinocchio). Any failure raises PeerError (or
NotExpressible when the peer's runner cannot carry the scene) naming peer and scene.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from ..spec import NotExpressible, PeerError, from_jsonable, make_spec, to_jsonable, to_model_coordinates

PEERS = ("mujoco", "pybullet", "siconos")
# The interpreter that can import Siconos: Debian's python3 (the python3-siconos package installs
# into its dist-packages only), i.e. /usr/bin/python3 where it exists, else the first python3 on
# PATH; $SICONOS_PYTHON overrides both.
SICONOS_PYTHON = os.environ.get("SICONOS_PYTHON") or (
    "/usr/bin/python3" if os.path.exists("/usr/bin/python3") else shutil.which("python3") or "python3")
_IMPORT = {"mujoco": "mujoco", "pybullet": "pybullet", "siconos": "siconos.kernel"}
_INSTALL = {"mujoco": "pip install mujoco", "pybullet": "pip install pybullet",
            "siconos": f"apt-get install -y python3-siconos (Debian; used from {SICONOS_PYTHON})"}
_PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # benchmarks/
# The subprocess: stubs for the packages benchmarks and benchmarks.peers (so that nothing but
# spec.py and the peer's module is loaded: no moreau_sim, no Pinocchio, which Debian's Python
# lacks), then spec.child_main. Run with -P: the current directory is not searched, so a module
# named like a peer (peers/mujoco.py) cannot shadow it.
_CHILD = """import sys, types
root = sys.argv[1]
for name, sub in (("benchmarks", ""), ("benchmarks.peers", "/peers")):
    mod = types.ModuleType(name)
    mod.__path__ = [root + sub]
    sys.modules[name] = mod
from benchmarks.spec import child_main
sys.exit(child_main(sys.argv[2:]))
"""


def _python(peer: str) -> str | None:
    """Interpreter to run `peer` in a subprocess, or None to run it in this process."""
    if peer == "siconos":
        return SICONOS_PYTHON
    if importlib.util.find_spec(_IMPORT[peer]) is not None:
        return None
    return os.environ.get("PEERS_PYTHON") or None


def _probe(python: str, module: str) -> str | None:
    try:
        cp = subprocess.run([python, "-c", f"import {module}"], capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot run {python}: {exc}"
    if cp.returncode != 0:
        last = (cp.stderr.strip().splitlines() or ["?"])[-1]
        return f"`import {module}` fails in {python}: {last}"
    return None


def available() -> dict:
    """{peer: None if it can run here, else a message saying why not and how to install it}."""
    out = {}
    for peer in PEERS:
        py = _python(peer)
        if py is None and importlib.util.find_spec(_IMPORT[peer]) is not None:
            out[peer] = None
        elif py is None:
            out[peer] = f"`{_IMPORT[peer]}` not importable in {sys.executable} and $PEERS_PYTHON unset; {_INSTALL[peer]}"
        else:
            msg = _probe(py, _IMPORT[peer])
            out[peer] = None if msg is None else f"{msg}; {_INSTALL[peer]}"
    return out


def _run_subprocess(python: str, peer: str, spec: dict, params: dict) -> dict:
    cmd = [python, "-P", "-c", _CHILD, str(_PACKAGE_ROOT), peer, json.dumps(to_jsonable(params))]
    try:
        cp = subprocess.run(cmd, input=json.dumps(to_jsonable(spec)), capture_output=True, text=True)
    except OSError as exc:
        raise PeerError(f"{peer}/{spec['name']}: cannot start {python}: {exc}") from exc
    if cp.returncode != 0:
        lines = cp.stderr.strip().splitlines()
        msg = next((ln for ln in reversed(lines) if ln.startswith(("PEER-ERROR", "NOT-EXPRESSIBLE"))), None)
        cls = NotExpressible if msg and msg.startswith("NOT-EXPRESSIBLE") else PeerError
        tail = "\n".join(lines[-15:])
        raise cls(f"{peer}/{spec['name']} failed (exit {cp.returncode}): {msg or 'no message'}\n"
                  f"--- stderr tail ---\n{tail}")
    try:
        return from_jsonable(json.loads(cp.stdout))
    except json.JSONDecodeError as exc:
        raise PeerError(f"{peer}/{spec['name']}: output is not JSON ({exc}); stdout starts {cp.stdout[:200]!r}") from exc


def run(peer: str, spec: dict, **params) -> dict:
    """Simulate `spec` in `peer` with the peer's parameters `params` (see the module doc)."""
    if peer not in PEERS:
        raise PeerError(f"{peer}/{spec.get('name')}: unknown peer; expected one of {PEERS}")
    py = _python(peer)
    if py is not None:
        return _run_subprocess(py, peer, spec, params)
    if peer != "siconos" and importlib.util.find_spec(_IMPORT[peer]) is None:
        raise PeerError(f"{peer}/{spec['name']}: not available: {available()[peer]}")
    mod = importlib.import_module(f".{peer}", __name__)
    try:
        return mod.run(spec, **params)
    except NotExpressible:
        raise
    except Exception as exc:  # noqa: BLE001
        raise PeerError(f"{peer}/{spec['name']} failed: {type(exc).__name__}: {exc}") from exc


def run_model(peer: str, model, *, e=None, h=None, T=None, stride: int = 1, **params):
    """`run` on the spec of a built moreau-sim model; (t, q, u) in the model's coordinates and the result."""
    res = run(peer, make_spec(model, e=e, h=h, T=T, stride=stride), **params)
    t, q, u = to_model_coordinates(model, res)
    return t, q, u, res
