"""Browser replay of a trajectory NPZ (docs/viewer.md).

The replay is one self-contained HTML page: the geometry of the scene (boxes, spheres, cylinders,
capsules, ellipsoids; half-spaces drawn as a finite ground plane), the world placement of every
moving geometry at each frame, and the percussion log, embedded as JSON and drawn by a small
WebGL renderer in ``viewer_assets/viewer.html`` (no third-party JavaScript, no network). The same
page is written by :func:`export_html` (opens from file://) and served by :func:`serve`.

The model is rebuilt from the trajectory alone (:func:`model_from_trajectory`): the scene TOML and
the URDF texts stored in its metadata, so the original files need not exist.
"""

from __future__ import annotations

import dataclasses
import http.server
import json
import math
import re
import tempfile
import threading
import tomllib
import webbrowser
from importlib import resources
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from .errors import MoreauSimError
from .model import Model, build_model
from .options import Options
from .scene import parse_scene
from .trajectory import Trajectory, load_trajectory

DEFAULT_FPS = 100.0  # frames kept per simulated second (0: every sample)
_PALETTE = ("#e07b39", "#3b82c4", "#4caf6a", "#b65fc8", "#d6b02a", "#3bb5b0", "#c8455a", "#7a8a99")
_STATIC_COLOR = "#9aa3ad"


def _trajectory(traj: Trajectory | str | Path) -> Trajectory:
    return traj if isinstance(traj, Trajectory) else load_trajectory(traj)


# --- the model, from the trajectory's own metadata ---------------------------------------------

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v) if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _toml_dumps(doc: dict) -> str:
    """TOML text of a parsed scene document (tables, arrays of tables, inline values)."""
    head, body = [], []
    for key, value in doc.items():
        k = json.dumps(key)
        if isinstance(value, dict):
            body += [f"[{k}]"] + [f"{json.dumps(a)} = {_toml_value(b)}" for a, b in value.items()] + [""]
        elif isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
            for table in value:
                body += [f"[[{k}]]"] + [f"{json.dumps(a)} = {_toml_value(b)}" for a, b in table.items()] + [""]
        else:
            head.append(f"{k} = {_toml_value(value)}")
    return "\n".join(head + [""] + body)


def model_from_trajectory(traj: Trajectory | str | Path) -> Model:
    """Rebuild the :class:`Model` of a trajectory from its metadata alone (scene TOML and URDF
    texts written to a temporary folder, each body's ``urdf`` pointed at its copy), with the
    options the run used (``meta['options']``, e.g. a command-line restitution) where valid.

    Raises ValueError when the metadata lacks them, SceneError when they do not build (e.g. a URDF
    whose collision meshes were separate files)."""
    traj = _trajectory(traj)
    sc = traj.meta.get("scene") or {}
    text, urdfs = sc.get("toml"), sc.get("urdf")
    if not isinstance(text, str) or not isinstance(urdfs, dict):
        raise ValueError("trajectory metadata has no scene TOML and URDF texts (meta['scene']['toml'/'urdf'])")
    doc = tomllib.loads(text)
    name = Path(sc.get("path") or "scene.toml").name
    with tempfile.TemporaryDirectory(prefix="moreau-sim-view-") as tmp:
        for i, body in enumerate(doc.get("bodies", [])):
            bname = body.get("name")
            if bname not in urdfs:
                raise ValueError(f"trajectory metadata has no URDF text for body {bname!r}")
            key = "mjcf" if "mjcf" in body else "urdf"  # an MJCF body keeps its key and its .xml
            path = Path(tmp) / f"{i}_{re.sub(r'[^A-Za-z0-9_.-]', '_', str(bname))}.{'xml' if key == 'mjcf' else 'urdf'}"
            path.write_text(urdfs[bname], encoding="utf-8")
            body[key] = str(path)
        scene_path = Path(tmp) / name
        scene_text = _toml_dumps(doc)
        scene_path.write_text(scene_text, encoding="utf-8")
        scene = parse_scene(scene_text, path=scene_path)
        known = {f.name for f in dataclasses.fields(Options)}
        try:
            scene = scene.with_options(**{k: v for k, v in (traj.meta.get("options") or {}).items() if k in known})
        except (MoreauSimError, TypeError, ValueError):
            pass  # options of another version: keep the scene file's
        return build_model(scene)


# --- frames ------------------------------------------------------------------------------------

