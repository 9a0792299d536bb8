"""The stress suite side by side: every stress scene in moreau-sim (its default options
and the plain scheme: position_correction = "none", bias = "explicit") and, where the peer can
express it, in MuJoCo, PyBullet (default and tuned configs) and Siconos; one row per scene with
the scene's own metric and pass bound; writes out/stability.json and its plots (out/img/), or
docs/bench/stability.json and docs/img/ with --out docs/bench; --table rewrites the generated
parts of docs/stability.md (between its markers) from the JSON. The page's prose (causes, the
tunnelling fix, the scenes' parameters) is written by hand in docs/stability.md.

    pip install -e '.[peers]'; apt-get install -y python3-siconos   # the peers (optional)
    python -m benchmarks.stability            # everything (~4 min), into out/
    python -m benchmarks.stability --out docs/bench   # regenerate the committed JSON and plots
    python -m benchmarks.stability --table docs/bench/stability.json docs/stability.md
    python -m benchmarks.stability --quick --no-peers --out /tmp/stability        # smoke test
    python -m benchmarks.stability --write-scenes        # regenerate the generated scene files

Every method's energy and gaps are measured by moreau-sim's own functions (Pinocchio energies,
coal signed distances of the scene's collision pairs) from the configurations it produced, so a
number means the same thing in every column. Peers run the neutral spec of benchmarks.spec
(spheres and boxes on free or slide joints, half-space and box statics) with their runners'
defaults (benchmarks.peers); "n/a" marks what a peer cannot express (the reason is in the notes).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim.energy import kinetic, potential
from moreau_sim.options import Options, RootJoint
from moreau_sim.recording import versions
from moreau_sim.testing.references import ZENO_GAP, G, cradle_simultaneous, zeno_rest_bound, zeno_time

from . import OUT, REPO, add_table_option, peers, pyplot, rewrite_tables, scene_path
from .spec import to_jsonable

PLAIN = {"position_correction": "none", "bias": "explicit"}
METHODS = ("moreau-sim", "moreau-sim plain", "mujoco", "pybullet-default", "pybullet-tuned", "siconos")
PEER_OF = {"mujoco": ("mujoco", {}), "pybullet-default": ("pybullet", {"config": "default"}),
           "pybullet-tuned": ("pybullet", {"config": "tuned"}), "siconos": ("siconos", {})}


# ------------------------------------------------------------------------------------ runs
@dataclass
class Run:
    """What a method produced, in moreau-sim's coordinates of `model`: t, q, u; E = T + V [J];
    gap (samples x pairs) [m]; P_max: the largest logged percussion [N s] (moreau-sim only);
    impacts_after(t): new impacts after t (moreau-sim only); cpu [s]."""

    model: object
    t: np.ndarray
    q: np.ndarray
    u: np.ndarray
    E: np.ndarray
    gap: np.ndarray
    cpu: float
    traj: object = None
    error: str | None = None
    settings: dict = field(default_factory=dict)

    def impacts_after(self, t0: float) -> int:
        if self.traj is None:
            return 0
        return int(np.sum(self.traj.log_impact & (self.traj.log_t > t0)))


def scene_of(name: str, **options) -> ms.Scene:
    return ms.load_scene(scene_path(name)).with_options(**options)


def run_moreau(sc: ms.Scene, **options) -> Run:
    sc = sc.with_options(**options)
    model = ms.build_model(sc)
    c0 = time.process_time()
    try:
        traj = ms.simulate(model, progress=False)
        err = None
    except ms.SimulationError as exc:
        traj, err = exc.trajectory, str(exc).splitlines()[0]
    cpu = time.process_time() - c0
    return Run(model, traj.t, traj.q, traj.u, traj.kinetic_energy + traj.potential_energy, traj.gap, cpu, traj, err,
               sc.options.to_dict())


def run_peer(method: str, sc: ms.Scene, stride: int = 1, **options) -> Run:
    sc = sc.with_options(**options)
    model = ms.build_model(sc)
    data = ms.make_data(model)
    peer, params = PEER_OF[method]
    t, q, u, res = peers.run_model(peer, model, stride=stride, **params)
    E = np.array([kinetic(model, data, a, b) + potential(model, data, a) for a, b in zip(q, u)])
    gap = np.array([ms.pair_distances(model, data, a) for a in q]).reshape(len(t), -1)
    return Run(model, t, q, u, E, gap, float(res["cpu_seconds"]), None, None, res.get("settings", {}))


class Skip(Exception):
    """A method that cannot run a row (the message says why)."""


def run_method(method: str, sc: ms.Scene, stride: int = 1, **options) -> Run:
    if method == "moreau-sim":
        return run_moreau(sc, **options)
    if method == "moreau-sim plain":
        return run_moreau(sc, **{**options, **PLAIN})
    if method == "moreau-sim + swept":
        return run_moreau(sc, **{**options, "tunnelling": "always"})
    try:
        return run_peer(method, sc, stride, **options)
    except peers.PeerError as exc:
        raise Skip(str(exc).splitlines()[0]) from exc


# --------------------------------------------------------------------------------- metrics
def drift(model, q) -> tuple[float, float]:
    """(largest position drift [m], largest orientation drift [rad]) of any body."""
    dpos = drot = 0.0
    for b in model.bodies:
        x = q[:, b.q_slice]
        if b.root_joint is RootJoint.FREE:
            dpos = max(dpos, float(np.abs(x[:, :3] - x[0, :3]).max()))
            dot = np.abs((x[:, 3:] * x[0, 3:]).sum(axis=1)) / np.linalg.norm(x[:, 3:], axis=1)
            drot = max(drot, float((2 * np.arccos(dot.clip(0, 1))).max()))
        elif x.shape[1]:
            dpos = max(dpos, float(np.abs(x - x[0]).max()))
    return dpos, drot


def pen(run: Run) -> np.ndarray:
    """Penetration per sample: -min over pairs of the signed gap, >= 0."""
    if not run.gap.size:
        return np.zeros(len(run.t))
    return np.maximum(0.0, -run.gap.min(axis=1))


def fmt(x, unit="") -> str:
    if x is None:
        return "—"
    if isinstance(x, str):
        return x
    if x == 0:
        return f"0{unit}"
    if not math.isfinite(x):
        return f"{x}{unit}"
    return f"{x:.2g}{unit}" if abs(x) >= 1e-3 or abs(x) < 1e-300 else f"{x:.1e}{unit}"


@dataclass
class Cell:
    text: str
    ok: bool | None  # None: not applicable / not run
    detail: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.ok is not None:
            self.ok = bool(self.ok)


def zeno_check(e, h, d0=ZENO_GAP):
    t_inf, bound = zeno_time(e, d0), zeno_rest_bound(e, h, d0)

    def check(run: Run) -> Cell:
        speed = np.abs(run.u[:, 0])
        still = speed <= 1e-12
        moving = np.flatnonzero(~still)
        t_rest = run.t[moving[-1] + 1] if len(moving) and moving[-1] + 1 < len(run.t) else (
            run.t[0] if not len(moving) else None)
        last = run.t >= run.t[-1] - 10.0
        creep = float(np.ptp(run.q[last, 0]))
        umax = float(speed[last].max())
        p = float(pen(run)[last].max())
        if t_rest is None:
            return Cell(f"never at rest: \\|u\\| {fmt(umax, ' m/s')} in the last 10 s, creep {fmt(creep, ' m')}", False,
                        {"umax_last10": umax, "creep": creep, "pen": p})
        ok = (abs(t_rest - t_inf) <= bound and run.t[-1] - t_rest >= 10.0 and creep <= 1e-12 and umax <= 1e-12
              and run.impacts_after(t_rest) == 0 and p <= h * h * G)
        return Cell(f"rest at t∞{t_rest - t_inf:+.3f} s (bound ±{bound:.2f}), creep {fmt(creep, ' m')}, "
                    f"pen {fmt(p, ' m')}", ok, {"t_rest_minus_t_inf": t_rest - t_inf, "bound": bound, "creep": creep,
                                                 "umax_last10": umax, "pen": p})
    return check, t_inf + bound + 10.5


def rest_check(dpos_b, drot_b, pen_b, dE_rel):
    def check(run: Run) -> Cell:
        dp, dr = drift(run.model, run.q)
        p = pen(run)
        dE = float(np.max(run.E - run.E[0]))
        grow = float(p[len(p) // 2:].max() - p[: len(p) // 2].max()) if len(p) > 2 else 0.0
        ok = (run.error is None and dp <= dpos_b and dr <= drot_b and p.max() <= pen_b and grow <= 1e-12
              and dE <= dE_rel * max(1.0, abs(run.E[0])))
        txt = f"drift {fmt(dp, ' m')} / {fmt(dr, ' rad')}, pen {fmt(float(p.max()), ' m')}, ΔE+ {fmt(dE, ' J')}"
        if run.error:
            txt += f"; stopped: {run.error[:60]}"
        return Cell(txt, ok, {"drift_m": dp, "drift_rad": dr, "pen": float(p.max()), "pen_growth": grow, "dE": dE})
    return check


def large_step_check(h):
    def check(run: Run) -> Cell:
        E0 = max(1.0, abs(run.E[0]))
        dE = float(np.max(run.E - run.E[0]))
        vmax = float(np.abs(run.u).max())
        bound = 2 * h * run.model.reach * vmax + h * h * G
        p = float(pen(run).max())
        allowed = (1e-2 if run.model.scene.name == "pendulum_wall" else 1e-9) * E0
        ok = run.error is None and np.isfinite(run.q).all() and dE <= allowed and p <= bound
        return Cell(f"ΔE+/E0 {fmt(dE / E0)}, pen {fmt(p, ' m')} (≤ {bound:.2g})", ok,
                    {"dE_rel": dE / E0, "pen": p, "pen_bound": bound})
    return check


def spin_check(run: Run) -> Cell:
    T = np.array([kinetic(run.model, ms.make_data(run.model), a, b) for a, b in zip(run.q, run.u)])
    flight = run.t < 10.0
    d = float(np.abs(T[flight] - T[0]).max() / T[0])
    land = float(T[~flight].max() / T[flight][-1] - 1) if (~flight).any() else 0.0
    return Cell(f"free-flight \\|ΔT\\|/T0 {fmt(d)}, landing ΔT/T {land:+.2g}", d <= 1e-9 and land <= 1e-12,
                {"drift": d, "landing": land, "T": T})


def beads_check(run: Run) -> Cell:
    h = run.model.options.dt
    E0 = abs(run.E[0])
    dE = float(np.max(run.E - run.E[0]))
    bound = h * math.sqrt(2 * G * float(run.q[0].max()))
    p = float(pen(run).max())
    ok = run.error is None and dE <= 1e-12 * E0 and p <= bound
    return Cell(f"ΔE+/E0 {fmt(dE / E0)}, pen {fmt(p, ' m')} (≤ {bound:.2g}), E(T)/E0 {run.E[-1] / E0:.4f}", ok,
                {"dE_rel": dE / E0, "pen": p, "bound": bound})


def cradle_check(e):
    ref = np.array(cradle_simultaneous(e))

    def check(run: Run) -> Cell:
        err = float(np.abs(run.u[-1] - ref).max())
        return Cell(f"max \\|u − ref\\| {fmt(err, ' m/s')}", err <= 1e-14, {"err": err, "u_end": run.u[-1].tolist()})
    return check


def slider_check(run: Run) -> Cell:
    h = run.model.options.dt
    tr = run.traj
    F = float(tr.log_P.max() / h) if tr is not None and len(tr.log_P) else float("nan")
    dE = float(np.max(run.E - run.E[0]))
    ok = run.error is None and np.isfinite(run.q).all() and F <= 2e4 and dE <= 1e-4 * abs(run.E[0])
    return Cell(f"max P/h {F:.3g} N (≤ 2e4), ΔE+/E0 {fmt(dE / abs(run.E[0]))}, pen {fmt(float(pen(run).max()), ' m')}",
                ok, {"F_max": F, "dE": dE, "pen": float(pen(run).max()),
                     "impacts": tr.impacts if tr is not None else None})


# ------------------------------------------------------------------------------------ rows
@dataclass
class Row:
    key: str
    scene: str
    metric: str
    bound: str
    options: dict
    check: object
    methods: tuple = METHODS
    na: dict = field(default_factory=dict)  # method -> why it cannot run
    stride: int = 1
    cells: dict = field(default_factory=dict)
    runs: dict = field(default_factory=dict)


NA_BOX_SICONOS = ("Siconos runner: spheres on collinear slide joints, or one free box over the ground through its "
                  "Bullet mechanics (not run in this suite)")
NA_CHAIN = "a 3-link revolute chain: not in the generic spec (spheres/boxes on free or slide joints)"
NA_PLANAR = "planar / revolute root joints: not in the generic spec"


def rows(quick: bool) -> list[Row]:
    R: list[Row] = []
    for e in (0.5, 0.8, 0.95):
        chk, T = zeno_check(e, 1e-3)
        R.append(Row(f"zeno_ball e={e}", "zeno_ball", "time of rest after t∞; creep and penetration over the last 10 s",
                     "rest within the stated O(h) of t∞ (either side), \\|u\\| ≤ 1e-12 m/s, creep ≤ 1e-12 m, pen ≤ h²g for 10 s",
                     dict(restitution=e, dt=1e-3, duration=T), chk))
    for h in (1e-2, 1e-3):
        R.append(Row(f"resting_box h={h:g}", "resting_box", "drift, penetration, energy gain over 60 s",
                     "drift ≤ 1e-9 m / 1e-9 rad, pen ≤ 1e-9 m not growing, ΔE+ ≤ 1e-12 J",
                     dict(dt=h, duration=10.0 if quick else 60.0), rest_check(1e-9, 1e-9, 1e-9, 1e-12),
                     na={"siconos": NA_BOX_SICONOS}, stride=1 if h == 1e-2 else 10))
    for n in (5, 10):
        for h, T in ((1e-2, 10.0), (1e-3, 1.0)):
            R.append(Row(f"box_stack_{n} h={h:g}", f"box_stack_{n}", f"drift, penetration, energy gain over {T:g} s",
                         "drift ≤ 1e-6 m / 1e-6 rad, pen ≤ 1e-6 m, ΔE+ ≤ 1e-9 J",
                         dict(dt=h, duration=min(T, 2.0) if quick else T), rest_check(1e-6, 1e-6, 1e-6, 1e-9),
                         na={"siconos": NA_BOX_SICONOS}, stride=1 if h == 1e-2 else 5))
    for kind in ("box", "ball"):
        for ratio in (100, 1000):
            for h in (1e-2, 1e-3):
                b = (1e-6, 1e-6, 1e-6, 1e-9) if kind == "box" else (1e-9, 1e-9, 1e-9, 1e-11)
                R.append(Row(f"heavy_on_light_{kind}_{ratio} h={h:g}", f"heavy_on_light_{kind}_{ratio}",
                             "drift, penetration, energy gain over 10 s",
                             f"drift ≤ {b[0]:g} m{' / 1e-6 rad' if kind == 'box' else ''}, pen ≤ {b[2]:g} m, "
                             f"ΔE+ ≤ {b[3]:g} \\|E0\\|",
                             dict(dt=h, duration=3.0 if quick else 10.0), rest_check(b[0], b[1], b[2], b[3]),
                             na={"siconos": NA_BOX_SICONOS} if kind == "box" else {}, stride=1 if h == 1e-2 else 10))
    for key, name in (("heavy_on_light_box_10000 h=0.01", "heavy_on_light_box_10000"),
                      ("alternating_stack_10 h=0.01", "alternating_stack_10")):
        R.append(Row(key, name, "drift, penetration, energy gain over 10 s",
                     "drift ≤ 1e-06 m / 1e-6 rad, pen ≤ 1e-06 m, ΔE+ ≤ 1e-09 \\|E0\\|",
                     dict(dt=1e-2, duration=3.0 if quick else 10.0), rest_check(1e-6, 1e-6, 1e-6, 1e-9),
                     na={"siconos": NA_BOX_SICONOS}))
    for name in ("bouncing_ball", "box_drop", "newton_cradle_5_gapped", "rocking_block", "pendulum_wall",
                 "block_on_step", "corner_point"):
        for h in (2e-2, 5e-2):
            na = {}
            if name in ("rocking_block", "pendulum_wall", "block_on_step", "corner_point"):
                na = {m: NA_PLANAR for m in ("mujoco", "pybullet-default", "pybullet-tuned", "siconos")}
            elif name == "box_drop":
                na = {"siconos": NA_BOX_SICONOS}
            R.append(Row(f"large_step {name} h={h:g}", name, "energy gain, penetration (the scene's own duration)",
                         "completes; ΔE+ ≤ 1e-9 \\|E0\\| (pendulum_wall: 1 %); pen ≤ 2 h reach max\\|u\\| + h²g",
                         dict(dt=h), large_step_check(h), na=na))
    R.append(Row("fast_impact", "fast_impact", "start phases (of 20, over one step's 5 cm) at which the marble passes "
                 "the plate", "never passes (0 of 20)", dict(duration=0.012), None,
                 methods=("moreau-sim", "moreau-sim plain", "moreau-sim + swept", "mujoco", "pybullet-default",
                          "pybullet-tuned", "siconos"),
                 na={"siconos": "its 1-dof relation is a half-space (cannot be tunnelled): the thin plate needs its "
                                "Bullet detection, not built"}))
    for h in (1e-3, 1e-2):
        R.append(Row(f"spinning_box h={h:g}", "spinning_box", "free-flight kinetic-energy drift (10 s), landing",
                     "\\|ΔT\\|/T0 ≤ 1e-9 in flight; the landing never raises T", dict(dt=h), spin_check,
                     na={"siconos": NA_BOX_SICONOS}))
    for name in ("column_of_beads", "column_of_beads_100"):
        R.append(Row(name, name, "energy gain, penetration over 3 s (h = 5e-4)",
                     "ΔE+ ≤ 1e-12 \\|E0\\|, pen ≤ h √(2 g z_top)", dict(duration=1.0 if quick else 3.0), beads_check,
                     stride=10))
    for name in ("cradle_rounding", "cradle_rounding_perturbed", "newton_cradle_5"):
        R.append(Row(f"{name} e=1", name, "final velocities against Glocker's simultaneous result",
                     "max \\|u − ref\\| ≤ 1e-14 m/s", dict(restitution=1.0, duration=0.2), cradle_check(1.0)))
    R.append(Row("slider_crank_clearance", "slider_crank_clearance", "largest contact force, energy, over 0.2 s at h = 1e-5",
                 "completes, max P/h ≤ 2e4 N, ΔE+ ≤ 1e-4 \\|E0\\|", dict(duration=0.05 if quick else 0.2), slider_check,
                 methods=("moreau-sim", "moreau-sim plain"), na={}))
    return R


# --------------------------------------------------------------------------- fast_impact row
PHASES = 0.606 + 0.05 * np.arange(20) / 20


def fast_impact_cells(row: Row, methods) -> None:
    base = scene_of("fast_impact")
    for method in methods:
        if method in row.na:
            row.cells[method] = Cell("n/a", None, {"why": row.na[method]})
            continue
        passed, zmins = 0, []
        try:
            for q0 in PHASES:
                sc = dataclasses.replace(base, bodies=(dataclasses.replace(base.bodies[0], q0=(float(q0),)),))
                run = run_method(method, sc, **row.options)
                z = run.q[:, 0]
                zmins.append(float(z.min()))
                passed += bool(z.min() < 0.49 - 0.01)
                if abs(q0 - 0.656) < 1e-9 or q0 == PHASES[0]:
                    row.runs.setdefault(method, run)
        except Skip as exc:
            row.cells[method] = Cell("n/a", None, {"why": str(exc)})
            continue
        row.cells[method] = Cell(f"{passed} of 20 pass through", passed == 0, {"passed": passed, "zmin": zmins})


# ------------------------------------------------------------------------------------ driver
def evaluate(R: list[Row], methods, log) -> None:
    avail = peers.available()
    for row in R:
        if row.scene == "fast_impact":
            ms_ = [m for m in row.methods if m in methods]
            for m in ms_:
                peer = PEER_OF.get(m, (None,))[0]
                if peer and avail.get(peer):
                    row.na.setdefault(m, f"not installed: {avail[peer][:80]}")
            t0 = time.time()
            fast_impact_cells(row, ms_)
            log(f"{row.key}: {time.time() - t0:.1f} s")
            continue
        sc = scene_of(row.scene)
        for m in row.methods:
            if m not in methods:
                continue
            peer = PEER_OF.get(m, (None,))[0]
            if m in row.na:
                row.cells[m] = Cell("n/a", None, {"why": row.na[m]})
                continue
            if peer and avail.get(peer):
                row.cells[m] = Cell("n/a", None, {"why": f"not installed: {avail[peer][:80]}"})
                continue
            t0 = time.time()
            try:
                run = run_method(m, sc, row.stride, **row.options)
            except Skip as exc:
                row.cells[m] = Cell("n/a", None, {"why": str(exc)})
                log(f"{row.key} / {m}: n/a ({exc})")
                continue
            row.runs[m] = run
            row.cells[m] = row.check(run)
            log(f"{row.key} / {m}: {row.cells[m].text} [{'pass' if row.cells[m].ok else 'FAIL'}] "
                f"({time.time() - t0:.1f} s)")


# ------------------------------------------------------------------------------------- plots
def plots(R: list[Row], img: Path) -> list[tuple[str, str]]:
    plt = pyplot()

    out = []
    style = {"moreau-sim": ("C0", "-"), "moreau-sim plain": ("C1", "--"), "moreau-sim + swept": ("C5", "-"),
             "mujoco": ("C2", "-"), "pybullet-default": ("C3", "-"), "pybullet-tuned": ("C4", ":"), "siconos": ("C7", "-.")}

    def rowby(key):
        return next((r for r in R if r.key == key), None)

    def save(fig, name, caption):
        fig.tight_layout()
        fig.savefig(img / name, dpi=110)
        plt.close(fig)
        out.append((name, caption))

    r = rowby("zeno_ball e=0.8")
    if r and r.runs:
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        for m, run in r.runs.items():
            c, ls = style[m]
            ax[0].semilogy(run.t, np.abs(run.u[:, 0]) + 1e-18, color=c, ls=ls, label=m, lw=1)
            ax[1].semilogy(run.t, pen(run) + 1e-18, color=c, ls=ls, label=m, lw=1)
        ax[0].axvline(zeno_time(0.8, ZENO_GAP), color="k", lw=0.5)
        ax[0].set_ylabel("|u| [m/s] (+1e-18)")
        ax[1].set_ylabel("penetration [m] (+1e-18)")
        ax[1].set_xlabel("t [s]  (vertical line: t∞)")
        ax[0].legend(fontsize=7)
        ax[0].set_title("zeno_ball, e = 0.8, h = 1e-3")
        save(fig, "stability_zeno_ball.png", "zeno_ball (e = 0.8): speed and penetration; moreau-sim rests exactly "
             "after t∞, the soft/regularised peers keep micro-motion")
    for key, name, title in (("box_stack_5 h=0.01", "stability_box_stack_5.png", "box_stack_5, h = 1e-2"),
                             ("heavy_on_light_box_1000 h=0.01", "stability_heavy_on_light_box_1000.png",
                              "heavy_on_light_box_1000, h = 1e-2")):
        r = rowby(key)
        if r and r.runs:
            fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
            for m, run in r.runs.items():
                c, ls = style[m]
                ax[0].semilogy(run.t, pen(run) + 1e-18, color=c, ls=ls, label=m, lw=1)
                ax[1].plot(run.t, run.E - run.E[0], color=c, ls=ls, label=m, lw=1)
            ax[0].set_ylabel("penetration [m] (+1e-18)")
            ax[1].set_ylabel("T + V − E0 [J]")
            ax[1].set_xlabel("t [s]")
            ax[0].legend(fontsize=7)
            ax[0].set_title(title)
            save(fig, name, f"{title}: penetration and energy vs time")
    r = rowby("spinning_box h=0.001")
    if r and r.runs:
        fig, ax = plt.subplots(figsize=(8, 4))
        for m, run in r.runs.items():
            c, ls = style[m]
            T = r.cells[m].detail.get("T")
            if T is not None:
                ax.plot(run.t, T / T[0] - 1, color=c, ls=ls, label=m, lw=1)
        ax.axvline(10.0, color="k", lw=0.5)
        ax.set_ylabel("T / T0 − 1")
        ax.set_xlabel("t [s]  (free flight until ~10.5 s)")
        ax.legend(fontsize=7)
        ax.set_title("spinning_box, h = 1e-3: kinetic energy in free flight (bias = midpoint vs explicit)")
        save(fig, "stability_spinning_box.png", "spinning_box: kinetic energy drift in free flight; moreau-sim's "
             "midpoint bias holds T to round-off, the explicit gyroscopic term (moreau-sim plain, MuJoCo, PyBullet) gains")
    r = rowby("fast_impact")
    if r and r.runs:
        fig, ax = plt.subplots(figsize=(8, 4))
        for m, run in r.runs.items():
            c, ls = style[m]
            ax.plot(run.t * 1e3, run.q[:, 0], color=c, ls=ls, label=m, lw=1, marker=".", ms=3)
        ax.axhspan(0.49, 0.5, color="k", alpha=0.3, label="plate")
        ax.set_ylim(-0.05, 0.75)
        ax.set_xlabel("t [ms]")
        ax.set_ylabel("marble centre z [m]")
        ax.legend(fontsize=7)
        ax.set_title("fast_impact (start 0.606 m): 50 m/s onto a 1 cm plate, h = 1e-3")
        save(fig, "stability_fast_impact.png", "fast_impact: the marble's height; midpoint activation lets it "
             "through with tunnelling = \"none\", the default swept detection stops it")
    r = rowby("column_of_beads")
    if r and r.runs:
        fig, ax = plt.subplots(figsize=(8, 4))
        for m, run in r.runs.items():
            c, ls = style[m]
            ax.plot(run.t, run.E / run.E[0], color=c, ls=ls, label=m, lw=1)
        ax.set_ylabel("(T + V) / E0")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
        ax.set_title("column_of_beads (10 beads, e = 0.9, h = 5e-4)")
        save(fig, "stability_column_of_beads.png", "column_of_beads: total energy vs time")
    r = rowby("slider_crank_clearance")
    if r and r.runs:
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        for m, run in r.runs.items():
            c, ls = style[m]
            tr = run.traj
            h = run.model.options.dt
            ax[0].semilogy(tr.log_t, tr.log_P / h, ".", color=c, ms=2, label=m)
            ax[1].plot(run.t, run.gap * 1e3, color=c, ls=ls, lw=0.8)
        ax[0].axhline(2e4, color="k", lw=0.5)
        ax[0].set_ylabel("P / h [N]")
        ax[1].set_ylabel("slider-guide gaps [mm]")
        ax[1].set_xlabel("t [s]")
        ax[0].legend(fontsize=7)
        ax[0].set_title("slider_crank_clearance, h = 1e-5")
        save(fig, "stability_slider_crank.png", "slider_crank_clearance: contact forces P/h and the slider's gaps")
    return out


# ------------------------------------------------------------------------------------ report
def projection_note(rows: list[dict]) -> str:
    """The paragraph on position_correction = "projection", from a run's rows (report_data)."""
    def cell(key, m):
        r = next((r for r in rows if r["key"] == key), None)
        return r["cells"].get(m) if r else None

    parts = []
    z, zp = cell("zeno_ball e=0.95", "moreau-sim"), cell("zeno_ball e=0.95", "moreau-sim plain")
    if z and zp and "t_rest_minus_t_inf" in z["detail"] and "t_rest_minus_t_inf" in zp["detail"]:
        parts.append(f"the Zeno ball (e = 0.95) rests {z['detail']['t_rest_minus_t_inf']:+.2f} s from t∞ with it, "
                     f"{zp['detail']['t_rest_minus_t_inf']:+.2f} s with \"none\" (both within the bound)")
    b, bp = cell("column_of_beads_100", "moreau-sim"), cell("column_of_beads_100", "moreau-sim plain")
    if b and bp and "pen" in b["detail"] and "pen" in bp["detail"]:
        parts.append(f"in the 100-bead column (3 s, still settling) the largest penetration is "
                     f"{b['detail']['pen']:.2g} m with it against {bp['detail']['pen']:.2g} m with \"none\" "
                     f"(bound h v_max = {b['detail']['bound']:.2g} m); bodies that come to rest are lifted to "
                     "their contacts (theory.md §2.5)")
    c, cp = cell("slider_crank_clearance", "moreau-sim"), cell("slider_crank_clearance", "moreau-sim plain")
    if c and cp and c["detail"].get("impacts") is not None and cp["detail"].get("impacts") is not None:
        parts.append(f"the slider-crank penetrates {c['detail']['pen']:.2g} m with {c['detail']['impacts']} impacts "
                     f"against {cp['detail']['pen']:.2g} m with {cp['detail']['impacts']} impacts with \"none\"")
    if not parts:
        return ""
    return ("- **position_correction = \"projection\" (the default)**: " + "; ".join(parts) +
            ".")


