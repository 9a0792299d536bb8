"""`moreau-sim run`, `info`, `outcomes` and `plot`: the commands over a scene or a trajectory (docs/cli.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from .. import interrupts
from ..checkpoint import Checkpoint
from ..errors import MoreauSimError, SceneError, SimulationError, SimulationInterrupted
from ..invariants import InvariantViolation, flagged, one_line
from ..model import build_model
from ..scene import load_scene
from ..simulate import simulate, summary
from .common import fail
from .paths import model_inputs, output_path


def _load(scene: str, **overrides):
    try:
        sc = load_scene(scene)
    except MoreauSimError as exc:
        fail(str(exc))
    try:
        sc = sc.with_options(**overrides)
    except MoreauSimError as exc:  # "options: restitution: ..." -> "--restitution: ..."
        fail(f"command line: {str(exc).replace('options: ', '--', 1).replace('_', '-')}")
    try:
        return sc, build_model(sc)
    except MoreauSimError as exc:
        fail(str(exc))


def _settings(settings) -> dict:
    """--set NAME=VALUE pairs -> option overrides, parsed as a sweep's one-value --param."""
    from ..sweep import parse_settings

    try:
        return parse_settings(settings)
    except MoreauSimError as exc:
        fail(f"command line: {exc}")


def _output(out: str | None, sc, model) -> Path:
    """Where `run` writes: -o/--out as given; else the scene's [output] file, resolved in the
    scene's folder and never outside it; else NAME.npz here. Checked (cli/paths.py: suffix, not an
    input, folder writable) before simulating."""
    inputs = model_inputs(sc, model)
    roots = [sc.path.parent] if sc.path else []
    default = Path(f"{sc.name}.npz")
    if out is not None:
        return output_path(out, default=default, suffix=".npz", where="--out", inputs=inputs, roots=roots,
                           then="nothing was simulated")
    if sc.output is not None:
        where = f"{sc.path} [output] file" if sc.path else "[output] file"
        if not sc.output.strip():
            fail(f"{where}: empty file name; give a file ending in .npz (or remove the field)")
        base = (sc.path.parent if sc.path else Path.cwd()).resolve()
        path = (base / sc.output).resolve()
        if not path.is_relative_to(base):
            fail(f"{where} = {sc.output!r}: must stay inside the scene's folder {base}; give -o/--out to write "
                 "elsewhere")
        given = str(path) + ("/" if sc.output.endswith("/") else "")
        return output_path(given, default=default, suffix=".npz", where=where, inputs=inputs, roots=[base],
                           then="nothing was simulated")
    return output_path(None, default=default, suffix=".npz", where="output", inputs=inputs,
                       then="nothing was simulated")


def _show_progress(flag: bool | None, as_json: bool) -> bool:
    """--progress forces the bar, --no-progress hides it; by default it is drawn on a terminal only
    (never into a log file or a CI log)."""
    return (sys.stderr.isatty() if flag is None else flag) and not as_json


VIOLATED = 3  # the exit status of a --strict run that broke an invariant (docs/cli.md)


def _simulate(model, out: Path, ck: Checkpoint | None, progress: bool, strict: bool):
    """simulate() for `run`, its recorded rows waiting in unnamed files beside the output instead of
    in memory (docs/output.md); a stop saves the samples so far as FILE.partial.npz and exits."""
    try:
        return simulate(model, progress=progress, checkpoint=ck, spill=out.parent, strict=strict)
    except SceneError as exc:  # a damaged checkpoint, or one of another run
        fail(str(exc))
    except SimulationInterrupted as exc:
        partial = out.with_name(out.stem + ".partial.npz")
        exc.trajectory.save(partial)
        again = (f"; --resume continues from the last checkpoint {ck.path}" if ck is not None and ck.path.exists()
                 else "")
        click.echo(f"moreau-sim: {exc} ({interrupts.signal_name()}); the samples so far are in {partial} (meta "
                   f"status 'failed'){again}", err=True)
        sys.exit(interrupts.exit_status())
    except SimulationError as exc:
        partial = out.with_name(out.stem + ".partial.npz")
        code = VIOLATED if isinstance(exc, InvariantViolation) else 2
        if exc.trajectory is not None:
            exc.trajectory.save(partial)
            fail(f"{exc}\n  nothing written to {out}; the samples up to the failure are in {partial} "
                  "(meta status 'failed')", code)
        fail(str(exc), code)


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--dt", type=float, help="Time step h [s] (overrides the scene).")
@click.option("--duration", type=float, help="Simulated time [s].")
@click.option("--restitution", "-e", type=float, help="Global restitution e in [0, 1].")
@click.option("--save-every", type=int, help="Record every N steps.")
@click.option("--qp-form", type=click.Choice(["primal", "dual"]), help="Form of the impact QP.")
@click.option("--set", "-s", "settings", multiple=True, metavar="NAME=VALUE",
              help="Any option of the scene's [simulation] table, by its scene-file name (repeatable), "
                   "e.g. --set bias=explicit --set gravity=[0,0,-1.62] (docs/scenes.md).")
