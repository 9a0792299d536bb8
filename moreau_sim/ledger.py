"""The energy ledger of a run (docs/theory.md §5): the terms of one step, the ledger of a
trajectory (`ledger(traj)`), its figures as a flat record, and the comparison with a baseline.

One step from (q_k, u_k), with the law's frame at the midpoint q_m, M = M(q_m):

    u_free = (1 + e) v_free - e u_k                 the contact-free velocity of the step
    u-     = v_free,  u+ = u_{k+1} - e (v_free - u_k) = (1 + e) v - e v_free      (the impact)
    dissipation  D = T- - T+ = 1/2 |u-|_M^2 - 1/2 |u+|_M^2
    law          L = (1 - e^2)/2 |u- - v|_M^2 - P.b   (b: the per-contact bounds of §2.7, else 0)
    smooth error S = E(q_m (+) h/2 u_free, u_free) - E(q_k, u_k)    (the step without its contacts)

(D and L are not computed in a persistent contact step, at_rest, §5.2: no impact, the same S)

and the budget E_end - E_0 = sum W_c + sum correction + sum S + sum W_a + sum W_o + residual, with the
work done on the system (§5.5): the torques' W_a = h tau.(u_k + u_{k+1})/2 and the moving statics'
W_o = -P.dg/dt (S is then the contact-free step's change less its own torque work). Recorder fills the
arrays (recording.py); this module reads them. Its products are sums.ordered's (docs/theory.md §2.8; the
quadratic forms of a few coordinates the same sums on Python floats, _quad), which the compiled run loop
(src/run.cpp) sums alike. Units: J, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .sums import ordered
from .trajectory import Trajectory

BASELINE_SAMPLES = 100  # at most this many samples of E(t) go into a baseline record
# A closed contact is at rest in a step when |gamma^k| and |gamma^{k+1}| are at most this fraction of the sum
# their rounding carries (at_rest; docs/theory.md §5.2): the law's accuracy, not a physical speed
REST_ACCURACY = 1e-9
QUAD_FLOATS = 8  # _quad sums on Python floats up to this many coordinates (cheaper than numpy's calls there)


def impact_terms(M: np.ndarray, v_free: np.ndarray, v: np.ndarray, u_k: np.ndarray, u_next: np.ndarray,
                 e: float, P: np.ndarray, b: np.ndarray | None) -> tuple[float, float, float]:
    """(T-, T+, law) of a contact step [J] (module doc). D = T- - T+ is measured on the step's own
    u_{k+1}; the law's figure uses only the projection (v_free, v), so they agree exactly when the
    step applied the law, to the QP's accuracy otherwise."""
    u_plus = u_next - e * (v_free - u_k)
    r = v_free - v
    law = 0.5 * (1.0 - e * e) * _quad(M, r)
    if b is not None and len(b):
        law -= float(ordered(P, b))
    return 0.5 * _quad(M, v_free), 0.5 * _quad(M, u_plus), law


def at_rest(W: np.ndarray, u_k: np.ndarray, u_free: np.ndarray, gamma_minus: np.ndarray,
            gamma_plus: np.ndarray) -> bool:
    """Whether every closed contact of a step is at rest (docs/theory.md §5.2): |gamma_i^k| and |gamma_i^{k+1}|
    [m/s] <= REST_ACCURACY rho_i, rho_i = sum_j |W_ji| (|u_k,j| + |u_free,j - u_k,j|) the size of the terms whose
    rounding they carry (W (nv, m); summed in index order, sums.ordered, as src/run.cpp sums it)."""
    rho = ordered(np.abs(W).T, np.abs(u_k) + np.abs(u_free - u_k))
    bound = REST_ACCURACY * rho
    return bool((np.abs(gamma_minus) <= bound).all() and (np.abs(gamma_plus) <= bound).all())


def law_kept(v: np.ndarray, u_k: np.ndarray, u_next: np.ndarray, e: float) -> bool:
    """Whether the step's u_{k+1} is the law's, law.outcome(v, u_k, e), bit for bit: no energy cap (§2.10, whose
    removal D - L shows) and no lift paid with the velocities (§2.5) changed it (a persistent step needs it)."""
    return (v - e * (u_k - v)).tobytes() == u_next.tobytes()


