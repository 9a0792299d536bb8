"""The event rules of the integrators that locate events (docs/theory.md §7, §8), as plain
functions on the per-feature gaps of gaps.py: the constrained accelerations of a persistent set
(dynamics), the phase's watched sets (phase_sets), and at an event the impact with the Zeno rule
and the persistent set (resolve). What they carry between accepted points is an EventState the
integrator owns and passes in. Products are sums in index order (sums.ordered), square solves qp's written-out
LU (docs/theory.md §2.8)."""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import NamedTuple

import coal
import numpy as np
import pinocchio as pin

from . import compiled_events
from .constraints import assemble_constraints, corner_faces
from .corners import MAX_PIECES, corner_law
from .contacts import Contacts, FeatureKind, detect, from_rows
from .data import Data
from .errors import SimulationError
from .gaps import (BOX_FEATURES, CYLINDER_KINDS, Feature, FeatureState, Gaps,  # noqa: F401
                   UnsupportedModel, feature_list)
from .kinematics import G_RES
from .law import impact, outcome, percussion, project
from .model import Model
from .protocol import Impact
from .state import State
from .qp import _lu_solve
from .sums import ordered

V_TOL = 1e-9  # [m/s] |gamma| <= this on a closed feature: touching, not impacting
G_ZENO = 1e-12  # [m] a rebound whose apex would stay below this is not resolved (Zeno rule)
V_ZENO = 1e-8  # [m/s] nor an impact slower than this
DT_ZENO = 1e-12  # [s] nor an impact this soon after the previous one
LAM_EPS = 1e-9  # [N] a persistent contact is released when its multiplier falls below -LAM_EPS
G_REGION = 1e-6  # [m] ... or a persistent box feature when it passes its region's end by this (§7.1)
ACC_TOL = 1e-8  # [m/s^2] relative acceleration below this (scaled): a touching contact persists
IDLE_TOL = 1e-12  # [m/s^2] a persistent contact's force acting on itself below this (scaled): idle, not in C (§7)


@dataclass(frozen=True, eq=False)
class Rules:
    """What the event rules read of a model, fixed for a run (make_rules): its features (gaps.Gaps),
    restitution e, gap_tol [m] (a feature at most this far is closed: the tolerance contacts.detect
    uses), box_index (pair -> the index of its feature 0: box pairs' features are consecutive),
    cyl_swapped (cylinder feature -> coal lists its A second), impact (the compiled _impact,
    compiled_events.CompiledImpact, where it applies; None: the Python one)."""

    model: Model
    data: Data
    e: float
    feats: tuple[Feature, ...]
    gap_tol: float
    gaps: Gaps
    box_index: dict
    cyl_swapped: dict
    zero: np.ndarray
    impact: object = None


_MODEL_FEATURES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> gaps.feature_list(model)
_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> (features, their box_index, cyl_swapped)


def model_features(model: Model) -> tuple[Feature, ...]:
    """gaps.feature_list(model), made once per model (a model is never modified after build_model): a run's build
    reads it (UnsupportedModel as feature_list raises it)."""
    feats = _MODEL_FEATURES.get(model)
    if feats is None:
        feats = _MODEL_FEATURES[model] = feature_list(model)
    return feats


def _tables(model: Model, feats: tuple[Feature, ...]) -> tuple[dict, dict]:
    """Rules.box_index and Rules.cyl_swapped of `feats`, made once per model and features."""
    got = _TABLES.get(model)
    if got is not None and got[0] is feats:
        return got[1], got[2]
    first = {p.index: model.geom.geometryObjects[p.first].geometry for p in model.pairs}
    box_index = {f.pair: i for i, f in reversed(list(enumerate(feats))) if f.box is not None}
    cyl_swapped = {i: (f.kind == "sphere_cylinder") == isinstance(first[f.pair], coal.Cylinder)
                   for i, f in enumerate(feats) if f.kind in CYLINDER_KINDS}
    _TABLES[model] = (feats, box_index, cyl_swapped)
    return box_index, cyl_swapped


