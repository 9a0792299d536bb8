"""What plot.py draws: every legend entry names a curve that can be seen (curves that coincide,
as in symmetric scenes, are drawn once under all their names), and q and u carry their SI units."""

from itertools import combinations

import matplotlib
import numpy as np
import pytest

from moreau_sim import plot

from helpers import run

matplotlib.use("Agg")
PANELS = ("energy", "gap", "percussion", "q", "u")


def _named(ax) -> list:
    return [line for line in ax.get_lines() if not line.get_label().startswith("_")]


@pytest.mark.parametrize("name", ["resting_box", "newton_cradle_5", "box_stack_5"])
def test_no_legend_entry_is_hidden_under_another_curve(name):
    """resting_box: x, y, qx, qy, qz are all 0 and V = T + V; newton_cradle_5: four balls share a
    velocity; box_stack_5: the resting cubes' gaps are equal. No two named curves of a panel
    coincide (a dashed curve over a solid one stays visible: the ledger over T + V), and every
    curve drawn in colour is named."""
    fig = plot.figure(run(name, duration=0.3), PANELS)
    try:
        for ax in fig.axes:
            named = [line for line in _named(ax) if line.get_linestyle() != "--"]
            ys = [np.asarray(line.get_ydata(), float) for line in named]
            values = np.concatenate(ys) if ys else np.zeros(0)
            span = np.ptp(values[np.isfinite(values)]) if values.size else 0.0
            span = span if span > 0 else 1.0
            for (a, ya), (b, yb) in combinations(zip(named, ys), 2):
                same = len(ya) == len(yb) and np.array_equal(a.get_xdata(), b.get_xdata()) and \
                    np.allclose(ya, yb, rtol=0, atol=plot.SAME * span, equal_nan=True)
                assert not same, f"{ax.get_ylabel()}: {a.get_label()!r} hides under {b.get_label()!r}"
            for line in ax.get_lines():  # grey: the pairs no legend names; black: the zero line
                assert line.get_color() in ("0.75", "k") or not line.get_label().startswith("_"), ax.get_ylabel()
        legend = "\n".join(t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts())
        if name == "resting_box":
            assert "potential V\n= total T + V" in legend
            assert "box/root/x [m]\n= box/root/y [m]\n= box/root/qx [1]" in legend
        if name == "newton_cradle_5":
            assert all(f"ball{i}/root/v_x [m/s]" in legend for i in range(5))
    finally:
        matplotlib.pyplot.close(fig)


@pytest.mark.parametrize(("name", "q", "u"), [("bouncing_ball", "[m]", "[m/s]"), ("pendulum_wall", "[rad]", "[rad/s]"),
                                              ("box_drop", "[m, 1]", "[m/s, rad/s]")])
def test_coordinates_carry_their_units(name, q, u):
    fig = plot.figure(run(name, duration=0.2), ("q", "u"))
    try:
        ax_q, ax_u = fig.axes[:2]
        assert ax_q.get_ylabel().endswith(q) and ax_u.get_ylabel().endswith(u)
        for ax in (ax_q, ax_u):
            assert all(line.get_label().endswith("]") for line in _named(ax))  # each name with its unit
    finally:
        matplotlib.pyplot.close(fig)


def test_joint_limit_percussions_are_named_by_joint_and_side():
    """pendulum_limit strikes its lower limit (pair = number of pairs + the limit's index): the percussion
    legend names it "limit pendulum/hinge lower", never "pair k"; and its dots are the logged percussions."""
    tr = run("pendulum_limit", duration=1.0)
    fig = plot.figure(tr, ("percussion",))
    try:
        dots = [line for line in _named(fig.axes[0]) if line.get_label() != "new impact"]
        assert [line.get_label() for line in dots] == ["limit pendulum/hinge lower"]
        lim = next(x for x in tr.meta["model"]["joint_limits"] if x["name"] == "pendulum/hinge lower")
        sel = tr.arrays["log_pair"] == lim["pair"]
        assert np.array_equal(dots[0].get_ydata(), (tr.arrays["log_P"] / tr.arrays["log_steps"])[sel])
    finally:
        matplotlib.pyplot.close(fig)


def test_a_rest_is_drawn_as_a_line_at_its_percussion_a_step():
    """A ball that comes to rest (zeno_ball, e = 0): its rest is one log row (a stretch of persistent steps,
    docs/theory.md §5.2), drawn as a line from its first step to its last at its mean percussion a step, the
    weight times h (not its sum: a dot at log_P would sit n times too high)."""
    tr = run("zeno_ball", restitution=0.0, duration=0.5)
    a = tr.arrays
    rest = int(np.argmax(a["log_steps"]))
    n, h = int(a["log_steps"][rest]), tr.meta["options"]["dt"]
    assert n > 100
    fig = plot.figure(tr, ("percussion",))
    try:
        lines = [x for x in fig.axes[0].get_lines() if len(x.get_xdata()) == 3 and np.isnan(x.get_xdata()[2])]
        (line,) = lines
        x, y = line.get_xdata(), line.get_ydata()
        assert x[0] == a["log_t"][rest] and x[1] == pytest.approx(a["log_t"][rest] + (n - 1) * h, rel=1e-12)
        assert y[0] == y[1] == a["log_P"][rest] / n and y[0] == pytest.approx(9.81 * h, rel=1e-9)  # 1 kg
    finally:
        matplotlib.pyplot.close(fig)


def test_the_ledger_curve_of_a_driven_run_books_the_work_done_on_it():
    """A driven run (panda_tapping: PD torques) draws the ledger E0 + sum(W_c + corr. + smooth + W_a), which
    follows T + V (to the run's own residual) where the passive ledger would not."""
    tr = run("panda_tapping", duration=0.6)
    fig = plot.figure(tr, ("energy",))
    try:
        line = next(x for x in fig.axes[0].get_lines() if x.get_label().startswith("ledger"))
        assert "W_a" in line.get_label()
        a = tr.arrays
        E = a["kinetic_energy"] + a["potential_energy"]
        assert np.abs(line.get_ydata() - E).max() <= 1e-2 * np.abs(E).max()  # the flagged residual, 1e-3 J
    finally:
        matplotlib.pyplot.close(fig)
