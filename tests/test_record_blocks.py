"""A step's dense-output samples recorded and checked as one block (driver._Loop._block: Recorder.block and
write_block, Invariants.samples; docs/theory.md §9, §10): the adaptive ball's impact times and apexes against their
closed forms (§4.1) with the samples recorded in blocks; every array and the run's ledger, violations and status
bitwise those of the same run recorded sample by sample (the one-by-one path, which the block path falls back to);
runs with an injected fault (a booked energy that was not there, a penetration, a NaN) flagged or stopped at the
same sample as one by one, strict included; each check of a block at its edge; and the cheap paths the recording
took on the way (ledger._quad on floats, the spare rows a group keeps) at theirs."""

from __future__ import annotations

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import columns, compiled_events, driver, invariants, recording, trajectory
from moreau_sim.adaptive import AdaptiveRun, simulate_adaptive
from moreau_sim.columns import Columns
from moreau_sim.data import make_data
from moreau_sim.errors import SimulationError
from moreau_sim.invariants import Invariant, Invariants, InvariantViolation
from moreau_sim.ledger import QUAD_FLOATS, _quad
from moreau_sim.recording import Recorder
from moreau_sim.state import State
from moreau_sim.sums import ordered
from moreau_sim.testing.references import BALL_GAP, ball_apex_times, ball_impact_times

from helpers import scene

BELOW, ABOVE = 0.5, 1.5  # a check at this fraction of its bound passes / finds something
TIGHT = dict(rtol=1e-12, atol=1e-12)


def adaptive_model(name: str, **options) -> ms.Model:
    return ms.build_model(scene(name, integrator="adaptive", **options))


@pytest.fixture
def blocks(monkeypatch):
    """Count the blocks written (Recorder.write_block) and their samples. Blocks come from the compiled DenseSampler:
    the package's build always has it, and a test of blocks without it would prove nothing."""
    assert ms.compiled.available(), ms.compiled.unavailable_reason()
    seen = []
    write = Recorder.write_block

    def counted(self, b):
        seen.append(len(b.t))
        return write(self, b)
    monkeypatch.setattr(Recorder, "write_block", counted)
    return seen


def one_by_one(monkeypatch) -> None:
    """The driver records every sample by itself (what it did before blocks, and where a block goes back to)."""
    monkeypatch.setattr(driver._Loop, "_block", lambda self, *args: False)


def same_bits(a: ms.Trajectory, b: ms.Trajectory) -> None:
    assert set(a.arrays) == set(b.arrays)
    for k in a.arrays:
        assert a.arrays[k].shape == b.arrays[k].shape and a.arrays[k].tobytes() == b.arrays[k].tobytes(), k
    for k in ("status", "ledger", "invariants", "zeno"):
        assert a.meta.get(k) == b.meta.get(k), k


# ---- the physics, recorded in blocks ------------------------------------------------------------------------------


@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_block_recorded_ball_meets_its_impact_times_and_apexes(e, blocks):
    """Samples every 5 ms and at each apex (its closed form, docs/theory.md §4.1), recorded in blocks under the
    invariant checks: the impacts at t_k and the apexes at 0.9 e^(2k) m at rest, the run complete."""
    n = 6
    tn = np.array(ball_impact_times(e, n + 1))
    apex_t = np.array(ball_apex_times(e, n))
    T = float(tn[n]) + 0.01
    grid = np.union1d(np.linspace(0.0, T, int(T / 0.005) + 1), apex_t)
    model = adaptive_model("bouncing_ball", restitution=e, duration=T, **TIGHT)
    tr = simulate_adaptive(model, t_eval=grid, check=Invariants(model, rtol=TIGHT["rtol"]))
    assert tr.complete and tr.meta["run"]["steps_fixed"] == 0
    assert sum(blocks) == len(grid) - 1 and max(blocks) > 1  # every sample but the start's, in blocks
    assert np.abs(tr.log_t[:n + 1] - tn).max() < 1e-9
    at = np.searchsorted(tr.t, apex_t)
    assert np.array_equal(tr.t[at], apex_t)
    assert np.abs(tr.gap[at, 0] - BALL_GAP * e ** (2 * np.arange(1, n + 1))).max() < 1e-9
    assert np.abs(tr.u[at, 0]).max() < 1e-9