@click.option("--out", "-o", type=click.Path(),
              help="Output NPZ (default: the scene's [output] file); a folder (DIR/) gets SCENE_NAME.npz.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--progress/--no-progress", default=None,
              help="Progress bar on runs longer than 2 s (default: only when stderr is a terminal).")
@click.option("--checkpoint-every", type=float, metavar="SECONDS",
              help="Save a checkpoint FILE.checkpoint.npz every SECONDS of simulated time, at the integrator's "
                   "accepted points (any integrator; the event-driven one checkpoints at events).")
@click.option("--resume", is_flag=True,
              help="Continue from FILE.checkpoint.npz if it exists; the result is bit-identical to an "
                   "uninterrupted run.")
@click.option("--strict", is_flag=True,
              help="A broken invariant (docs/theory.md §10) stops the run as an error (exit 3) instead of flagging it.")
def run(scene, dt, duration, restitution, save_every, qp_form, settings, out, as_json, progress, checkpoint_every,
        resume, strict):
    """Simulate SCENE and write a self-describing NPZ."""
    overrides = _settings(settings)
    for key, value in (("dt", dt), ("duration", duration), ("restitution", restitution), ("save_every", save_every),
                       ("qp_form", qp_form)):
        if value is not None:
            overrides[key] = value
    sc, model = _load(scene, **overrides)
    out = _output(out, sc, model)
    if checkpoint_every is not None and not (checkpoint_every > 0 and np.isfinite(checkpoint_every)):
        fail(f"command line: --checkpoint-every: must be a finite time > 0 s, got {checkpoint_every!r}")
    ck = None
    if checkpoint_every is not None or resume:
        ck = Checkpoint(path=out.with_name(out.stem + ".checkpoint.npz"), every=checkpoint_every, resume=resume,
                        keep=True)
        if resume and not ck.path.exists():
            click.echo(f"moreau-sim: no checkpoint {ck.path}: starting from the beginning", err=True)
    try:  # SIGTERM as Ctrl-C (cli/__init__.py): the samples so far are kept
        traj = _simulate(model, out, ck, _show_progress(progress, as_json), strict)
        traj.save(out)
    except OSError as exc:  # the output's folder filled up (the run's spill files, a partial file, the output)
        fail(f"{out.parent}: cannot write there ({exc.strerror or exc}); nothing written to {out}")
    if ck is not None:
        ck.path.unlink(missing_ok=True)  # the run is complete and saved
    out.with_name(out.stem + ".partial.npz").unlink(missing_ok=True)  # an interrupted attempt's samples: superseded
    s = summary(traj)
    s["output"] = str(out)
    if flagged(traj.meta):  # one line on stderr (also with --json): the run ran to its end but broke an invariant
        click.echo(f"moreau-sim: flagged: {one_line(traj.meta.get('invariants', []))} (meta invariants; "
                   "--strict makes it an error)", err=True)
    if as_json:
        click.echo(json.dumps(s, indent=2))
        return
    if s["integrator"] == "event-driven":
        how = f"{s['events']} events (event-driven)"
    elif s["integrator"] == "adaptive":
        how = (f"{s['steps'] - s['steps_fixed']} extrapolated and {s['steps_fixed']} fixed steps (h = "
               f"{sc.options.dt:g} s), {s['events']} events (adaptive)")
    else:
        how = f"{s['steps']} steps of h = {sc.options.dt:g} s"
    click.echo(f"{s['scene']}: {how} to t = {s['t_end']:g} s, e = {sc.options.restitution:g}")
    click.echo(f"  impacts {s['impacts']}, percussions logged {s['percussions_logged']}"
               + (f", corner impacts with several outcomes {s['branching_steps']}" if s["branching_steps"] else ""))
    click.echo(f"  energy {s['energy_start']:.6g} J -> {s['energy_end']:.6g} J "
               f"(contact work {s['contact_work_total']:.6g} J, max rise {s['energy_max_increase']:.3g} J)")
    if s["law_difference_max"] is not None:
        click.echo(f"  ledger: smooth error {s['smooth_error_total']:.3g} J, impacts against the law within "
                   f"{s['law_difference_max']:.2g} J (docs/regression.md)")
    if s["min_gap"] is not None:
        click.echo(f"  min gap {s['min_gap']:.3g} m")
    per_step = f", {s['us_per_step']:.1f} us/step" if s["us_per_step"] is not None else ""  # event-driven: no steps
    click.echo(f"  wall {s['wall_seconds']:.3f} s{per_step}  -> {out}")


