"""The records' gap column of a scene of many pairs (more than model.GAP_PAIRS, and every scene without a pair list;
contacts.geometry_gaps, recording.Recorder, src/step.cpp Stepper::geometry_gaps): one column per geometry, its nearest
partner's signed distance within Model.gap_reach, +inf beyond; against the distances of every pair, which the same
scene recorded per pair gives (docs/theory.md §2.12, docs/output.md)."""

import json
import subprocess
import sys

import numpy as np
import pytest
from test_broad_phase import ROOT, column, pile

import moreau_sim as ms
from moreau_sim import broad_phase, compiled, plot
from moreau_sim.contacts import geometry_gaps, pair_distances
from moreau_sim.model import Model


def _nearest(model: Model, gaps: np.ndarray) -> np.ndarray:
    """(n, geometries): each geometry's least gap over its pairs, from the (n, pairs) gaps of a listed model."""
    out = np.full((len(gaps), len(model.geometries)), np.inf)
    for k, p in enumerate(model.pairs):
        for g in (p.first, p.second):
            out[:, g] = np.minimum(out[:, g], gaps[:, k])
    return out


def _as_table(monkeypatch) -> None:
    """Scenes built from here on without a pair list (model.LAZY_PAIRS) and with the broad phase
    (broad_phase.MIN_PAIRS): the configuration of every scene above 20,000 pairs, on small scenes."""
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 0)
    monkeypatch.setattr(broad_phase, "MIN_PAIRS", 0)


def _both(sc: ms.Scene, monkeypatch) -> tuple:
    """The run of sc built with its pairs listed, then as a pair table (model.LAZY_PAIRS): (listed, table) models
    and trajectories."""
    listed = ms.build_model(sc)
    a = ms.simulate(listed, progress=False)
    _as_table(monkeypatch)
    table = ms.build_model(sc)
    b = ms.simulate(table, progress=False)
    assert listed.listed and not table.listed
    return listed, a, table, b


@pytest.mark.parametrize("integrator", ["time-stepping", "adaptive"])
@pytest.mark.parametrize("make, T", [(lambda: column(12, exclude=False), 0.02), (lambda: pile(27), 0.06)],
                         ids=["column", "pile"])
def test_a_table_records_each_geometrys_nearest_gap(make, T, integrator, monkeypatch):
    """The same run (q, u bit for bit) records per geometry what the listed run's pair gaps give, bit for bit: the
    least over the geometry's pairs where it is within the reach, +inf elsewhere."""
    sc = make().with_options(integrator=integrator, duration=T)
    listed, a, table, b = _both(sc, monkeypatch)
    assert a.meta["status"] == b.meta["status"] == "complete"
    assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u)
    assert a.gap.shape == (len(a.t), len(listed.pairs)) and b.gap.shape == (len(b.t), len(table.geometries))
    ref = _nearest(listed, a.gap)
    near = ref <= table.gap_reach
    assert near.mean() > 0.5 and np.array_equal(b.gap, np.where(near, ref, np.inf))
    assert ms.summary(b)["min_gap"] == ms.summary(a)["min_gap"]
    m = b.meta["model"]
    assert m["collision_pairs"] is None and m["pair_count"] == len(listed.pairs) == len(table.pairs)
    assert m["gap_columns"] == "geometries" and m["gap_reach"] == table.gap_reach
    assert m["geometries"] == list(table.gap_names) == [go.name for go in listed.geometries]
    logged = sorted(set(b.log_pair.tolist()))
    assert logged and m["logged_pairs"] == {str(k): listed.pairs[k].name for k in logged}
    assert a.meta["model"]["gap_columns"] == "pairs" and "logged_pairs" not in a.meta["model"]


def _two_beads(d: float, *, ground: bool = True) -> ms.Scene:
    """Bead 0 on the ground (gap 0), bead 1 d [m] above it, on vertical prismatic joints (radius 0.1 m)."""
    b = ms.SceneBuilder("two_beads", folder=f"{ROOT}/scenes", restitution=0.5, dt=1e-3, duration=0.01)
    b.add_body("bead0", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1])
    b.add_body("bead1", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.3 + d])
    if ground:
        b.add_halfspace("ground")
    return b.build()