CASES = [("bouncing_ball", 0.5, 1.3), ("bouncing_ball", 0.8, 3.1), ("bouncing_ball", 1.0, 6.0),
         ("newton_cradle_5", 1.0, 1.0), ("newton_cradle_5_gapped", 1.0, 0.5), ("zeno_ball", 0.5, 2.0)]


@pytest.mark.parametrize("name, e, T", CASES)
def test_blocks_are_bitwise_the_samples_one_by_one_and_repeat(name, e, T, monkeypatch, blocks):
    """ms.simulate at rtol 1e-10, a sample every dt = 0.025 s: the arrays, ledger, violations and status of the
    block-recorded run are those of the same run recorded sample by sample, and of itself run again."""
    model = adaptive_model(name, restitution=e, duration=T, rtol=1e-10, atol=1e-12, dt=0.025, save_every=1)
    a = ms.simulate(model, progress=False)
    assert blocks and a.meta["status"] == "complete"
    same_bits(a, ms.simulate(model, progress=False))
    one_by_one(monkeypatch)
    same_bits(a, ms.simulate(model, progress=False))


# ---- faults: flagged or stopped at the same sample ----------------------------------------------------------------


def faulty(monkeypatch, after: int, *, corr: float = 0.0, work: float = 0.0) -> list:
    """The first accepted point of a smooth step (no contact work) after the `after`-th of each adaptive run reports
    `corr` [J] of correction energy and `work` [J] of contact work that did not happen (an energy booked that T + V
    does not show). Returns [(t of the point before it, t of it) [s]] per run."""
    step = AdaptiveRun.step
    where = []

    def faulted(self, t_sample=np.inf):
        before = self.s.state.t
        rep = step(self, t_sample)
        n = self.__dict__["_points"] = self.__dict__.get("_points", 0) + 1
        if n > after and rep.work == 0.0 and not self.__dict__.get("_faulted"):
            self.__dict__["_faulted"] = True
            rep.corr += corr
            rep.work += work
            where.append((before, rep.t))
        return rep
    monkeypatch.setattr(AdaptiveRun, "step", faulted)
    return where


def sampled(monkeypatch, fault) -> None:
    """The compiled samples changed by fault(t, Q, U, T, V, G) (in place) before the driver sees them."""
    make = compiled_events.sampler

    def wrapped(*args, **kw):
        samples = make(*args, **kw)
        if samples is None:
            return None

        def changed(t0, q0, u0, a0, t1, q1, u1, a1, grid):
            Q, U, T, V, G = samples(t0, q0, u0, a0, t1, q1, u1, a1, grid)
            Q, U, T, V, G = Q.copy(), U.copy(), T.copy(), V.copy(), G.copy()
            fault(np.asarray(grid), Q, U, T, V, G)
            return Q, U, T, V, G
        return changed
    monkeypatch.setattr(compiled_events, "sampler", wrapped)


def both_ways(monkeypatch, run):
    """run() with blocks, then one by one: (its result or the SimulationError it raised) each way."""
    out = []
    for k in range(2):
        if k:
            one_by_one(monkeypatch)
        try:
            out.append(run())
        except SimulationError as exc:
            out.append(exc)
    return out


BALL = dict(restitution=0.8, duration=1.5, rtol=1e-10, atol=1e-12, dt=0.025, save_every=1)