SHOWN = ("moreau-sim", "moreau-sim plain", "moreau-sim + swept", "mujoco", "pybullet-default", "pybullet-tuned",
         "siconos")


def report_data(R: list[Row], figs, elapsed: float, quick: bool) -> dict:
    """What docs/stability.md shows of a run, as JSON: every row's cells (ok, text, detail), the
    plots, the options and versions."""
    rows = [{"key": r.key, "metric": r.metric, "bound": r.bound,
             "cells": {m: {"ok": c.ok, "text": c.text, "detail": to_jsonable(c.detail)} for m, c in r.cells.items()}}
            for r in R]
    meta = {"created": datetime.date.today().isoformat(), "minutes": elapsed / 60, "quick": quick,
            "options": to_jsonable(Options().to_dict()), "versions": versions()}
    return {"meta": meta, "rows": rows, "figures": [list(f) for f in figs]}


def run_md(data: dict) -> str:
    meta = data["meta"]
    return "\n".join([
        f"Generated by `python -m benchmarks.stability` on {meta['created']}{' (--quick: shortened runs)' if meta['quick'] else ''}"
        f" in {meta['minutes']:.1f} min into [`bench/stability.json`](bench/stability.json); the table, the "
        "failures, the projection note, the plots and the versions on this page are written from that JSON. "
        "Regenerate with", "",
        "    .venv/bin/pip install -e '.[peers]' && apt-get install -y python3-siconos && "
        ".venv/bin/python -m benchmarks.stability --out docs/bench", "",
        "(`python -m benchmarks.stability --table docs/bench/stability.json docs/stability.md` rewrites them from the JSON "
        "alone.)", "", "Every stress scene is a bundled scene file (`scenes/*.toml`) whose description states its "
        "metric and pass bound; `tests/test_stress.py` asserts the bound at a CI size (a strict xfail, "
        "with its cause, wherever moreau-sim fails one). Methods:", "",
        "- **moreau-sim**: the scene's options, i.e. the defaults (" + ", ".join(
            f"{k} = \"{v}\"" for k, v in meta["options"].items() if isinstance(v, str)) + ")."])


