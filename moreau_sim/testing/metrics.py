"""Error metrics between a trajectory and a reference (work-precision benchmarks).

Every function takes :class:`~moreau_sim.trajectory.Trajectory` objects or plain mappings with
the same array names (``t``, ``q``, ``u``, ``gap``, ``kinetic_energy``, ``potential_energy``,
``log_t``, ``log_pair``, ``log_impact``, ``log_gamma_minus``), so a peer simulator's output
converted to those names is measured by the same code as ours. Units are SI throughout:
times [s], gaps and heights [m], q in its own units (m, rad), u in m/s, rad/s, energies [J].
Errors are absolute and maximum-norm (the worst component, instant or impact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin


def _get(x, name: str) -> np.ndarray:
    """Array `name` of a Trajectory or a mapping."""
    return np.asarray(x[name] if isinstance(x, dict) else getattr(x, name))


@dataclass(frozen=True)
class ImpactTimesError:
    """max_abs [s]: the largest |t_k - t_ref,k| over matched impacts; errors [s] and pairs: per
    matched impact (signed, t - t_ref); missing / extra: reference impacts without a partner /
    impacts beyond the reference's (per pair, in order)."""

    max_abs: float
    errors: np.ndarray
    pairs: np.ndarray
    missing: int
    extra: int


def impact_times(traj, *, min_speed: float = 0.0, t_max: float = np.inf) -> dict[int, np.ndarray]:
    """{pair: sorted impact instants [s]} from the percussion log: rows flagged as new impacts,
    with approach speed |gamma-| >= min_speed [m/s] and t <= t_max [s]; several rows of one pair
    at one instant (corners of a face, one step of the stepper) count once."""
    t, pair = _get(traj, "log_t"), _get(traj, "log_pair")
    keep = _get(traj, "log_impact").astype(bool) & (t <= t_max)
    keep &= np.abs(_get(traj, "log_gamma_minus")) >= min_speed
    return {int(p): np.unique(t[keep & (pair == p)]) for p in np.unique(pair[keep])}


def impact_times_error(traj, ref, *, count: int | None = None, min_speed: float = 0.0,
                       t_max: float = np.inf) -> ImpactTimesError:
    """Impact instants of `traj` against `ref`, matched per collision pair in order (the k-th
    impact of a pair with the reference's k-th impact of the same pair); `count`: only the
    first `count` impacts of each pair; min_speed, t_max: as :func:`impact_times`."""
    a = impact_times(traj, min_speed=min_speed, t_max=t_max)
    r = impact_times(ref, min_speed=min_speed, t_max=t_max)
    errs, pairs, missing, extra = [], [], 0, 0
    for p in sorted(set(a) | set(r)):
        ta, tr = a.get(p, np.zeros(0))[:count], r.get(p, np.zeros(0))[:count]
        k = min(len(ta), len(tr))
        errs.append(ta[:k] - tr[:k])
        pairs.append(np.full(k, p))
        missing += len(tr) - k
        extra += len(ta) - k
    e = np.concatenate(errs) if errs else np.zeros(0)
    return ImpactTimesError(float(np.abs(e).max(initial=0.0)), e, np.concatenate(pairs) if pairs else
                            np.zeros(0, np.int64), missing, extra)