def test_the_reach_at_its_edge(monkeypatch):
    """Bead 1 1e-12 m within the reach from bead 0 records their distance; 1e-12 m beyond it, +inf (its only other
    partner, the ground, is farther still; the broad phase examines the pair, its boxes being within twice the
    reach); the others record 0 all along."""
    _as_table(monkeypatch)
    probe = ms.build_model(_two_beads(0.0))
    reach = probe.gap_reach
    assert reach == 0.1  # half the bead's diameter (the median of the bounded geometries' largest sides)
    for d, expect in ((reach - 1e-12, "finite"), (reach + 1e-12, "inf")):
        model = ms.build_model(_two_beads(d))
        data = ms.make_data(model)
        q = ms.initial_state(model, data).q
        g = geometry_gaps(model, data, q)
        whole = pair_distances(model, data, q)  # every pair, for the reference
        names = model.gap_names
        assert len(names) == 3 and names[1].startswith("bead1/") and names[2] == "ground"
        assert g[0] == g[2] == 0.0
        if expect == "finite":
            assert g[1] == pytest.approx(d, abs=1e-15) and g[1] == min(whole[k] for k, p in enumerate(model.pairs)
                                                                       if 1 in (p.first, p.second))
        else:
            assert g[1] == np.inf and min(whole) == 0.0


