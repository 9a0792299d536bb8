"""The neutral scene spec every peer runner reads, built from a moreau-sim model, and the way back.

A spec is a JSON-able dict: rigid bodies that are spheres or boxes on a free joint or on one
prismatic ("slide") joint, and static half-spaces and boxes. That covers the work-precision scenes
(bouncing_ball, newton_cradle_5, box_drop) and the stress scenes zeno_ball, resting_box, the box
stacks, heavy_on_light, fast_impact, spinning_box, the bead columns and the cradles (not chains such
as the slider-crank, nor planar / revolute roots: those raise NotExpressible).

    spec = {"name", "e", "h", "T", "gravity": [3], "stride": k,
            "bodies": [{"name", "shape": "sphere" | "box", "radius" | "half_extents": [3],
                        "mass", "inertia": [3] (principal, body frame),
                        "joint": "free", "pos": [3], "quat": [w x y z], "v": [3] (world), "w": [3] (body frame)
                        | "joint": "slide", "axis": [3] (unit, world), "origin": [3], "q0", "u0"}],
            "statics": [{"name", "shape": "halfspace", "normal": [3], "offset"}
                        | {"name", "shape": "box", "half_extents": [3], "pos": [3], "quat": [w x y z]}],
            "pairs": [[a, b]]: colliding pairs, a a body index, b a body index or "s<k>" (static k)}

A peer's result: {"peer", "scene", "t", "bodies": [free: {"pos", "quat" (w x y z), "vel", "omega_world"}
| slide: {"q", "u"}], "cpu_seconds" (the stepping loop only), "settings" (every setting used), "version"};
`to_model_coordinates` turns it into moreau-sim's (t, q, u), so every method is measured by the same
functions. Series hold the initial state and every `stride`-th step (len = round(T/h)/stride + 1).

This module's top level is numpy-only: the peer runners import it in Debian's /usr/bin/python3
(Siconos), which has neither Pinocchio nor coal; `make_spec` imports them when called.
"""

from __future__ import annotations

import json
import math
import os
import sys
import traceback
import xml.etree.ElementTree as ET

import numpy as np


class PeerError(RuntimeError):
    """A peer failed (or is unavailable) on a scene; the message names both."""


class NotExpressible(PeerError):
    """The scene uses something the spec (or this peer's runner) cannot carry."""


def n_steps(h: float, T: float) -> int:
    n = int(round(T / h))
    if n < 1:
        raise ValueError(f"T={T} must be at least one step h={h}")
    return n


def merge_params(peer: str, defaults: dict, params: dict) -> dict:
    """The peer's defaults updated with `params`; unknown names are an error (typos)."""
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(f"unknown {peer} parameter(s) {unknown}; known: {sorted(defaults)}")
    return {**defaults, **params}


# ---------------------------------------------------------------- rotations (w x y z quaternions)
def rpy_to_quat(rpy) -> np.ndarray:
    """Quaternion (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr = math.cos(r / 2), math.sin(r / 2)
    cp, sp = math.cos(p / 2), math.sin(p / 2)
    cy, sy = math.cos(y / 2), math.sin(y / 2)
    return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


def quat_to_mats(q: np.ndarray) -> np.ndarray:
    """(N,4) wxyz quaternions -> (N,3,3) rotation matrices (normalised first)."""
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def z_to(n) -> np.ndarray:
    """Quaternion (w x y z) rotating +z onto the unit vector n."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    c = float(n[2])
    if c > 1 - 1e-15:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if c < -1 + 1e-15:
        return np.array([0.0, 1.0, 0.0, 0.0])
    a = np.cross([0.0, 0.0, 1.0], n)
    s = math.sqrt(2 * (1 + c))
    return np.array([s / 2, a[0] / s, a[1] / s, a[2] / s])


def min_corner_height(pos: np.ndarray, quat: np.ndarray, half_extents) -> np.ndarray:
    """Lowest corner z of a box over time (pos (N,3), quat (N,4) w x y z); negative = below z = 0."""
    R = quat_to_mats(quat)
    hx, hy, hz = half_extents
    c = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    z = np.asarray(pos)[:, 2][:, None] + np.einsum("nj,kj->nk", R[:, 2, :], c)
    return z.min(axis=1)