def _quad(M: np.ndarray, x: np.ndarray) -> float:
    """x'Mx as (x'M) x, each product summed in index order (sums.ordered; src/run.cpp quad: the same sums); up to
    QUAD_FLOATS coordinates on Python floats: the same operations (each product rounded, summed from the first, then
    + 0.0; CPython contracts nothing into an FMA) at a fraction of numpy's per-call cost."""
    n = len(x)
    if not 0 < n <= QUAD_FLOATS:
        return float(ordered(ordered(x, M), x))
    xs, rows = x.tolist(), M.tolist()
    first = rows[0]
    quad = 0.0
    for j in range(n):
        s = xs[0] * first[j]  # (x'M)_j
        for i in range(1, n):
            s = s + xs[i] * rows[i][j]
        s = s + 0.0
        quad = s * xs[0] if j == 0 else quad + s * xs[j]
    return quad + 0.0


@dataclass(frozen=True, slots=True)
class ImpactRow:
    """One step with a new impact: step, t [s] (step midpoint), pushing contacts, T- and T+ [J]
    (the law's frame), dissipated = T- - T+ [J], predicted = the law's figure [J]."""

    step: int
    t: float
    contacts: int
    T_minus: float
    T_plus: float
    dissipated: float
    predicted: float

    @property
    def difference(self) -> float:
        return self.dissipated - self.predicted


@dataclass(frozen=True)
class Ledger:
    """The energy ledger of a run (docs/theory.md §5). Energies [J], times [s].

    energy_start/end: T + V at the first/last sample; scale: max(|E_0|, max T), the energy the
    relative tolerances refer to; contact_work, correction, smooth_error, dissipation, law,
    actuator_work, obstacle_work (the work done on the system, §5.5; 0 in a passive run): the run's
    totals; residual = E_end - E_0 - (contact_work + correction + smooth_error + actuator_work + obstacle_work);
    max_step_rise: the largest increase of T + V over one step, less the energy the position
    correction booked in it (docs/theory.md §2.5) (at t_step_rise, the step's end; in
    event-driven and adaptive runs, over one stretch of smooth motion between samples and events);
    max_law_difference: the largest |D - L| of any contact step but the persistent ones (at_rest, §5.2:
    dissipation and law leave those out too; contact_steps counts them) (at t_law_difference);
    impacts: the steps with a new impact; t, E, residuals: per sample (residuals: the budget's
    leftover over the steps since the previous sample)."""

    scene: str
    restitution: float
    dt: float
    energy_start: float
    energy_end: float
    scale: float
    contact_work: float
    correction: float
    smooth_error: float
    dissipation: float
    law: float
    residual: float
    max_step_rise: float
    t_step_rise: float
    max_law_difference: float
    t_law_difference: float
    contact_steps: int
    impacts: tuple[ImpactRow, ...]
    t: np.ndarray
    E: np.ndarray
    residuals: np.ndarray
    actuator_work: float = 0.0
    obstacle_work: float = 0.0

    def totals(self) -> dict[str, float]:
        """The per-run figures by name (what a baseline records and compares)."""
        return {"energy_start": self.energy_start, "energy_end": self.energy_end, "contact_work": self.contact_work,
                "correction": self.correction, "smooth_error": self.smooth_error, "dissipation": self.dissipation,
                "law": self.law, "residual": self.residual, "max_step_rise": self.max_step_rise,
                "impacts": len(self.impacts), "actuator_work": self.actuator_work, "obstacle_work": self.obstacle_work}

    def record(self) -> dict:
        """A JSON-able record for a baseline: the totals, every impact, E(t) at <= BASELINE_SAMPLES samples."""
        stride = max(1, math.ceil(len(self.t) / BASELINE_SAMPLES))
        idx = np.unique(np.r_[np.arange(0, len(self.t), stride), len(self.t) - 1]) if len(self.t) else []
        return {"totals": self.totals(),
                "impacts": {"t": [r.t for r in self.impacts], "dissipated": [r.dissipated for r in self.impacts]},
                "energy": {"t": [float(self.t[i]) for i in idx], "E": [float(self.E[i]) for i in idx]}}

    def table(self) -> str:
        """The ledger as a short text table (per run, then the first impacts)."""
        s = self.scale
        lines = [f"ledger of {self.scene} (e = {self.restitution:g}, h = {self.dt:g} s): "
                 f"E_0 = {self.energy_start:.9g} J, E_end = {self.energy_end:.9g} J, scale {s:.3g} J",
                 f"  contact work     {self.contact_work:+.6e} J",
                 f"  correction       {self.correction:+.6e} J",
                 f"  smooth error     {self.smooth_error:+.6e} J",
                 *([f"  actuator work    {self.actuator_work:+.6e} J",
                    f"  obstacle work    {self.obstacle_work:+.6e} J"] if self.actuator_work or self.obstacle_work
                   else []),
                 f"  residual         {self.residual:+.6e} J  ({_rel(self.residual, s)} of scale)",
                 f"  dissipation      {self.dissipation:.6e} J, law {self.law:.6e} J, largest step difference "
                 f"{self.max_law_difference:.2e} J ({_rel(self.max_law_difference, s)}) "
                 f"at t = {self.t_law_difference:.6g} s",
                 f"  largest rise of one step {self.max_step_rise:+.3e} J at t = {self.t_step_rise:.6g} s",
                 f"  {len(self.impacts)} impacts in {self.contact_steps} contact steps"]
        if self.impacts:
            lines.append(f"  {'t [s]':>10} {'contacts':>8} {'T- [J]':>13} {'T+ [J]':>13} {'dissipated':>13} "
                         f"{'law':>13} {'difference':>10}")
            for r in self.impacts[:10]:
                lines.append(f"  {r.t:10.6g} {r.contacts:8d} {r.T_minus:13.6e} {r.T_plus:13.6e} {r.dissipated:13.6e} "
                             f"{r.predicted:13.6e} {r.difference:10.2e}")
            if len(self.impacts) > 10:
                lines.append(f"  ... {len(self.impacts) - 10} more")
        return "\n".join(lines)


