"""Robot descriptions: ``package://`` resolution, URDF meshes, the SRDF beside a URDF
(find_srdf; self_pairs.py reads it), MJCF (its elements read, ignored or refused by name and line;
``<include>`` inside the model's folder; joint ranges into the position limits), mesh collision modes.

Search order for a ``package://PKG/rel/path`` URI (docs/robots.md):

1. the body's ``package_dirs`` (scene key, relative to the scene file), in order;
2. the folders in the environment variable ``MOREAU_SIM_PACKAGE_PATH`` (``os.pathsep``-separated);
3. the ``share`` folder of an installed ``example-robot-data`` distribution (found through
   ``importlib.metadata``: its files ``.../share/example-robot-data/robots/...``), whose URDFs name
   their meshes ``package://example-robot-data/robots/...``;
4. the folder of the file that names the URI (the URDF for a mesh, the scene file for a body's
   ``urdf``/``mjcf``) and the PARENT_LEVELS folders above it, nearest first, never further up.

A folder D resolves the URI when ``D/PKG/rel/path`` is a file (Pinocchio's rule), so a folder that
*is* the package is found through its parent (step 4 covers a package the URDF lives in).

Meshes of a URDF are resolved here, not by Pinocchio: the URDF text handed to Pinocchio has every
collision ``<mesh filename>`` replaced by the absolute file, so a URI that resolves nowhere is a
:class:`SceneError` naming the scene, the body, the link, the URI and the folders searched (not a
C++ error or a silently empty geometry), and Pinocchio's own ``ROS_PACKAGE_PATH`` lookup never
picks a different file.

Mesh collision geometry (``meshes`` body key, :class:`MeshMode`): ``convex`` (default) replaces
each mesh by its convex hull (``coal.ConvexBase``: points and face normals, which contacts.py uses
as vertices and to snap patch normals); ``bvh`` keeps the triangle soup Pinocchio loads
(``coal.BVHModelOBBRSS``: one closest-point contact per pair). docs/robots.md has the measurement.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import os
import re
import sys
import tempfile
import warnings
import weakref
import xml.etree.ElementTree as ET
from xml.parsers import expat
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from .errors import SceneError, one_line
from .options import MeshMode

ENV_PACKAGE_PATH = "MOREAU_SIM_PACKAGE_PATH"
ERD = "example-robot-data"


@functools.lru_cache(maxsize=None)
def example_robot_data_share() -> Path | None:
    """The ``share`` folder holding ``example-robot-data/robots`` of the installed
    ``example-robot-data`` distribution (cmeel wheels install it under ``cmeel.prefix/share``),
    or None if it is not installed."""
    try:
        dist = importlib.metadata.distribution(ERD)
    except importlib.metadata.PackageNotFoundError:
        return None
    for f in dist.files or ():
        parts = f.parts
        for k in range(len(parts) - 1):
            if parts[k] == "share" and parts[k + 1] == ERD:
                share = Path(dist.locate_file(Path(*parts[:k + 1]))).resolve()
                if (share / ERD).is_dir():
                    return share
                return None  # listed but not on disk (a broken install)
    return None


def real_path(p: Path, where: str) -> Path:
    """``p.resolve()``, or a SceneError naming `where` and the file for a symbolic-link loop
    (pathlib raises RuntimeError, or OSError ELOOP, for one)."""
    try:
        return Path(p).expanduser().resolve()
    except (RuntimeError, OSError) as exc:
        raise SceneError(f"{where}: {p}: cannot be resolved: a symbolic-link loop "
                         f"({getattr(exc, 'strerror', None) or exc})") from None


def _quiet_resolve(p: Path) -> Path:
    """``p.resolve()``, or ``p.absolute()`` for a folder behind a symbolic-link loop (searched, never found)."""
    try:
        return Path(p).expanduser().resolve()
    except (RuntimeError, OSError):
        return Path(p).expanduser().absolute()


@contextlib.contextmanager
def quiet_output(*fds: int):
    """Silence the C/C++ libraries' own writes to the file descriptors `fds` (2: stderr, 1: stdout)
    for the block; errors they raise still reach the caller, who says what failed."""
    saved = {}
    try:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        for fd in fds:
            saved[fd] = os.dup(fd)
    except (OSError, ValueError, AttributeError):  # no real descriptors (embedded interpreters): nothing to silence
        for fd in saved.values():
            os.close(fd)
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            for fd in fds:
                os.dup2(null.fileno(), fd)
            yield
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)


def env_package_dirs() -> list[Path]:
    """The folders of ``MOREAU_SIM_PACKAGE_PATH`` (read at each call, so tests may set it)."""
    value = os.environ.get(ENV_PACKAGE_PATH, "")
    return [_quiet_resolve(Path(p)) for p in value.split(os.pathsep) if p.strip()]


PARENT_LEVELS = 2  # folders above the naming file's own that package:// may search


def search_dirs(package_dirs, folder: Path) -> list[Path]:
    """Folders searched for ``package://`` URIs, in order (module docstring): the body's
    `package_dirs`, the environment variable, example-robot-data's share folder, then `folder`
    (that of the file naming the URI) and the PARENT_LEVELS folders above it (a ROS layout
    share/PKG/urdf/x.urdf finds share/PKG/meshes/...), never further up. Duplicates are dropped."""
    out: list[Path] = []
    share = example_robot_data_share()
    folder = _quiet_resolve(Path(folder))
    near = [folder, *list(folder.parents)[:PARENT_LEVELS]]
    for d in [*map(Path, package_dirs), *env_package_dirs(), *([share] if share else []), *near]:
        if d not in out:
            out.append(d)
    return out


def is_uri(value: str) -> bool:
    return "://" in value


def resolve(uri: str, dirs: list[Path], base: Path) -> Path | None:
    """The file `uri` names, or None. ``package://PKG/rel`` and ``model://PKG/rel``: the first
    ``D/PKG/rel`` that is a file, D in `dirs`; ``file:///abs``: that file; a plain path:
    relative to the folder `base`, else (as Pinocchio does) to each D in `dirs`.
    Raises SceneError for any other scheme."""
    if is_uri(uri):
        scheme, rest = uri.split("://", 1)
        if scheme in ("package", "model"):
            rel = rest.lstrip("/")
            if ".." in Path(rel).parts:
                raise SceneError(f"{uri}: '..' may not climb out of a package root")
            for d in dirs:
                p = d / rel
                if p.is_file():
                    return p.resolve()
            return None
        if scheme == "file":
            p = Path(rest)
            p = p if p.is_absolute() else base / p
            return p.resolve() if p.is_file() else None
        raise SceneError(f"URI scheme '{scheme}://' is not supported (package://, model://, file:// or a path)")
    p = Path(uri).expanduser()
    if p.is_absolute():
        return p if p.is_file() else None
    for d in (base, *dirs):
        if (d / p).is_file():
            return (d / p).resolve()
    return None


def _searched(dirs: list[Path], uri: str) -> str:
    """The folders searched, and what to do when the URI names example-robot-data but it is absent."""
    out = "[" + ", ".join(str(d) for d in dirs) + "]"
    if uri.split("://", 1)[-1].lstrip("/").startswith(ERD + "/") and example_robot_data_share() is None:
        out += f"; {ERD} is not installed (pip install {ERD})"
    return out


def resolve_model_file(value: str, base: Path, package_dirs, where: str) -> Path:
    """A body's ``urdf``/``mjcf`` value -> the file. A plain path is relative to the scene
    folder `base` (nothing else is searched); a URI goes through :func:`search_dirs` with the
    scene file's folders last. `where` names the scene, the body and the key."""
    if not is_uri(value):
        p = real_path(base / value, where)
        if not p.is_file():
            what = "not a file" if p.exists() else "file not found"
            if (base / value).is_symlink():
                what += f" (the symbolic link {base / value} points there)"
            raise SceneError(f"{where}: {what}: {p}")
        return p
    dirs = search_dirs(package_dirs, base)
    try:
        p = resolve(value, dirs, base)
    except SceneError as exc:
        raise SceneError(f"{where}: '{value}': {exc}") from None
    if p is None:
        raise SceneError(f"{where}: '{value}' resolves to no file; searched {_searched(dirs, value)} "
                         f"(add the folder holding '{value.split('://', 1)[1].split('/')[0]}' to the body's "
                         f"package_dirs or to ${ENV_PACKAGE_PATH})")
    return p


