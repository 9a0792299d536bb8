"""Browser replay of a trajectory NPZ (docs/viewer.md), drawn by viser.

The replay is one self-contained HTML page: viser's prebuilt client (shipped in the ``viser``
wheel as a single HTML file) with a viser scene recording embedded in it
(:meth:`viser.infra.StateSerializer.as_html`): the models' visual meshes (collision geometry
where a link has none), one colour per link, a half-space as a large thin box, the camera
framing the moving bodies, the world placement of every link at each frame, and the percussion
log as arrows. viser's playback bar gives play/pause, the time slider and the speed; a small
energy and gap plot (a 2D canvas added to the page) follows that slider. The same page is
written by :func:`export_html` (opens from file://) and served by :func:`serve`.

The model is rebuilt from the trajectory alone (:func:`model_from_trajectory`): the scene TOML and
the URDF texts stored in its metadata. Mesh files are read only where those texts name them, by a
``package://`` URI or a relative path without ``..`` (see :func:`check_named_files`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import html as _html
import http.server
import io
import json
import math
import re
import tempfile
import threading
import tomllib
import webbrowser
import xml.etree.ElementTree as ET
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from . import robots
from .errors import MoreauSimError, SceneError
from .model import Model, build_model
from .options import Options
from .scene import parse_scene
from .trajectory import Trajectory, load_trajectory

DEFAULT_FPS = 100.0  # frames kept per simulated second (0: every sample)
_PALETTE = ((224, 123, 57), (59, 130, 196), (76, 175, 106), (182, 95, 200), (214, 176, 42), (59, 181, 176),
            (200, 69, 90), (122, 138, 153), (240, 160, 190), (120, 90, 60))
_STATIC_COLOR = (170, 176, 184)
_IMPACT_COLOR = (224, 32, 42)
_PUSH_COLOR = (240, 170, 30)
MESH_SUFFIXES = (".stl", ".obj", ".dae", ".ply", ".off", ".glb", ".gltf")


def _trajectory(traj: Trajectory | str | Path) -> Trajectory:
    return traj if isinstance(traj, Trajectory) else load_trajectory(traj)


# --- which files a stored scene may name --------------------------------------------------------

_FILE_ATTR = re.compile(r"""\b(filename|file|meshdir|texturedir|assetdir)\s*=\s*(["'])(.*?)\2""", re.S)


def check_named_files(text: str, where: str) -> None:
    """Refuse a stored URDF/MJCF text that names a file (``filename``, ``file``, MJCF's
    ``meshdir``/``texturedir``/``assetdir``) other than by a ``package://`` or ``model://`` URI or
    a relative path, or whose path climbs with ``..``: a crafted NPZ must not make the viewer read
    arbitrary local files. Raises SceneError."""
    for m in _FILE_ATTR.finditer(text):
        uri = m.group(3)
        rest = uri.split("://", 1)[1] if "://" in uri else uri
        scheme = uri.split("://", 1)[0] if "://" in uri else ""
        if scheme not in ("", "package", "model") or rest.startswith(("/", "~")) or re.match(r"^[A-Za-z]:", rest) \
                or ".." in re.split(r"[\\/]", rest):
            raise SceneError(f"{where}: the stored model names the file '{uri}': the viewer reads only files named "
                             f"by a package:// URI or a relative path inside the model's folders")

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
            check_named_files(str(urdfs[bname]), f"trajectory metadata, body {bname!r}")
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



# --- what is drawn: one mesh per visual (or collision) geometry of each link ----------------------

@dataclasses.dataclass
class Part:
    """One drawn mesh: `frame` is a Pinocchio frame of ``model.pin`` (0: the world), `placement`
    the mesh in that frame, `vertices`/`faces` the mesh in its own frame, `color` RGB 0-255.
    `link` names the link ("<body>/<link>") or the static; `source` is "visual" or "collision"."""
    name: str
    link: str
    frame: int
    placement: pin.SE3
    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[int, int, int]
    source: str
    static: bool = False


def shape_mesh(geometry):
    """A trimesh of a coal shape in its own frame (boxes, spheres, cylinders, capsules, ellipsoids,
    convex hulls, triangle meshes); None for a half-space or a plane (see :func:`ground_box`)."""
    import trimesh

    if isinstance(geometry, coal.Box):
        return trimesh.creation.box(extents=2 * np.asarray(geometry.halfSide))
    if isinstance(geometry, coal.Sphere):
        return trimesh.creation.icosphere(subdivisions=3, radius=max(float(geometry.radius), 2e-3))
    if isinstance(geometry, coal.Ellipsoid):
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        m.apply_scale(np.asarray(geometry.radii, float))
        return m
    if isinstance(geometry, coal.Cylinder):
        return trimesh.creation.cylinder(radius=geometry.radius, height=2 * geometry.halfLength, sections=32)
    if isinstance(geometry, coal.Capsule):
        return trimesh.creation.capsule(radius=geometry.radius, height=2 * geometry.halfLength, count=[24, 24])
    if isinstance(geometry, (coal.Halfspace, coal.Plane)):
        return None
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array([geometry.points(i) for i in range(geometry.num_points)], float)
        return trimesh.convex.convex_hull(pts)
    if isinstance(geometry, coal.BVHModelBase):
        v = np.array([geometry.vertices(i) for i in range(geometry.num_vertices)], float)
        f = np.array([[t[0], t[1], t[2]] for t in (geometry.tri_indices(i) for i in range(geometry.num_tris))], int)
        return trimesh.Trimesh(v, f, process=False)
    geometry.computeLocalAABB()  # anything else: its bounding box
    lo, hi = np.asarray(geometry.aabb_local.min_), np.asarray(geometry.aabb_local.max_)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((hi + lo) / 2))


