"""Browser replay (moreau_sim.viewer, docs/viewer.md): the model rebuilt from the NPZ alone, what is
drawn (visual meshes, collision geometry where a link has none), the files a stored scene may
name, scene text escaping, the CLI, Pinocchio's visualizers on the helper's geometry, and the
exported pages of box_drop, solo_drop and the MJCF pendulum drawn by headless Chromium, with their
screenshots checked. Chromium is required: without it these tests fail (never skip).

Screenshots are written to out/viewer/; MOREAU_SIM_DOCS_IMG=1 also writes docs/img/viewer_box_drop.png,
docs/img/viewer_solo_drop.png and docs/img/viewer_mjcf_example.png.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from click.testing import CliRunner

import moreau_sim as ms
from moreau_sim import viewer
from moreau_sim.cli.viewer import view
from moreau_sim.errors import SceneError

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "viewer"
INSTALL = ("headless Chromium is required for the viewer tests: apt-get install -y chromium chromium-driver, "
           "and pip install selenium pillow")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--window-size=900,600")
NASTY = "box</title><!--<script>alert(1)</script>\u2028'\"&"


@pytest.fixture(scope="module")
def npz(tmp_path_factory) -> Path:
    """box_drop for 0.6 s (three corner impacts), simulated from copies of its scene and URDF that
    are deleted before the viewer sees the NPZ."""
    d = tmp_path_factory.mktemp("viewer")
    (d / "scenes").mkdir()
    (d / "models").mkdir()
    shutil.copy(ROOT / "scenes/box_drop.toml", d / "scenes")
    shutil.copy(ROOT / "models/box.urdf", d / "models")
    path = ms.run(d / "scenes/box_drop.toml", duration=0.6, restitution=0.4).save(d / "box_drop.npz")
    shutil.rmtree(d / "scenes")
    shutil.rmtree(d / "models")
    return path


@pytest.fixture(scope="module")
def traj(npz):
    return ms.load_trajectory(npz)


@pytest.fixture(scope="module")
def mjcf():
    """The MJCF pendulum (scenes/mjcf_example.toml) swinging into its wall: 0.8 s, past its first impact."""
    return ms.run(ROOT / "scenes/mjcf_example.toml", duration=0.8)


# models/pendulum.xml's colours (rgba 0-1 -> 0-255): the bracket's and axle's rgba (visual-only
# geoms), the rod's material "steel", the bob's rgba
MJCF_COLORS = {"bracket": (76, 76, 76), "rod": (89, 115, 153), "bob": (217, 76, 38), "axle": (230, 191, 51)}


@pytest.fixture(scope="module")
def solo():
    return ms.run(ROOT / "scenes/solo_drop.toml", duration=0.5)


def test_model_from_trajectory_without_the_files(traj):
    model = viewer.model_from_trajectory(traj)
    assert (model.nq, model.nv) == (7, 6)
    assert model.scene.options.restitution == 0.4  # the run's, not the scene file's 0.5
    assert [g.name for g in model.geom.geometryObjects] == traj.meta["model"]["geometries"]
    X = viewer.frames(traj, model)
    assert X.shape == (len(traj.t), 2, 7)
    assert np.abs(X[:, 0, :3] - traj.q[:, :3]).max() < 1e-12
    assert np.abs(X[:, 1] - X[0, 1]).max() == 0  # the ground does not move


def test_contacts_per_frame(traj):
    idx = viewer.frame_indices(traj.t, 100)
    ft = traj.t[idx]
    assert len(ft) == 61 and ft[-1] == pytest.approx(0.6)
    c = viewer.contacts_per_frame(traj, ft)
    # every logged percussion lands in exactly one frame: the one whose interval holds its time
    assert sum(x[6] for f in c for x in f) == pytest.approx(traj.log_P.sum(), rel=1e-5)
    t_hit = float(traj.log_t[traj.log_impact][0])
    f = int(np.searchsorted(ft, t_hit))
    assert any(x[7] for x in c[f]) and not any(c[f - 1])


def test_a_rest_shows_in_every_frame_it_spans():
    """A ball that comes to rest (zeno_ball, e = 0): its rest is one log row (a stretch of persistent steps,
    docs/theory.md §5.2), and the replay gives every frame of the rest the contact with its steps' share, the
    weight times the frame's time; the frames' shares sum to the row's percussion."""
    tr = ms.run(ROOT / "scenes/zeno_ball.toml", restitution=0.0, duration=0.5)
    rest = int(np.argmax(tr.log_steps))
    assert tr.log_steps[rest] > 100
    ft = tr.t[viewer.frame_indices(tr.t, 26)]
    c = viewer.contacts_per_frame(tr, ft)
    assert sum(x[6] for f in c for x in f) == pytest.approx(tr.log_P.sum(), rel=1e-5)
    h = tr.meta["options"]["dt"]
    weight = tr.log_P[rest] / tr.log_duration[rest]  # [N]: m g
    for i in range(1, len(ft)):
        if ft[i - 1] > tr.log_t[rest]:  # a frame inside the rest
            assert len(c[i]) == 1 and abs(c[i][0][6] - weight * (ft[i] - ft[i - 1])) <= 1.01 * weight * h