def table_md(data: dict) -> str:
    rows = data["rows"]
    shown = [m for m in SHOWN if any(m in r["cells"] for r in rows)]
    L = ["| row | metric | bound | " + " | ".join(shown) + " |", "|---|---|---|" + "---|" * len(shown)]
    for r in rows:
        cells = []
        for m in shown:
            c = r["cells"].get(m)
            cells.append("" if c is None else "n/a" if c["ok"] is None else f"{'✓' if c['ok'] else '✗'} {c['text']}")
        L.append(f"| {r['key']} | {r['metric']} | {r['bound']} | " + " | ".join(cells) + " |")
    L += ["", "n/a reasons:", ""]
    seen = set()
    for r in rows:
        for m, c in r["cells"].items():
            why = c["detail"].get("why")
            if c["ok"] is None and why and (m, why) not in seen:
                seen.add((m, why))
                L.append(f"- {m}: {why}")
    fails = [(r, m) for r in rows for m in ("moreau-sim", "moreau-sim plain")
             if r["cells"].get(m) and r["cells"][m]["ok"] is False]
    L += ["", "## Where moreau-sim does not pass, and why", ""]
    L += [f"- **{r['key']}** ({m}): {r['cells'][m]['text']}" for r, m in fails] or ["- none"]
    return "\n".join(L)