def ground_box(normal, offset: float, center, size: float) -> tuple[pin.SE3, np.ndarray]:
    """(placement, half sides) of a thin box standing for the half-space {n.x <= offset}: its top
    face on the boundary plane, `size` wide, centred under `center`, 1 % of `size` thick."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    thick = 0.01 * size
    c = np.asarray(center, float)
    c = c - (n @ c - offset) * n - 0.5 * thick * n  # project on the plane, then half a thickness inside
    R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), n).matrix()
    return pin.SE3(R, c), np.array([size / 2, size / 2, thick / 2])


def _float_list(text, n, default):
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        return list(default)
    return v if len(v) == n else list(default)


def _origin(el) -> pin.SE3:
    o = el.find("origin") if el is not None else None
    xyz = _float_list(o.get("xyz") if o is not None else None, 3, (0, 0, 0))
    rpy = _float_list(o.get("rpy") if o is not None else None, 3, (0, 0, 0))
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.array(xyz))


def _resolve_mesh(uri: str, dirs: list[Path], base: Path) -> Path | None:
    """The mesh file a stored URDF names (check_named_files has vetted the text), or None."""
    if Path(uri.split("?")[0]).suffix.lower() not in MESH_SUFFIXES:
        return None
    try:
        p = robots.resolve(uri, dirs, base)
    except SceneError:
        return None
    return p if p is not None and p.suffix.lower() in MESH_SUFFIXES else None


def _load_mesh(path: Path, scale):
    """A mesh file as a trimesh: read by coal (assimp: .dae, .obj, .stl, ...), else by trimesh."""
    import trimesh

    try:
        b = coal.MeshLoader().load(str(path), np.asarray(scale, float))
        v = np.asarray(b.vertices(), float)
        f = np.array([[t[0], t[1], t[2]] for t in (b.tri_indices(i) for i in range(b.num_tris))], np.int64)
        if len(v) and len(f):
            return trimesh.Trimesh(v, f, process=False)
    except Exception:  # noqa: BLE001 (assimp's errors: try trimesh, then the collision geometry)
        pass
    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception:  # noqa: BLE001
        return None
    if not isinstance(m, trimesh.Trimesh) or not len(m.faces):
        return None
    m.apply_scale(np.asarray(scale, float))
    return m


def rods(traj: Trajectory | str | Path, model: Model, index: np.ndarray | None = None) -> np.ndarray | None:
    """(frames, segments, 2, 3): the segments that show the links of articulated bodies whose
    collision geometry may be just their bobs (the double pendulum): each joint's origin to its
    child joints' origins and to its offset geometries' centres. None when there are none."""
    traj = _trajectory(traj)
    pm, gm = model.pin, model.geom
    pairs = [(pm.parents[j], j, None) for j in range(1, pm.njoints) if pm.parents[j] > 0]
    pairs += [(go.parentJoint, None, g) for g, go in enumerate(gm.geometryObjects)
              if go.parentJoint > 0 and np.linalg.norm(go.placement.translation) > 1e-9]
    if not pairs:
        return None
    data, gdata = pm.createData(), pin.GeometryData(gm)
    q = traj.q if index is None else traj.q[index]
    out = np.empty((len(q), len(pairs), 2, 3))
    for k, qk in enumerate(q):
        pin.updateGeometryPlacements(pm, data, gm, gdata, qk)
        for i, (a, j, g) in enumerate(pairs):
            out[k, i, 0] = data.oMi[a].translation
            out[k, i, 1] = data.oMi[j].translation if g is None else gdata.oMg[g].translation
    return out


def _urdf_visuals(text: str, dirs: list[Path], base: Path) -> dict:
    """link name -> [(placement in the link frame, mesh, rgb or None)] of a URDF's <visual>s that load."""
    import trimesh

    try:
        root = ET.fromstring(text)
    except ET.ParseError:
        return {}
    named = {m.get("name"): m.find("color") for m in root.findall("material")}
    out: dict[str, list] = {}
    for link in root.findall("link"):
        for vis in link.findall("visual"):
            geo = vis.find("geometry")
            kid = geo[0] if geo is not None and len(geo) else None
            if kid is None:
                continue
            mesh = None
            if kid.tag == "mesh":
                path = _resolve_mesh(kid.get("filename", ""), dirs, base)
                mesh = _load_mesh(path, _float_list(kid.get("scale"), 3, (1, 1, 1))) if path else None
            elif kid.tag == "box":
                mesh = trimesh.creation.box(extents=_float_list(kid.get("size"), 3, (0, 0, 0)))
            elif kid.tag == "sphere":
                mesh = trimesh.creation.icosphere(subdivisions=3, radius=float(kid.get("radius", 0)))
            elif kid.tag == "cylinder":
                mesh = trimesh.creation.cylinder(radius=float(kid.get("radius", 0)),
                                                 height=float(kid.get("length", 0)), sections=32)
            if mesh is None:
                continue
            rgb = None
            mat = vis.find("material")
            if mat is not None:
                col = mat.find("color") if mat.find("color") is not None else named.get(mat.get("name"))
                if col is not None:
                    rgba = _float_list(col.get("rgba"), 4, (0.7, 0.7, 0.7, 1))
                    rgb = tuple(int(round(255 * min(max(c, 0.0), 1.0))) for c in rgba[:3])
            out.setdefault(link.get("name"), []).append((_origin(vis), mesh, rgb))
    return out