SRDF_FOLDER = "srdf"  # example-robot-data: <robot>_description/{urdf,robots}/X.urdf beside .../srdf/


def find_srdf(urdf: Path) -> Path | None:
    """The SRDF example-robot-data ships beside `urdf`: in the folder ``srdf`` next to the URDF's
    folder, the file named as the URDF (``go2.urdf`` -> ``go2.srdf``), else the one whose name is
    the longest prefix of the URDF's (``solo12.urdf`` -> ``solo.srdf``, ``ur5_robot.urdf`` ->
    ``ur5.srdf``: the pairs the package's own loaders make). None when there is none."""
    folder = Path(urdf).parent.parent / SRDF_FOLDER
    if not folder.is_dir():
        return None
    stems = [p.stem for p in folder.glob("*.srdf") if p.is_file() and Path(urdf).stem.startswith(p.stem)]
    return (folder / f"{max(stems, key=len)}.srdf").resolve() if stems else None


_MESH_ATTR = re.compile(r"""(<mesh\b[^>]*?\bfilename\s*=\s*)(["'])(.*?)\2""", re.S)


def urdf_with_resolved_meshes(path: Path, package_dirs, where: str) -> str:
    """The URDF text of `path` with every collision mesh's filename replaced by the absolute
    file it resolves to (module docstring). Raises SceneError (scene, body, link, URI, folders
    searched) for a collision mesh that resolves nowhere. Visual meshes are left as they are
    (only collision geometry is loaded) unless they name a collision mesh's URI."""
    text = path.read_text(encoding="utf-8")
    root = ET.fromstring(text)
    dirs = search_dirs(package_dirs, path.parent)
    found: dict[str, Path] = {}
    for link in root.findall("link"):
        for col in link.findall("collision"):
            mesh = col.find("geometry/mesh")
            if mesh is None:
                continue
            uri = mesh.get("filename", "")
            if uri in found:
                continue
            try:
                p = resolve(uri, dirs, path.parent) if uri else None
            except SceneError as exc:
                raise SceneError(f"{path}: link '{link.get('name')}': collision mesh '{uri}': {exc} "
                                 f"[{where} urdf]") from None
            if p is None:
                raise SceneError(f"{path}: link '{link.get('name')}': collision mesh '{uri}' resolves to no file; "
                                 f"searched {_searched(dirs, uri)} [{where} urdf]")
            found[uri] = p

    def sub(m: re.Match) -> str:
        # here (meshes only): xml.sax.saxutils imports urllib.request and with it ssl, ~8 MiB of RSS
        from xml.sax.saxutils import escape, unescape

        p = found.get(unescape(m.group(3), {"&quot;": '"', "&apos;": "'"}))
        return m.group(0) if p is None else f"{m.group(1)}{m.group(2)}{escape(str(p), {chr(34): '&quot;'})}{m.group(2)}"

    return _MESH_ATTR.sub(sub, text) if found else text