PAIRS_SHOWN = 10  # `info` lists this many collision pairs unless --all-pairs


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--all-pairs", is_flag=True, help=f"List every collision pair (default: the count and the first "
                                                f"{PAIRS_SHOWN}).")
@click.option("--json", "as_json", is_flag=True, help="Print as JSON (every pair).")
def info(scene, all_pairs, as_json):
    """Dofs, bodies, joints (in the order of q and u), actuators, collision pairs, e and h of SCENE."""
    sc, model = _load(scene)
    d = model.describe()
    d["actuators"] = [] if model.actuation is None else model.actuation.describe()
    d["drives"] = [_drive(dr) for dr in sc.drives]
    if as_json:
        click.echo(json.dumps(d, indent=2))
        return
    click.echo(f"{d['scene']}: nq = {d['nq']}, nv = {d['nv']}, e = {d['restitution']:g}, h = {d['dt']:g} s, "
               f"duration = {d['duration']:g} s, gravity = {d['gravity']}")
    for b in d["bodies"]:
        srdf = f"; SRDF {b['srdf']}" if b["srdf"] else ""
        click.echo(f"  body {b['name']}: root {b['root_joint']}, nq = {b['nq']}, nv = {b['nv']} ({b['urdf']}{srdf})")
    names = model.coordinates()
    click.echo(f"  coordinates q ({len(names['q_names'])}): {', '.join(names['q_names'])}")
    click.echo(f"  velocities u ({len(names['u_names'])}): {', '.join(names['u_names'])}")
    click.echo(f"  joints in the order of q ({len(d['joints'])}): name, type, q indices, position limits")
    width = max([len(j["name"]) for j in d["joints"]] + [0])
    for j in d["joints"]:
        q = f"q[{j['q'][0]}]" if j["q"][1] - j["q"][0] == 1 else f"q[{j['q'][0]}:{j['q'][1]}]"
        click.echo(f"    {j['name']:<{width}}  {j['type']:<24} {q:<10} {_limits(j)}")
    _list(f"actuators ({len(d['actuators'])}): name, joint, kind, gains, limits",
          [_actuator(a) for a in d["actuators"]], True)
    _list(f"driven joints ({len(d['drives'])}): body, joint, prescribed motion x(t), q(t) = q(0) + x(t) - x(0)",
          [f"{dr['body']}  {dr['joint']}  {dr['motion']}" for dr in d["drives"]], True)
    pairs = d["collision_pairs"]
    if pairs is None:  # a model without a pair list (model.LAZY_PAIRS): its pairs are every two geometries but these
        click.echo(f"  collision pairs ({d['pair_count']}): every two geometries but the excluded pairs below; "
                   f"not listed one by one (the records' gaps are per geometry, within {d['gap_reach']:.3g} m)")
    else:
        _list(f"collision pairs ({len(pairs)}):", pairs, all_pairs)
    excluded = d["excluded_pairs"]
    _list(f"excluded pairs ({len(excluded)}: the SRDF's, overlapping at a reference pose, [collisions] exclude):",
          [f"{e['pair']}  ({e['why']})" for e in excluded], all_pairs)


def _list(title: str, rows: list[str], every: bool) -> None:
    """One indented title and its rows (the first PAIRS_SHOWN unless `every`)."""
    shown = rows if every else rows[:PAIRS_SHOWN]
    click.echo(f"  {title}")
    for p in shown:
        click.echo(f"    {p}")
    if len(shown) < len(rows):
        click.echo(f"    ... and {len(rows) - len(shown)} more (--all-pairs or --json lists them)")


def _drive(dr) -> dict:
    """One [[drives]] entry of `info`: its body, joint and motion (docs/scenes.md)."""
    m = dr.motion
    if m.kind == "sine":
        motion = f"sine: amplitude {float(m.amplitude[0]):g}, {m.frequency:g} Hz, phase {m.phase:g} rad"
    elif m.rate is not None:
        motion = f"velocity {float(m.rate[0]):g}"
    elif m.kind == "table":
        motion = f"table of {len(m.t)} rows over [{float(m.t[0]):g}, {float(m.t[-1]):g}] s"
    else:
        motion = f"{m.kind} {float(m.x[0][0]):g}"
    return {"body": dr.body, "joint": dr.joint, "motion": motion}


