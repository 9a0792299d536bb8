"""Every admissible outcome of an impact at a given state (docs/theory.md §1 and §3).

At a smooth contact configuration the law has one outcome (the proximal point); at a corner
(a vertex at an edge or vertex of a box) the admissible set is a union of cones and every
Clarke-stationary point of 1/2 |v - u-|_M^2 over it is an outcome u+ = (1 + e) v - e u-.
This is the analysis entry point behind `moreau-sim outcomes`; the stepper uses the same law.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constraints import assemble_constraints
from .contacts import detect
from .corners import select, stationary_points
from .data import Data, make_data
from .law import impact, outcome
from .model import Model
from .state import State


@dataclass(frozen=True)
class Outcome:
    """u_plus (nv,): the post-impact velocity; v: the stationary point; distance: 1/2 |v - u-|_M^2
    [J]; energy_loss: T(u-) - T(u+) [J]; global_min: a global minimizer of the distance;
    pieces: which way of staying apart at each corner it takes, as text ("smooth" without corner);
    selected: the one the scene's corner_selection policy continues with."""

    u_plus: np.ndarray
    v: np.ndarray
    distance: float
    energy_loss: float
    global_min: bool
    pieces: str
    selected: bool


def impact_outcomes(model: Model, state: State, *, e: float | None = None, data: Data | None = None) -> list[Outcome]:
    """All admissible outcomes of the impact at `state` (q, u- = u), with no forces, restitution
    e (default: the scene's). The contacts are those closed at q (gap <= contact_tolerance)."""
    data = data or make_data(model)
    e = model.options.restitution if e is None else e
    q, u = state.q, state.u
    cs = assemble_constraints(model, data, q, detect(model, data, q))
    M, W, cp = cs.M, cs.W, cs.pieces
    T_minus = 0.5 * float(u @ M @ u)
    if cp is None:
        imp = impact(M, W, u, e)
        return [Outcome(imp.u_plus, imp.qp.v, 0.5 * float((u - imp.qp.v) @ M @ (u - imp.qp.v)),
                        T_minus - 0.5 * float(imp.u_plus @ M @ imp.u_plus), True, "smooth", True)]
    sol = stationary_points(M, u, list(cp.pieces), W if W.shape[1] else None)
    chosen = select(sol, model.options.corner_selection)
    out = []
    for k, cand in enumerate(sol.candidates):
        v = np.asarray(cand.v)
        u_plus = outcome(v, u, e)
        faces = " + ".join(
            ", ".join(f"corner {i}: n = {np.round(cp.corners[i].normals[cp.choice[j][i]], 3).tolist()}"
                      for i in range(len(cp.corners))) for j in cand.pieces)
        out.append(Outcome(u_plus, v, float(cand.distance), T_minus - 0.5 * float(u_plus @ M @ u_plus),
                           bool(cand.global_min), faces, k == chosen))
    return out