def test_parts_box_and_solo(traj, solo):
    box = viewer.parts(traj)
    assert [(p.source, p.static) for p in box] == [("collision", False)]  # box.urdf has no <visual>
    assert np.ptp(box[0].vertices, axis=0) == pytest.approx([0.2, 0.2, 0.4])
    ps = viewer.parts(solo)
    assert len(ps) == 13 and {p.source for p in ps} == {"visual"}  # solo's 13 OBJ visual meshes
    assert min(len(p.faces) for p in ps) > 100  # real meshes, not boxes
    links = {p.link: p.color for p in ps}
    assert len(links) == 13 and len(set(links.values())) >= 9  # a colour per link (10-colour palette)
    grey = {p.color for p in viewer.parts(solo, colors="model")}
    assert grey == {(204, 204, 204)}  # the URDF's material "grey" 0.8


def test_parts_mjcf_from_the_visual_model(mjcf, tmp_path):
    model = viewer.model_from_trajectory(mjcf)
    collision = {go.name for go in model.geom.geometryObjects}
    assert collision == {"pendulum/rod", "pendulum/bob", "wall"}  # the axle and the bracket are visual only
    for t in (mjcf, _without_files(mjcf, tmp_path)):  # the original model file, or the NPZ's copy of it
        ps = viewer.parts(t, colors="model")
        vis = [p for p in ps if p.source == "visual"]
        assert [p.source for p in ps] == ["visual"] * 4 + ["collision"]  # the wall is a static
        assert sorted(p.color for p in vis) == sorted(MJCF_COLORS.values())
        assert {p.link for p in vis} == {"pendulum/universe", "pendulum/link"}
        assert len({p.color for p in viewer.parts(t)}) == 3  # colors="link": one per link, statics grey
    # the visual rod and bob sit where the collision rod and bob are, at every frame (pin's placements)
    gdata, data = model.geom.createData(), model.pin.createData()
    by_color = {p.color: p for p in viewer.parts(mjcf, colors="model")}
    for k in (0, 300, 700):
        pin.framesForwardKinematics(model.pin, data, mjcf.q[k])
        pin.updateGeometryPlacements(model.pin, data, model.geom, gdata, mjcf.q[k])
        for name in ("rod", "bob"):
            p = by_color[MJCF_COLORS[name]]
            world = data.oMf[p.frame] * p.placement
            g = model.geom.getGeometryId(f"pendulum/{name}")
            np.testing.assert_allclose(world.homogeneous, gdata.oMg[g].homogeneous, atol=1e-14)
    bracket = by_color[MJCF_COLORS["bracket"]]  # on the world body: the scene's fixed root placement
    assert bracket.frame == 0 and bracket.placement.translation == pytest.approx([0, 0, 1.05], abs=1e-15)


def _without_files(traj, tmp_path):
    """`traj` as if its scene and model files had moved away: the NPZ's stored texts only."""
    t = ms.Trajectory(traj.arrays, json.loads(json.dumps(traj.meta)))
    t.meta["scene"]["path"] = str(tmp_path / "gone" / "mjcf_example.toml")
    return t


