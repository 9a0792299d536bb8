"""Shared pieces of the peer runners: scene definitions, exact references, CLI, analysis.

Pure Python + numpy only: this module is imported both by the venv runners (MuJoCo,
PyBullet) and by the Siconos runner under Debian's /usr/bin/python3 (numpy 1.24).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import traceback

import numpy as np

G = 9.81

SCENES = ("bouncing_ball", "newton_cradle_5", "box_drop")

# Scene parameters and their defaults (SI units). Peers add their own settings on top.
SCENE_DEFAULTS = {
    "bouncing_ball": {"r": 0.1, "m": 1.0, "z0": 1.0, "g": G, "stride": 1},
    "newton_cradle_5": {"n": 5, "r": 0.1, "m": 1.0, "v0": 1.0, "gap": 0.0, "stride": 1},
    "box_drop": {
        "half_extents": [0.1, 0.1, 0.2],
        "m": 1.0,
        "rpy": [0.3, 0.2, 0.0],
        "z0": 0.6,
        "g": G,
        "stride": 1,
    },
}


class PeerError(RuntimeError):
    """A peer failed (or is unavailable) on a scene; the message names both."""


def merge_params(scene: str, peer_defaults: dict, params: dict) -> dict:
    """Scene defaults < peer defaults < user params; unknown keys are an error (typos)."""
    if scene not in SCENE_DEFAULTS:
        raise ValueError(f"unknown scene {scene!r}; expected one of {SCENES}")
    out = dict(SCENE_DEFAULTS[scene])
    out.update(peer_defaults)
    unknown = sorted(set(params) - set(out))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {unknown} for scene {scene!r}; known: {sorted(out)}"
        )
    out.update(params)
    return out


def n_steps(h: float, T: float) -> int:
    n = int(round(T / h))
    if n < 1:
        raise ValueError(f"T={T} must be at least one step h={h}")
    return n


# ---------------------------------------------------------------- rotations
def rpy_to_quat(rpy) -> np.ndarray:
    """Quaternion (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr = math.cos(r / 2), math.sin(r / 2)
    cp, sp = math.cos(p / 2), math.sin(p / 2)
    cy, sy = math.cos(y / 2), math.sin(y / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


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


def box_corners_local(half_extents) -> np.ndarray:
    hx, hy, hz = half_extents
    return np.array(
        [[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    )


def min_corner_height(pos: np.ndarray, quat: np.ndarray, half_extents) -> np.ndarray:
    """Lowest corner z of the box over time; negative = penetration of the ground z=0."""
    R = quat_to_mats(quat)
    c = box_corners_local(half_extents)  # (8,3)
    z = pos[:, 2][:, None] + np.einsum("nj,kj->nk", R[:, 2, :], c)
    return z.min(axis=1)


# ---------------------------------------------------------------- exact references
def ball_reference(e: float, d0: float = 0.9, g: float = G, nbounce: int = 3) -> dict:
    """impact-law.md §4: first impact t0 = sqrt(2 d0/g); apex gap after bounce n: e^{2n} d0;
    Zeno time t_inf = t0 (1 + 2e/(1-e)) for e < 1."""
    t0 = math.sqrt(2 * d0 / g)
    apex = [e ** (2 * n) * d0 for n in range(1, nbounce + 1)]
    # impact times: t_k = t0 (1 + 2 e + ... + 2 e^k)
    impacts = [t0 * (1 + 2 * sum(e ** j for j in range(1, k + 1))) for k in range(nbounce + 1)]
    apex_t = [impacts[n - 1] + e ** n * t0 for n in range(1, nbounce + 1)]
    t_inf = t0 * (1 + 2 * e / (1 - e)) if e < 1 else math.inf
    return {"t0": t0, "apex_gap": apex, "apex_time": apex_t, "impact_times": impacts,
            "t_inf": t_inf}


def cradle_reference(e: float, n: int = 5, v0: float = 1.0) -> list:
    """Moreau's simultaneous result for N exactly touching equal balls (impact-law.md §4)."""
    return [((1 + e) / n - e) * v0] + [(1 + e) / n * v0] * (n - 1)


def cradle_sequential_reference(e: float, n: int = 5, v0: float = 1.0) -> list:
    """Sequence of binary Newton impacts (gapped balls, each pair collides once, left to
    right) — what a gapped cradle gives when each ball leaves before the next impact.
    A binary impact of equal masses: v1' = (1-e)/2 v1 + (1+e)/2 v2, v2' = (1+e)/2 v1 + (1-e)/2 v2.
    For e < 1 the balls can re-collide; we iterate until no pair approaches."""
    v = [0.0] * n
    v[0] = v0
    for _ in range(10000):
        hit = False
        for i in range(n - 1):
            if v[i] > v[i + 1] + 1e-15:
                a, b = v[i], v[i + 1]
                v[i] = (1 - e) / 2 * a + (1 + e) / 2 * b
                v[i + 1] = (1 + e) / 2 * a + (1 - e) / 2 * b
                hit = True
        if not hit:
            break
    return v


# ---------------------------------------------------------------- analysis
def apexes(t, z, vz=None, r: float = 0.1, g: float = G, count: int = 3, skip_t: float = 0.0):
    """Apex gaps (centre height - r) and times of the first `count` bounces.

    Apexes are the strict local maxima of the sampled z after `skip_t`, refined by the
    parabola through the three samples around the maximum (exact for any constant-
    acceleration integrator in free flight, since its samples are a quadratic in k).
    Returns lists (possibly shorter than `count`: a missing bounce is a result)."""
    t = np.asarray(t, float)
    z = np.asarray(z, float)
    out_gap, out_t = [], []
    k = 1
    n = len(z)
    while k < n - 1 and len(out_gap) < count:
        if t[k] > skip_t and z[k] >= z[k - 1] and z[k] > z[k + 1]:
            z0, z1, z2 = z[k - 1], z[k], z[k + 1]
            den = z0 - 2 * z1 + z2
            if den < 0:
                s = 0.5 * (z0 - z2) / den  # offset in steps from k
                zmax = z1 - 0.25 * (z0 - z2) * s
                tmax = t[k] + s * (t[k + 1] - t[k])
            else:
                zmax, tmax = z1, t[k]
            if zmax - r > 1e-9:  # ignore contact-phase wiggles at/below the surface
                out_gap.append(float(zmax - r))
                out_t.append(float(tmax))
        k += 1
    return out_gap, out_t


def first_crossing(t, y, level=0.0):
    """First time y crosses `level` downward (linear interpolation), or None."""
    t = np.asarray(t, float)
    y = np.asarray(y, float) - level
    idx = np.nonzero((y[:-1] > 0) & (y[1:] <= 0))[0]
    if len(idx) == 0:
        return None
    k = idx[0]
    return float(t[k] + (t[k + 1] - t[k]) * y[k] / (y[k] - y[k + 1]))


# ---------------------------------------------------------------- JSON + CLI
def to_jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else (1e308 if obj > 0 else -1e308)
    return obj


def from_jsonable(res: dict) -> dict:
    """Series lists -> numpy arrays (same shape as an in-process result)."""
    out = dict(res)
    for k, v in res.items():
        if k in ("peer", "scene", "settings", "version", "cpu_seconds", "notes"):
            continue
        if isinstance(v, list):
            try:
                out[k] = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                pass
    return out


def _parse_value(s: str):
    try:
        return json.loads(s)
    except json.JSONDecodeError:
        return s


def cli(peer: str, run_fn, argv=None) -> int:
    """`python X_runner.py SCENE --e E --h H --T T [--param k=v ...] [--params JSON]`.
    Prints the result as JSON on stdout. On failure: message on stderr, exit code 1."""
    ap = argparse.ArgumentParser(description=f"Run a moreau-sim impact scene in {peer}.")
    ap.add_argument("scene", choices=SCENES)
    ap.add_argument("--e", type=float, required=True, help="restitution coefficient")
    ap.add_argument("--h", type=float, required=True, help="time step [s]")
    ap.add_argument("--T", type=float, required=True, help="duration [s]")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                    help="extra scene/peer parameter (value parsed as JSON if possible)")
    ap.add_argument("--params", default=None, help="extra parameters as one JSON object")
    ap.add_argument("--indent", type=int, default=None)
    a = ap.parse_args(argv)
    params = {}
    if a.params:
        params.update(json.loads(a.params))
    for kv in a.param:
        if "=" not in kv:
            ap.error(f"--param expects KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        params[k] = _parse_value(v)
    # Keep fd 1 for the JSON only: C libraries print banners/diagnostics on stdout (pybullet
    # prints its build time from a stdio buffer flushed at exit), so fd 1 goes to stderr while
    # the peer runs and the JSON is written to a saved duplicate of the real stdout.
    sys.stdout.flush()
    json_fd = os.dup(1)
    os.dup2(2, 1)
    try:
        res = run_fn(a.scene, e=a.e, h=a.h, T=a.T, **params)
    except Exception as exc:  # noqa: BLE001 - reported to the caller
        traceback.print_exc(file=sys.stderr)
        print(f"PEER-ERROR {peer}/{a.scene}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    with os.fdopen(json_fd, "w") as out:
        out.write(json.dumps(to_jsonable(res), indent=a.indent))
        out.write("\n")
    return 0