def apply_mesh_mode(geom: pin.GeometryModel, mode: MeshMode, where: str = "") -> None:
    """Replace every mesh (coal BVH model) of `geom` by its convex hull for ``convex``
    (``buildConvexHull(True, "Qt")``: the hull's triangles are kept, so the ConvexBase has
    points, triangle normals and neighbours); leave it for ``bvh``. Primitive shapes stay.

    A convex mesh without face normals (Pinocchio's ``<collision_checking><convex/>`` URDF
    extension builds one) gets its hull rebuilt with normals in either mode: coal 3.0.3's
    ``normals()`` of such a shape is a null pointer (segfault), and contacts.py reads it.
    A mesh whose hull coal cannot build (qhull output with a vertex of more than 255 neighbours:
    "Too many neighbors") is a SceneError that suggests ``meshes = "bvh"``."""
    for go in geom.geometryObjects:
        g = go.geometry
        if isinstance(g, coal.BVHModelBase):
            name = go.meshPath or go.name
            V = np.asarray(g.vertices(), float).reshape(-1, 3)
            bad = int((~np.isfinite(V).all(axis=1)).sum())
            if bad:
                raise SceneError(f"{where}: collision mesh {name}: {bad} of its {len(V)} vertices are not finite "
                                 "(NaN or inf); fix the mesh file")
            if mode is MeshMode.BVH:
                continue
            if g.convex is None:  # meshes come from a cache (model._MESH_LOADER): build each hull once
                thickness = _thickness(V)
                if thickness <= 1e-9 * max(1.0, float(np.ptp(V, axis=0).max(initial=0.0))):
                    # qhull on a flat point set crashes coal 3.0.3 (segfault): refuse it here
                    raise SceneError(f"{where}: collision mesh {name} is flat (its {len(V)} vertices lie within "
                                     f"{thickness:.2g} m of one plane) and has no convex hull; give this body "
                                     "meshes = \"bvh\", or a closed mesh")
                try:
                    g.buildConvexHull(True, "Qt")
                except Exception as exc:  # coal raises RuntimeError with its C++ location first
                    reason = str(exc).strip().splitlines()[-1]
                    raise SceneError(f"{where}: collision mesh {go.meshPath or go.name}: coal cannot build its convex "
                                     f"hull ({reason}); give this body meshes = \"bvh\"") from None
            go.geometry = g.convex
        elif isinstance(g, coal.ConvexBase) and g.num_normals_and_offsets == 0:
            points = coal.StdVec_Vec3s()
            for x in np.asarray(g.points(), float).reshape(-1, 3):
                points.append(x)
            go.geometry = coal.ConvexBase.convexHull(points, True, "Qt")


