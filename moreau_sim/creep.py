"""Motion below the energy's round-off (docs/theory.md §10, §2.11): a body whose kinetic energy stays within the
round-off of T + V, ROUND_OFF max(|E_0|, max T), moves at speeds no energy check can tell from round-off (a
1 kg cube beside a 1e5 kg one: 1e-4 m/s). Where the whole system's T stays that low over a stretch of samples
and the motion the change of those speeds makes, the integral of u - u_s over the stretch (u_s: its first
sample's; a body coasting at a constant speed is Newton's, not round-off's), exceeds the contact tolerance in some
coordinate (times the model's reach) at a sample whose T is above the stretch's first (the bodies gained the
energy for it), the run cannot vouch for that motion. Read from a run's
recorded arrays, so both step implementations and every integrator are checked alike.
"""

from __future__ import annotations

import numpy as np

CHUNK = 1 << 16  # samples read at a time


def first_creep(arrays: dict, *, reach: float, tol: float, rel: float,
                persist: int) -> tuple[float, float, float] | None:
    """(t [s], motion [m], tol [m]) where, over a stretch of more than `persist` consecutive samples at which the
    kinetic energy T is at most rel max(|E_0|, max T so far) [J], the motion of the change of those speeds,
    X = sum (t_{j+1} - t_j)((u_j + u_{j+1})/2 - u_s) from the stretch's first sample s, has an entry beyond tol / reach
    at a sample whose T is above T_s
    (reach: model.reach, at least 1, a point's motion per unit of |u|_inf, as contacts.detect's travel): t the
    first sample where it did, motion the largest reach |X|_inf over the run; or None. The position correction's
    lifts, which move q with no speed, are not counted."""
    T, V = np.asarray(arrays["kinetic_energy"]), np.asarray(arrays["potential_energy"])
    if len(T) < 2:
        return None
    scale = np.maximum(abs(float(T[0] + V[0])), np.maximum.accumulate(T))
    low = T <= rel * scale
    if not low.any():
        return None
    t, u = np.asarray(arrays["t"], float), arrays["u"]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], low.astype(np.int8), [0]])))  # starts, ends of stretches
    first, most = None, 0.0
    for s, e in zip(edges[::2].tolist(), edges[1::2].tolist()):
        if e - s <= persist:  # a few samples at rest in a motion (a block chattering on its corners): no creep
            continue
        X, us = np.zeros(u.shape[1]), np.asarray(u[s], float)
        for a in range(s, e - 1, CHUNK):
            b = min(a + CHUNK, e - 1)
            ua = np.asarray(u[a:b + 1], float)
            steps = np.diff(t[a:b + 1])[:, None] * (0.5 * (ua[:-1] + ua[1:]) - us)  # each interval's motion
            path = X + np.cumsum(steps, axis=0)
            moved = np.where(T[a + 1:b + 1] > T[s], np.abs(path).max(axis=1) * reach, 0.0)  # energy gained
            over = np.flatnonzero(moved > tol)
            if len(over):
                first = float(t[a + 1 + int(over[0])]) if first is None else first
                most = max(most, float(moved.max()))
            X = path[-1]
    return None if first is None else (first, most, tol)
