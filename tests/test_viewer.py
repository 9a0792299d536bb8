"""Browser replay (moreau_sim.viewer, docs/viewer.md): the model rebuilt from the NPZ alone, the
frames, and the page drawn for real by headless Chromium, served by `moreau-sim view` and opened
from an exported file. Chromium is required: without it these tests fail (never skip).

MOREAU_SIM_DOCS_IMG=1 also writes the screenshot docs/img/viewer_box_drop.png.
"""

from __future__ import annotations

import colorsys
import io
import os
import shutil
import subprocess
import sys
import time
import tomllib
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import moreau_sim as ms
from moreau_sim import viewer
from moreau_sim.viewer_cli import view

ROOT = Path(__file__).resolve().parents[1]
INSTALL = ("headless Chromium is required for the viewer tests: apt-get install -y chromium chromium-driver, "
           "and pip install selenium pillow")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--window-size=1000,650")


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


def test_scene_toml_round_trip():
    for path in sorted((ROOT / "scenes").glob("*.toml")):
        doc = tomllib.loads(path.read_text())
        assert tomllib.loads(viewer._toml_dumps(doc)) == doc, path.name


def test_model_from_trajectory_without_the_files(traj):
    model = viewer.model_from_trajectory(traj)
    assert (model.nq, model.nv) == (7, 6)
    assert model.scene.options.restitution == 0.4  # the run's, not the scene file's 0.5
    assert [g.name for g in model.geom.geometryObjects] == traj.meta["model"]["geometries"]
    X = viewer.frames(traj, model)
    assert X.shape == (len(traj.t), 2, 7)
    # the box's collision origin is its joint: its placement is q = [x y z qx qy qz qw]
    assert np.abs(X[:, 0, :3] - traj.q[:, :3]).max() < 1e-12
    assert np.abs(np.abs(np.einsum("ij,ij->i", X[:, 0, 3:], traj.q[:, 3:])) - 1).max() < 1e-12
    assert np.abs(X[:, 1] - X[0, 1]).max() == 0  # the ground does not move


def test_scene_data_frames_and_contacts(traj):
    d = viewer.scene_data(traj, fps=100)
    assert [g["type"] for g in d["geometries"]] == ["box", "halfspace"]
    assert d["geometries"][0]["size"] == pytest.approx([0.2, 0.2, 0.4])
    assert d["moving"] == [0] and len(d["poses"]) == len(d["t"]) == 61  # 0.6 s at 100 frames/s
    assert d["t"][0] == 0.0 and d["t"][-1] == pytest.approx(0.6)
    # every logged percussion lands in exactly one frame: the one whose interval holds its time
    assert sum(c[6] for f in d["contacts"] for c in f) == pytest.approx(traj.log_P.sum(), rel=1e-5)
    t_hit = float(traj.log_t[traj.log_impact][0])
    f = int(np.searchsorted(d["t"], t_hit))
    assert d["t"][f - 1] < t_hit <= d["t"][f]
    assert any(c[7] for c in d["contacts"][f]) and not any(d["contacts"][f - 1])
    assert len(viewer.scene_data(traj, fps=0)["t"]) == len(traj.t)


def test_articulated_bodies_get_their_links():
    """pendulum_wall's collision geometry is its two bobs: the page also draws the links."""
    tr = ms.run(ROOT / "scenes/pendulum_wall.toml", duration=0.01)
    d = viewer.scene_data(tr)
    assert [g["type"] for g in d["geometries"]] == ["sphere", "sphere", "box"]
    seg = np.reshape(d["sticks"][0], (-1, 2, 3))  # pivot -> elbow, pivot -> bob 1, elbow -> bob 2
    assert np.allclose(seg[0], [[0, 0, 1.2], [-0.5, 0, 1.2]]) and np.allclose(seg[-1, 1], [-1.0, 0, 1.2])
    assert viewer.scene_data(ms.run(ROOT / "scenes/box_drop.toml", duration=0.01))["sticks"] is None