def _thickness(V: np.ndarray) -> float:
    """The smallest extent [m] of a point set across its principal axes (0 when flat or < 4 points)."""
    if len(V) < 4:
        return 0.0
    X = V - V.mean(axis=0)
    s = np.linalg.svd(X, compute_uv=False)
    return float(s[-1] / np.sqrt(len(V))) if len(s) == 3 else 0.0


def unique_frame_names(model: pin.Model) -> None:
    """Rename frames whose name another frame of a different type also has (a URDF link and a
    joint of the same name: anymal_c, z1, so100 in example-robot-data): Pinocchio's appendModel
    refuses such a model ("Several frames match the filter"). The link (BODY) frame keeps the
    name, which [collisions] and the geometry names use; the other gets "<name>:<type>", e.g.
    "gripperStator:FIXED_JOINT"."""
    names = [f.name for f in model.frames]
    taken = set(names)
    for i, f in enumerate(model.frames):
        if names.count(f.name) > 1 and f.type != pin.FrameType.BODY:
            new = f"{f.name}:{str(f.type).rsplit('.', 1)[-1]}"
            k = 1
            while new in taken:
                k += 1
                new = f"{f.name}:{str(f.type).rsplit('.', 1)[-1]}{k}"
            model.frames[i].name = new
            taken.add(new)


# MJCF elements by what the reader does with them (docs/robots.md). READ: Pinocchio 4.1's MJCF
# reader builds them into the model (materials colour the replay); <include> is expanded here;
# <motor> and <position> under <actuator> are read by mjcf_actuators.py.
# IGNORED: ignoring them cannot change the motion (drawing, sensors, MuJoCo's own solver settings
# and memory sizes, named poses: the scene gives q0, the step, gravity and the contact law): one
# warning names them. Any other element is refused by name: it would change the motion (tendons,
# equality constraints, other actuators, explicit contacts, composites, height fields) and would be dropped.
MJCF_READ = frozenset({"mujoco", "compiler", "default", "asset", "mesh", "material", "worldbody", "body", "joint",
                       "freejoint", "geom", "site", "inertial", "include", "actuator", "motor", "position"})
MJCF_IGNORED = frozenset({"visual", "statistic", "light", "camera", "texture", "skin", "sensor", "keyframe",
                          "custom", "size", "option"})  # (their children are not looked at)
MJCF_WHY = {"equality": "equality constraints", "tendon": "tendons",
            "general": "MJCF actuators other than <motor> and <position>",
            "velocity": "MJCF actuators other than <motor> and <position>",
            "intvelocity": "MJCF actuators other than <motor> and <position>",
            "damper": "MJCF actuators other than <motor> and <position>",
            "cylinder": "MJCF actuators other than <motor> and <position>",
            "muscle": "MJCF actuators other than <motor> and <position>",
            "adhesion": "MJCF actuators other than <motor> and <position>",
            "contact": "explicit contact pairs and exclusions: give them in the scene's [collisions]",
            "composite": "composite bodies", "flexcomp": "flexible bodies", "deformable": "deformable bodies",
            "hfield": "height fields", "plugin": "plugins", "extension": "plugins"}


