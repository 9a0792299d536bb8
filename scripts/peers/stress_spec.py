"""Host side of the stress-scene peers (issue 5): a moreau-sim scene -> the neutral spec of
stress_runners.py, the peer run as a subprocess, and its result -> moreau-sim coordinates
(q, u per sample) so that energies and pair gaps are measured by moreau-sim's own functions
(kinetic / potential energy from Pinocchio, signed distances from coal) for every method alike.

    from scripts.peers.stress_spec import make_spec, run_spec, to_model_coordinates
    spec = make_spec(model)                       # model = moreau_sim.build_model(scene)
    res = run_spec("mujoco", spec)                # or "pybullet" (config=...), "siconos"
    t, q, u = to_model_coordinates(model, res)

MuJoCo / PyBullet run under $PEERS_PYTHON (default /work/peersenv/bin/python) unless importable
here; Siconos under $SICONOS_PYTHON (default /usr/bin/python3). Needs the moreau-sim venv
(Pinocchio, coal): it reads the built model.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np

from ._common import PeerError, from_jsonable, to_jsonable

_HERE = os.path.dirname(os.path.abspath(__file__))
_IMPORT = {"mujoco": "mujoco", "pybullet": "pybullet"}


class NotExpressible(PeerError):
    """The scene uses something the generic spec (spheres/boxes on free or slide joints,
    half-space/box statics) cannot carry."""


def _python(peer: str) -> str:
    if peer == "siconos":
        return os.environ.get("SICONOS_PYTHON", "/usr/bin/python3")
    if importlib.util.find_spec(_IMPORT[peer]) is not None:
        return sys.executable
    return os.environ.get("PEERS_PYTHON", "/work/peersenv/bin/python")


def _inertia(urdf) -> tuple[float, np.ndarray]:
    root = ET.parse(urdf).getroot()
    links = root.findall("link")
    inert = [ln.find("inertial") for ln in links if ln.find("inertial") is not None]
    if len(links) != 1 or len(inert) != 1:
        raise NotExpressible(f"{urdf}: not a single rigid link")
    i = inert[0]
    o = i.find("origin")
    if o is not None and any(abs(float(x)) > 0 for x in o.get("xyz", "0 0 0").split()):
        raise NotExpressible(f"{urdf}: centre of mass off the link origin")
    I = i.find("inertia")
    if any(abs(float(I.get(k, 0))) > 0 for k in ("ixy", "ixz", "iyz")):
        raise NotExpressible(f"{urdf}: inertia not principal")
    return float(i.find("mass").get("value")), np.array([float(I.get(k)) for k in ("ixx", "iyy", "izz")])


def make_spec(model, *, e=None, h=None, T=None, stride: int = 1) -> dict:
    """The neutral spec of a built moreau-sim model (see stress_runners.py), or NotExpressible."""
    import coal
    import pinocchio as pin

    from moreau_sim.scene import RootJoint, StaticShape

    sc = model.scene
    o = sc.options
    bodies = []
    index = {}
    for info, b in zip(model.bodies, sc.bodies):
        geoms = [g for g, go in enumerate(model.geom.geometryObjects) if model.geometry_body[g] == b.name]
        if len(geoms) != 1:
            raise NotExpressible(f"{b.name}: {len(geoms)} collision geometries (one expected)")
        go = model.geom.geometryObjects[geoms[0]]
        if np.abs(go.placement.translation).max() > 0 or np.abs(go.placement.rotation - np.eye(3)).max() > 0:
            raise NotExpressible(f"{b.name}: collision shape off the link frame")
        shape = go.geometry
        mass, inertia = _inertia(b.urdf)
        d = {"name": b.name, "mass": mass, "inertia": inertia.tolist()}
        if isinstance(shape, coal.Sphere):
            d.update(shape="sphere", radius=float(shape.radius))
        elif isinstance(shape, coal.Box):
            d.update(shape="box", half_extents=[float(x) for x in shape.halfSide])
        else:
            raise NotExpressible(f"{b.name}: shape {type(shape).__name__}")
        q, u = model.q0[info.q_slice], model.u0[info.v_slice]
        if info.root_joint is RootJoint.FREE:
            quat = pin.Quaternion(q[6], q[3], q[4], q[5])
            d.update(joint="free", pos=q[:3].tolist(), quat=[quat.w, quat.x, quat.y, quat.z], v=u[:3].tolist(),
                     w=u[3:6].tolist())
        elif info.root_joint is RootJoint.PRISMATIC:
            ax = np.asarray(b.axis, float) / np.linalg.norm(b.axis)
            R = pin.rpy.rpyToMatrix(*b.rpy)
            d.update(joint="slide", axis=(R @ ax).tolist(), origin=list(b.position), q0=float(q[0]), u0=float(u[0]))
        else:
            raise NotExpressible(f"{b.name}: root joint {info.root_joint.value}")
        index[b.name] = len(bodies)
        bodies.append(d)
    statics = []
    for k, s in enumerate(sc.statics):
        index[s.name] = f"s{k}"
        if s.shape is StaticShape.HALFSPACE:
            statics.append({"name": s.name, "shape": "halfspace", "normal": list(s.normal), "offset": s.offset})
        elif s.shape is StaticShape.BOX:
            R = pin.rpy.rpyToMatrix(*s.rpy)
            qq = pin.Quaternion(R)
            statics.append({"name": s.name, "shape": "box", "half_extents": [x / 2 for x in s.size],
                            "pos": list(s.position), "quat": [qq.w, qq.x, qq.y, qq.z]})
        else:
            raise NotExpressible(f"static {s.name}: {s.shape.value}")
    pairs = []
    for p in model.pairs:
        a, b = model.geometry_body[p.first], model.geometry_body[p.second]
        ia, ib = index[a], index[b]
        if isinstance(ia, str):
            ia, ib = ib, ia
        pairs.append([ia, ib])
    return {"name": sc.name, "e": o.restitution if e is None else e, "h": o.dt if h is None else h,
            "T": o.duration if T is None else T, "gravity": list(o.gravity), "stride": int(stride),
            "bodies": bodies, "statics": statics, "pairs": pairs}


def run_spec(peer: str, spec: dict, **params) -> dict:
    """Run `spec` in `peer` ("mujoco", "pybullet", "siconos") as a subprocess; the result dict
    (series as numpy arrays). Raises PeerError (NotExpressible for Siconos on non-sphere specs)."""
    if peer not in ("mujoco", "pybullet", "siconos"):
        raise PeerError(f"{peer}: unknown peer")
    py = _python(peer)
    cmd = [py, os.path.join(_HERE, "stress_runners.py"), peer, "--params", json.dumps(to_jsonable(params))]
    try:
        cp = subprocess.run(cmd, input=json.dumps(to_jsonable(spec)), capture_output=True, text=True)
    except OSError as exc:
        raise PeerError(f"{peer}/{spec['name']}: cannot start {py}: {exc}") from exc
    if cp.returncode != 0:
        lines = cp.stderr.strip().splitlines()
        msg = next((ln for ln in reversed(lines) if ln.startswith("PEER-ERROR")), "no message")
        cls = NotExpressible if "takes spheres on" in msg or "half-space statics only" in msg else PeerError
        raise cls(f"{peer}/{spec['name']} failed (exit {cp.returncode}): {msg}")
    res = json.loads(cp.stdout)
    res["t"] = np.asarray(res["t"], float)
    res["bodies"] = [{k: np.asarray(v, float) for k, v in b.items()} for b in res["bodies"]]
    return from_jsonable(res) | {"bodies": res["bodies"], "t": res["t"]}


def to_model_coordinates(model, res: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, q, u) in moreau-sim's coordinates of `model` from a peer result: free bodies
    q = [x y z qx qy qz qw], u = [v world, omega body]; slide bodies their coordinate."""
    from moreau_sim.scene import RootJoint

    t = np.asarray(res["t"], float)
    n = len(t)
    q = np.tile(model.q0, (n, 1))
    u = np.zeros((n, model.nv))
    for info, r in zip(model.bodies, res["bodies"]):
        if info.root_joint is RootJoint.FREE:
            quat = np.asarray(r["quat"], float)
            quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
            from ._common import quat_to_mats

            R = quat_to_mats(quat)
            q[:, info.q_slice] = np.concatenate([r["pos"], quat[:, 1:4], quat[:, :1]], axis=1)
            u[:, info.v_slice] = np.concatenate([r["vel"], np.einsum("nji,nj->ni", R, r["omega_world"])], axis=1)
        else:
            q[:, info.q_slice.start] = r["q"]
            u[:, info.v_slice.start] = r["u"]
    return t, q, u