def make_rules(model: Model, data: Data, e: float, feats: tuple[Feature, ...] | None = None) -> Rules:
    """The Rules of `model` on its features (default: gaps.feature_list(model))."""
    gap_tol = max(model.options.contact_tolerance, G_RES)
    feats = model_features(model) if feats is None else feats
    gaps = Gaps(model, data, feats, gap_tol)
    gaps.compiled = compiled_events.feature_gaps(model, data, feats)
    return Rules(model, data, e, feats, gap_tol, gaps, *_tables(model, feats), np.zeros(model.nv),
                 compiled_events.impact(model, data, feats, gap_tol=gap_tol, v_tol=V_TOL, g_zeno=G_ZENO,
                                        v_zeno=V_ZENO, dt_zeno=DT_ZENO))


@dataclass(eq=False)
class EventState:
    """What the event rules carry from one accepted point to the next, owned by the integrator:
    the Zeno declarations, the last impact's time [s], counters (impacts, nfev: dynamics calls,
    constrained: those with a persistent set C),
    faces ((pair, vertex feature) -> the face a persistent vertex keeps through its phase),
    redundant (persistent set -> its rows are linearly dependent, decided once per set)."""

    zeno: list = field(default_factory=list)
    last_impact: float = -np.inf
    impacts: int = 0
    nfev: int = 0
    constrained: int = 0
    faces: dict = field(default_factory=dict)
    redundant: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"zeno": self.zeno,
                "last_impact": None if self.last_impact == -np.inf else self.last_impact,
                "impacts": self.impacts, "nfev": self.nfev, "constrained": self.constrained,
                "redundant": [[list(C), r] for C, r in self.redundant.items()],
                "faces": [[p, k, f] for (p, k), f in self.faces.items()]}

    @classmethod
    def from_json(cls, d: dict) -> "EventState":
        return cls(list(d["zeno"]), -np.inf if d["last_impact"] is None else float(d["last_impact"]),
                   int(d["impacts"]), int(d["nfev"]), int(d.get("constrained", 0)),
                   {(int(p), int(k)): int(f) for p, k, f in d["faces"]}, {tuple(C): bool(r) for C, r in d["redundant"]})


class Resolution(NamedTuple):
    """resolve()'s decisions at an event: u (after the impact, if any), C (the persistent
    features), shadow (duplicates of C's rows), records (the impact to record, protocol.Impact),
    work (its contact work [J]), g (the gaps of all features at q where they are functions of q
    alone, the compiled features': phase_sets takes them; else None)."""

    u: np.ndarray
    C: tuple
    shadow: tuple
    records: tuple
    work: float
    g: np.ndarray | None = None


def features(r: Rules, st: EventState, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True) -> FeatureState:
    """Gaps.features with the phase's persistent vertex faces (st.faces)."""
    return r.gaps.features(q, u, idx, rows, faces=st.faces)


def phase_sets(r: Rules, st: EventState, q: np.ndarray, u: np.ndarray, C, shadow, opened=frozenset(), g=None):
    """The features a phase starting at (q, u) with the persistent set C watches: (free, g0, low),
    free: neither in C nor shadows of it, g0 their gaps, low: those within G_RES / 2 of contact
    (watched by their rise and return, not their gap; `opened`, whose gaps just jumped open, never).
    g: the gaps of all features at q where already known (Resolution.g: the same floats)."""
    free = [i for i in range(len(r.feats)) if i not in C and i not in shadow]
    if not free:
        g0 = np.zeros(0)
    else:
        g0 = features(r, st, q, u, free, rows=False).g if g is None else g[free]
    low = [i for i, g in zip(free, g0) if g < 0.5 * G_RES and i not in opened]
    return free, g0, low