def _actuator(a: dict) -> str:
    """One actuator of `info`: [[actuators]] PD (kp, kd, target) or an MJCF motor/position (gear, kp, kv,
    ctrl and force ranges, where its ctrl comes from) and the joint's effort clamp."""
    if a["kind"] == "pd":
        what = f"kp = {a['kp']:g}, kd = {a['kd']:g}, target {a['target']}"
        lim = f"effort {a['effort']:g}" if a["effort"] is not None else ""
    else:
        what = f"gear = {a['gear']:g}" + (f", kp = {a['kp']:g}, kv = {a['kv']:g}" if "kp" in a else "")
        what += ", ctrl from scene" if a["ctrl"] == "scene" else ", ctrl 0 (none given)"
        lim = ", ".join(f"{k} [{a[k][0]:g}, {a[k][1]:g}]" for k in ("ctrlrange", "forcerange") if a[k] is not None)
    if a["effort_limit"] is not None:
        lim = ", ".join(x for x in (lim, f"joint effort limit {a['effort_limit']:g}") if x)
    return f"{a['name']}  {a['joint']}  {a['kind']}  {what}  ({lim or 'no clamp'})"


def _limits(joint: dict) -> str:
    """A joint's position limits, [lower, upper] per limited coordinate with its unit, or "unlimited"."""
    unit = " rad" if joint["type"].startswith(("revolute", "continuous")) else (
        " m" if joint["type"].startswith("prismatic") else "")
    pairs = [(lo, up) for lo, up in zip(joint["lower"], joint["upper"]) if lo is not None or up is not None]
    if not pairs:
        return "unlimited"
    return ", ".join(f"[{'-inf' if lo is None else f'{lo:.6g}'}, {'inf' if up is None else f'{up:.6g}'}]"
                     for lo, up in pairs) + unit


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--trajectory", "npz", type=click.Path(dir_okay=False),
              help="Take the state from this trajectory NPZ (the sample nearest --time).")
@click.option("--time", "t", type=float, default=0.0, show_default=True, help="Sample time [s] in --trajectory.")
@click.option("--restitution", "-e", type=float, help="Restitution e (default: the scene's).")
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
def outcomes(scene, npz, t, restitution, as_json):
    """Every admissible outcome of the impact at a state of SCENE (its initial state by default).

    At a corner (a vertex at an edge or vertex of a box) the law has several stationary points:
    all are listed with their distance 1/2 |v - u-|_M^2, the global minimizers marked, and the one
    the scene's corner_selection policy picks."""
    from ..outcomes import impact_outcomes
    from ..state import State
    from ..trajectory import load_trajectory

    sc, model = _load(scene, restitution=restitution)
    state = None
    if npz:
        try:
            traj = load_trajectory(npz)
        except ValueError as exc:
            fail(str(exc))
        i = int(abs(traj.t - t).argmin())
        if traj.q.shape[1] != model.nq:
            fail(f"{npz}: its q has {traj.q.shape[1]} coordinates, scene {scene} has nq = {model.nq}")
        state = State(float(traj.t[i]), traj.q[i], traj.u[i])
    else:
        from ..model import initial_state
        state = initial_state(model)
    res = impact_outcomes(model, state)
    if as_json:
        click.echo(json.dumps({"scene": sc.name, "t": state.t, "u_minus": state.u.tolist(),
                               "restitution": sc.options.restitution,
                               "outcomes": [{"u_plus": o.u_plus.tolist(), "v": o.v.tolist(), "distance": o.distance,
                                             "energy_loss": o.energy_loss, "global_min": o.global_min,
                                             "selected": o.selected, "pieces": o.pieces} for o in res]}, indent=2))
        return
    click.echo(f"{sc.name} at t = {state.t:g} s, e = {sc.options.restitution:g}, u- = {np.round(state.u, 6).tolist()}:"
               f" {len(res)} admissible outcome(s)")
    for k, o in enumerate(res):
        flags = ("global min" if o.global_min else "stationary") + (", selected" if o.selected else "")
        click.echo(f"  [{k}] u+ = {np.round(o.u_plus, 6).tolist()}  distance {o.distance:.6g} J  "
                   f"energy loss {o.energy_loss:.6g} J  ({flags})  {o.pieces}")


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "-o", "png", type=click.Path(),
              help="PNG (or .svg, .pdf) to write (default: FILE with .png); a folder (DIR/) gets NAME.png.")
@click.option("--save", "png", type=click.Path(), hidden=True)  # the old name of --out
@click.option("--panels", default="energy,gap,percussion", show_default=True,
              help="Comma-separated panels among energy, gap, percussion, q, u.")
def plot(file, png, panels):
    """Energy, gaps, percussions (and q, u) against time from a trajectory FILE."""
    from ..plot import save

    png = output_path(png, default=Path(file).with_suffix(".png"), suffix=(".png", ".svg", ".pdf"), where="--out",
                      inputs=[file], roots=[Path(file).parent])
    try:
        path = save(file, png, [p.strip() for p in panels.split(",") if p.strip()])
    except ValueError as exc:
        fail(str(exc))
    click.echo(f"wrote {path}")
