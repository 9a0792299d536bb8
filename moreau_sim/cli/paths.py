"""Where the commands write (docs/cli.md, "Output files"): one rule for every output.

An output must carry its suffix, must not be one of the files the command read (compared after
resolving symlinks), a trailing slash or an existing folder means "that folder, default name",
and a missing folder is created only below the current directory, the scene's folder or the
temporary folder."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .common import fail


def model_inputs(sc, model=None) -> list[Path]:
    """Every file a run reads: the scene, its URDF/MJCF files and their meshes."""
    files = [sc.path] if sc.path else []
    files += [b.urdf for b in sc.bodies if isinstance(b.urdf, Path)]
    if model is not None:
        files += [Path(go.meshPath) for go in model.geom.geometryObjects if getattr(go, "meshPath", "")]
    return files


def _roots(roots) -> list[Path]:
    """The folders below which a missing output folder is created: the current one, the input's
    (`roots`) and the temporary folder (scratch space)."""
    return [Path(r).resolve() for r in (Path.cwd(), *roots, tempfile.gettempdir())]


def _same(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == Path(b).resolve()
    except (OSError, RuntimeError):
        return False


def output_path(given: str | os.PathLike | None, *, default: Path, suffix: str | tuple[str, ...], where: str,
                inputs=(), roots=(), then: str = "nothing was written") -> Path:
    """Check an output path and return it (its folder exists and is writable on return).

    given: what the user wrote (None: `default`); a trailing slash or an existing folder means
    `folder/default.name`; where: how the message names the option or field; inputs: the files the
    command read; roots: folders besides the current one below which missing folders may be made;
    then: what the message says was (not) done."""
    suffixes = (suffix,) if isinstance(suffix, str) else suffix
    suffix = " or ".join(suffixes)
    if given is None:
        path = default
    else:
        text = os.fspath(given)
        if not text.strip():
            fail(f"{where}: empty file name; give a file ending in {suffix}")
        path = Path(text)
        if text.endswith(("/", os.sep)) or path.is_dir():
            path = path / default.name
    for f in inputs:
        if _same(path, f):
            fail(f"{where}: {path} is an input of this command ({f}); choose another output file")
    if path.suffix not in suffixes:
        fail(f"{where}: {path}: the output must end in {suffix}")
    parent = path.parent
    _creatable(parent, where, roots, f"{where}: the folder {parent} does not exist; create it first (moreau-sim only "
               "creates folders below the current directory, the scene's folder or the temporary folder)")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=parent, prefix=f".{path.name}.", suffix=".check"):
            pass
    except OSError as exc:
        fail(f"{where}: cannot write to {parent} ({exc.strerror or exc}); {then}")
    if path.is_dir():
        fail(f"{where}: {path} is a folder; give a file name")
    return path


def output_dir(given: str | None, *, default: Path, where: str, roots=()) -> Path:
    """A folder the command writes into (a sweep's): not empty, not a file, and created only
    below the current directory or one of `roots` when missing."""
    if given is not None and not given.strip():
        fail(f"{where}: empty folder name")
    path = default if given is None else Path(given)
    if path.exists() and not path.is_dir():
        fail(f"{where}: {path} is a file, not a folder; choose another output folder")
    _creatable(path, where, roots, f"{where}: the folder {path} does not exist and is outside the current "
               "directory, the scene's folder and the temporary folder; create it first")
    return path


def _creatable(folder: Path, where: str, roots, outside: str) -> None:
    """A missing `folder` may be created only below the current directory, `roots` or the
    temporary folder: else fail with `outside`."""
    if folder.exists():
        return
    try:
        target = folder.resolve()
    except (OSError, RuntimeError) as exc:
        fail(f"{where}: cannot use the folder {folder} ({exc})")
    if not any(target.is_relative_to(r) for r in _roots(roots)):
        fail(outside)