def dynamics(r: Rules, st: EventState, q, u, C, at_q: dict | None = None):
    """(a, lam, fs): free accelerations (ABA) plus the bilateral forces of the persistent set C,
    their multipliers, and C's FeatureState (None without C). Counts the call in st.nfev (and
    st.constrained with C) and records in st.redundant whether a new C's rows are dependent.
    at_q: where the caller calls again at the same q and C (a midpoint's fixed point in u), a dict
    that keeps what depends on q alone (M^-1, M^-1 W_C, W_C'M^-1 W_C: the same floats) from the
    first call for the next ones."""
    st.nfev += 1
    a = pin.aba(r.model.pin, r.data.pin, q, u, r.zero).copy()
    if not C:
        return a, np.zeros(0), None
    st.constrained += 1
    fs = features(r, st, q, u, C)
    if at_q:
        MiW, G = at_q["MiW"], at_q["G"]
    else:
        Minv = pin.computeMinverse(r.model.pin, r.data.pin, q)
        MiW = ordered(Minv, fs.W)
        G = ordered(fs.W.T, MiW)
        if at_q is not None:
            at_q["MiW"], at_q["G"] = MiW, G
    rhs = -(ordered(fs.W.T, a) + fs.drift)
    redundant = _redundant(st, C, fs.W)

    def solve(b):
        return _solve(G, b, redundant)
    lam = solve(rhs)
    a_c = a + ordered(MiW, lam)
    # one step of iterative refinement (as the impact's, docs/theory.md §1.5): lam ~ R m g is exact only
    # to its own magnitude, which leaves a light body accelerating at ~R eps g along the rows it should
    # hold; the residual W_C'a_C + drift is computed where it is ~0, accurately, and removed
    dl = solve(-(ordered(fs.W.T, a_c) + fs.drift))
    return a_c + ordered(MiW, dl), lam + dl, fs


def _redundant(st: EventState, C: tuple, W: np.ndarray) -> bool:
    """Whether the rows W (nv, len(C)) of the persistent set C are dependent (4 corners of a face on a face),
    decided once per set (st.redundant)."""
    redundant = st.redundant.get(C)
    if redundant is None:
        redundant = st.redundant[C] = _rank(W) < len(C)
    return redundant


def _rank(W: np.ndarray) -> int:
    """np.linalg.matrix_rank(W) of a 2-d W with its default tolerance (the same SVD and the same test), without
    its wrapper's cost: the singular values above their largest times max(W.shape) times the machine epsilon."""
    S = np.linalg.svd(W, compute_uv=False)
    return int(np.count_nonzero(S > S.max() * (max(W.shape) * np.finfo(S.dtype).eps))) if S.size else 0


def _solve(G: np.ndarray, b: np.ndarray, redundant: bool) -> np.ndarray:
    """G^-1 b by qp's written-out LU (docs/theory.md §2.8), or for dependent rows (or a singular G) the
    minimum-norm least-squares solution (LAPACK's, whose bits follow the BLAS kernel)."""
    x = None if redundant else _lu_solve(G, b)
    return np.linalg.lstsq(G, b, rcond=1e-12)[0] if x is None else x


def thin_limit(r: Rules, u: np.ndarray, a: np.ndarray) -> float:
    """Gaps.thin_limit: the longest step [s] no point can cross the thinnest pair's extent in."""
    return r.gaps.thin_limit(u, a)