_SOURCE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # MJCF element -> (file, line)


def _parse_with_lines(path: Path) -> ET.Element:
    """``ET.parse(path).getroot()`` (comments dropped), each element's file and line recorded in
    _SOURCE, so that a refusal names the line (an included file's element names that file)."""
    builder, parser = ET.TreeBuilder(), expat.ParserCreate()

    def start(tag, attrs):
        _SOURCE[builder.start(tag, attrs)] = (path, parser.CurrentLineNumber)

    parser.StartElementHandler, parser.EndElementHandler = start, builder.end
    parser.CharacterDataHandler, parser.buffer_text = builder.data, True
    with open(path, "rb") as f:
        parser.ParseFile(f)
    return builder.close()


def _at(el: ET.Element, path: Path) -> str:
    """"file:line" of an MJCF element read by _parse_with_lines, else the file `path`."""
    found = _SOURCE.get(el)
    return f"{found[0]}:{found[1]}" if found else str(path)


def _mjcf_expanded(path: Path, where: str, _seen: tuple[Path, ...] = ()) -> ET.Element:
    """The MJCF tree of `path` with every ``<include file=...>`` replaced by the children of the
    included file's root (MuJoCo's rule), each resolved against the model's folder and refused
    when it lies outside it (symbolic links followed) or includes itself."""
    top = _seen[0].parent if _seen else path.parent
    try:
        root = _parse_with_lines(path)
    except expat.ExpatError as exc:
        raise SceneError(f"{path}: malformed MJCF (XML error: {exc}) [{where} mjcf]") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read this MJCF ({exc.strerror or exc}) [{where} mjcf]") from None
    if root.tag != "mujoco":
        raise SceneError(f"{path}: not an MJCF file: root element is <{root.tag}>, expected <mujoco> "
                         f"[{where} mjcf]")
    for parent in list(root.iter()):
        for k, child in enumerate(list(parent)):
            if child.tag != "include":
                continue
            name = child.get("file", "")
            if not name.strip():
                raise SceneError(f"{_at(child, path)}: an <include> without a file=\"...\" [{where} mjcf]")
            inc = real_path(top / name, f"{_at(child, path)}: <include file=\"{name}\"> [{where} mjcf]")
            if not inc.is_relative_to(top.resolve()):
                raise SceneError(f"{_at(child, path)}: <include file=\"{name}\">: only files inside the model's folder "
                                 f"{top} may be included [{where} mjcf]")
            if inc in _seen or inc == path:
                raise SceneError(f"{_at(child, path)}: <include file=\"{name}\"> includes itself [{where} mjcf]")
            if not inc.is_file():
                raise SceneError(f"{_at(child, path)}: <include file=\"{name}\">: file not found: {inc} [{where} mjcf]")
            sub = _mjcf_expanded(inc, where, (*(_seen or (path,)), inc))
            parent.remove(child)
            for i, c in enumerate(list(sub)):
                parent.insert(k + i, c)
    return root


def check_mjcf(root: ET.Element, path: Path, where: str) -> list[str]:
    """Refuse (SceneError) any element the reader would drop and that can change the motion, and
    a geom of a type it cannot collide; return the ignored elements' names (module note above)."""
    ignored: list[str] = []

    def visit(el: ET.Element) -> None:
        for child in el:
            tag = child.tag if isinstance(child.tag, str) else ""
            if not tag:
                continue  # a comment
            if tag in MJCF_IGNORED:
                if tag not in ignored:
                    ignored.append(tag)
                continue
            if tag not in MJCF_READ or (tag in ("motor", "position")) != (el.tag == "actuator"):
                why = MJCF_WHY.get(tag, "an element moreau-sim's MJCF reader does not read")
                raise SceneError(f"{_at(child, path)}: <{tag}> is not supported ({why}); remove it [{where} mjcf]")
            if tag == "geom" and child.get("type") in ("hfield", "sdf"):
                raise SceneError(f"{_at(child, path)}: <geom type=\"{child.get('type')}\"> is not supported "
                                 f"({MJCF_WHY['hfield'] if child.get('type') == 'hfield' else 'SDF geoms'}) "
                                 f"[{where} mjcf]")
            if tag != "default":
                visit(child)

    visit(root)
    tops = [b.get("name", "?") for w in root.findall("worldbody") for b in w.findall("body")]
    if len(tops) > 1:  # Pinocchio 4.1's reader reads the first and drops the others without a word
        raise SceneError(f"{path}: <worldbody> has {len(tops)} top-level bodies ({', '.join(tops[:5])}"
                         f"{', ...' if len(tops) > 5 else ''}); the MJCF reader reads one tree: give each its own "
                         f"[[bodies]] entry (one file each) [{where} mjcf]")
    return ignored