def test_cli_export_and_errors(npz, tmp_path):
    r = CliRunner().invoke(view, [str(npz), "--export", str(tmp_path / "r.html")])
    assert r.exit_code == 0, r.output
    html = (tmp_path / "r.html").read_text()
    assert "box_drop" in html and "http://" not in html and "https://" not in html  # nothing fetched
    r = CliRunner().invoke(view, [str(tmp_path / "missing.npz"), "--export", str(tmp_path / "x.html")])
    assert r.exit_code == 2 and "missing.npz" in r.output


# --- the page, drawn by headless Chromium ------------------------------------------------------

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
    drv = webdriver.Chrome(service=Service(driver), options=opts)
    drv.set_page_load_timeout(30)
    yield drv
    drv.quit()


def _hues(img, lo: float, hi: float, sat: float = 0.5) -> int:
    """Pixels whose hue [deg] is in [lo, hi] (wrapping through 0 if lo > hi) and saturation >= sat."""
    a = np.asarray(img.convert("RGB"), float).reshape(-1, 3) / 255
    mx, mn = a.max(1), a.min(1)
    s = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0)
    h = np.array([colorsys.rgb_to_hsv(*p)[0] * 360 for p in a[s >= sat]])
    if not len(h):
        return 0
    return int(np.count_nonzero((h >= lo) & (h <= hi) if lo <= hi else (h >= lo) | (h <= hi)))


def _load(drv, url):
    from PIL import Image
    from selenium.webdriver.support.ui import WebDriverWait

    drv.get(url)
    WebDriverWait(drv, 30).until(lambda d: d.execute_script(
        "return !!window.viewer && (window.viewer.ready || !!window.viewer.error)"))
    assert drv.execute_script("return window.viewer.error") is None
    return lambda: Image.open(io.BytesIO(drv.get_screenshot_as_png())).convert("RGB")


def _check_replay(drv, url, t_hit, save: Path | None = None):
    shot = _load(drv, f"{url}#t={t_hit}&contacts=1&play=0")
    img = shot()
    colours = len(np.unique(np.asarray(img).reshape(-1, 3), axis=0))
    box = _hues(img, 15, 35)       # the box, #e07b39 shaded
    red = _hues(img, 350, 8, 0.6)  # the new-impact marker and arrow, #e0202a shaded
    assert colours > 200, f"blank page? {colours} colours"
    assert box > 2000, f"the box is not drawn ({box} orange pixels)"
    assert red > 150, f"the impact percussion is not drawn ({red} red pixels)"
    assert drv.execute_script("return window.viewer.contactsShown") >= 1
    if save:
        save.parent.mkdir(parents=True, exist_ok=True)
        img.save(save)
    drv.find_element("id", "contacts").click()  # the toggle hides contacts and arrows
    time.sleep(0.2)
    img = shot()
    assert drv.execute_script("return window.viewer.contactsShown") == 0
    off = _hues(img, 350, 8, 0.6)  # only the red x axis at the origin is left
    assert off < 60 and red > off + 150 and _hues(img, 15, 35) > 2000
    frame = drv.execute_script("return window.viewer.frame")
    drv.find_element("id", "play").click()  # plays on from the impact
    time.sleep(0.5)
    assert drv.execute_script("return window.viewer.frame") > frame
    drv.find_element("id", "play").click()


def test_served_replay_in_chromium(npz, traj, browser):
    t_hit = float(traj.log_t[traj.log_impact][0])
    proc = subprocess.Popen([sys.executable, "-u", "-m", "moreau_sim.viewer_cli", str(npz), "--port", "0",
                             "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("serving "), (line, proc.stderr.read() if proc.poll() is not None else "")
        url = line.split(" at ")[1].split()[0]
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.headers["Content-Type"].startswith("text/html") and b"box_drop" in r.read()
        save = ROOT / "docs/img/viewer_box_drop.png" if os.environ.get("MOREAU_SIM_DOCS_IMG") else None
        _check_replay(browser, url, t_hit, save)
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_exported_replay_from_file_in_chromium(traj, browser, tmp_path):
    path = viewer.export_html(traj, tmp_path / "replay.html")
    _check_replay(browser, path.as_uri(), float(traj.log_t[traj.log_impact][0]))