def test_mjcf_visual_that_does_not_load_falls_back_to_collision(tmp_path):
    (tmp_path / "models").mkdir()
    text = (ROOT / "models/pendulum.xml").read_text().replace(
        '<asset>', '<asset>\n    <mesh name="gone" file="gone.stl"/>').replace(
        '<body name="link" pos="0 0 0">', '<body name="link" pos="0 0 0">\n      <geom type="mesh" mesh="gone" '
        'contype="0" conaffinity="0" mass="0"/>')
    (tmp_path / "models/pendulum.xml").write_text(text)
    (tmp_path / "scene.toml").write_text((ROOT / "scenes/mjcf_example.toml").read_text().replace(
        "../models/pendulum.xml", "models/pendulum.xml"))
    t = ms.run(tmp_path / "scene.toml", duration=0.01)
    assert [(p.name, p.source) for p in viewer.parts(t)] == [
        ("pendulum/link/collision_0", "collision"), ("pendulum/link/collision_1", "collision"),
        ("wall/collision_2", "collision")]


def test_ground_box():
    M, half = viewer.ground_box([0, 0, 1], 0.0, [0.3, -0.2, 5.0], 4.0)
    assert half == pytest.approx([2, 2, 0.02])
    assert M.translation == pytest.approx([0.3, -0.2, -0.02])  # top face on z = 0, under the centre


@pytest.fixture(scope="module")
def stack():
    return ms.run(ROOT / "scenes/box_stack_5.toml")  # 2 s: the stack stands, then its top cubes shift


@pytest.fixture(scope="module")
def panda():
    return ms.run(ROOT / "scenes/panda_table.toml", duration=0.6)


def _world_vertices(t, k, p, model, data):
    pin.framesForwardKinematics(model.pin, data, t.q[k])
    M = data.oMf[p.frame] * p.placement
    return p.vertices.astype(float) @ M.rotation.T + M.translation


@pytest.mark.parametrize("name", ["stack", "panda", "traj", "mjcf"])
def test_camera_frames_every_body_over_the_run(name, request):
    """Every vertex of every moving part, at every frame of the replay, is seen by the initial
    camera within FILL of its vertical field of view (so within the view at any aspect wider than
    tall): box_stack_5's top cube included."""
    t = request.getfixturevalue(name)
    model = viewer.model_from_trajectory(t)
    cam = viewer.initial_camera(t, model)
    assert cam["fov"] == viewer.camera_fov
    axis = (cam["look_at"] - cam["position"]) / np.linalg.norm(cam["look_at"] - cam["position"])
    data = model.pin.createData()
    worst = 0.0
    moving = [p for p in viewer.parts(t, model) if not p.static]
    for k in viewer.frame_indices(t.t):
        for p in moving:
            v = _world_vertices(t, k, p, model, data) - cam["position"]
            cos = v @ axis / np.linalg.norm(v, axis=1)
            worst = max(worst, float(np.arccos(np.clip(cos, -1, 1)).max()))
    assert worst <= viewer.camera_fill * cam["fov"] / 2 + 1e-9, f"a body leaves the view ({np.degrees(worst):.1f} deg)"
    assert worst > 0.3 * cam["fov"] / 2  # and the scene is not lost in the distance


def _plot_data(html: str) -> dict:
    return json.loads(html[html.index("const D = ") + len("const D = "):html.index(";\nwindow.moreauReplay")])


@pytest.mark.parametrize("values", [[-5e-12] * 4, [-5.0e-12, -4.96e-12], [0.0], [], [float("nan")], [12.3] * 3,
                                    [1e6, 1e6 + 1e-3], [0.0, 0.09479]])
def test_plot_axis_is_never_degenerate(values):
    for zero in (False, True):
        lo, hi, a, b = viewer.overlay.axis(values, min_span=1e-3, zero=zero)
        assert hi - lo >= 1e-3 * (1 - 1e-12) and a != b, (values, lo, hi, a, b)
        assert all(lo <= v <= hi for v in values if v == v)
        if zero:
            assert lo <= 0 <= hi


def test_replay_plot_axes_of_a_resting_stack(stack):
    """box_stack_5's smallest gap stays at -5e-12 m for 1.5 s (its axis read -5.0e-12 at both ends)."""
    d = _plot_data(viewer.page(stack))
    for key in ("energy", "gap"):
        (lo, hi), (a, b) = d[f"{key}_axis"], d[f"{key}_labels"]
        assert lo < hi and a != b and lo <= min(d[key]) and max(d[key]) <= hi
    assert d["gap_axis"][0] < 0 < d["gap_axis"][1]