def default_classes(tree: ET.Element, own) -> dict[str, dict]:
    """The attributes each <default> class gives, by class name (nested classes inherit their parent's; the top
    class is "main": MuJoCo's rule); own(d): the attributes the class element d sets itself (a dict)."""
    out: dict[str, dict] = {"main": {}}

    def walk(d: ET.Element, inherited: dict, name: str) -> None:
        out[name] = attrs = {**inherited, **own(d)}
        for child in d.findall("default"):
            walk(child, attrs, child.get("class", "main"))

    for d in tree.findall("default"):
        walk(d, {}, d.get("class", "main"))
    return out


def _joint_defaults(tree: ET.Element) -> dict[str, dict[str, str]]:
    """The <joint> attributes each <default> class gives (default_classes)."""
    return default_classes(tree, lambda d: {k: v for j in d.findall("joint") for k, v in j.attrib.items()})


_JOINT_NQ = {"free": 7, "ball": 4, "hinge": 1, "slide": 1}


def mjcf_joint_limits(tree: ET.Element, m: pin.Model, path: Path, where: str) -> None:
    """Set the position limits of `m` (built by Pinocchio from the MJCF `tree`) from each joint's
    ``range`` and ``limited`` as MuJoCo reads them: its own attributes over its class's (``class``,
    else the nearest ``childclass`` above it, else "main"); ``limited="auto"`` (the default) means
    limited when a range is given unless ``<compiler autolimits="false">``; a hinge's range in
    degrees unless ``<compiler angle="radian">``, a slide's in metres. Unlimited: -inf, inf.
    Pinocchio 4.1's reader alone converts a slide's range from degrees and keeps the range of a
    joint with ``limited="false"``. A limited ball joint (a cone) is refused by name. No effort limit:
    Pinocchio's reader puts a joint's ``actuatorfrcrange`` upper bound there (a symmetric clamp of every torque,
    whatever ``actuatorfrclimited`` says); mjcf_actuators clamps the joint's actuators' sum to it as MuJoCo does."""
    compiler: dict[str, str] = {}
    for c in tree.findall("compiler"):
        compiler.update(c.attrib)
    degrees = compiler.get("angle", "degree") != "radian"
    auto = compiler.get("autolimits", "true") == "true"
    defaults = _joint_defaults(tree)
    found: list[tuple[str, int, float, float]] = []  # (name, nq, lower, upper) in the order of q

    def visit(el: ET.Element, childclass: str) -> None:
        for child in el:
            if child.tag == "body":
                visit(child, child.get("childclass", childclass))
            elif child.tag == "freejoint":
                found.append((child.get("name", "?"), 7, -np.inf, np.inf))
            elif child.tag == "joint":
                a = {**defaults.get(child.get("class", childclass), {}), **child.attrib}
                kind, name, rng = a.get("type", "hinge"), a.get("name", "?"), a.get("range")
                limited = a.get("limited", "auto")
                limited = limited == "true" or (limited == "auto" and auto and rng is not None)
                at = f"{_at(child, path)}: joint '{name}'"
                if kind not in _JOINT_NQ:
                    raise SceneError(f"{at}: type \"{kind}\" is not a MuJoCo joint type [{where} mjcf]")
                lo, up = -np.inf, np.inf
                if limited:
                    try:
                        lo, up = (float(x) for x in (rng or "").split())
                    except ValueError:
                        raise SceneError(f"{at}: limited, but range={rng!r} is not two numbers (lower upper) "
                                         f"[{where} mjcf]") from None
                    if not (np.isfinite(lo) and np.isfinite(up) and lo < up):
                        raise SceneError(f"{at}: range {lo:g} {up:g} must be finite with lower < upper "
                                         f"[{where} mjcf]")
                    if kind in ("ball", "free"):
                        raise SceneError(f"{at}: a limited {kind} joint (range: a cone about its reference) "
                                         f"is not supported; remove its range or set limited=\"false\" "
                                         f"[{where} mjcf]")
                    if kind == "hinge" and degrees:
                        lo, up = np.deg2rad(lo), np.deg2rad(up)
                found.append((name, _JOINT_NQ[kind], lo, up))

    for w in tree.findall("worldbody"):
        visit(w, "main")
    if sum(n for _, n, _, _ in found) != m.nq:
        raise SceneError(f"{path}: its joints have {sum(n for _, n, _, _ in found)} coordinates, Pinocchio's MJCF "
                         f"reader made nq = {m.nq}; the joint limits cannot be matched [{where} mjcf]")
    lower, upper = m.lowerPositionLimit.copy(), m.upperPositionLimit.copy()
    k = 0
    for _, n, lo, up in found:
        if n == 1:
            lower[k], upper[k] = lo, up
        k += n
    m.lowerPositionLimit, m.upperPositionLimit = lower, upper
    m.effortLimit = np.full(m.nv, np.inf)