def figures_md(data: dict) -> str:
    L = []
    for name, cap in data["figures"]:
        L += [f"![{cap}](img/{name})", "", f"*{cap}*", ""]
    return "\n".join(L)


def doc_tables(data: dict) -> dict[str, str]:
    """The generated parts of docs/stability.md (marker name: Markdown) from a stability.json."""
    return {"stability run": run_md(data), "stability table": table_md(data),
            "stability projection note": projection_note(data["rows"]), "stability plots": figures_md(data),
            "stability versions": "    " + ", ".join(f"{k} {v}" for k, v in data["meta"]["versions"].items())}


# ------------------------------------------------------------------------------ scene files
def write_generated_scenes(root: Path = REPO) -> None:
    """box_stack_5/10, alternating_stack_10, column_of_beads(_100), cradle_rounding(_perturbed): the scene files with many
    bodies or exact floating-point positions, written here so they can be regenerated."""
    sc = root / "scenes"
    for n in (5, 10):
        (sc / f"box_stack_{n}.toml").write_text(_box_stack(n))
    (sc / "alternating_stack_10.toml").write_text(_alternating_stack(10))
    (sc / "column_of_beads.toml").write_text(_column(10, 0.05, 0.2))
    (sc / "column_of_beads_100.toml").write_text(_column(100, 0.01, 0.11))
    xs = [0.1 + 0.2 * i for i in range(5)]
    pert = [x + d for x, d in zip(xs, (0.0, 1e-16, -1e-16, 2e-16, -2e-16))]
    ref = ("Glocker's simultaneous result of newton_cradle_5: u+_1 = (1+e)/5 - e, u+_(i>1) = (1+e)/5 "
           "(e = 1: -0.6, 0.4, 0.4, 0.4, 0.4)")
    (sc / "cradle_rounding.toml").write_text(_cradle(
        "cradle_rounding", xs,
        "Rounding stress: the touching Newton cradle of newton_cradle_5 (5 balls r = 0.1 m, 1 kg, prismatic x, no "
        "gravity, ball 0 at 1 m/s) with its positions computed in floating point, x_i = 0.1 + 0.2 * i, written "
        "with full repr (0.1, 0.30000000000000004, 0.5, 0.7000000000000001, 0.9): neighbour gaps of +-5.6e-17 m "
        f"instead of 0. Metric and pass bound: the final velocities equal {ref} to 1e-14 m/s, as for exact touching."))
    (sc / "cradle_rounding_perturbed.toml").write_text(_cradle(
        "cradle_rounding_perturbed", pert,
        "Rounding stress: the touching Newton cradle (5 balls r = 0.1 m, 1 kg, prismatic x, no gravity, ball 0 at "
        "1 m/s) with each ball moved by 0, +1e-16, -1e-16, +2e-16, -2e-16 m from x_i = 0.1 + 0.2 * i: neighbour gaps "
        "of a few 1e-16 m, some negative. Metric and pass bound: the final velocities equal "
        f"{ref} to 1e-14 m/s, as for exact touching."))