def _time(t) -> float:
    return math.nan if t is None else float(t)


def _rel(x: float, scale: float) -> str:
    return f"{abs(x) / scale:.1e}" if scale > 0 else "n/a"


def ledger(traj: Trajectory) -> Ledger:
    """The energy ledger of a trajectory (docs/theory.md §5). Raises ValueError for a file written
    before the ledger was recorded (format 1 or 2)."""
    a, meta = traj.arrays, traj.meta
    led = meta.get("ledger")
    if led is None or (len(a["t"]) and not np.isfinite(a["smooth_error"]).all()):
        raise ValueError(f"{meta.get('scene', {}).get('name', 'trajectory')}: no energy ledger recorded "
                         f"({meta.get('format', '?')}); run the scene again")
    E = a["kinetic_energy"] + a["potential_energy"]
    opts = meta.get("options", {})
    if not len(E):
        E = np.zeros(1)
    budget = a["contact_work"] + a["correction_energy"] + a["smooth_error"]
    act, obs = (a.get(k, np.zeros(len(a["t"]))) for k in ("actuator_work", "obstacle_work"))
    if "actuator_work" in a:
        budget = budget + act + obs
    residuals = np.r_[0.0, np.diff(E) - budget[1:]] if len(a["t"]) else np.zeros(0)
    scale = max(abs(float(E[0])), float(a["kinetic_energy"].max(initial=0.0)))
    impacts = tuple(ImpactRow(int(s), float(t), int(c), float(tm), float(tp), float(d), float(p))
                    for s, t, c, tm, tp, d, p in zip(a["impact_step"], a["impact_t"], a["impact_contacts"],
                                                     a["impact_T_minus"], a["impact_T_plus"], a["impact_dissipation"],
                                                     a["impact_law"]))
    return Ledger(
        scene=meta.get("scene", {}).get("name", "?"), restitution=float(opts.get("restitution", math.nan)),
        dt=float(opts.get("dt", math.nan)), energy_start=float(E[0]), energy_end=float(E[-1]), scale=scale,
        contact_work=float(a["contact_work"].sum()), correction=float(a["correction_energy"].sum()),
        smooth_error=float(a["smooth_error"].sum()), dissipation=float(a["dissipation"].sum()),
        law=float(a["law_dissipation"].sum()), residual=float(E[-1] - E[0] - budget[1:].sum()),
        max_step_rise=float(led["max_step_rise"]), t_step_rise=_time(led["t_step_rise"]),
        max_law_difference=float(led["max_law_difference"]), t_law_difference=_time(led["t_law_difference"]),
        contact_steps=int(led["contact_steps"]), impacts=impacts, t=a["t"], E=E, residuals=residuals,
        actuator_work=float(act.sum()), obstacle_work=float(obs.sum()))


