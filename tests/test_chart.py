"""moreau_sim.chart and `moreau-sim chart`: the reference against the bouncing ball's closed form
(docs/theory.md §4.1), the time-stepper's errors falling at its order along the dt ladder, the
Richardson-style reference of a driven scene, the files written, bad input in one line and the
partial JSON of an interrupted chart."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from moreau_sim.chart import ChartInterrupted, chart
from moreau_sim.testing.references import BALL_GAP, G, ball_first_impact, ball_impact_times, zeno_time

ROOT = Path(__file__).resolve().parent.parent
BALL = ROOT / "scenes" / "bouncing_ball.toml"
RADIUS = 0.1  # [m] the bouncing ball's radius: q = gap + RADIUS


def ball_closed_form(e: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q [m] and u [m/s] of the bouncing ball at t (docs/theory.md §4.1): free fall from rest at gap
    d0, each impact reversing the speed times e, at rest on the ground from the accumulation point on."""
    times = ball_impact_times(e, 40)
    v1 = G * ball_first_impact()
    q, u = np.empty_like(t), np.empty_like(t)
    for k, tk in enumerate(t):
        n = int(np.searchsorted(times, tk, side="right"))  # impacts before tk
        if tk >= zeno_time(e):
            q[k], u[k] = RADIUS, 0.0
        elif n == 0:
            q[k], u[k] = RADIUS + BALL_GAP - G * tk ** 2 / 2, -G * tk
        else:
            s, v = tk - times[n - 1], e ** n * v1
            q[k], u[k] = RADIUS + v * s - G * s ** 2 / 2, v - G * s
    return q, u


@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_reference_is_the_closed_form_of_the_ball(e, tmp_path):
    res = chart(BALL, out_dir=tmp_path, dts=[1e-2], tolerances=[1e-4], duration=1.5, repeats=1,
                options={"restitution": e})
    ref = res.reference
    assert ref.kind == "two methods" and not ref.uncertain and max(ref.q_agreement, ref.u_agreement) < 1e-9
    t, q, u = res.reference_samples
    q_exact, u_exact = ball_closed_form(e, t)
    assert len(t) == 151 and np.abs(q[:, 0] - q_exact).max() < 1e-9 and np.abs(u[:, 0] - u_exact).max() < 1e-8


@pytest.mark.parametrize("e", [0.5, 0.9, 1.0])
def test_errors_fall_along_the_dt_ladder_at_first_order(e):
    """An impact instant resolved to within the step makes the midpoint Moreau step first order in q
    (docs/theory.md §4): error <= C h, C depending on where the impact falls in its step (within a
    factor ~3 here), so on a ladder of ratio 4 the error falls at every rung, by about 4."""
    dts = (1e-2 / 2, 1e-2 / 8, 1e-2 / 32, 1e-2 / 128)
    res = chart(BALL, integrators=["time-stepping", "adaptive"], dts=dts, tolerances=[1e-4], duration=1.0,
                repeats=1, options={"restitution": e})
    runs = [r for r in res.runs if r.integrator == "time-stepping"]
    err = np.array([r.q_error for r in runs])
    assert [r.setting for r in runs] == list(dts) and np.all(np.diff(err) < 0), err
    order = np.polyfit(np.log(dts), np.log(err), 1)[0]
    assert 0.8 < order < 1.3, (order, err)
    assert (err / dts).max() < 3 * (err / dts).min(), err / dts
    assert all(r.cpu_per_second > 0 for r in res.runs)


def test_files_are_written_and_name_every_run(tmp_path):
    res = chart(BALL, out_dir=tmp_path / "c", dts=[1e-2, 5e-3], tolerances=[1e-4, 1e-8], duration=0.6, repeats=2)
    for name in ("chart.png", "chart.json", "chart.md"):
        assert (tmp_path / "c" / name).stat().st_size > 1000, name
    data = json.loads((tmp_path / "c" / "chart.json").read_text())
    assert data["status"] == "complete" and data["samples"] == 61 and "pin.difference" in data["norm"]
    assert [(r["integrator"], r["setting"]) for r in data["runs"]] == [
        ("time-stepping", 1e-2), ("time-stepping", 5e-3), ("event-driven", 1e-4), ("event-driven", 1e-8),
        ("adaptive", 1e-4), ("adaptive", 1e-8)]
    assert all(len(r["cpu_seconds"]) == 2 for r in data["runs"])
    assert data["reference"]["kind"] == "two methods" and data["reference"]["uncertain"] is False
    table = (tmp_path / "c" / "chart.md").read_text()
    assert table.count("| time-stepping | dt = ") == 2 and table.count("| adaptive | rtol = ") == 2
    assert res.runs[2].q_error < 1e-9 < res.runs[0].q_error  # the event integrators: exact free flight