# ---- events --------------------------------------------------------------------------------
def resolve(r: Rules, st: EventState, t: float, q: np.ndarray, u: np.ndarray, released: frozenset) -> Resolution:
    """Impact (with the Zeno rule), then the persistent set C at (t, q, u) (module doc); features
    in `released` (released at this event) are not re-admitted. Updates st: the faces of C's
    vertices, and at an impact its Zeno declaration, time and count."""
    st.faces = {}  # chosen afresh at an event
    fs = features(r, st, q, u)
    closed = (fs.g <= r.gap_tol) & fs.smooth  # an edge pair's stand-in is never a contact (§7.1)
    records, work = (), 0.0
    if (closed & (fs.gamma < -V_TOL)).any():
        u, imp, work = _impact(r, st, t, q, u, fs)
        records = (imp,)
        fs = features(r, st, q, u)
    # a box feature past the end of its region (margin < -G_REGION/2: a phase ends at -G_REGION, docs/theory.md
    # §7.1) does not persist; a corner resting exactly on an edge (margin 0 to rounding and drift) does
    inside = fs.margin > -0.5 * G_REGION
    touching = [i for i in (closed & (np.abs(fs.gamma) <= V_TOL) & inside).nonzero()[0] if i not in released]
    g = fs.g if r.gaps.compiled is not None else None  # functions of q alone (the compiled kinds)
    if not touching:
        return Resolution(u, (), (), records, work, g)
    # distinct rows only (the front and back corners of a planar block repeat each other)
    keep, shadow = [], []
    scale = 1e-12 * (1.0 + np.abs(fs.W).max())
    for i in touching:
        (shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in keep) else keep).append(i)
    pm, pd = r.model.pin, r.data.pin
    a_free = pin.aba(pm, pd, q, u, r.zero).copy()
    M = pin.crba(pm, pd, q)
    Minv = pin.computeMinverse(pm, pd, q)  # Pinocchio's (qp.solve would invert M by LAPACK: §2.8)
    Wk, dk = fs.W[:, keep], fs.drift[keep]
    res = project(M, Wk, a_free, b=-dk, Minv=Minv)
    if not res.ok:
        raise SimulationError(f"the contact-force QP failed ({res.status}) at t = {t:.12g} s")
    rel = ordered(Wk.T, res.v) + dk
    acc_scale = 1.0 + np.abs(dk).max() + np.abs(ordered(Wk.T, a_free)).max()  # [m/s^2]
    tol = ACC_TOL * acc_scale
    C = tuple(int(i) for i, x in zip(keep, rel) if x <= tol)
    lam = res.lam
    for i in C:  # a persistent vertex keeps its face through the phase (its row may not flip at a tie)
        f = r.feats[i]
        if f.kind == "vertex_box":
            wv, faces = fs.faces[f.pair]
            st.faces[(f.pair, f.feature)] = int(faces[np.searchsorted(wv, f.feature)])
    if C:  # remove the residual normal velocity of the touching contacts, idle ones too (~1e-16)
        W = fs.W[:, list(C)]
        MiW = ordered(Minv, W)
        u = u - ordered(MiW, _solve(ordered(W.T, MiW), ordered(W.T, u), _redundant(st, C, W)))
        # that removal moves bodies along M^-1 W_C: where it leaves another closed feature approaching
        # (a state handed back by fixed steps, overlapping by ~1e-8 m), the velocity is projected onto
        # the tangent cone of all closed features (the plastic law on ~1e-9 m/s): no phase starts with
        # a closed feature approaching, which it would watch by nothing (docs/theory.md §8)
        if (closed & (ordered(fs.W.T, u) < -V_TOL)).any():
            res = project(M, fs.W[:, np.flatnonzero(closed)], u, Minv=Minv)
            if not res.ok:
                raise SimulationError(f"the contact QP failed ({res.status}) at t = {t:.12g} s")
            u = res.v
    A = _carrying(r, st, q, u, C, keep, lam, fs, Minv, IDLE_TOL * acc_scale, MiW if C else None)
    shadow = tuple(int(i) for i in shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in A))
    return Resolution(u, A, shadow, records, work, g)


