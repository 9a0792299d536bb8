"""Exact references of the bundled scenes, the one home of each formula in code: the bouncing
ball (impact times, apexes, Zeno time and rest bound; docs/theory.md §4.1), the touching and the
gapped Newton cradle (§4.2, §4.3) and the corner point's admissible outcomes (§3.4, §4.4).

Pure Python (math only): imported by the tests, the benchmarks and the peer runners. Units SI.
"""

from __future__ import annotations

import math

G = 9.81  # gravity of the bundled scenes [m/s^2]
BALL_GAP = 0.9  # bouncing_ball: initial gap [m] (centre at 1 m, radius 0.1 m)
ZENO_GAP = 0.5  # zeno_ball: initial gap [m] (centre at 0.6 m, radius 0.1 m)


def ball_first_impact(d0: float = BALL_GAP, g: float = G) -> float:
    """t0 = sqrt(2 d0 / g) [s]: the first impact of a ball dropped from rest with gap d0."""
    return math.sqrt(2 * d0 / g)


def ball_impact_times(e: float, n: int, d0: float = BALL_GAP, g: float = G) -> list[float]:
    """The first n impact instants t_k = t0 (1 + 2 e + ... + 2 e^k), k = 0..n-1 [s]."""
    t0 = ball_first_impact(d0, g)
    return [t0 * (1 + 2 * sum(e ** j for j in range(1, k + 1))) for k in range(n)]


def ball_apex_gaps(e: float, n: int, d0: float = BALL_GAP) -> list[float]:
    """Apex gap after bounce 1..n: e^(2n) d0 [m]."""
    return [e ** (2 * k) * d0 for k in range(1, n + 1)]


def ball_apex_times(e: float, n: int, d0: float = BALL_GAP, g: float = G) -> list[float]:
    """Instant of the apex after bounce 1..n: t_(k-1) + e^k t0 [s]."""
    t0, impacts = ball_first_impact(d0, g), ball_impact_times(e, n, d0, g)
    return [impacts[k - 1] + e ** k * t0 for k in range(1, n + 1)]


def zeno_time(e: float, d0: float = BALL_GAP, g: float = G) -> float:
    """t_inf = t0 (1 + 2 e / (1 - e)) [s], the accumulation point of the impacts (inf for e >= 1)."""
    return ball_first_impact(d0, g) * (1 + 2 * e / (1 - e)) if e < 1 else math.inf


def zeno_bounces(e: float, h: float, d0: float = ZENO_GAP, g: float = G) -> float:
    """N = ln(h g / v0) / ln(e), v0 = sqrt(2 g d0): the bounces faster than h g (those the step resolves)."""
    return math.log(h * g / math.sqrt(2 * g * d0)) / math.log(e)


def zeno_rest_bound(e: float, h: float, d0: float = ZENO_GAP, g: float = G) -> float:
    """|t_rest - t_inf| <= 2 N h / (1 - e) + 2 ln(1e-12 / (h g)) / ln(e) h [s] (zeno_ball.toml's
    stated bound): the N bounces faster than h g each end O(h) off (carried to the next times e),
    and a residual speed <= h g then dies out by e every two steps down to 1e-12 m/s."""
    return 2 * zeno_bounces(e, h, d0, g) * h / (1 - e) + 2 * math.log(1e-12 / (h * g)) / math.log(e) * h


def ball_reference(e: float, d0: float = BALL_GAP, g: float = G, nbounce: int = 3) -> dict:
    """All of the ball's references at once: t0, apex_gap, apex_time, impact_times (nbounce + 1),
    t_inf."""
    return {"t0": ball_first_impact(d0, g), "apex_gap": ball_apex_gaps(e, nbounce, d0),
            "apex_time": ball_apex_times(e, nbounce, d0, g), "impact_times": ball_impact_times(e, nbounce + 1, d0, g),
            "t_inf": zeno_time(e, d0, g)}


def cradle_simultaneous(e: float, n: int = 5, v0: float = 1.0) -> list[float]:
    """Glocker's simultaneous result for n exactly touching equal balls, ball 1 at v0 [m/s]."""
    return [((1 + e) / n - e) * v0] + [(1 + e) / n * v0] * (n - 1)


def cradle_sequential(e: float, n: int = 5, v0: float = 1.0) -> list[float]:
    """Gapped cradle: binary Newton impacts of equal masses, left to right, repeated until no pair
    approaches (v1' = (1-e)/2 v1 + (1+e)/2 v2, v2' = (1+e)/2 v1 + (1-e)/2 v2)."""
    v = [0.0] * n
    v[0] = v0
    for _ in range(10000):
        hit = False
        for i in range(n - 1):
            if v[i] > v[i + 1] + 1e-15:
                a, b = v[i], v[i + 1]
                v[i] = (1 - e) / 2 * a + (1 + e) / 2 * b
                v[i + 1] = (1 + e) / 2 * a + (1 - e) / 2 * b
                hit = True
        if not hit:
            break
    return v


def corner_point_outcomes(e: float) -> set[tuple[float, float]]:
    """corner_point: the admissible post-impact velocities of a unit point mass at u- = (1, 1)
    into the corner of the walls x = 0 and z = 0 (corner-law.md): one wall, the other, or both."""
    return {(-e, 1.0), (1.0, -e), (-e, -e)}


def ball_energy_lost(e: float, t_end: float, m: float = 1.0, d0: float = BALL_GAP, g: float = G) -> float:
    """T + V the ball has lost by t_end [J]: (1 - e^(2n)) m g d0 after the n impacts at t_k <= t_end,
    all of m g d0 once at rest (t_end >= t_inf)."""
    if t_end >= zeno_time(e, d0, g):
        return m * g * d0
    n = 0
    while ball_impact_times(e, n + 1, d0, g)[n] <= t_end:
        n += 1
    return m * g * d0 * (1 - e ** (2 * n))