def test_panda_drawn_from_its_visual_meshes(panda):
    """panda_arm_collision.urdf names example-robot-data's visual meshes: every link is drawn from
    them (none also from its collision spheres, the fixed link0 included), and no rod."""
    ps = viewer.parts(panda)
    links = {p.link for p in ps if p.source == "visual"}
    assert len(links) == 11 and min(len(p.faces) for p in ps if p.source == "visual") > 500
    assert [p.name for p in ps if p.source == "collision"] == ["table/collision_39"]  # the table only
    model = viewer.model_from_trajectory(panda)
    assert viewer.rods(panda, model) is None


def test_rods_only_where_the_geometry_leaves_a_link_unseen(panda, tmp_path):
    """Drawn from its collision shapes (the visuals removed), the Panda gets no rods: its shapes
    cover its joints. The double pendulum (its bobs only) keeps its three."""
    t = ms.Trajectory(panda.arrays, json.loads(json.dumps(panda.meta)))
    urdf = t.meta["scene"]["urdf"]["panda"]
    t.meta["scene"]["urdf"]["panda"] = re.sub(r"<visual>\s*<(geometry|origin)\b.*?</visual>", "", urdf, flags=re.S)
    assert {p.source for p in viewer.parts(t) if not p.static} == {"collision"}
    assert viewer.rods(t, viewer.model_from_trajectory(t)) is None
    pendulum = ms.run(ROOT / "scenes/pendulum_wall.toml", duration=0.05)
    assert viewer.rods(pendulum, viewer.model_from_trajectory(pendulum)).shape == (len(pendulum.t), 3, 2, 3)


def test_crafted_npz_reads_no_other_file(traj, tmp_path):
    visual = '<visual><geometry><mesh filename="{}"/></geometry></visual></link>'
    for new in [visual.format(u) for u in ("/etc/passwd", "file:///etc/hostname.obj", "~/a.obj",
                                             "package://x/../../../etc/passwd.obj", "../../a.stl")] + \
               ['<compiler meshdir="/etc"/></link>']:  # MJCF's folder attributes too
        bad = ms.Trajectory(traj.arrays, json.loads(json.dumps(traj.meta)))
        bad.meta["scene"]["urdf"]["box"] = bad.meta["scene"]["urdf"]["box"].replace("</link>", new, 1)
        with pytest.raises(SceneError, match="reads only files"):
            viewer.model_from_trajectory(bad)
        path = bad.save(tmp_path / "bad.npz")
        r = CliRunner().invoke(view, [str(path), "-o", str(tmp_path / "bad.html")])
        assert r.exit_code == 2 and "reads only files" in r.output and not (tmp_path / "bad.html").exists()


def test_scene_text_is_escaped(traj):
    t = ms.Trajectory(traj.arrays, json.loads(json.dumps(traj.meta)))
    t.meta["scene"]["name"] = NASTY
    t.meta["scene"]["description"] = NASTY + " -->"
    page = viewer.page(t)
    overlay = page[page.rindex('<div id="ms-panel">'):]
    assert "<!--" not in overlay and "alert(1)</script>" not in overlay and "\u2028" not in overlay
    assert page.count("</title>") == 1 and "&lt;!--&lt;script&gt;" in page


def test_cli_out_export_alias_and_errors(npz, tmp_path):
    r = CliRunner().invoke(view, [str(npz), "-o", str(tmp_path / "r.html")])
    assert r.exit_code == 0, r.output
    html = (tmp_path / "r.html").read_text()
    assert "box_drop" in html and "__VISER_EMBED_DATA__" in html
    r = CliRunner().invoke(view, [str(npz), "--export", str(tmp_path / "old.html")])  # hidden alias
    assert r.exit_code == 0 and (tmp_path / "old.html").exists()
    assert "--export" not in CliRunner().invoke(view, ["--help"]).output
    r = CliRunner().invoke(view, [str(tmp_path / "missing.npz"), "-o", str(tmp_path / "x.html")])
    assert r.exit_code == 2 and "missing.npz" in r.output