@pytest.mark.parametrize("kind", ["correction", "work"])
def test_a_booked_energy_that_was_not_there_is_flagged_at_the_same_sample(kind, monkeypatch, blocks):
    """A correction energy (or contact work) of -1 mJ booked at a smooth step after the 4th accepted point: a gain
    the checks must find, an energy gain at that point (correction) and the ledger's residual at the first sample
    after the point before it, with the same violations (time, point, size, message) in blocks as one by one."""
    model = adaptive_model("bouncing_ball", **BALL)
    where = faulty(monkeypatch, 4, **({"corr": -1e-3} if kind == "correction" else {"work": -1e-3}))
    a, b = both_ways(monkeypatch, lambda: ms.simulate(model, progress=False))
    assert a.meta["status"] == "flagged" and len(where) == 2 and where[0] == where[1] and blocks
    found = {v["invariant"]: v for v in a.meta["invariants"]}
    assert set(found) == ({Invariant.LEDGER.value} if kind == "work" else
                          {Invariant.LEDGER.value, Invariant.ENERGY_GAIN.value})
    t_before, t_point = where[0]
    ledger_v = found[Invariant.LEDGER.value]
    assert ledger_v["size"] == pytest.approx(1e-3, rel=1e-6)
    assert ledger_v["t"] == a.t[np.searchsorted(a.t, t_before, side="right")]  # the first sample after it
    if kind == "correction":
        assert found[Invariant.ENERGY_GAIN.value]["t"] == t_point
    same_bits(a, b)


def test_strict_stops_at_the_same_sample(monkeypatch):
    """strict: the ledger's violation raised at the same sample, the same samples kept before it."""
    model = adaptive_model("bouncing_ball", **BALL)
    faulty(monkeypatch, 4, work=-1e-3)
    a, b = both_ways(monkeypatch, lambda: ms.simulate(model, progress=False, strict=True))
    assert isinstance(a, InvariantViolation) and isinstance(b, InvariantViolation) and str(a) == str(b)
    assert 1 < len(a.trajectory.t) < 61
    same_bits(a.trajectory, b.trajectory)


@pytest.mark.parametrize("samples, flagged", [(2, False), (3, True)])
def test_a_penetration_at_samples_is_flagged_at_its_third(samples, flagged, monkeypatch, blocks):
    """The gaps of the samples from 0.2 s on (2 or 3 of them, before the first impact) 1 mm inside: beyond the
    sample allowance contact_tolerance + h max |gamma-| for PERSIST = 3 samples is a penetration, flagged at the
    third, in blocks as one by one; for 2 the run ends complete."""
    lo, hi = 0.2 - 1e-9, 0.2 + 0.025 * (samples - 1) + 1e-9

    def fault(t, Q, U, T, V, G):
        G[(t > lo) & (t < hi)] = -1e-3
    sampled(monkeypatch, fault)
    model = adaptive_model("bouncing_ball", **BALL)
    a, b = both_ways(monkeypatch, lambda: ms.simulate(model, progress=False))
    same_bits(a, b)
    assert blocks  # the other steps' samples went in blocks
    pen = [v for v in a.meta.get("invariants", []) if v["invariant"] == Invariant.PENETRATION.value]
    assert bool(pen) == flagged and a.meta["status"] == ("flagged" if flagged else "complete")
    if flagged:
        deep = a.t[(a.t > lo) & (a.t < hi)]
        assert len(deep) == 3 and pen[0]["t"] == deep[-1] and "for 3 samples" in pen[0]["message"]


@pytest.mark.parametrize("where", ["q", "T"])
def test_a_non_finite_sample_stops_the_run_at_it(where, monkeypatch):
    """A NaN in q (or in T) of the sample at 0.5 s: the run stops there with the message it gave one by one, the
    samples before it kept (and that sample too when only its energy is non-finite: it is recorded, then found)."""
    def fault(t, Q, U, T, V, G):
        (Q if where == "q" else T[:, None])[t == 0.5] = np.nan
    sampled(monkeypatch, fault)
    model = adaptive_model("bouncing_ball", **BALL)
    a, b = both_ways(monkeypatch, lambda: ms.simulate(model, progress=False))
    assert isinstance(a, SimulationError) and isinstance(b, SimulationError) and str(a) == str(b)
    assert "t = 0.5 s" in str(a) and "non-finite" in str(a)
    kept = a.trajectory.t
    assert len(kept) == (20 if where == "q" else 21) and kept[-1] == (0.475 if where == "q" else 0.5)
    same_bits(a.trajectory, b.trajectory)


