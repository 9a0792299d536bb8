"""The replay page: viser's standalone client with a recording of the scene embedded in it
(meshes, lights, camera, link placements per frame, percussions as arrows) and the energy/gap
plot (docs/viewer.md, "How it is built")."""

from __future__ import annotations

import contextlib
import html as _html
import io
import math
import re
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from ..model import Model
from ..trajectory import Trajectory
from .camera import FOV, camera, corners
from .meshes import ground_box
from .overlay import OVERLAY, axis, js_string
from .parts import STATIC_COLOR, frame_placements, parts, rods
from .stored import as_trajectory, model_from_trajectory

DEFAULT_FPS = 100.0  # frames kept per simulated second (0: every sample)
_IMPACT_COLOR = (224, 32, 42)
_PUSH_COLOR = (240, 170, 30)


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


def contacts_per_frame(traj: Trajectory, ft: np.ndarray) -> list[list[list[float]]]:
    """Per frame i: the percussions logged in (ft[i-1], ft[i]], summed per contact (pair, kind, feature):
    [px, py, pz, nx, ny, nz, P, impact] with the point and normal of the latest step. A row covering a stretch
    of persistent steps (log_steps > 1, docs/theory.md §5.2) gives each frame its steps' share of its P."""
    a = traj.arrays
    lt, steps = a["log_t"], a["log_steps"]
    order = np.argsort(lt, kind="stable")
    out: list[dict] = [{} for _ in ft]
    for j in order:
        n = int(steps[j])
        per = float(a["log_P"][j]) / n
        t_last = float(lt[j]) + float(a["log_duration"][j]) * (n - 1) / n if n > 1 else float(lt[j])
        first, last = np.searchsorted(ft, [lt[j], t_last], side="left")  # frame i gets ft[i-1] < t <= ft[i]
        key = (int(a["log_pair"][j]), int(a["log_kind"][j]), int(a["log_feature"][j]))
        for b in range(first, min(last, len(ft) - 1) + 1):
            # the stretch's steps (midpoints lt + i d, i < n; d = duration / n) up to ft[b], less those up to ft[b-1]
            share = n if n == 1 else _steps_until(ft[b], lt[j], t_last, n) - (
                _steps_until(ft[b - 1], lt[j], t_last, n) if b else 0)
            if share <= 0:
                continue
            prev = out[b].get(key)
            P = per * share + (prev[6] if prev else 0.0)
            imp = (bool(a["log_impact"][j]) and b == first) or bool(prev and prev[7])
            out[b][key] = [*np.round(a["log_point"][j], 6).tolist(), *np.round(a["log_normal"][j], 6).tolist(),
                           float(f"{P:.6g}"), int(imp)]
    return [list(d.values()) for d in out]


def _steps_until(x: float, t0: float, t_last: float, n: int) -> int:
    """How many of n evenly spaced step midpoints t0 .. t_last lie at or before x."""
    if x < t0:
        return 0
    return min(n, int(np.floor((x - t0) / (t_last - t0) * (n - 1))) + 1)


def _view(model: Model, drawn: list, W: np.ndarray, col: dict):
    """(camera position, look_at, center, radius, up, half-spaces): the camera frames the sphere
    around the box that bounds every moving part at every frame of the replay (W: the frames'
    placements, col: frame id -> column of W)."""
    boxes = [corners(p.vertices, W[:, col[p.frame]] @ p.placement.homogeneous) for p in drawn if not p.static]
    pts = np.concatenate([b.reshape(-1, 3) for b in boxes]) if boxes else np.zeros((1, 3))
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
    return cam, look, center, radius, up, halfspaces


def initial_camera(traj: Trajectory | str | Path, model: Model | None = None, fps: float = DEFAULT_FPS, *,
                   colors: str = "link") -> dict:
    """The replay's initial camera: position and look_at [m], up, vertical fov [rad]."""
    traj = as_trajectory(traj)
    model = model or model_from_trajectory(traj)
    drawn = parts(traj, model, colors=colors)
    fids = sorted({p.frame for p in drawn if not p.static})
    W = frame_placements(model, traj.q[frame_indices(traj.t, fps)], fids)
    cam, look, _, _, up, _ = _view(model, drawn, W, {f: j for j, f in enumerate(fids)})
    return {"position": cam, "look_at": look, "up": up, "fov": FOV}


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
    W = frame_placements(model, traj.q[idx], fids)  # (frames, frame ids, 4, 4)
    col = {f: j for j, f in enumerate(fids)}
    cam, look, center, radius, up, halfspaces = _view(model, drawn, W, col)

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
        ic.position, ic.look_at, ic.fov = tuple(map(float, cam)), tuple(map(float, look)), FOV
        size = max(4 * radius, 2.0)
        for k, (n, d) in enumerate(halfspaces):
            M, half = ground_box(n, d, center, size)
            b = trimesh.creation.box(extents=2 * half)
            sc.add_mesh_simple(f"/statics/ground_{k}", b.vertices, b.faces, color=STATIC_COLOR, opacity=0.45,
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
        contacts = contacts_per_frame(traj, ft)
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
    reach = (traj.meta.get("model") or {}).get("gap_reach")
    if reach is not None:  # a gap per geometry, +inf where no partner is within the reach: drawn at the reach
        gmin = np.where(np.isposinf(gmin), float(reach), gmin)
    r = lambda x: [float(f"{v:.6g}") for v in np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)]  # noqa: E731
    meta = traj.meta
    data = {"scene": str((meta.get("scene") or {}).get("name") or model.scene.name),
            "description": str((meta.get("scene") or {}).get("description") or ""),
            "restitution": model.options.restitution, "dt": model.options.dt,
            "t": r(ft), "kinetic": r(T), "potential": r(V), "energy": r(T + V), "gap": r(gmin)}
    E = np.concatenate([data["kinetic"], data["potential"], data["energy"]])
    scale = float(np.max(np.abs(E))) if E.size else 0.0
    for key, values, span, zero in (("energy", E, max(1e-3 * scale, 1e-9), False),
                                    ("gap", data["gap"], 0.02 * radius, True)):  # radius >= 5 cm: span >= 1 mm
        lo, hi, a, b = axis(values, min_span=span, zero=zero)
        data[f"{key}_axis"], data[f"{key}_labels"] = [lo, hi], [a, b]
    return page, data


def page(traj: Trajectory | str | Path, model: Model | None = None, fps: float = DEFAULT_FPS, *,
         colors: str = "link", arrows: float = 0.8, shadows: bool = False) -> str:
    """The self-contained replay page: viser's client, the recorded scene, the energy/gap plot.
    `arrows`: length of the largest percussion's arrow, in units of the largest part's diagonal;
    `shadows`: the default lights cast shadows (off: lighter on software WebGL)."""
    traj = as_trajectory(traj)
    model = model or model_from_trajectory(traj)
    html, data = _record(traj, model, fps, colors, arrows, shadows)
    overlay = OVERLAY.replace("__MS_DATA__", js_string(data))
    title = f"<title>{_html.escape(data['scene'])} - moreau-sim replay</title>"
    html = re.sub(r"<title>.*?</title>", lambda m: title, html, count=1, flags=re.S)
    i = html.rindex("</body>")
    return html[:i] + overlay + html[i:]