# ---- comparison with a baseline record -----------------------------------------------------------

DEFAULT_TOLERANCE = (1e-6, 1e-9)  # (rtol, atol [J]) of every quantity unless given
TOTALS = ("energy_start", "energy_end", "contact_work", "correction", "smooth_error", "dissipation", "law", "residual",
          "max_step_rise", "impacts", "actuator_work", "obstacle_work")  # the keys of Ledger.totals()
QUANTITIES = TOTALS + ("impact_t", "impact_dissipated", "energy", "default")  # what a tolerance can name


@dataclass(frozen=True, slots=True)
class Drift:
    """A quantity that moved beyond its tolerance: name, baseline and current value, where in
    time (s, None for a per-run total or a count), and the tolerance (rtol, atol) it broke."""

    quantity: str
    baseline: float
    current: float
    t: float | None
    tolerance: tuple[float, float]

    @property
    def change(self) -> float:
        return self.current - self.baseline


def tolerance_of(name: str, tolerances: dict | None) -> tuple[float, float]:
    """(rtol, atol) of a quantity: tolerances[name], else tolerances["default"], else DEFAULT_TOLERANCE.
    "impacts" (a count) is compared exactly unless given."""
    tolerances = tolerances or {}
    if name in tolerances:
        return tuple(map(float, tolerances[name]))
    if name == "impacts":
        return (0.0, 0.0)
    return tuple(map(float, tolerances.get("default", DEFAULT_TOLERANCE)))


def _off(base: float, cur: float, tol: tuple[float, float]) -> bool:
    rtol, atol = tol
    if not (math.isfinite(base) and math.isfinite(cur)):
        return not (base == cur or (math.isnan(base) and math.isnan(cur)))
    return abs(cur - base) > atol + rtol * abs(base)


def compare(current: dict, baseline: dict, tolerances: dict | None = None) -> list[Drift]:
    """The drifts of a ledger record (Ledger.record()) from a baseline record: every total out of
    tolerance; the first impact whose time or dissipation moved (impacts are matched in order);
    the first sample of E(t) that moved (the same sample instants; if they differ, that is the drift)."""
    out = []
    for name, base in baseline["totals"].items():
        cur = current["totals"].get(name, math.nan)
        tol = tolerance_of(name, tolerances)
        if _off(float(base), float(cur), tol):
            out.append(Drift(name, float(base), float(cur), None, tol))
    bi, ci = baseline["impacts"], current["impacts"]
    tol_t, tol_d = tolerance_of("impact_t", tolerances), tolerance_of("impact_dissipated", tolerances)
    for k in range(min(len(bi["t"]), len(ci["t"]))):
        if _off(bi["t"][k], ci["t"][k], tol_t):
            out.append(Drift(f"impact {k + 1} time", bi["t"][k], ci["t"][k], bi["t"][k], tol_t))
            break
        if _off(bi["dissipated"][k], ci["dissipated"][k], tol_d):
            out.append(Drift(f"impact {k + 1} dissipated", bi["dissipated"][k], ci["dissipated"][k], bi["t"][k], tol_d))
            break
    be, ce = baseline["energy"], current["energy"]
    tol_e = tolerance_of("energy", tolerances)
    if len(be["t"]) != len(ce["t"]) or not np.allclose(be["t"], ce["t"], rtol=1e-12, atol=0.0):
        out.append(Drift("sample instants", float(len(be["t"])), float(len(ce["t"])), None, (0.0, 0.0)))
    else:
        for t, b, c in zip(be["t"], be["E"], ce["E"]):
            if _off(b, c, tol_e):
                out.append(Drift("energy E(t)", b, c, t, tol_e))
                break
    return out


def drift_table(drifts: list[Drift], title: str = "") -> str:
    """What moved, by how much, where in time: one line per drift."""
    lines = [title] if title else []
    lines.append(f"  {'quantity':<24} {'baseline':>15} {'now':>15} {'change':>11} {'at t [s]':>10} {'rtol, atol':>16}")
    for d in drifts:
        at = "run" if d.t is None else f"{d.t:.6g}"
        lines.append(f"  {d.quantity:<24} {d.baseline:15.9g} {d.current:15.9g} {d.change:+11.3e} {at:>10} "
                     f"{d.tolerance[0]:7.0e}, {d.tolerance[1]:7.0e}")
    return "\n".join(lines)