def frame_indices(t: np.ndarray, fps: float = DEFAULT_FPS) -> np.ndarray:
    """Sample indices at least 1/fps apart in t (always the first and the last); all if fps <= 0."""
    n = len(t)
    if fps <= 0 or n <= 2:
        return np.arange(n)
    keep, last = [0], t[0]
    for i in range(1, n - 1):
        if t[i] - last >= 1.0 / fps - 1e-12:
            keep.append(i)
            last = t[i]
    keep.append(n - 1)
    return np.array(keep)


def frames(traj: Trajectory | str | Path, model: Model | None = None,
           index: np.ndarray | None = None) -> np.ndarray:
    """World placements of every geometry object at each sample (or at samples `index`):
    (n, ngeoms, 7) [x y z qx qy qz qw], in the order of ``model.geom.geometryObjects``."""
    traj = _trajectory(traj)
    model = model or model_from_trajectory(traj)
    q = traj.q if index is None else traj.q[index]
    data, gdata = model.pin.createData(), pin.GeometryData(model.geom)
    out = np.empty((len(q), model.geom.ngeoms, 7))
    for k, qk in enumerate(q):
        pin.updateGeometryPlacements(model.pin, data, model.geom, gdata, qk)
        for g, M in enumerate(gdata.oMg):
            out[k, g] = pin.SE3ToXYZQUAT(M)
    return out


def _sticks(traj: Trajectory, model: Model, index: np.ndarray) -> list[list[float]] | None:
    """Per frame, the segments [ax ay az bx by bz ...] that show the links of articulated bodies
    (collision geometry alone may be just their bobs): each joint's origin to its child joints'
    origins and to its offset geometries' centres. None when there are none (single rigid bodies
    whose geometry sits at their joint)."""
    pm, gm = model.pin, model.geom
    pairs = [(pm.parents[j], j, None) for j in range(1, pm.njoints) if pm.parents[j] > 0]
    pairs += [(go.parentJoint, None, g) for g, go in enumerate(gm.geometryObjects)
              if go.parentJoint > 0 and np.linalg.norm(go.placement.translation) > 1e-9]
    if not pairs:
        return None
    data, gdata = pm.createData(), pin.GeometryData(gm)
    out = []
    for q in traj.q[index]:
        pin.updateGeometryPlacements(pm, data, gm, gdata, q)
        seg = []
        for a, j, g in pairs:
            b = data.oMi[j].translation if g is None else gdata.oMg[g].translation
            seg += [*data.oMi[a].translation, *b]
        out.append(np.round(seg, 6).tolist())
    return out


def _shape(geometry) -> dict:
    """The page's description of a coal shape, in its geometry frame."""
    if isinstance(geometry, coal.Box):
        return {"type": "box", "size": (2 * np.asarray(geometry.halfSide)).tolist()}
    if isinstance(geometry, coal.Sphere):
        return {"type": "sphere", "radius": float(geometry.radius)}
    if isinstance(geometry, coal.Ellipsoid):
        return {"type": "ellipsoid", "radii": np.asarray(geometry.radii, float).tolist()}
    if isinstance(geometry, (coal.Cylinder, coal.Capsule)):
        kind = "cylinder" if isinstance(geometry, coal.Cylinder) else "capsule"
        return {"type": kind, "radius": float(geometry.radius), "half_length": float(geometry.halfLength)}
    if isinstance(geometry, (coal.Halfspace, coal.Plane)):
        return {"type": "halfspace" if isinstance(geometry, coal.Halfspace) else "plane",
                "normal": np.asarray(geometry.n, float).tolist(), "offset": float(geometry.d)}
    geometry.computeLocalAABB()  # anything else (meshes): its bounding box, flagged
    lo, hi = np.asarray(geometry.aabb_local.min_), np.asarray(geometry.aabb_local.max_)
    return {"type": "box", "size": (hi - lo).tolist(), "center": ((hi + lo) / 2).tolist(), "approximate": True}


def _contacts(traj: Trajectory, ft: np.ndarray) -> list[list[list[float]]]:
    """Per frame i: the percussions logged in (ft[i-1], ft[i]], summed per contact (pair, kind, feature):
    [px, py, pz, nx, ny, nz, P, impact] with the point and normal of the latest step."""
    a = traj.arrays
    lt = a["log_t"]
    order = np.argsort(lt, kind="stable")
    bins = np.searchsorted(ft, lt[order], side="left")  # frame i gets ft[i-1] < t <= ft[i]
    out: list[dict] = [{} for _ in ft]
    for j, b in zip(order, bins):
        if b >= len(ft):
            continue
        key = (int(a["log_pair"][j]), int(a["log_kind"][j]), int(a["log_feature"][j]))
        prev = out[b].get(key)
        P = float(a["log_P"][j]) + (prev[6] if prev else 0.0)
        imp = bool(a["log_impact"][j]) or bool(prev and prev[7])
        out[b][key] = [*np.round(a["log_point"][j], 6).tolist(), *np.round(a["log_normal"][j], 6).tolist(),
                       float(f"{P:.6g}"), int(imp)]
    return [list(d.values()) for d in out]


