"""Kinetic energy paid by sinking (docs/theory.md §2.11, §10): a fixed step lets a loaded contact lie inside by
its transient (the penetration invariant's allowance, millimetres at h = 1e-2), and the potential energy a
load F releases by sinking a depth d into its support, F d, is no energy the scene has: lifted back out, the
bodies would need it. So T + V at a sample, with the sunk energy put back, must stay within the energy
bound as T + V does: T + sum_pairs F d <= E_0 - V + booked + external + bound. F is the pair's mean force
P / duration over the continuing (not new) fixed-step rows of the percussion log that cover the sample, d its
depth, -min(gap, 0). Read from a run's recorded arrays, so both step implementations are checked alike.
"""

from __future__ import annotations

import numpy as np

CHUNK = 1 << 16  # samples a stretch's depths are read at a time


def sunk_energy(arrays: dict, slow: float) -> np.ndarray:
    """(n_samples,) [J] sum over pairs of F d at each sample: F [N] the mean force over the sample's interval of
    the pair's loads, its continuing fixed-step rows (not new) that approached no faster than `slow` [m/s a
    second of step: 2 |gravity|] times their step (an impact's percussions, P/h of its approach, are no load;
    a row covers the samples its steps lead to: log_t its first step's midpoint, log_steps steps of
    log_duration in all; a stretch of persistent steps is one row), d [m] the pair's depth."""
    E = np.zeros(len(arrays["t"]))
    for at, add in _terms(arrays, slow):
        if isinstance(at, slice):
            E[at] += add
        else:
            np.add.at(E, at, add)
    return E


def _terms(arrays: dict, slow: float):
    """sunk_energy's terms in the order it adds them: (sample indices or a slice of samples, F d there [J])."""
    t = np.asarray(arrays["t"])
    P = np.asarray(arrays.get("log_P", ()))
    gap = np.asarray(arrays["gap"], float)
    n_pairs = gap.shape[1] if gap.ndim == 2 else 0
    if not len(P) or not n_pairs or len(t) < 2:
        return
    dur = np.asarray(arrays["log_duration"], float)
    pair, steps = np.asarray(arrays["log_pair"]), np.maximum(np.asarray(arrays["log_steps"]), 1)
    approach = -np.asarray(arrays["log_gamma_minus"], float)  # [m/s]
    keep = np.flatnonzero((dur > 0.0) & (P > 0.0) & ~np.asarray(arrays["log_impact"], bool) & (pair >= 0)
                          & (pair < n_pairs)  # collision pairs (a joint limit's row has no gap column)
                          & (approach <= slow * dur / steps))
    if not len(keep):
        return
    t_row = np.asarray(arrays["log_t"])
    h = dur[keep] / steps[keep]  # [s] the row's step; log_t is its first step's midpoint
    first = np.searchsorted(t, t_row[keep] + 0.25 * h, side="left")  # the sample its first step leads to
    last = np.minimum(np.searchsorted(t, t_row[keep] + dur[keep] - 0.75 * h, side="left"), len(t) - 1)  # its last
    force = P[keep] / dur[keep]  # [N] the row's mean force over its steps
    j = pair[keep]
    ok = first < len(t)
    one = ok & (last <= first)  # a row within one sample's interval (most): at once, its P over the interval
    at = first[one]
    span = t[at] - np.where(at > 0, t[np.maximum(at - 1, 0)], t[0] - 1.0)  # [s] those samples' intervals
    force[one] = P[keep][one] / np.maximum(span, dur[keep][one])
    d = gap[at, j[one]]
    yield at, force[one] * -np.minimum(np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    for s, e, k, f in zip(first[ok & ~one].tolist(), last[ok & ~one].tolist(), j[ok & ~one].tolist(),
                          force[ok & ~one].tolist()):  # a stretch over several samples
        for a in range(s, e + 1, CHUNK):  # in chunks: a rest of 10^6 samples makes no (10^6,) temporaries
            b = min(a + CHUNK, e + 1)
            d = gap[a:b, k]  # [m] the pair's depth at the samples it covers (a failed distance, NaN: none)
            yield slice(a, b), f * -np.minimum(np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0), 0.0)


def first_paid(arrays: dict, slow: float, rel: float, persist: int) -> tuple[float, float, float] | None:
    """The first sample (t [s], the sunk energy [J] (sunk_energy(arrays, slow)), the energy the bound leaves for
    it [J]) ending `persist` consecutive samples where T + sunk energy exceeds E_0 - V + booked + external +
    rel * scale (scale:
    max(|E_0|, max T so far); booked: the positive correction energy and smooth error so far; external: the
    work done on the system so far, §5.5), or None."""
    T, V = np.asarray(arrays["kinetic_energy"]), np.asarray(arrays["potential_energy"])
    if len(T) < persist:
        return None
    if not any((add > 0.0).any() for _, add in _terms(arrays, slow)):  # nothing sunk: no (n_samples,) arrays
        return None
    sunk = sunk_energy(arrays, slow)
    booked = np.cumsum(np.maximum(arrays["correction_energy"], 0.0) + np.maximum(arrays["smooth_error"], 0.0))
    external = np.zeros(len(T))
    for k in ("actuator_work", "obstacle_work"):
        if k in arrays:
            external = external + np.cumsum(arrays[k])
    E0 = float(T[0] + V[0])
    scale = np.maximum(abs(E0), np.maximum.accumulate(T))
    room = (E0 - V + booked + external + rel * scale) - T
    over = sunk > room
    if over.sum() < persist:
        return None
    run = np.convolve(over.astype(int), np.ones(persist, int), mode="full")[:len(T)]
    hit = np.flatnonzero(run >= persist)
    if not len(hit):
        return None
    i = int(hit[0])
    return float(arrays["t"][i]), float(sunk[i]), float(max(room[i], 0.0))