# ---------------------------------------------------------------- moreau-sim model <-> spec
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
    """The spec of a built moreau-sim model (e, h, T default to the scene's options), or NotExpressible."""
    import coal
    import pinocchio as pin

    sc = model.scene
    o = sc.options
    bodies, index = [], {}
    for info, b in zip(model.bodies, sc.bodies):
        geoms = [g for g, _ in enumerate(model.geom.geometryObjects) if model.geometry_body[g] == b.name]
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
        joint = info.root_joint.value
        if joint == "free":
            quat = pin.Quaternion(q[6], q[3], q[4], q[5])
            d.update(joint="free", pos=q[:3].tolist(), quat=[quat.w, quat.x, quat.y, quat.z], v=u[:3].tolist(),
                     w=u[3:6].tolist())
        elif joint == "prismatic":
            ax = np.asarray(b.axis, float) / np.linalg.norm(b.axis)
            R = pin.rpy.rpyToMatrix(*b.rpy)
            d.update(joint="slide", axis=(R @ ax).tolist(), origin=list(b.position), q0=float(q[0]), u0=float(u[0]))
        else:
            raise NotExpressible(f"{b.name}: root joint {joint}")
        index[b.name] = len(bodies)
        bodies.append(d)
    statics = []
    for k, s in enumerate(sc.statics):
        index[s.name] = f"s{k}"
        if s.shape.value == "halfspace":
            statics.append({"name": s.name, "shape": "halfspace", "normal": list(s.normal), "offset": s.offset})
        elif s.shape.value == "box":
            qq = pin.Quaternion(pin.rpy.rpyToMatrix(*s.rpy))
            statics.append({"name": s.name, "shape": "box", "half_extents": [x / 2 for x in s.size],
                            "pos": list(s.position), "quat": [qq.w, qq.x, qq.y, qq.z]})
        else:
            raise NotExpressible(f"static {s.name}: {s.shape.value}")
    pairs = []
    for p in model.pairs:
        ia, ib = index[model.geometry_body[p.first]], index[model.geometry_body[p.second]]
        if isinstance(ia, str):
            ia, ib = ib, ia
        pairs.append([ia, ib])
    return {"name": sc.name, "e": o.restitution if e is None else e, "h": o.dt if h is None else h,
            "T": o.duration if T is None else T, "gravity": list(o.gravity), "stride": int(stride),
            "bodies": bodies, "statics": statics, "pairs": pairs}


def to_model_coordinates(model, res: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, q, u) in moreau-sim's coordinates of `model` from a peer result: free bodies
    q = [x y z qx qy qz qw] (normalised), u = [v world, omega body]; slide bodies their coordinate."""
    t = np.asarray(res["t"], float)
    n = len(t)
    q = np.tile(model.q0, (n, 1))
    u = np.zeros((n, model.nv))
    for info, r in zip(model.bodies, res["bodies"]):
        if info.root_joint.value == "free":
            quat = np.asarray(r["quat"], float)
            quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
            R = quat_to_mats(quat)
            q[:, info.q_slice] = np.concatenate([r["pos"], quat[:, 1:4], quat[:, :1]], axis=1)
            u[:, info.v_slice] = np.concatenate([r["vel"], np.einsum("nji,nj->ni", R, r["omega_world"])], axis=1)
        else:
            q[:, info.q_slice.start] = r["q"]
            u[:, info.v_slice.start] = r["u"]
    return t, q, u


# ---------------------------------------------------------------- JSON, and the peers' subprocess side
def to_jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else (1e308 if obj > 0 else -1e308)
    return obj


def from_jsonable(res: dict) -> dict:
    """A result read from JSON: series as numpy arrays (as an in-process result)."""
    out = dict(res)
    out["t"] = np.asarray(res["t"], float)
    out["bodies"] = [{k: np.asarray(v, float) for k, v in b.items()} for b in res["bodies"]]
    return out


def child_main(argv=None) -> int:
    """The subprocess side of a peer run: `PEER PARAMS_JSON`, the spec as JSON on stdin, the result
    as JSON on stdout; on failure a `PEER-ERROR peer/scene: ...` line on stderr and exit code 1."""
    import importlib

    peer, params = (argv if argv is not None else sys.argv[1:])[:2]
    spec = json.load(sys.stdin)
    # Keep fd 1 for the JSON only: C libraries print banners on stdout (pybullet prints its build
    # time from a stdio buffer flushed at exit), so fd 1 goes to stderr while the peer runs.
    sys.stdout.flush()
    json_fd = os.dup(1)
    os.dup2(2, 1)
    try:
        res = importlib.import_module(f"benchmarks.peers.{peer}").run(spec, **json.loads(params))
    except Exception as exc:  # noqa: BLE001 - reported to the caller
        traceback.print_exc(file=sys.stderr)
        kind = "NOT-EXPRESSIBLE" if isinstance(exc, NotExpressible) else "PEER-ERROR"
        print(f"{kind} {peer}/{spec.get('name')}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    with os.fdopen(json_fd, "w") as out:
        out.write(json.dumps(to_jsonable(res)))
        out.write("\n")
    return 0