# ---- a block's checks at their edges, on hand-made samples of the ball ---------------------------------------------


def started(model):
    """A Recorder and the invariant checks after the ball's start sample at z = 1 m, at rest."""
    data = make_data(model)
    inv, rec = Invariants(model, rtol=1e-8), Recorder(model, data, 16)
    s = State(0.0, np.array([1.0]), np.array([0.0]))
    rec.sample(s, 0.0, 0.0, 0)
    assert inv("sample", s, None, rec) is None and inv("start", s, None, rec) is None
    return data, inv, rec


def ball_block(model, data, z, u, work=0.0):
    """Samples of the ball at heights z, speeds u, 1 ms apart, with their energies and gaps as the recorder takes
    them."""
    from moreau_sim.contacts import pair_distances
    from moreau_sim.energy import kinetic, potential

    k = len(z)
    t = 1e-3 * np.arange(1, k + 1)
    Q, U = np.array(z, float)[:, None], np.array(u, float)[:, None]
    T = np.array([kinetic(model, data, Q[i], U[i]) for i in range(k)])
    V = np.array([potential(model, data, Q[i]) for i in range(k)])
    G = np.array([pair_distances(model, data, Q[i]) for i in range(k)])
    return t, Q, U, T, V, G


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_blocks_ledger_check_at_its_bound(frac):
    """Contact work frac x the ledger's bound that T + V does not show: the block passes below the bound (recorded
    at once), and above it goes back one by one, where the sample flags it."""
    model = ms.build_model(scene("bouncing_ball", integrator="adaptive", rtol=1e-8))
    data, inv, rec = started(model)
    bound = inv.rel_ledger * inv.scale
    t, Q, U, T, V, G = ball_block(model, data, [0.99, 0.98, 0.97], [-0.1, -0.2, -0.3])
    b = rec.block(t, Q, U, T, V, G, -frac * bound, 0.0, 0)
    assert inv.samples(b, rec) == (frac < 1)
    data, inv, rec = started(model)  # (a block that passed has carried the checks' figures past it)
    found = None
    for i in range(3):  # one by one
        s = State(float(t[i]), Q[i], U[i])
        rec.sample(s, -frac * bound if i == 0 else 0.0, 0.0, 0, (float(T[i]), float(V[i]), G[i]))
        found = found or inv("sample", s, None, rec)
    assert (found is not None) == (frac > 1)


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_blocks_gap_check_at_its_allowance(frac):
    """A sample frac x the allowance contact_tolerance + h max |gamma-| inside: the block passes below it (and
    clears the count of deep samples), above it goes back one by one."""
    model = ms.build_model(scene("bouncing_ball", integrator="adaptive", rtol=1e-8))
    data, inv, rec = started(model)
    allowed = inv.tol + inv.h * inv.v_app + invariants.GAP_ROUND_OFF
    r = -float(ms.contacts.pair_distances(model, data, np.zeros(1))[0])  # the gap at z = 0 is -r
    t, Q, U, T, V, G = ball_block(model, data, [0.5, r - frac * allowed], [0.0, 0.0])
    inv.deep_samples = 2
    assert inv.samples(rec.block(t, Q, U, T, V, G, 0.0, 0.0, 0), rec) == (frac < 1)
    assert inv.deep_samples == (0 if frac < 1 else 2)