def load_mjcf(path: Path, root, where: str,
              kind: pin.GeometryType = pin.GeometryType.COLLISION) -> tuple[pin.Model, pin.GeometryModel]:
    """Model and collision geometry (or `kind`: VISUAL, what the replay draws) of an MJCF file.
    `root` (a JointModel or None) attaches the MJCF's world body to the world: Pinocchio 4.1's
    MJCF reader silently ignores a root joint when the top body has a joint of its own, so the
    root is built here (a one-joint model) and the MJCF model appended to it, which treats both
    cases alike (inertias of bodies welded to the world body move onto the root).

    Elements are checked first (:func:`check_mjcf`: refused by name, or ignored with one warning);
    a file with ``<include>`` or ignored elements is read from a copy in a temporary folder (the
    includes expanded, the ignored elements removed, its mesh, texture and asset folders made
    absolute): Pinocchio's reader skips ``<include>`` and would still parse what is ignored."""
    tree = _mjcf_expanded(path, where)
    ignored = check_mjcf(tree, path, where)
    if ignored and kind == pin.GeometryType.COLLISION:
        # attributed to the MJCF file (line 0: no source line under it), one line wherever it is shown
        warnings.warn_explicit(f"MJCF element(s) {', '.join(f'<{t}>' for t in ignored)} ignored: they do not "
                               "change the motion (drawing, sensors, MuJoCo's own settings; the scene sets q0, "
                               f"the step and gravity) [{where} mjcf]", UserWarning, str(path), 0)
    with contextlib.ExitStack() as stack:
        read_from = path
        if ignored or any(True for _ in ET.parse(path).getroot().iter("include")):
            for parent in [tree, *(el for el in tree.iter() if el.tag not in ("default", *MJCF_IGNORED))]:
                for child in [c for c in parent if c.tag in MJCF_IGNORED]:
                    parent.remove(child)  # ignored means not read by Pinocchio either
            compiler = tree.find("compiler")
            if compiler is None:
                compiler = ET.Element("compiler")
                tree.insert(0, compiler)
            asset = compiler.get("assetdir", "")  # MuJoCo: the default of meshdir and texturedir
            for key in ("meshdir", "texturedir", "assetdir"):
                compiler.set(key, str(path.parent / compiler.get(key, asset)) + os.sep)
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="moreau-sim-mjcf-")))
            read_from = folder / path.name
            ET.ElementTree(tree).write(read_from, encoding="unicode")
        try:
            with quiet_output(1, 2):  # Pinocchio prints its own "Warning - ..." lines to stdout
                m = pin.buildModelFromMJCF(str(read_from))
                g = pin.buildGeomFromMJCF(m, str(read_from), kind)
        except Exception as exc:  # Pinocchio raises plain RuntimeError/ValueError with C++ text
            raise SceneError(f"{path}: Pinocchio cannot load this MJCF: {one_line(exc)} [{where} mjcf]") from None
    mjcf_joint_limits(tree, m, path, where)
    if root is None:
        return m, g
    rm = pin.Model()
    rm.name = m.name
    j = rm.addJoint(0, root, pin.SE3.Identity(), "root")
    frame = rm.addJointFrame(j)
    return pin.appendModel(rm, m, pin.GeometryModel(), g, frame, pin.SE3.Identity())