def _carrying(r: Rules, st: EventState, q, u, C: tuple, keep: list, lam: np.ndarray, fs: FeatureState, Minv,
              tol: float, MiW: np.ndarray | None = None) -> tuple:
    """The contacts of the touching set C that carry something (docs/theory.md §7, "Idle contacts"):
    C without the idle ones, whose force changes their own relative acceleration by at most tol
    [m/s^2] (lam_i w_i'M^-1 w_i <= tol, tol = IDLE_TOL scaled), provided that C's rows are
    independent (its forces unique) and that under the phase's own
    accelerations on the rest (dynamics) none of them accelerates towards contact by more than
    tol; else C. keep, lam: the acceleration QP's rows and multipliers [N]; fs: all features at
    (q, u); MiW: M^-1 W_C where known (resolve's); drops the idle vertices' faces from st.faces."""
    if not C:
        return C
    W = fs.W[:, list(C)]
    if _redundant(st, C, W):
        return C  # dependent rows: their forces are not unique, a zero multiplier says nothing
    at = {i: k for k, i in enumerate(keep)}
    MiW = ordered(Minv, W) if MiW is None else MiW
    wMw = np.add.accumulate(W * MiW, axis=0)[-1] + 0.0  # w_i'M^-1 w_i, summed as sums.ordered sums
    idle = lam[[at[i] for i in C]] * wMw <= tol
    if not idle.any():
        return C
    A = tuple(i for i, x in zip(C, idle) if not x)
    out = [i for i, x in zip(C, idle) if x]
    if (ordered(fs.W[:, out].T, dynamics(r, st, q, u, A)[0]) + fs.drift[out] < -tol).any():
        return C
    for i in out:
        st.faces.pop((r.feats[i].pair, r.feats[i].feature), None)
    return A


def missed_features(r: Rules, fs: FeatureState, W: np.ndarray) -> list:
    """Contact rows (as contacts.from_rows takes them) of the closed box-box vertices and of the
    closed, approaching active edge pairs whose row is not in the span of coal's rows W, and of
    the closed, not separating cylinder features where their gap is the distance (§7.2: coal's
    one witness of a cylinder on a box's edge) that are not one of those rows: an edge lying
    across a face meets the face's edges at points coal's one witness of that segment contact
    does not stand for, and coal's point query gives a vertex exactly on a face (|g| ~ 1e-17 m)
    an arbitrary normal (docs/theory.md §7.1). Needs fs = features(r, st, q, u) of all features."""
    out = []
    for col, row, box in _missed_candidates(r, fs):
        w = fs.W[:, col]
        if box and row[6] >= 16 and W.shape[1]:  # an edge pair (a closed vertex's own row always replaces coal's)
            resid = w - ordered(W, np.linalg.lstsq(W, w, rcond=1e-12)[0])
            if np.abs(resid).max() <= 1e-9 * np.abs(w).max():
                continue
        elif not box and W.shape[1] and (
                np.abs(W - w[:, None]).max(axis=0) <= 1e-9 * np.abs(w).max()).any():
            continue  # already a row (a combination of rows would not keep it from approaching)
        out.append(row)
        W = np.column_stack((W, w))
    return out


def _missed_candidates(r: Rules, fs: FeatureState):
    """missed_features' candidates before the test against coal's rows: (feature column, contact row, of a box
    pair) of the closed box-box vertices, the closed approaching active edge pairs, and the closed, not separating
    cylinder features whose gap is the distance, in that order. None at all (so no missed feature: coal's rows are
    the rows) is the compiled impact's condition (_impact, compiled_events.CompiledImpact)."""
    for pair, (which, P_a, P_b, nn) in fs.points.items():
        e_which, active = fs.edges.get(pair, (np.zeros(0, int), np.zeros(0, bool)))
        for i, k in enumerate(which.tolist()):
            if k >= 16 and not active[np.searchsorted(e_which, k)]:
                continue
            col = r.box_index[pair] + k
            if fs.g[col] > r.gap_tol or (k >= 16 and fs.gamma[col] >= -V_TOL):
                continue
            yield col, (float(fs.g[col]), P_a[i], P_b[i], nn[i], pair,
                        FeatureKind.VERTEX if k < 16 else FeatureKind.WITNESS, k), True
    # cylinder features (§7.2): coal's one witness per pair misses e.g. a cylinder's side on a box's edge
    # touching ones too: coal's witness normal of a cylinder on an edge is off by ~1e-6, and an impact
    # elsewhere then left the exact feature approaching at 2e-7 m/s, neither impacted nor persistent
    for i, (pa, pb, n) in fs.witness.items():
        if fs.g[i] > r.gap_tol or fs.gamma[i] > V_TOL or not fs.exact.get(i, False):
            continue
        f = r.feats[i]
        # WITNESS features 1.. (coal's own witness of the pair is 0): 1 sphere_cylinder, 1-2 rims, 3-14 sides
        k = 1 + f.feature + (2 if f.kind == "side_edge" else 0) if f.feature >= 0 else 1
        if r.cyl_swapped[i]:  # coal's A is the feature's B: points swapped, normal reversed
            pa, pb, n = pb, pa, -n
        yield i, (float(fs.g[i]), pa, pb, n, f.pair, FeatureKind.WITNESS, k), False