def scene_data(traj: Trajectory | str | Path, model: Model | None = None, fps: float = DEFAULT_FPS) -> dict:
    """Everything the page draws, JSON-able: geometries, frame times, placements, contacts."""
    traj = _trajectory(traj)
    model = model or model_from_trajectory(traj)
    idx = frame_indices(traj.t, fps)
    X = frames(traj, model, idx)
    bodies = [b.name for b in model.bodies]
    geoms, moving = [], []
    for g, go in enumerate(model.geom.geometryObjects):
        static = go.parentJoint == 0
        owner = model.geometry_body[g]
        color = _STATIC_COLOR if static else _PALETTE[bodies.index(owner) % len(_PALETTE)]
        plane = isinstance(go.geometry, (coal.Halfspace, coal.Plane))
        go.geometry.computeLocalAABB()
        geoms.append({"name": go.name, "body": owner, "static": static, "color": color,
                      "bound": 0.0 if plane else float(np.linalg.norm(go.geometry.aabb_center)
                                                       + go.geometry.aabb_radius),
                      "pose": np.round(X[0, g], 7).tolist(), **_shape(go.geometry)})
        if not static:
            moving.append(g)
    ft = np.asarray(traj.t)[idx]
    meta = traj.meta
    return {
        "scene": (meta.get("scene") or {}).get("name") or model.scene.name,
        "description": (meta.get("scene") or {}).get("description") or "",
        "status": meta.get("status"),
        "restitution": model.options.restitution,
        "dt": model.options.dt,
        "gravity": list(model.options.gravity),
        "geometries": geoms,
        "moving": moving,
        "t": np.round(ft, 9).tolist(),
        "poses": np.round(X[:, moving, :], 6).reshape(len(ft), -1).tolist(),  # (frames, 7 * moving)
        "contacts": _contacts(traj, ft),
        "sticks": _sticks(traj, model, idx),
    }


# --- the page ----------------------------------------------------------------------------------

def _template() -> str:
    return resources.files(__package__).joinpath("viewer_assets/viewer.html").read_text(encoding="utf-8")


def page(traj: Trajectory | str | Path, model: Model | None = None, fps: float = DEFAULT_FPS) -> str:
    """The self-contained replay page (HTML with its data and renderer inlined)."""
    data = json.dumps(scene_data(traj, model, fps), separators=(",", ":"), allow_nan=False)
    data = data.replace("</", "<\\/")  # never close the <script> element early
    return _template().replace("/*__DATA__*/null", data, 1)


def export_html(traj: Trajectory | str | Path, path: str | Path, *, fps: float = DEFAULT_FPS) -> Path:
    """Write the replay page to `path`: one file that opens from file:// without a server."""
    path = Path(path)
    html = page(traj, fps=fps)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html, encoding="utf-8")
    return path


class _Handler(http.server.BaseHTTPRequestHandler):
    body: bytes = b""

    def do_GET(self):  # noqa: N802 (http.server's name)
        if self.path.split("?")[0].split("#")[0] not in ("/", "/index.html"):
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, *args):  # quiet
        pass


def make_server(traj: Trajectory | str | Path, port: int = 0, host: str = "127.0.0.1", *,
                fps: float = DEFAULT_FPS) -> http.server.ThreadingHTTPServer:
    """An HTTP server (not yet serving) whose page is the replay; port 0 picks a free port
    (``server.server_address[1]``). Call ``serve_forever()`` and ``shutdown()``."""
    handler = type("ReplayHandler", (_Handler,), {"body": page(traj, fps=fps).encode("utf-8")})
    return http.server.ThreadingHTTPServer((host, port), handler)


def url_of(server: http.server.HTTPServer) -> str:
    host, port = server.server_address[:2]
    return f"http://{host if host not in ('', '0.0.0.0') else '127.0.0.1'}:{port}/"


def serve(traj: Trajectory | str | Path, port: int = 0, host: str = "127.0.0.1", *, open_browser: bool = True,
          fps: float = DEFAULT_FPS, ready=None) -> None:
    """Serve the replay until interrupted (Ctrl-C). `ready(url)` is called once it listens."""
    server = make_server(traj, port, host, fps=fps)
    url = url_of(server)
    if ready:
        ready(url)
    if open_browser:
        threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