def apexes(t, y, *, count: int | None = None, min_height: float = 1e-9, skip_t: float = -np.inf):
    """(heights, times) of the strict local maxima of the sampled y(t) after skip_t [s] and above
    min_height, refined by the parabola through the three samples around each: exact for any
    sampling of a free flight under constant acceleration (a quadratic in t)."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    k = np.flatnonzero((y[1:-1] >= y[:-2]) & (y[1:-1] > y[2:]) & (t[1:-1] > skip_t)) + 1
    heights, times = [], []
    for i in k:
        (t0, t1, t2), (y0, y1, y2) = t[i - 1:i + 2], y[i - 1:i + 2]
        c2, c1, c0 = np.polyfit([t0 - t1, 0.0, t2 - t1], [y0, y1, y2], 2)
        s = -c1 / (2 * c2) if c2 < 0 else 0.0
        h = c0 + c1 * s + c2 * s * s if c2 < 0 else y1
        if h > min_height:
            heights.append(float(h))
            times.append(float(t1 + s))
        if count is not None and len(heights) == count:
            break
    return np.array(heights), np.array(times)


@dataclass(frozen=True)
class ApexError:
    """max_abs [m] over the first `count` apexes (a missing apex counts as its full reference
    height); heights, reference [m]: those compared; missing: reference apexes not reached."""

    max_abs: float
    heights: np.ndarray
    reference: np.ndarray
    missing: int


def apex_error(traj, ref, *, pair: int = 0, count: int = 3, min_height: float = 1e-9) -> ApexError:
    """Rebound heights of a flight sequence: the apexes of traj's gap[:, pair] against the
    reference's (a Trajectory/mapping, whose apexes are taken the same way, or the heights
    themselves, e.g. the closed form e^(2n) d0 of docs/theory.md §4)."""
    h, _ = apexes(_get(traj, "t"), _get(traj, "gap")[:, pair], count=count, min_height=min_height)
    if isinstance(ref, (list, tuple, np.ndarray)):
        href = np.asarray(ref, float)[:count]
    else:
        href, _ = apexes(_get(ref, "t"), _get(ref, "gap")[:, pair], count=count, min_height=min_height)
    k = min(len(h), len(href))
    err = np.abs(h[:k] - href[:k])
    worst = max(err.max(initial=0.0), np.abs(href[k:]).max(initial=0.0))
    return ApexError(float(worst), h[:k], href[:k], len(href) - k)


def _interp_q(t, q, times, model):
    """q at `times`, linear in each component (Euclidean) or along the group (pin.interpolate)."""
    if model is None:
        return np.stack([np.interp(times, t, q[:, j]) for j in range(q.shape[1])], axis=1)
    out = []
    for s in times:
        i = int(np.clip(np.searchsorted(t, s, side="right") - 1, 0, len(t) - 2))
        a = 0.0 if t[i + 1] == t[i] else (s - t[i]) / (t[i + 1] - t[i])
        out.append(pin.interpolate(model, q[i], q[i + 1], float(np.clip(a, 0.0, 1.0))))
    return np.array(out)


@dataclass(frozen=True)
class StateError:
    """q_max (q's units, tangent space on a Lie group) and u_max: the largest error over the
    components and instants; q_err, u_err (k,): the max-norm error at each instant."""

    q_max: float
    u_max: float
    q_err: np.ndarray
    u_err: np.ndarray


def state_error(traj, ref, times, *, model: pin.Model | None = None) -> StateError:
    """State error at fixed instants `times` [s], both trajectories interpolated linearly between
    their samples (choose instants away from impacts, or sample the reference at them). With a
    Pinocchio `model` q is a Lie-group element (quaternions): interpolation by pin.interpolate and
    the error by pin.difference(model, q_ref, q)."""
    times = np.asarray(times, float)
    tq, tr = _get(traj, "t"), _get(ref, "t")
    qa, qr = _interp_q(tq, _get(traj, "q"), times, model), _interp_q(tr, _get(ref, "q"), times, model)
    ua, ur = _interp_q(tq, _get(traj, "u"), times, None), _interp_q(tr, _get(ref, "u"), times, None)
    if model is None:
        dq = qa - qr
    else:
        dq = np.array([pin.difference(model, b, a) for a, b in zip(qa, qr)])
    qe, ue = np.abs(dq).max(axis=1), np.abs(ua - ur).max(axis=1)
    return StateError(float(qe.max(initial=0.0)), float(ue.max(initial=0.0)), qe, ue)


def energy_error(traj, ref, times=None) -> float:
    """max |E(t) - E_ref(t)| [J], E = T + V, over `times` (default: traj's samples inside the
    reference's time span), both interpolated linearly. Near an impact this includes the jump
    times the difference of impact instants: it measures timing as well as dissipation."""
    ta, tr = _get(traj, "t"), _get(ref, "t")
    Ea = _get(traj, "kinetic_energy") + _get(traj, "potential_energy")
    Er = _get(ref, "kinetic_energy") + _get(ref, "potential_energy")
    if times is None:
        times = ta[(ta >= tr[0]) & (ta <= tr[-1])]
    times = np.asarray(times, float)
    return float(np.abs(np.interp(times, ta, Ea) - np.interp(times, tr, Er)).max(initial=0.0))


def max_penetration(x) -> float:
    """-min(gap) [m] over samples and pairs, 0 if no gap is negative; `x` a Trajectory, a
    mapping with "gap", or the gap array itself."""
    g = np.asarray(x) if isinstance(x, np.ndarray) else _get(x, "gap")
    return float(max(0.0, -g.min(initial=np.inf))) if g.size else 0.0