def _impact(r: Rules, st: EventState, t, q, u, fs: FeatureState) -> tuple[np.ndarray, Impact, float]:
    """The impact law on the contacts detect() closes at q: law.impact (docs/theory.md §1), or at
    a corner the set-valued law with the scene's selection policy (§3, §7.2). Returns (u+, the
    impact to record, the contact work -(energy lost) [J])."""
    model, data = r.model, r.data
    pm, pd = model.pin, data.pin
    # the pairs whose features are closed are in contact: detect examines two polytopes' vertices
    # then whatever coal's narrow phase says (it can report exactly touching boxes, -7e-12 m, as apart)
    closed_pairs = {r.feats[i].pair for i in (fs.g <= r.gap_tol).nonzero()[0]}
    # compiled where it applies (src/impact.hpp: the same floats; no missed feature), else Python
    if r.impact is not None and r.impact.takes(next(_missed_candidates(r, fs), None) is None):
        got = r.impact(q, u, r.e, t, st.last_impact, fs, closed_pairs)
        if got is not None:
            f, zeno, speed, a_n, work = got
            c = Contacts(*(f[k] for k in Contacts.ARRAYS))
            e = 0.0 if zeno else r.e
            imp = Impact(t, q, u, f["u_next"], f["M"], f["v"], e, c, f["P"], f["gamma_minus"], f["gamma_plus"], None)
            _impacted(r, st, t, zeno, speed, a_n, c)
            return imp.u_plus, imp, work
    data.warm_start_pairs = set(data.warm_start_pairs) | closed_pairs
    c = detect(model, data, q)
    cs = assemble_constraints(model, data, q, c)
    # (at a corner the struck vertex is the corner's: its faces are the pieces, not a feature row)
    missed = missed_features(r, fs, cs.W) if cs.pieces is None else []
    if missed:  # they replace coal's contacts of the same vertices
        keys = {(m[4], int(m[5]), m[6]) for m in missed}
        keep = np.array([k not in keys for k in zip(c.pair.tolist(), c.kind.tolist(), c.feature.tolist())], bool)
        cs = assemble_constraints(model, data, q, c.select(keep).concat(from_rows(model, missed)))
    c, M, W = cs.contacts, cs.M, cs.W
    if c.m == 0 and cs.pieces is None:
        raise SimulationError(f"a gap event at t = {t:.12g} s but coal finds no closed contact")
    if cs.pieces is None and not (ordered(W.T, u) < -V_TOL).any():
        raise SimulationError(f"a feature approaches at t = {t:.12g} s (gamma = {fs.gamma.min():.3g} m/s) but "
                              "none of coal's closed contacts does")
    # the Zeno rule (module doc) on the approaching features: their free normal accelerations a_n
    appr = np.flatnonzero((fs.g <= r.gap_tol) & (fs.gamma < -V_TOL))
    a_n = ordered(fs.W[:, appr].T, pin.aba(pm, pd, q, u, r.zero)) + fs.drift[appr]
    speed = -fs.gamma[appr]
    low = ((r.e * speed) ** 2 < -2.0 * a_n * G_ZENO) | (speed < V_ZENO)
    zeno = bool(low.all()) or t - st.last_impact < DT_ZENO
    e = 0.0 if zeno else r.e
    if cs.pieces is None:
        imp = impact(M, W, u, e, Minv=pin.computeMinverse(pm, pd, q))  # Pinocchio's M^-1 (§2.8)
        P, v, u_plus, loss = imp.P, imp.qp.v, imp.u_plus, imp.energy_loss
        gm, gp = ordered(W.T, u), ordered(W.T, u_plus)
        branch = None
    else:  # the set-valued law at one instant (v0 = u-), the stepper's corners.corner_law
        cp = cs.pieces
        law = corner_law(M, u, u, e, W, cp.pieces, cp.rows, cp.choice, selection=model.options.corner_selection)
        if law is None:
            raise SimulationError(f"the corner law failed (TOO_MANY_CORNER_PIECES ({len(cp.pieces)} > "
                                  f"{MAX_PIECES})) at t = {t:.12g} s")
        c = c.concat(*[corner_faces(cp.corners[i], np.array([f])) for i, f in law.faces], corners=())
        v, u_plus, P = law.v, outcome(law.v, u, e), percussion(law.lam, e)
        gm, gp = ordered(law.W.T, u), ordered(law.W.T, u_plus)
        dv = u - v  # the impact's energy identity holds at every stationary point (§3)
        loss = 0.5 * (1.0 - e * e) * float(ordered(ordered(dv, M), dv))
        branch = None if law.u_plus is None else (law.solution, law.chosen, law.u_plus)
    _impacted(r, st, t, zeno, speed, a_n, c)
    return u_plus, Impact(t, q, u, u_plus, M, v, e, c, P, gm, gp, branch), -loss


