"""What the replay draws: one mesh per visual geometry of each link (its collision geometry
where it has none), the statics, and their world placements at each sample (docs/viewer.md)."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from .. import robots
from ..errors import SceneError
from ..model import Model
from ..trajectory import Trajectory
from .meshes import ground_box, mjcf_visuals, shape_mesh, urdf_visuals
from .stored import as_trajectory, model_from_trajectory

PALETTE = ((224, 123, 57), (59, 130, 196), (76, 175, 106), (182, 95, 200), (214, 176, 42), (59, 181, 176),
           (200, 69, 90), (122, 138, 153), (240, 160, 190), (120, 90, 60))
STATIC_COLOR = (170, 176, 184)


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


def frames(traj: Trajectory | str | Path, model: Model | None = None,
           index: np.ndarray | None = None) -> np.ndarray:
    """World placements of every geometry object at each sample (or at samples `index`):
    (n, ngeoms, 7) [x y z qx qy qz qw], in the order of ``model.geom.geometryObjects``."""
    traj = as_trajectory(traj)
    model = model or model_from_trajectory(traj)
    q = traj.q if index is None else traj.q[index]
    data, gdata = model.pin.createData(), pin.GeometryData(model.geom)
    out = np.empty((len(q), model.geom.ngeoms, 7))
    for k, qk in enumerate(q):
        pin.updateGeometryPlacements(model.pin, data, model.geom, gdata, qk)
        for g, M in enumerate(gdata.oMg):
            out[k, g] = pin.SE3ToXYZQUAT(M)
    return out


def rods(traj: Trajectory | str | Path, model: Model, index: np.ndarray | None = None) -> np.ndarray | None:
    """(frames, segments, 2, 3): the segments that show the links of articulated bodies whose
    collision geometry leaves them unseen (the double pendulum, just its bobs): each joint's
    origin to its child joints' origins and to its offset geometries' centres, kept where most of
    the segment lies outside the bodies' geometry (a robot drawn by its collision shapes, whose
    joints those shapes cover, gets none). None when there are none."""
    traj = as_trajectory(traj)
    pm, gm = model.pin, model.geom
    pairs = [(pm.parents[j], j, None) for j in range(1, pm.njoints) if pm.parents[j] > 0]
    pairs += [(go.parentJoint, None, g) for g, go in enumerate(gm.geometryObjects)
              if go.parentJoint > 0 and np.linalg.norm(go.placement.translation) > 1e-9]
    if not pairs:
        return None
    data, gdata = pm.createData(), pin.GeometryData(gm)
    q = traj.q if index is None else traj.q[index]

    def segments(qk):
        pin.updateGeometryPlacements(pm, data, gm, gdata, qk)
        return [(data.oMi[a].translation.copy(), (data.oMi[j] if g is None else gdata.oMg[g]).translation.copy())
                for a, j, g in pairs]

    shown = _outside(model, gdata, segments(traj.q[0]))
    pairs = [p for p, keep in zip(pairs, shown) if keep]
    if not pairs:
        return None
    out = np.empty((len(q), len(pairs), 2, 3))
    for k, qk in enumerate(q):
        out[k] = segments(qk)
    return out


def _outside(model: Model, gdata: pin.GeometryData, segments) -> list[bool]:
    """For each segment (a, b): do most of 9 points inside it lie outside every geometry of the
    scene's bodies (placements in `gdata`)? coal's distance from each point to each shape."""
    bodies = {b.name for b in model.scene.bodies}
    shapes = [(go.geometry, gdata.oMg[g]) for g, go in enumerate(model.geom.geometryObjects)
              if model.geometry_body[g] in bodies and not isinstance(go.geometry, (coal.Halfspace, coal.Plane))]
    point, req = coal.Sphere(1e-9), coal.DistanceRequest()
    out = []
    for a, b in segments:
        outside = 0
        for s in np.linspace(0.1, 0.9, 9):
            x = coal.Transform3s(np.eye(3), (1 - s) * a + s * b)
            outside += all(coal.distance(point, x, shape, coal.Transform3s(M.rotation, M.translation), req,
                                         coal.DistanceResult()) > 0 for shape, M in shapes)
        out.append(outside > 4)
    return out


def parts(traj: Trajectory | str | Path, model: Model | None = None, *, colors: str = "link") -> list[Part]:
    """The meshes the replay draws: each link's visual geometry - a URDF's <visual>s (meshes loaded
    with trimesh, boxes, spheres, cylinders), an MJCF's visual geoms (:func:`mjcf_visuals`) -, its
    collision geometry where it has no visual that loads, and the statics (a half-space is left to
    the caller: :func:`ground_box`). `colors`: "link" gives each link its own colour of a palette,
    "model" keeps the model's colours (URDF materials; MJCF rgba and materials; the palette where a
    URDF visual has none)."""
    traj = as_trajectory(traj)
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
        return rgb if colors == "model" and rgb is not None else PALETTE[links.index(link) % len(PALETTE)]

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
            for link, f, M, mesh, rgb in mjcf_visuals(model, body, texts[body.name], original):
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
        for link, items in urdf_visuals(texts[name], dirs, base).items():
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
        if link in done or pm.frames[go.parentFrame].name in done:  # (a fixed root's link is a static)
            continue
        mesh = shape_mesh(go.geometry)
        if mesh is None:
            continue
        frame = 0 if static else go.parentFrame
        M = go.placement if static else pm.frames[go.parentFrame].placement.inverse() * go.placement
        out.append(Part(f"{link}/collision_{g}", link, frame, M, np.asarray(mesh.vertices, np.float32),
                        np.asarray(mesh.faces, np.uint32), STATIC_COLOR if static else color_of(link, None),
                        "collision", static))
    return out


def frame_placements(model: Model, q: np.ndarray, frame_ids: list[int]) -> np.ndarray:
    """(n, len(frame_ids), 4, 4) world placements of Pinocchio frames at each q."""
    data = model.pin.createData()
    out = np.empty((len(q), len(frame_ids), 4, 4))
    for k, qk in enumerate(q):
        pin.framesForwardKinematics(model.pin, data, qk)
        for j, f in enumerate(frame_ids):
            out[k, j] = data.oMf[f].homogeneous
    return out




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
            rgb = STATIC_COLOR if static else PALETTE[links.index(link) % len(PALETTE)]
            go.meshColor = np.array([*(c / 255 for c in rgb), 1.0])
            go.overrideMaterial = True
        out.addGeometryObject(go)
    return out