def _mjcf_visuals(model: Model, body, text: str, original: Path | None) -> list:
    """[(link, frame of model.pin, placement in that frame, mesh, rgb)] of an MJCF body's visual
    geometry: Pinocchio's reader with GeometryType.VISUAL (every geom but MuJoCo's collision-only
    group > 2; contype = conaffinity = 0 geoms are visual only), placed as bodies.load_body places
    the collision geometry, with each geom's rgba or its material's. The stored text is read from
    the `original` file when that file still holds it (its meshes are then found), else from a
    temporary copy; [] when Pinocchio cannot load it (the collision geometry is drawn instead)."""
    from .bodies import root_joint

    where = f"trajectory metadata, body {body.name!r}"
    with tempfile.TemporaryDirectory(prefix="moreau-sim-view-") as tmp:
        path = Path(tmp) / "model.xml"
        path.write_text(text, encoding="utf-8")
        try:
            if original is not None and original.is_file() and original.read_text(encoding="utf-8") == text:
                path = original
            m, g = robots.load_mjcf(path, root_joint(body, where), where, pin.GeometryType.VISUAL)
        except (OSError, SceneError):
            return []
    pm = model.pin
    fixed = pin.SE3(pin.rpy.rpyToMatrix(*body.rpy), np.array(body.position, float))  # a fixed root's placement
    out = []
    for go in g.geometryObjects:
        mesh = shape_mesh(go.geometry)
        if mesh is None:
            continue
        rgb = tuple(int(round(255 * min(max(float(c), 0.0), 1.0))) for c in go.meshColor[:3])
        frame = m.frames[go.parentFrame]
        name = f"{body.name}/{frame.name}"
        if go.parentFrame > 0 and pm.existFrame(name):
            out.append((name, pm.getFrameId(name), frame.placement.inverse() * go.placement, mesh, rgb))
        elif go.parentJoint == 0:  # a geom of the MJCF's world body under a fixed root
            out.append((name, 0, fixed * go.placement, mesh, rgb))
    return out