def test_a_run_with_a_geometry_beyond_reach_is_complete(monkeypatch, tmp_path):
    """+inf in a pair table's gaps is not an overflow: the run completes, its file keeps them, the figure draws; with
    no two geometries within reach all along (no ground), the summary's min gap is None (JSON has no inf)."""
    _as_table(monkeypatch)
    # bead 1 starts 1 cm beyond the reach of bead 0 and falls within it in 45 ms
    traj = ms.simulate(ms.build_model(_two_beads(0.11).with_options(duration=0.06)), progress=False)
    assert traj.meta["status"] == "complete" and traj.complete
    assert np.isposinf(traj.gap[0, 1]) and np.isfinite(traj.gap[-1]).all()
    back = ms.load_trajectory(traj.save(tmp_path / "beads.npz"))
    assert np.array_equal(back.gap, traj.gap) and back.meta["model"]["gap_columns"] == "geometries"
    fig = plot.figure(back)
    names = traj.meta["model"]["geometries"]
    gaps, percussions = ([t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes[1:3])
    assert names[1] in gaps and fig.axes[1].get_ylabel().startswith("nearest gap")
    g = back.gap[np.isfinite(back.gap)]
    assert fig.axes[1].get_ylim()[1] >= g.max() > 0.09  # every recorded gap in view (all within the reach)
    assert f"{names[0]}|{names[2]}" in "".join(percussions), percussions  # the logged pair's name (logged_pairs)
    apart = ms.simulate(ms.build_model(_two_beads(0.5, ground=False).with_options(gravity=(0.0, 0.0, 0.0))),
                        progress=False)
    assert apart.meta["status"] == "complete" and np.isposinf(apart.gap).all()
    assert ms.summary(apart)["min_gap"] is None
    json.dumps(dict(ms.summary(apart)), allow_nan=False)


@pytest.mark.slow
def test_info_of_a_scene_without_a_pair_list(tmp_path):
    """`moreau-sim info` on a column of 210 beads (22,155 pairs, above model.LAZY_PAIRS) counts the pairs and lists
    none of them; --json says the gap columns are the geometries."""
    b = ms.SceneBuilder("column_210", folder=f"{ROOT}/scenes", restitution=0.9, dt=5e-4, duration=0.01)
    for k in range(210):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    path = b.save(tmp_path / "column_210.toml")
    run = [sys.executable, "-m", "moreau_sim.cli", "info", str(path)]
    text = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert text.returncode == 0, text.stderr
    assert "collision pairs (22155): every two geometries but the excluded pairs below" in text.stdout
    assert "bead0|bead1" not in text.stdout
    d = json.loads(subprocess.run(run + ["--json"], capture_output=True, text=True, timeout=300).stdout)
    assert d["collision_pairs"] is None and d["pair_count"] == 22155 and d["gap_columns"] == "geometries"
    assert d["gap_reach"] == 0.1 and len(d["geometries"]) == 211


def _differ(a, b) -> list[str]:
    """The arrays of two trajectories that differ in dtype, shape or bits."""
    return sorted(k for k in set(a.arrays) | set(b.arrays) if k not in a.arrays or k not in b.arrays
                  or a.arrays[k].dtype != b.arrays[k].dtype or a.arrays[k].tobytes() != b.arrays[k].tobytes())


@pytest.mark.parametrize("make, T", [(lambda: column(30, exclude=False), 0.03), (lambda: pile(27), 0.3),
                                     (lambda: _two_beads(0.11), 0.06)], ids=["column", "pile", "beyond_reach"])
def test_the_compiled_run_records_a_table_as_the_python_run(make, T, monkeypatch):
    """A scene without a pair list runs in the compiled run loop (src/run.cpp, its samples' gaps per geometry:
    Stepper::geometry_gaps), with the Python run's arrays bit for bit (+inf beyond the reach included; the pile's
    box pairs warm-start GJK from the queries before, which a step the loop undoes puts back)."""
    _as_table(monkeypatch)
    sc = make().with_options(duration=T, step_impl="compiled")
    model = ms.build_model(sc)
    assert not model.listed and compiled.loop_refusal(model, "Runner", "the run loop", whole=False) is None
    ref = ms.simulate(model, progress=False, python_run=True)
    new = ms.simulate(model, progress=False, python_run=False)
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert new.meta["status"] == ref.meta["status"]  # (the pile's: flagged, a contact deeper than its allowance)
    assert _differ(ref, new) == [] and new.meta.get("invariants") == ref.meta.get("invariants")
    assert new.meta["run"]["python_steps"] < len(new.t) / 2  # mostly compiled
    if sc.name == "pile_27":  # a step handed back (the Python run's), after which the loop resumes from its queries
        assert new.meta["run"]["python_steps"] >= 1
    if sc.name == "two_beads":
        assert np.isposinf(new.gap[0, 1]) and np.isfinite(new.gap[-1]).all()


@pytest.mark.parametrize("make", [lambda: column(12, exclude=False), lambda: pile(27)], ids=["column", "pile"])
def test_the_compiled_gaps_are_pythons(make, monkeypatch):
    """Stepper::geometry_gaps is contacts.geometry_gaps bit for bit at states spread over a run (pulled together and
    apart: every geometry within the reach, some, none)."""
    _as_table(monkeypatch)
    model = ms.build_model(make().with_options(duration=0.05, step_impl="compiled"))
    traj = ms.simulate(model, progress=False, python_run=True)
    data = ms.make_data(model)
    stepper = compiled._context(model, data).stepper
    other = ms.make_data(model)
    states = list(traj.q[:: max(len(traj.q) // 5, 1)]) + [_spread(model, traj.q[-1], f) for f in (1.2, 1.5, 1.8, 3.0)]
    seen = set()
    for q in states:
        py, cpp = geometry_gaps(model, other, q), np.asarray(stepper.geometry_gaps(q))
        assert py.tobytes() == cpp.tobytes()
        seen.add("all" if np.isfinite(py).all() else "none" if np.isposinf(py).all() else "some")
    assert seen == {"all", "some", "none"}


def _spread(model: Model, q: np.ndarray, f: float) -> np.ndarray:
    """q with every body's position (a prismatic joint's coordinate, a free joint's x y z) times f."""
    q = q.copy()
    for j in model.joints():
        a = j["q"][0]
        q[a:a + (3 if j["type"].startswith("translation") else 1)] *= f
    return q


def test_a_failed_distance_names_the_geometry(monkeypatch):
    """A distance coal cannot compute (NaN) in a table's gaps stops the run naming the geometry, the step and the
    time (as a listed scene names the pair: test_gjk_guess), its records left finite or +inf; never complete."""
    import moreau_sim.contacts as contacts
    _as_table(monkeypatch)
    real = contacts.geometry_gaps  # (the recorder's record_gaps calls it for a table)

    def failing(model, data, q):
        g = real(model, data, q)
        if q[1] < 0.39:
            g[1] = np.nan
        return g
    monkeypatch.setattr(contacts, "geometry_gaps", failing)
    model = ms.build_model(_two_beads(0.1).with_options(duration=0.05))
    with pytest.raises(ms.SimulationError) as info:  # the Python loop (the compiled one hands a NaN gap's step to it)
        ms.simulate(model, progress=False, python_run=True)
    msg = str(info.value)
    assert "step " in msg and f"a pair of geometry {model.gap_names[1]}" in msg and "undefined" in msg, msg
    traj = info.value.trajectory
    assert not traj.complete and not np.isnan(traj.arrays["gap"]).any()


@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
def test_a_resting_column_without_a_pair_list_carries_its_weight(e):
    """A column of 250 touching beads (31,375 pairs: no pair list; the compiled run loop) from rest, 40 steps: each
    contact passes on the weight of the beads above it, P = (n - i) m |g| h a step (the closed form of a resting
    stack, to 1e-12 of it), whatever e; every gap stays within the contact tolerance, T + V never rises."""
    from benchmarks.scaling import column

    n, h = 250, 5e-4
    model = ms.build_model(column(n).with_options(restitution=e, duration=40 * h))
    assert not model.listed
    traj = ms.simulate(model, progress=False)
    assert traj.meta["run"]["loop"] == "compiled" and traj.meta["status"] == "complete"
    names = traj.meta["model"]["logged_pairs"]
    m, g = 1.0, 9.81
    for k, P, steps in zip(traj.log_pair.tolist(), traj.log_P.tolist(), traj.log_steps.tolist()):
        below = names[str(k)].split("|")  # "bead{i}/ball_0|bead{i-1}/ball_0" or "bead0/ball_0|ground"
        i = min(int(x.split("/")[0][4:]) for x in below if x.startswith("bead"))
        i = i + 1 if "ground" not in below else 0  # the contact under bead i
        assert P / steps == pytest.approx((n - i) * m * g * h, rel=1e-12, abs=0), (names[str(k)], P, steps)
    assert len(set(traj.log_pair.tolist())) == n  # every contact pushed
    assert traj.gap.shape == (len(traj.t), n + 1) and traj.gap.min() >= -model.options.contact_tolerance
    E = traj.total_energy
    assert (E - E[0]).max() <= 1e-12 * abs(E[0])


@pytest.mark.parametrize("make, T", [(lambda: column(30, exclude=False), 0.03), (lambda: pile(27), 0.15)],
                         ids=["column", "pile"])
def test_a_table_resumes_from_its_checkpoint_bitwise(make, T, monkeypatch, tmp_path):
    """A run of a scene without a pair list, checkpointed mid-run and resumed (the compiled run loop; the GJK warm
    starts of the pairs queried so far carried in Data.warm_start's "table"), gives the uninterrupted run's arrays, a
    gap per geometry; neither run makes a GeometryModel of every pair (a column of 1000 beads: 500,500 of them)."""
    from moreau_sim.checkpoint import Checkpoint

    _as_table(monkeypatch)
    sc = make().with_options(duration=T, step_impl="compiled", save_every=3)
    path = tmp_path / "c.npz"
    first, second = ms.build_model(sc), ms.build_model(sc)
    full = ms.simulate(first, progress=False, checkpoint=Checkpoint(path=path, every=T / 3, keep=True))
    ck = ms.load_trajectory(path).meta["checkpoint"]
    assert 0 < ck["steps"] < round(T / sc.options.dt)
    table = ck["warm_start"]["table"]
    assert table["collision"] and table["distance"] and all(len(row) == 5 for row in table["collision"])
    resumed = ms.simulate(second, progress=False, checkpoint=Checkpoint(path=path, resume=True))
    assert resumed.complete == full.complete and _differ(full, resumed) == []
    assert resumed.gap.shape[1] == len(resumed.meta["model"]["geometries"])
    assert first.geometry_model is None and second.geometry_model is None


@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_the_swept_test_of_a_table_queries_its_pairs_alone(impl, monkeypatch):
    """fast_impact's marble at 50 m/s onto a 1 cm plate (the swept test catches it, tunnelling.py) built without a
    pair list takes the listed run's steps bit for bit, its swept distances queried on each pair's own coal objects:
    no GeometryModel nor GeometryData of every pair is made."""
    from helpers import scene

    sc = scene("fast_impact", step_impl=impl)
    listed = ms.simulate(ms.build_model(sc), progress=False)
    _as_table(monkeypatch)
    model = ms.build_model(sc)
    table = ms.simulate(model, progress=False)
    assert not model.listed and model.geometry_model is None
    assert table.meta["status"] == listed.meta["status"] == "complete"
    for k in ("t", "q", "u", "log_P", "log_kind", "log_pair"):
        assert table.arrays[k].tobytes() == listed.arrays[k].tobytes(), k
    assert 4 in table.log_kind.tolist()  # a swept contact (contacts.FeatureKind.SWEPT) was logged
    assert table.q[:, 0].min() > 0.5  # the marble never passed the plate's top


@pytest.mark.parametrize("integrator", ["time-stepping", "adaptive"])
def test_a_listed_scene_of_many_pairs_records_a_gap_per_geometry(integrator, monkeypatch):
    """A column of 50 beads lists its 1275 pairs (below model.LAZY_PAIRS) but has more than model.GAP_PAIRS: its
    samples record a gap per geometry, the least of what the same run records per pair (model.GAP_PAIRS raised) where
    within the reach, bit for bit, +inf elsewhere; the compiled run loop records them as the Python one."""
    sc = column(50, exclude=False).with_options(integrator=integrator, duration=0.01, step_impl="compiled")
    model = ms.build_model(sc)
    assert model.listed and len(model.pairs) == 1275 > ms.model.GAP_PAIRS and model.gaps_per_geometry
    per_geometry = ms.simulate(model, progress=False)
    assert per_geometry.gap.shape[1] == 51 and per_geometry.meta["model"]["gap_columns"] == "geometries"
    assert per_geometry.meta["model"]["collision_pairs"] and "logged_pairs" not in per_geometry.meta["model"]
    if integrator == "time-stepping":
        assert per_geometry.meta["run"]["loop"] == "compiled"
        python = ms.simulate(model, progress=False, python_run=True)
        assert _differ(per_geometry, python) == []
    monkeypatch.setattr(ms.model, "GAP_PAIRS", 10 ** 6)
    per_pair_model = ms.build_model(sc)
    per_pair = ms.simulate(per_pair_model, progress=False)
    assert per_pair.gap.shape[1] == 1275 and np.array_equal(per_pair.q, per_geometry.q)
    ref = _nearest(per_pair_model, per_pair.gap)
    assert np.array_equal(per_geometry.gap, np.where(ref <= model.gap_reach, ref, np.inf))
