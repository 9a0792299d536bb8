"""The model a trajectory was run with, rebuilt from its metadata alone (the stored scene TOML
and URDF/MJCF texts), and the files such a text may name (docs/viewer.md, "Files read")."""

from __future__ import annotations

import dataclasses
import re
import tempfile
import tomllib
from pathlib import Path

import tomli_w

from ..errors import MoreauSimError, SceneError
from ..model import Model, build_model
from ..options import Options
from ..scene import parse_scene
from ..trajectory import Trajectory, load_trajectory


def as_trajectory(traj: Trajectory | str | Path) -> Trajectory:
    """`traj` itself, or the trajectory NPZ it names, loaded."""
    return traj if isinstance(traj, Trajectory) else load_trajectory(traj)


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


def model_from_trajectory(traj: Trajectory | str | Path) -> Model:
    """Rebuild the :class:`Model` of a trajectory from its metadata alone (scene TOML and URDF
    texts written to a temporary folder, each body's ``urdf`` pointed at its copy), with the
    options the run used (``meta['options']``, e.g. a command-line restitution) where valid.

    Raises ValueError when the metadata lacks them, SceneError when they do not build (e.g. a URDF
    whose collision meshes were separate files)."""
    traj = as_trajectory(traj)
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
            srdf = (sc.get("srdf") or {}).get(bname)  # the SRDF the run read (its pairs), or none
            body["srdf"] = False
            if isinstance(srdf, str):
                body["srdf"] = str(path.with_suffix(".srdf"))
                path.with_suffix(".srdf").write_text(srdf, encoding="utf-8")
        scene_path = Path(tmp) / name
        scene_text = tomli_w.dumps(doc)
        scene_path.write_text(scene_text, encoding="utf-8")
        scene = parse_scene(scene_text, path=scene_path)
        known = {f.name for f in dataclasses.fields(Options)}
        try:
            scene = scene.with_options(**{k: v for k, v in (traj.meta.get("options") or {}).items() if k in known})
        except (MoreauSimError, TypeError, ValueError):
            pass  # options of another version: keep the scene file's
        return build_model(scene)