def parts(traj: Trajectory | str | Path, model: Model | None = None, *, colors: str = "link") -> list[Part]:
    """The meshes the replay draws: each link's visual geometry - a URDF's <visual>s (meshes loaded
    with trimesh, boxes, spheres, cylinders), an MJCF's visual geoms (:func:`_mjcf_visuals`) -, its
    collision geometry where it has no visual that loads, and the statics (a half-space is left to
    the caller: :func:`ground_box`). `colors`: "link" gives each link its own colour of a palette,
    "model" keeps the model's colours (URDF materials; MJCF rgba and materials; the palette where a
    URDF visual has none)."""
    traj = _trajectory(traj)
    model = model or model_from_trajectory(traj)
    sc = traj.meta.get("scene") or {}
    texts = sc.get("urdf") or {}
    scene_path = Path(sc.get("path") or ".")
    doc = tomllib.loads(sc["toml"]) if isinstance(sc.get("toml"), str) else {}
    pm, gm = model.pin, model.geom
    links: list[str] = []

    def color_of(link, rgb):
        if link not in links:
            links.append(link)
        return rgb if colors == "model" and rgb is not None else _PALETTE[links.index(link) % len(_PALETTE)]

    visuals: dict[str, list] = {}
    frames: dict[str, int] = {}
    tables = {t.get("name"): t for t in doc.get("bodies", [])}
    for body in model.scene.bodies:
        if body.mjcf and body.name in texts:
            table = tables.get(body.name, {})
            try:
                original = robots.resolve_model_file(str(table.get("mjcf", "")), scene_path.parent,
                                                     [scene_path.parent / d for d in table.get("package_dirs", [])], "")
            except SceneError:
                original = None
            for link, f, M, mesh, rgb in _mjcf_visuals(model, body, texts[body.name], original):
                visuals.setdefault(link, []).append((M, mesh, rgb))
                frames[link] = f
    for table in doc.get("bodies", []):
        name = table.get("name")
        if "mjcf" in table or name not in texts:
            continue
        dirs0 = [scene_path.parent / d for d in table.get("package_dirs", [])]
        urdf_value = str(table.get("urdf", ""))
        base = scene_path.parent / Path(urdf_value).parent if not robots.is_uri(urdf_value) else scene_path.parent
        dirs = robots.search_dirs(dirs0, base)
        for link, items in _urdf_visuals(texts[name], dirs, base).items():
            visuals[f"{name}/{link}"] = items
    out: list[Part] = []
    done: set[str] = set()
    for link, items in visuals.items():
        if link in frames:
            f = frames[link]
        elif pm.existFrame(link, pin.FrameType.BODY):
            f = pm.getFrameId(link, pin.FrameType.BODY)
        else:
            continue
        for k, (M, mesh, rgb) in enumerate(items):
            out.append(Part(f"{link}/visual_{k}", link, f, M, np.asarray(mesh.vertices, np.float32),
                            np.asarray(mesh.faces, np.uint32), color_of(link, rgb), "visual"))
        done.add(link)
    for g, go in enumerate(gm.geometryObjects):
        static = go.parentJoint == 0
        link = model.geometry_body[g] if static else pm.frames[go.parentFrame].name
        if link in done:
            continue
        mesh = shape_mesh(go.geometry)
        if mesh is None:
            continue
        frame = 0 if static else go.parentFrame
        M = go.placement if static else pm.frames[go.parentFrame].placement.inverse() * go.placement
        out.append(Part(f"{link}/collision_{g}", link, frame, M, np.asarray(mesh.vertices, np.float32),
                        np.asarray(mesh.faces, np.uint32), _STATIC_COLOR if static else color_of(link, None),
                        "collision", static))
    return out


def _frame_placements(model: Model, q: np.ndarray, frame_ids: list[int]) -> np.ndarray:
    """(n, len(frame_ids), 4, 4) world placements of Pinocchio frames at each q."""
    data = model.pin.createData()
    out = np.empty((len(q), len(frame_ids), 4, 4))
    for k, qk in enumerate(q):
        pin.framesForwardKinematics(model.pin, data, qk)
        for j, f in enumerate(frame_ids):
            out[k, j] = data.oMf[f].homogeneous
    return out


# --- the camera -----------------------------------------------------------------------------------

def _segment_hits_box(a, b, lo, hi) -> bool:
    d = b - a
    t0, t1 = 0.0, 1.0
    for i in range(3):
        if abs(d[i]) < 1e-12:
            if a[i] < lo[i] or a[i] > hi[i]:
                return False
            continue
        u, v = (lo[i] - a[i]) / d[i], (hi[i] - a[i]) / d[i]
        t0, t1 = max(t0, min(u, v)), min(t1, max(u, v))
        if t0 > t1:
            return False
    return True