def _impacted(r: Rules, st: EventState, t: float, zeno: bool, speed: np.ndarray, a_n: np.ndarray, c) -> None:
    """An impact at t [s] in st: its Zeno declaration (zeno: the rule held; speed [m/s], a_n [m/s^2]: the approaching
    features' speeds and free normal accelerations; c: the impact's contacts), time and count."""
    if zeno and r.e < 1.0 and len(speed):
        k = int(np.argmax(speed))
        dt = 2.0 * r.e * speed[k] / ((1.0 - r.e) * -a_n[k]) if a_n[k] < 0 else 0.0
        st.zeno.append({"t": t, "t_accumulation": float(t + dt), "speed": float(speed[k]),
                          "pairs": sorted(set(c.pair.tolist()))})
    st.last_impact = t
    st.impacts += 1


def sample_grid(model: Model, state: State, t_end: float | None, t_eval) -> tuple[float, np.ndarray]:
    """t_end [s] (default: state.t + the scene's duration) and the sample instants of a run that
    locates events: t_eval, checked to increase strictly within [t0, t_end], or by default every
    save_every * dt of the scene's options (the instants ms.simulate records)."""
    opts = model.options
    t_end = state.t + opts.duration if t_end is None else float(t_end)
    if not t_end > state.t:
        raise ValueError(f"t_end = {t_end} s must be after the initial time {state.t} s")
    if t_eval is None:
        n = max(1, int(round((t_end - state.t) / (opts.dt * opts.save_every))))
        return t_end, state.t + (t_end - state.t) * np.arange(n + 1) / n
    t_grid = np.asarray(t_eval, float)
    if t_grid.ndim != 1 or np.any(np.diff(t_grid) <= 0) or t_grid[0] < state.t or t_grid[-1] > t_end:
        raise ValueError(f"t_eval must increase strictly within [{state.t}, {t_end}] s")
    return t_end, t_grid