def test_driven_scene_uses_time_stepping_and_says_why(tmp_path):
    res = chart(ROOT / "scenes" / "driven_paddle.toml", dts=[1e-2, 5e-3, 2.5e-3], duration=0.3, repeats=1)
    assert set(res.refused) == {"adaptive", "event-driven"} and "driven joint" in res.refused["adaptive"]
    assert res.reference.kind == "two smallest dt, Richardson-style"
    assert [r.status for r in res.runs][-1] == "reference"
    assert "Richardson-style" in res.reference.sentence() and res.reference.uncertain  # a first-order step: not 1e-8
    assert "UNCERTAIN" in res.reference.sentence()


@pytest.mark.parametrize("names, kind", [
    (["time-stepping", "adaptive"], "one method, two orders"),
    (["time-stepping", "event-driven"], "one method, two ODE solvers"),
    (["time-stepping"], "two smallest dt, Richardson-style"),
])
def test_reference_uses_only_the_integrators_asked_for(names, kind):
    res = chart(BALL, integrators=names, dts=[1e-2, 5e-3], tolerances=[1e-6], duration=0.6, repeats=1)
    assert res.reference.kind == kind and not res.refused
    assert "not among the integrators asked for" in res.reference.sentence()
    assert {r.integrator for r in res.runs} == set(names)
    if len(names) > 1:  # the ball's free flights: any two event methods agree to round-off
        assert not res.reference.uncertain and res.runs[-1].q_error < 1e-9


def test_adaptive_fixed_steps_are_said_and_the_check_halves_them():
    """solo_drop has too many features to extrapolate: the adaptive integrator takes fixed midpoint
    steps of the scene's dt, so its two orders would take the same steps; the check halves them."""
    res = chart(ROOT / "scenes" / "solo_drop.toml", integrators=["time-stepping", "adaptive"], dts=[1e-3],
                tolerances=[1e-6], duration=0.05, repeats=1)
    ref, dt = res.reference, 1e-3  # the scene's dt
    assert ref.kind == "one method, two orders" and f"fixed steps at dt = {dt / 2:g} s" in ref.check
    assert "fixed midpoint steps" in ref.why and any("rtol does not act" in n for n in res.notes)
    adaptive = [r for r in res.runs if r.integrator == "adaptive"]
    assert adaptive[0].fixed_steps == 50 and ref.q_agreement > 0  # 0.05 s in steps of 1 ms


def test_corner_scene_says_methods_may_disagree():
    res = chart(ROOT / "scenes" / "corner_point.toml", dts=[1e-2], tolerances=[1e-4], duration=0.2, repeats=1)
    assert any("several admissible outcomes" in n for n in res.notes)


def test_interrupt_keeps_the_runs_so_far(tmp_path):
    said = []

    def log(msg):
        said.append(msg)
        if len(said) == 3:  # the reference's sentence, two ladder runs: then Ctrl-C
            raise KeyboardInterrupt

    with pytest.raises(ChartInterrupted) as exc:
        chart(BALL, out_dir=tmp_path, integrators=["time-stepping"], dts=[1e-2, 5e-3, 2.5e-3], duration=0.5,
              repeats=1, log=log)
    data = json.loads(exc.value.path.read_text())
    assert exc.value.path.name == "chart.partial.json" and data["status"] == "interrupted"
    assert len(data["runs"]) == 2 and data["runs"][0]["q_error"] > 0
    assert not (tmp_path / "chart.json").exists()


def cli(*args):
    return subprocess.run([sys.executable, "-m", "moreau_sim", "chart", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


@pytest.mark.parametrize("args, words", [
    (["nope.toml"], "nope.toml"),
    ([BALL, "--integrators", "time-stepping,rk4"], "--integrators: unknown integrator 'rk4'"),
    ([BALL, "--dt", "3e-3"], "--dt: 0.003 s does not divide the sample step"),
    ([BALL, "--dt", "1e-2,x"], "--dt 1e-2,x"),
    ([BALL, "--tol", "0.5"], "--tol: 0.5 is outside"),
    ([BALL, "--duration", "0"], "--duration: must be a finite number > 0"),
    ([BALL, "--sample-step", "5"], "--sample-step: 5 s is longer than the duration"),
    ([BALL, "--repeats", "0"], "--repeats: must be an integer >= 1"),
    ([BALL, "--set", "restitution=2"], "--set restitution=2"),
])
def test_bad_input_is_one_line(args, words, tmp_path):
    r = cli(*args, "-o", tmp_path / "c")
    assert r.returncode == 2 and r.stderr.startswith("moreau-sim: error: ") and words in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "c" / "chart.json").exists()


def test_command_writes_the_chart(tmp_path):
    r = cli(BALL, "--dt", "1e-2", "--tol", "1e-6", "--duration", "0.3", "-r", "1", "-o", tmp_path / "c", "--json")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    assert Path(data["files"]["png"]).stat().st_size > 10_000 and len(data["runs"]) == 3
    assert math.isfinite(data["reference"]["q_agreement"])