def camera(center, radius: float, up, obstacles=(), halfspaces=(), fov: float = math.radians(50)):
    """(position, look_at) of a camera that frames a sphere (center, radius): from 25 degrees above
    the horizon (`up` from gravity), at the first of 12 azimuths whose line of sight misses every
    static obstacle (world AABBs (lo, hi)) and lies on the free side of every half-space (n, d)."""
    c, up = np.asarray(center, float), np.asarray(up, float) / np.linalg.norm(up)
    e1 = np.cross(up, [0.0, 1.0, 0.0] if abs(up[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    dist = 0.7 * max(radius, 0.05) / math.sin(fov / 2)
    best = None
    for k in range(12):
        az = math.radians(-60 + 30 * k)
        for el in (25.0, 45.0, 70.0):
            ell = math.radians(el)
            d = math.cos(ell) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(ell) * up
            p = c + dist * d
            ok = all(np.dot(n, p) > off for n, off in halfspaces) and \
                not any(_segment_hits_box(p, c, lo, hi) for lo, hi in obstacles)
            if ok:
                return p, c
            best = best if best is not None else p
    return best, c


# --- the page -----------------------------------------------------------------------------------

def _js_string(value) -> str:
    """JSON for an inline <script>: no "<", ">", "&" or line separators left raw, so no scene text
    can close the element or open a comment."""
    s = json.dumps(value, separators=(",", ":"), allow_nan=False, ensure_ascii=True)
    return s.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


_OVERLAY = r"""
<style>
#ms-panel{position:fixed;right:10px;top:10px;z-index:3;background:rgba(255,255,255,.93);border:1px solid #d5d9de;
border-radius:6px;padding:6px 8px;font:12px system-ui,sans-serif;color:#222;box-shadow:0 1px 6px rgba(0,0,0,.12)}
#ms-title{font-weight:600;max-width:330px;overflow:hidden;text-overflow:ellipsis;white-space:nowrap}
#ms-desc{max-width:330px;color:#555;display:none;white-space:normal;max-height:140px;overflow:auto}
#ms-title:hover+#ms-desc{display:block}
#ms-legend span{margin-right:8px;white-space:nowrap}
</style>
<div id="ms-panel"><div id="ms-title"></div><div id="ms-desc"></div>
<canvas id="ms-plot" width="330" height="150"></canvas><div id="ms-legend"></div></div>
<script>
(function(){
const D = __MS_DATA__;
window.moreauReplay = {ready:false, t:0, frame:0, error:null};
function fmt(x){return Math.abs(x)>=1e3||Math.abs(x)<1e-2&&x!==0?x.toExponential(1):x.toPrecision(3);}
function start(){
  document.title = D.scene + " - moreau-sim replay";
  document.getElementById("ms-title").textContent = D.scene + "  (e = " + D.restitution + ", dt = " + D.dt + " s)";
  document.getElementById("ms-desc").textContent = D.description;
  const cv = document.getElementById("ms-plot"), g = cv.getContext("2d");
  const W = cv.width, H = cv.height, L = 44, R = 8, hE = 78, top = 6, gTop = 96, hG = 44;
  const t = D.t, t0 = t[0], t1 = t[t.length-1] > t0 ? t[t.length-1] : t0 + 1;
  const X = x => L + (W-L-R)*(x-t0)/(t1-t0);
  const ser = [["E = T + V", D.energy, "#222"], ["T", D.kinetic, "#3b82c4"], ["V", D.potential, "#4caf6a"]];
  let lo = Infinity, hi = -Infinity;
  for (const s of ser) for (const v of s[1]) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (!(hi > lo)) { hi = lo + 1; }
  const YE = y => top + hE*(1-(y-lo)/(hi-lo));
  let glo = Math.min(0, ...D.gap), ghi = Math.max(...D.gap);
  if (!(ghi > glo)) ghi = glo + 1e-3;
  const YG = y => gTop + hG*(1-(y-glo)/(ghi-glo));
  function draw(tc){
    g.clearRect(0,0,W,H); g.font = "10px system-ui,sans-serif"; g.lineWidth = 1;
    g.strokeStyle = "#ccc"; g.strokeRect(L, top, W-L-R, hE); g.strokeRect(L, gTop, W-L-R, hG);
    g.fillStyle = "#555"; g.fillText(fmt(hi), 2, top+8); g.fillText(fmt(lo), 2, top+hE); g.fillText("J", 2, top+hE/2+4);
    g.fillText(fmt(ghi), 2, gTop+8); g.fillText(fmt(glo), 2, gTop+hG); g.fillText("gap m", 2, gTop+hG/2+4);
    g.fillText(t0.toFixed(2)+" s", L, H-2); g.fillText(t1.toFixed(2)+" s", W-R-36, H-2);
    if (glo < 0 && ghi > 0) {
      g.strokeStyle = "#e0a0a0"; g.beginPath(); g.moveTo(L, YG(0)); g.lineTo(W-R, YG(0)); g.stroke();
    }
    for (const [name, ys, col] of ser.concat([["min gap", D.gap, "#c8455a"]])) {
      const Y = name === "min gap" ? YG : YE;
      g.strokeStyle = col; g.lineWidth = name === "E = T + V" ? 1.6 : 1; g.beginPath();
      ys.forEach((y, i) => i ? g.lineTo(X(t[i]), Y(y)) : g.moveTo(X(t[i]), Y(y))); g.stroke();
    }
    g.strokeStyle = "#e0202a"; g.lineWidth = 1.5; g.beginPath();
    g.moveTo(X(tc), top); g.lineTo(X(tc), gTop+hG); g.stroke();
  }
  document.getElementById("ms-legend").innerHTML = "";
  for (const [name, , col] of ser.concat([["min gap", null, "#c8455a"]])) {
    const s = document.createElement("span"); s.style.color = col; s.textContent = "\u25a0 " + name;
    document.getElementById("ms-legend").appendChild(s);
  }
  let last = null;
  function tick(){
    const el = document.querySelector('[role="slider"][aria-valuenow]');
    const tc = el ? t0 + parseFloat(el.getAttribute("aria-valuenow")) : t0;
    if (tc !== last) { last = tc; draw(tc);
      let k = 0; while (k + 1 < t.length && t[k+1] <= tc + 1e-9) k++;
      window.moreauReplay.t = tc; window.moreauReplay.frame = k; }
    window.moreauReplay.ready = !!el && !!document.querySelector("canvas:not(#ms-plot)");
    requestAnimationFrame(tick);
  }
  draw(t0); tick();
}
try { if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start); else start(); }
catch (e) { window.moreauReplay.error = String(e); }
})();
</script>
"""


def _record(traj: Trajectory, model: Model, fps: float, colors: str, arrows: float,
            shadows: bool = False) -> tuple[str, dict]:
    """viser's standalone page with the replay recorded in it, and the data of the plot."""
    import trimesh
    import viser

    idx = frame_indices(traj.t, fps)
    ft = np.asarray(traj.t)[idx]
    drawn = parts(traj, model, colors=colors)
    moving = [p for p in drawn if not p.static]
    fids = sorted({p.frame for p in moving})
    W = _frame_placements(model, traj.q[idx], fids)  # (frames, frame ids, 4, 4)
    col = {f: j for j, f in enumerate(fids)}
    # what the camera frames: every moving mesh's vertices' bounding box over the replay
    pts = []
    for p in moving:
        Mv = p.vertices[:: max(1, len(p.vertices) // 64)].astype(float)
        loc = Mv @ p.placement.rotation.T + p.placement.translation
        for k in np.unique(np.linspace(0, len(idx) - 1, 12).astype(int)):
            T = W[k, col[p.frame]]
            pts.append(loc @ T[:3, :3].T + T[:3, 3])
    pts = np.concatenate(pts) if pts else np.zeros((1, 3))
    lo, hi = pts.min(0), pts.max(0)
    center, radius = (lo + hi) / 2, max(0.5 * float(np.linalg.norm(hi - lo)), 0.05)
    g = np.asarray(model.options.gravity, float)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
    halfspaces, obstacles = [], []
    for go in model.geom.geometryObjects:
        if go.parentJoint == 0 and isinstance(go.geometry, (coal.Halfspace, coal.Plane)):
            n = go.placement.rotation @ np.asarray(go.geometry.n, float)
            halfspaces.append((n, float(go.geometry.d) + n @ go.placement.translation))
    for p in drawn:
        if p.static:
            v = p.vertices.astype(float) @ p.placement.rotation.T + p.placement.translation
            obstacles.append((v.min(0), v.max(0)))
    cam, look = camera(center, radius, up, obstacles, halfspaces)

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        sc = server.scene
        sc.set_up_direction(tuple(float(x) for x in up))
        # lights without viser's default image-based environment map: as bright, and several times
        # lighter to draw where WebGL runs in software (headless Chromium, remote desktops)
        sc.configure_environment_map(hdri=None)
        sc.configure_default_lights(cast_shadow=shadows)
        sc.add_light_hemisphere("/lights/hemisphere", sky_color=(255, 255, 255), ground_color=(120, 120, 130),
                                intensity=1.6)
        ic = server.initial_camera
        ic.position, ic.look_at = tuple(map(float, cam)), tuple(map(float, look))
        size = max(4 * radius, 2.0)
        for k, (n, d) in enumerate(halfspaces):
            M, half = ground_box(n, d, center, size)
            b = trimesh.creation.box(extents=2 * half)
            sc.add_mesh_simple(f"/statics/ground_{k}", b.vertices, b.faces, color=_STATIC_COLOR, opacity=0.45,
                               wxyz=pin.Quaternion(M.rotation).coeffs()[[3, 0, 1, 2]], position=M.translation,
                               flat_shading=True)
            cell = 10 ** math.floor(math.log10(size / 20))  # 1, 2 or 5 times a power of ten, about size / 20
            cell *= 5 if size / 20 >= 5 * cell else 2 if size / 20 >= 2 * cell else 1
            sc.add_grid(f"/statics/ground_{k}_grid", size, size, cell_size=cell, section_size=5 * cell,
                        cell_color=(150, 150, 160), section_color=(110, 110, 120),
                        wxyz=pin.Quaternion(M.rotation).coeffs()[[3, 0, 1, 2]],
                        position=M.translation + M.rotation[:, 2] * (half[2] + 1e-4 * size))
        handles = {}
        for f in fids:
            handles[f] = sc.add_frame(f"/links/f{f}", show_axes=False)
        for i, p in enumerate(drawn):
            q = pin.Quaternion(p.placement.rotation).coeffs()[[3, 0, 1, 2]]
            parent = "/statics" if p.static else f"/links/f{p.frame}"
            sc.add_mesh_simple(f"{parent}/m{i}", p.vertices, p.faces, color=p.color, wxyz=q,
                               position=p.placement.translation)

        rod = rods(traj, model, idx) if not any(p.source == "visual" for p in drawn) else None
        rod_handle = None

        def place(k):
            nonlocal rod_handle
            for f in fids:
                T = W[k, col[f]]
                handles[f].position = T[:3, 3]
                handles[f].wxyz = pin.Quaternion(T[:3, :3]).coeffs()[[3, 0, 1, 2]]
            if rod is not None:
                if rod_handle is not None:
                    rod_handle.remove()
                rod_handle = sc.add_line_segments("/rods", rod[k].astype(np.float32), (70, 70, 80),
                                                  thickness=3.0, thickness_units="screen")

        place(0)
        rec = server.get_scene_serializer()
        contacts = _contacts(traj, ft)
        pmax = max([c[6] for fr in contacts for c in fr] + [1e-300])
        size = max([float(np.linalg.norm(np.ptp(p.vertices, axis=0))) for p in moving] + [0.02])  # largest part
        L = arrows * size
        shown: list = []
        for k in range(len(ft)):
            if k:
                rec.insert_sleep(float(ft[k] - ft[k - 1]))
                place(k)
            for h in shown:
                h.remove()
            shown = []
            if contacts[k]:
                c = np.array(contacts[k], float)
                length = np.maximum(L * c[:, 6] / pmax, 0.18 * size)
                # the percussion on the pair's first body, along the normal, drawn as a push: its tip
                # at the contact point, its tail outside that body (through the see-through ground)
                seg = np.stack([c[:, :3] - c[:, 3:6] * length[:, None], c[:, :3]], axis=1)
                cols = np.array([_IMPACT_COLOR if imp else _PUSH_COLOR for imp in c[:, 7]], np.uint8)
                shown.append(sc.add_arrows(f"/contacts/k{k}", seg.astype(np.float32), cols, shaft_radius=0.025 * size,
                                      head_radius=0.06 * size, head_length=0.15 * size))
                if c[:, 7].any():  # the largest new impact of the frame, labelled on top of everything
                    j = int(np.argmax(np.where(c[:, 7] > 0, c[:, 6], -1.0)))
                    shown.append(sc.add_label(f"/contacts/k{k}_label", f"impact P = {c[j, 6]:.3g} N s",
                                              position=c[j, :3], anchor="bottom-left"))
        page = rec.as_html()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
    a = traj.arrays
    T, V = np.asarray(a["kinetic_energy"])[idx], np.asarray(a["potential_energy"])[idx]
    gap = np.asarray(a["gap"])
    gmin = np.nanmin(gap.reshape(len(traj.t), -1)[idx], axis=1) if gap.size else np.zeros(len(idx))
    r = lambda x: [float(f"{v:.6g}") for v in np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)]  # noqa: E731
    meta = traj.meta
    data = {"scene": str((meta.get("scene") or {}).get("name") or model.scene.name),
            "description": str((meta.get("scene") or {}).get("description") or ""),
            "restitution": model.options.restitution, "dt": model.options.dt,
            "t": r(ft), "kinetic": r(T), "potential": r(V), "energy": r(T + V), "gap": r(gmin)}
    return page, data


def page(traj: Trajectory | str | Path, model: Model | None = None, fps: float = DEFAULT_FPS, *,
         colors: str = "link", arrows: float = 0.8, shadows: bool = False) -> str:
    """The self-contained replay page: viser's client, the recorded scene, the energy/gap plot.
    `arrows`: length of the largest percussion's arrow, in units of the largest part's diagonal;
    `shadows`: the default lights cast shadows (off: lighter on software WebGL)."""
    traj = _trajectory(traj)
    model = model or model_from_trajectory(traj)
    html, data = _record(traj, model, fps, colors, arrows, shadows)
    overlay = _OVERLAY.replace("__MS_DATA__", _js_string(data))
    title = f"<title>{_html.escape(data['scene'])} - moreau-sim replay</title>"
    html = re.sub(r"<title>.*?</title>", lambda m: title, html, count=1, flags=re.S)
    i = html.rindex("</body>")
    return html[:i] + overlay + html[i:]


def export_html(traj: Trajectory | str | Path, path: str | Path, *, fps: float = DEFAULT_FPS,
                colors: str = "link") -> Path:
    """Write the replay page to `path`: one file that opens from file:// without a server."""
    path = Path(path)
    text = page(traj, fps=fps, colors=colors)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
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
                fps: float = DEFAULT_FPS, colors: str = "link") -> http.server.ThreadingHTTPServer:
    """An HTTP server (not yet serving) whose page is the replay; port 0 picks a free port
    (``server.server_address[1]``). Call ``serve_forever()`` and ``shutdown()``."""
    handler = type("ReplayHandler", (_Handler,), {"body": page(traj, fps=fps, colors=colors).encode("utf-8")})
    return http.server.ThreadingHTTPServer((host, port), handler)


def url_of(server: http.server.HTTPServer) -> str:
    host, port = server.server_address[:2]
    return f"http://{host if host not in ('', '0.0.0.0') else '127.0.0.1'}:{port}/"


def serve(traj: Trajectory | str | Path, port: int = 0, host: str = "127.0.0.1", *, open_browser: bool = True,
          fps: float = DEFAULT_FPS, colors: str = "link", ready=None) -> None:
    """Serve the replay until interrupted (Ctrl-C). `ready(url)` is called once it listens."""
    server = make_server(traj, port, host, fps=fps, colors=colors)
    url = url_of(server)
    try:
        if ready:
            ready(url)
        if open_browser:
            threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()


# --- Pinocchio's own visualizers ------------------------------------------------------------------

def drawable_geometry(model: Model, ground_size: float = 10.0, *, colors: bool = True) -> pin.GeometryModel:
    """A copy of ``model.geom`` that Pinocchio's visualizers (ViserVisualizer, MeshcatVisualizer)
    can draw: each half-space or plane becomes a thin box (`ground_size` wide, 1 % of it thick,
    its top face on the boundary plane, centred on the point of the plane nearest the origin), and
    each shape they do not draw (capsules, ellipsoids, ...) its convex hull as a coal.Convex.
    `colors`: give each link a colour of the replay's palette (statics grey).

    >>> viz = pin.visualize.ViserVisualizer(model.pin, geom, geom); viz.initViewer(); viz.loadViewerModel()
    """
    out = pin.GeometryModel()
    links: list[str] = []
    for g, src in enumerate(model.geom.geometryObjects):
        go = src.copy()
        geo = go.geometry
        if isinstance(geo, (coal.Halfspace, coal.Plane)):
            n = np.asarray(geo.n, float)
            M, half = ground_box(n, float(geo.d), n * float(geo.d), ground_size)
            go.geometry, go.placement = coal.Box(*(2 * half)), go.placement * M
            go.meshPath = ""
        elif not isinstance(geo, (coal.Box, coal.Sphere, coal.Cylinder, coal.ConvexBase, coal.BVHModelBase)):
            mesh = shape_mesh(geo)
            go.geometry = coal.Convex.convexHull(np.asarray(mesh.vertices, float), True, "")
            go.meshPath = ""
        if colors:
            static = go.parentJoint == 0
            link = model.geometry_body[g] if static else model.pin.frames[go.parentFrame].name
            if link not in links:
                links.append(link)
            rgb = _STATIC_COLOR if static else _PALETTE[links.index(link) % len(_PALETTE)]
            go.meshColor = np.array([*(c / 255 for c in rgb), 1.0])
            go.overrideMaterial = True
        out.addGeometryObject(go)
    return out