def _body(name, urdf, root, **kw):
    lines = ["[[bodies]]", f'name = "{name}"', f'urdf = "../models/{urdf}.urdf"', f'root_joint = "{root}"']
    lines += [f"{k} = {v}" for k, v in kw.items()]
    return "\n".join(lines) + "\n"


def _exclude(names, ground, comment):
    n = len(names)
    excl = [[names[i], names[j]] for i in range(n) for j in range(i + 2, n)]
    excl += [[names[i], ground] for i in range(1, n)]
    return f"[collisions]\n# {comment}\nexclude = [" + ", ".join(f'["{a}", "{b}"]' for a, b in excl) + "]\n"


def _box_stack(n):
    desc = (f"Stacking stress: {n} free cubes (0.1 m, 1 kg each, 6 dof each: {6 * n} dof) stacked at rest on the "
            "frictionless ground, exactly touching (centres at z = 0.05 + 0.1 i written as decimals), each offset "
            "by +-2 mm in x and y and yawed by +-0.1 rad from the one below, so neighbours touch along the octagon "
            "of their overlap. Collision pairs: all (automatic), so a stack that breaks up falls as it would. Metric and pass "
            "bound, at h = 1e-2 and 1e-3 (the file runs 2 s at h = 1e-2; docs/stability.md 10 s at 1e-2 and 1 s at "
            "1e-3): drift of every cube <= 1e-6 m in position and <= 1e-6 rad in orientation, "
            "penetration (-min gap) <= 1e-6 m and not growing, T + V never above its start by more than 1e-9 J.")
    out = [f'[scene]\nname = "box_stack_{n}"\ndescription = "{desc}"\n',
           "[simulation]\nrestitution = 0.5\ndt = 1e-2\nduration = 2.0\n", f'[output]\nfile = "box_stack_{n}.npz"\n']
    for i in range(n):
        x = 0.002 * (1 if i % 2 else -1) if i else 0.0
        y = 0.002 * (1 if (i // 2) % 2 else -1) if i else 0.0
        yaw = 0.1 * (1 if i % 2 else -1) if i else 0.0
        out.append(_body(f"cube{i}", "cube", "free", position=f"[{x!r}, {y!r}, {0.05 + 0.1 * i:.2f}]",
                         rpy=f"[0.0, 0.0, {yaw!r}]"))
    out.append('[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    return "\n".join(out)


def _alternating_stack(n):
    desc = (f"Stacking and mass-ratio stress: {n} free cubes (0.1 m, 6 dof each: {6 * n} dof) of alternating masses "
            "1 kg and 100 kg (the bottom one light), stacked aligned (side faces coplanar) and exactly touching "
            "(centres at z = 0.05 + 0.1 i written as decimals) on the frictionless ground, at h = 1e-2: "
            "every light cube carries at least 100 times its weight. Collision pairs: neighbours and the bottom cube "
            "with the ground. Metric and pass bound: drift of every cube <= 1e-6 m in position and <= 1e-6 rad in "
            "orientation, penetration (-min gap) <= 1e-6 m, T + V never above its start by more than 1e-9 |E0| (the "
            "file runs 2 s; docs/stability.md 10 s).")
    out = [f'[scene]\nname = "alternating_stack_{n}"\ndescription = "{desc}"\n',
           "[simulation]\nrestitution = 0.5\ndt = 1e-2\nduration = 2.0\n",
           f'[output]\nfile = "alternating_stack_{n}.npz"\n']
    names = [f"cube{i}" for i in range(n)]
    for i in range(n):
        out.append(_body(names[i], "cube_100kg" if i % 2 else "cube", "free", position=f"[0.0, 0.0, {0.05 + 0.1 * i:.2f}]"))
    out.append('[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    out.append(_exclude(names, "ground", "a stack: only neighbours touch; only the bottom cube touches the ground"))
    return "\n".join(out)


def _column(n, gap, z0):
    name = "column_of_beads" if n == 10 else f"column_of_beads_{n}"
    T = 2.0 if n == 10 else 0.5
    desc = (f"A Siconos benchmark: a column of {n} beads (balls r = 0.1 m, 1 kg, each on a vertical prismatic "
            f"joint: {n} dof), the bottom one's centre at {z0} m, {gap} m between neighbours' surfaces, released "
            f"from rest under gravity, e = 0.9, h = 5e-4 (the file runs {T} s; docs/stability.md 3 s): the bottom "
            "bead bounces first and a cascade of impacts runs up the column. Collision pairs: neighbours only, "
            "plus the ground for the bottom bead. Metric and pass bound: T + V never above its start by more than "
            "1e-12 |E0| (translations under constant gravity are integrated exactly), penetration (-min gap) <= h "
            "v_max with v_max = sqrt(2 g z_top) the largest speed any bead can reach, the contact work of every "
            "step <= round-off.")
    out = [f'[scene]\nname = "{name}"\ndescription = "{desc}"\n',
           f"[simulation]\nrestitution = 0.9\ndt = 5e-4\nduration = {T}\n", f'[output]\nfile = "{name}.npz"\n']
    for i in range(n):
        out.append(_body(f"bead{i}", "ball", "prismatic", axis="[0, 0, 1]", q0=f"[{round(z0 + i * (0.2 + gap), 10)!r}]"))
    out.append('[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    out.append(_exclude([f"bead{i}" for i in range(n)], "ground",
                        "beads on one line: only neighbours touch; only the bottom bead touches the ground"))
    return "\n".join(out)


def _cradle(name, xs, desc):
    out = [f'[scene]\nname = "{name}"\ndescription = "{desc}"\n',
           "[simulation]\nrestitution = 1.0\ndt = 1e-3\nduration = 0.2\ngravity = [0, 0, 0]\n",
           f'[output]\nfile = "{name}.npz"\n']
    for i, x in enumerate(xs):
        kw = dict(axis="[1, 0, 0]", q0=f"[{x!r}]")
        if i == 0:
            kw["u0"] = "[1.0]"
        out.append(_body(f"ball{i}", "ball", "prismatic", **kw))
    n = len(xs)
    excl = [[f"ball{i}", f"ball{j}"] for i in range(n) for j in range(i + 2, n)]
    out.append("[collisions]\n# balls on one line: only neighbours can touch\nexclude = [" +
               ", ".join(f'["{a}", "{b}"]' for a, b in excl) + "]\n")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder of stability.json (docs/bench: the committed one; plots go to ../img beside a "
                         "folder named bench, else to its img/)")
    ap.add_argument("--img", type=Path, default=None, help="plot folder (default: see --out)")
    ap.add_argument("--quick", action="store_true", help="shortened runs (smoke test)")
    ap.add_argument("--no-peers", action="store_true", help="moreau-sim only")
    ap.add_argument("--only", default=None, help="comma-separated row-key prefixes")
    ap.add_argument("--write-scenes", action="store_true", help="regenerate the generated scene files and exit")
    add_table_option(ap, "stability.json", "docs/stability.md")
    a = ap.parse_args(argv)
    if a.write_scenes:
        write_generated_scenes()
        return 0
    if rewrite_tables(a, doc_tables):
        return 0
    methods = ("moreau-sim", "moreau-sim plain", "moreau-sim + swept") if a.no_peers else (
        METHODS + ("moreau-sim + swept",))
    R = rows(a.quick)
    if a.only:
        keys = tuple(k.strip() for k in a.only.split(","))
        R = [r for r in R if r.key.startswith(keys)]
    t0 = time.time()
    evaluate(R, methods, lambda s: print(s, flush=True))
    img = a.img or (a.out.parent / "img" if a.out.name == "bench" else a.out / "img")
    img.mkdir(parents=True, exist_ok=True)
    figs = plots(R, img)
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / "stability.json"
    path.write_text(json.dumps(report_data(R, figs, time.time() - t0, a.quick), indent=1))
    print(f"wrote {path} and {len(figs)} plots in {img}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