def test_a_block_is_the_samples_rows_and_figures():
    """The rows write_block records and the ledger's figures it leaves are sample()'s, bit for bit (an impact's
    ledger terms carried into the first), and the checks' running figures Invariants._sample's."""
    model = ms.build_model(scene("bouncing_ball", integrator="adaptive", rtol=1e-8))
    data, inv, rec = started(model)
    data2, inv2, rec2 = started(model)
    t, Q, U, T, V, G = ball_block(model, data, [0.9, 0.7, 0.71, 0.72], [-1.0, 2.0, 1.5, 1.0])
    for r in (rec, rec2):  # an impact's terms before them, its E such that the ledger closes
        r._diss, r._law, r._smooth, r._E = 0.25, 0.125, 1e-3, inv.Es + 0.1 + 0.2 + 1e-3
    b = rec.block(t, Q, U, T, V, G, 0.1, 0.2, 1)
    assert inv.samples(b, rec)
    rec.write_block(b)
    for i in range(4):
        s = State(float(t[i]), Q[i], U[i])
        rec2.sample(s, 0.1 if i == 0 else 0.0, 0.2 if i == 0 else 0.0, 1, (float(T[i]), float(V[i]), G[i]))
        assert inv2("sample", s, None, rec2) is None
    for k, a in rec.arrays().items():
        assert a.tobytes() == rec2.arrays()[k].tobytes(), k
    assert (rec._rise, rec._E, rec._TV, rec._smooth, rec._diss) == (rec2._rise, rec2._E, rec2._TV, 0.0, 0.0)
    assert (inv.residual, inv.Es, inv.deep_samples) == (inv2.residual, inv2.Es, inv2.deep_samples)


# ---- the cheap paths at their edges ------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, QUAD_FLOATS, QUAD_FLOATS + 1])
def test_quad_on_floats_is_ordereds_bit_for_bit(n):
    """x'Mx on Python floats (n <= QUAD_FLOATS) and through sums.ordered (above) are the same sums: the same bits
    on random M and x of mixed magnitudes, with zeros, signed zeros and an infinity."""
    rng = np.random.default_rng(n)
    for trial in range(300):
        M = rng.standard_normal((n, n)) * 10.0 ** rng.integers(-6, 6, (n, n))
        x = rng.standard_normal(n) * 10.0 ** rng.integers(-6, 6, n)
        if trial % 5 == 1:
            x[rng.integers(n)] = 0.0
        if trial % 7 == 2:
            x[:] = -0.0
        if trial % 50 == 3:
            M[0, 0] = np.inf
        got = np.float64(_quad(M, x))
        want = np.float64(float(ordered(ordered(x, M), x)))
        assert got.tobytes() == want.tobytes() or (np.isnan(got) and np.isnan(want))


@pytest.mark.parametrize("spare", [-1, 1])
def test_a_group_keeps_spare_rows_up_to_fit_slack_bytes(spare):
    """At the end of a recording a group cuts its unused rows when they are more than FIT_SLACK_BYTES, and keeps
    them when they are at most that; its arrays are its n rows either way."""
    sizes = {"nq": 1, "nv": 1, "pairs": 1}
    row = sum(Columns(trajectory.IMPACTS, sizes, 1).row_bytes.values())
    rows = columns.FIT_SLACK_BYTES // row + (1 if spare > 0 else 0) + 3
    g = Columns(trajectory.IMPACTS, sizes, rows)
    for j in range(3):
        i = g.free()
        g.cols["impact_t"][i] = 0.5 * j
        g.commit()
    g.fit()
    assert len(g.cols["impact_t"]) == (3 if spare > 0 else rows)
    assert np.array_equal(g.arrays()["impact_t"], [0.0, 0.5, 1.0])


@pytest.mark.parametrize("size", [recording.FINITE_FLOATS, recording.FINITE_FLOATS + 3])
@pytest.mark.parametrize("bad", [None, np.nan, np.inf, -np.inf])
def test_a_blocks_finiteness_on_floats_and_through_sums(size, bad):
    """_finite says whether every entry of Q, U, G is finite, on Python floats (up to FINITE_FLOATS entries) as
    through numpy's sums (above): a NaN or an infinity anywhere is found, at either size."""
    rng = np.random.default_rng(size)
    k = size // 3
    Q, U, G = rng.standard_normal((k, 1)), rng.standard_normal((k, 1)), rng.standard_normal((k, 1 + size % 3))
    assert Q.size + U.size + G.size == size
    for a in (Q, U, G):
        x = a.copy()
        if bad is not None:
            x[-1, -1] = bad
        args = [x if b is a else b for b in (Q, U, G)]
        assert recording._finite(*args) == (bad is None)