def test_pinocchio_viser_visualizer_draws_the_helper_geometry(traj):
    from pinocchio.visualize import ViserVisualizer

    model = viewer.model_from_trajectory(traj)
    with contextlib.redirect_stdout(io.StringIO()):
        with pytest.raises(RuntimeError, match="Halfspace"):  # what users meet without the helper
            v = ViserVisualizer(model.pin, model.geom, model.geom)
            v.initViewer(open=False)
            try:
                v.loadViewerModel()
            finally:
                v.viewer.stop()
        geom = viewer.drawable_geometry(model)
        v = ViserVisualizer(model.pin, geom, geom)
        v.initViewer(open=False)
        v.loadViewerModel()
        v.display(traj.q[-1])
        v.viewer.stop()
    ground = geom.geometryObjects[1]
    assert ground.geometry.halfSide == pytest.approx([5, 5, 0.05]) and ground.placement.translation[2] == -0.05


def test_served_page(npz):
    proc = subprocess.Popen([sys.executable, "-u", "-m", "moreau_sim.cli", "view", str(npz), "--port", "0",
                             "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("serving "), (line, proc.stderr.read() if proc.poll() is not None else "")
        url = line.split(" at ")[1].split()[0]
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as r:
            body = r.read()
            assert r.headers["Content-Type"].startswith("text/html") and b"__VISER_EMBED_DATA__" in body
        with pytest.raises(urllib.error.HTTPError):  # nothing but the page is served
            urllib.request.urlopen(url + "etc/passwd", timeout=10)
    finally:
        proc.terminate()
        proc.wait(timeout=10)


# --- the exported pages, drawn by headless Chromium ---------------------------------------------

@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or "/usr/bin/chromedriver"
    if not chromium or not os.path.exists(driver):
        pytest.fail(f"{INSTALL} (chromium: {chromium}, chromedriver: {driver} not found)")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.fail(INSTALL + " (selenium is missing)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for a in FLAGS + (f"--user-data-dir={tmp_path_factory.mktemp('chromium')}",):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(driver), options=opts)
    drv.set_page_load_timeout(60)
    yield drv
    drv.quit()


def _hsv(img) -> np.ndarray:
    """Per pixel (hue [deg], saturation, value)."""
    a = np.asarray(img.convert("RGB"), float) / 255
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    mx, mn = a.max(-1), a.min(-1)
    d = mx - mn
    dd = np.maximum(d, 1e-9)
    h = np.where(mx == r, ((g - b) / dd) % 6, np.where(mx == g, (b - r) / dd + 2, (r - g) / dd + 4)) * 60
    return np.stack([np.where(d > 0, h, 0), np.where(mx > 0, d / np.maximum(mx, 1e-9), 0), mx], -1)


def _hue_count(hsv, lo, hi, sat=0.35, val=0.25) -> int:
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    inside = (h >= lo) & (h <= hi) if lo <= hi else (h >= lo) | (h <= hi)
    return int(np.count_nonzero(inside & (s >= sat) & (v >= val)))


# [s] how long a page may take to load and start playing before the test calls it hung: a guard, not a speed test (a
# robot's meshes in Chromium beside the slow job's other heavy tests on 2 cores took over a minute, stop 51's CI)
HANG = 240


class Page:
    """An exported replay open in Chromium: seek with the slider, screenshot the 3D view."""

    def __init__(self, drv, path: Path):
        from selenium.webdriver.support.ui import WebDriverWait

        self.drv = drv
        drv.get_log("browser")  # drop earlier entries
        drv.get(path.as_uri())
        WebDriverWait(drv, HANG).until(lambda d: d.execute_script(
            "return !!window.moreauReplay && (window.moreauReplay.ready || !!window.moreauReplay.error)"))
        assert drv.execute_script("return window.moreauReplay.error") is None
        time.sleep(1.0)  # the loading screen fades out
        drv.execute_script("document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())")
        WebDriverWait(drv, HANG).until(lambda d: self.t() > 0, "the replay does not play")
        drv.execute_script("document.querySelector('.mantine-Slider-root').parentElement.querySelector('button').click()")
        seen = [self.t()]  # paused: the time stops
        WebDriverWait(drv, HANG, 0.3).until(lambda d: seen.append(self.t()) or seen[-1] == seen[-2])
        self.duration = float(drv.execute_script(
            "return parseFloat(document.querySelector('[role=slider]').getAttribute('aria-valuemax'))"))

    def t(self) -> float:
        """The playback time shown by viser's slider."""
        return float(self.drv.execute_script(
            "return parseFloat(document.querySelector('[role=slider]').getAttribute('aria-valuenow'))"))

    def seek(self, t: float, tol: float = 0.003) -> None:
        """Click viser's slider where time `t` is (corrected by what it then reads), wait for the frame."""
        from selenium.common.exceptions import TimeoutException
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.support.ui import WebDriverWait

        track = self.drv.find_element("css selector", ".mantine-Slider-root")
        w = track.rect["width"]
        x = (t / self.duration - 0.5) * w
        for _ in range(4):
            before = self.t()
            ActionChains(self.drv).move_to_element_with_offset(track, int(round(x)), 0).click().perform()
            with contextlib.suppress(TimeoutException):
                WebDriverWait(self.drv, 3, 0.1).until(lambda d, b=before: self.t() != b)
            now = self.t()
            if abs(now - t) < tol:
                break
            x = min(max(x + (t - now) / self.duration * w, -0.5 * w + 1), 0.5 * w - 1)
        assert self.t() == pytest.approx(t, abs=tol)
        WebDriverWait(self.drv, 20).until(lambda d: d.execute_script("return window.moreauReplay.t") == self.t())
        time.sleep(0.4)  # the frame is drawn

    def shot(self):
        """(screenshot, HSV of the 3D view without the plot panel and the playback bar)."""
        from PIL import Image

        img = Image.open(io.BytesIO(self.drv.get_screenshot_as_png())).convert("RGB")
        panel = self.drv.execute_script("const r = document.getElementById('ms-panel').getBoundingClientRect();"
                                        "return [r.left, r.top, r.right, r.bottom]")
        bar = self.drv.execute_script(
            "return document.querySelector('.mantine-Slider-root').getBoundingClientRect().top")
        a = np.asarray(img).copy()
        x0, y0, x1, y1 = (int(v) for v in panel)
        a[max(y0 - 2, 0):y1 + 2, max(x0 - 2, 0):x1 + 2] = 255
        a[int(bar) - 20:] = 255
        return img, _hsv(Image.fromarray(a).reduce(2))  # half resolution: counts are per 4 pixels

    def errors(self) -> list:
        return [e for e in self.drv.get_log("browser") if e["level"] == "SEVERE"]


def _save(img, name):
    OUT.mkdir(parents=True, exist_ok=True)
    img.save(OUT / name)
    if os.environ.get("MOREAU_SIM_DOCS_IMG"):
        img.save(ROOT / "docs/img" / name)


def test_box_drop_replay_in_chromium(traj, browser, tmp_path):
    t = ms.Trajectory(traj.arrays, json.loads(json.dumps(traj.meta)))
    t.meta["scene"]["description"] = NASTY + " -->"  # hidden until hovered: the screenshot is unchanged
    path = viewer.export_html(t, tmp_path / "box_drop.html")
    p = Page(browser, path)
    assert browser.execute_script("return document.getElementById('ms-desc').textContent") == NASTY + " -->"
    ft = traj.t[viewer.frame_indices(traj.t, 100)]
    t_hit = float(traj.log_t[traj.log_impact][0])
    f = int(np.searchsorted(ft, t_hit))
    p.seek(0.02)
    assert p.t() == pytest.approx(0.02, abs=0.01)
    early, hsv0 = p.shot()
    assert _hue_count(hsv0, 15, 35) > 800, "the box is not drawn"
    p.seek(0.5 * (ft[f] + ft[f + 1]))  # the first impact's frame: its arrows
    img, hsv = p.shot()
    _save(img, "viewer_box_drop.png")
    assert p.t() == pytest.approx(0.5 * (ft[f] + ft[f + 1]), abs=0.004)
    assert _hue_count(hsv, 15, 35) > 800
    red = _hue_count(hsv, 330, 8, 0.15, 0.5)  # the impact arrow, red, seen through the grey ground
    assert red > 15 and _hue_count(hsv0, 330, 8, 0.15, 0.5) < 5, f"the impact arrow is not drawn ({red} pixels)"
    moved = np.abs(np.asarray(early, float) - np.asarray(img, float)).sum(-1) > 60
    assert moved.sum() > 2000, "the slider does not move the box"
    _save(img, "viewer_box_drop.png")
    assert p.errors() == []


@pytest.mark.slow  # (a robot's meshes in the browser: tens of seconds)
def test_solo_drop_replay_in_chromium(solo, browser, tmp_path):
    path = viewer.export_html(solo, tmp_path / "solo_drop.html")
    p = Page(browser, path)
    p.seek(0.05)
    early, hsv0 = p.shot()
    p.seek(0.45)
    img, hsv = p.shot()
    coloured = int(np.count_nonzero((hsv[..., 1] >= 0.3) & (hsv[..., 2] >= 0.25)))
    assert coloured > 1500, f"solo is not drawn ({coloured} coloured pixels)"
    assert _hue_count(hsv, 15, 35) > 100 and _hue_count(hsv, 195, 225) > 30  # the body's and a leg's colour
    moved = np.abs(np.asarray(early, float) - np.asarray(img, float)).sum(-1) > 60
    assert moved.sum() > 1500, "the slider does not move solo"
    _save(img, "viewer_solo_drop.png")
    assert p.errors() == []


def test_mjcf_pendulum_replay_in_chromium(mjcf, browser, tmp_path):
    path = viewer.export_html(mjcf, tmp_path / "mjcf_example.html", colors="model")
    p = Page(browser, path)
    p.seek(0.05)
    early, hsv0 = p.shot()
    p.seek(0.5)
    img, hsv = p.shot()
    _save(img, "viewer_mjcf_example.png")
    bob, rod, axle = _hue_count(hsv, 5, 22), _hue_count(hsv, 205, 228, 0.25), _hue_count(hsv, 40, 52)
    assert bob > 150, f"the bob (rgba of its geom) is not drawn ({bob} pixels)"  # counts per 4 pixels
    assert rod > 60, f"the rod (its material's rgba) is not drawn ({rod} pixels)"
    assert axle > 15, f"the axle (a visual-only geom) is not drawn ({axle} pixels)"
    moved = np.abs(np.asarray(early, float) - np.asarray(img, float)).sum(-1) > 60
    assert moved.sum() > 1500, "the slider does not move the pendulum"
    assert p.errors() == []


def test_box_stack_5_replay_in_chromium(stack, browser, tmp_path):
    """The top cube (the palette's yellow) is drawn whole: no subject pixel on the top edge of the view."""
    p = Page(browser, viewer.export_html(stack, tmp_path / "box_stack_5.html"))
    p.seek(1.0, tol=0.02)
    img, hsv = p.shot()
    _save(img, "viewer_box_stack_5.png")
    assert _hue_count(hsv, 40, 52) > 300, "the top cube is not drawn"
    coloured = (hsv[..., 1] >= 0.3) & (hsv[..., 2] >= 0.25)
    assert not coloured[:3].any() and not coloured[:, :3].any() and not coloured[:, -3:].any(), "the view crops a cube"
    assert p.errors() == []


@pytest.mark.slow  # (a robot's meshes in the browser: tens of seconds)
def test_panda_table_replay_in_chromium(panda, browser, tmp_path):
    p = Page(browser, viewer.export_html(panda, tmp_path / "panda_table.html"))
    p.seek(0.5, tol=0.02)
    img, hsv = p.shot()
    _save(img, "viewer_panda_table.png")
    coloured = (hsv[..., 1] >= 0.3) & (hsv[..., 2] >= 0.25)
    # measured 1448 px since joint limits (the elbow strikes its limit: the arm lies flatter on the table)
    assert coloured.sum() > 1200, "the arm is not drawn"
    assert not coloured[:3].any() and not coloured[:, :3].any() and not coloured[:, -3:].any()
    assert p.errors() == []


def test_replay_gap_of_a_scene_without_a_pair_list(monkeypatch):
    """A gap per geometry (a scene without a pair list) is +inf where no partner is within the reach: the replay's
    smallest-gap curve draws it at the reach, never a 0 (contact) nor a non-finite value in its JSON."""
    from test_record_gaps import _two_beads

    from moreau_sim import broad_phase

    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 0)
    monkeypatch.setattr(broad_phase, "MIN_PAIRS", 0)
    model = ms.build_model(_two_beads(0.11, ground=False).with_options(duration=0.01))
    traj = ms.simulate(model, progress=False)
    assert np.isposinf(traj.gap).all()
    d = _plot_data(viewer.page(traj))
    assert d["gap"] and all(g == model.gap_reach for g in d["gap"])
